"""``register --roi cranium`` and ``--roi-mask FILE``: the region the registration follows."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from registration.io import dicom
from tests.app.test_commands import run


def test_register_with_a_users_mask_and_a_bad_one(small_export: Path, tmp_path: Path, capsys) -> None:
    volume = dicom.read_volume(small_export / "volume")
    np.savez(tmp_path / "roi.npz", mask=np.ones(volume.shape, dtype=np.uint8))
    args = ["register", "--volume", str(small_export / "volume"), "--image", str(small_export / "xa_fluoro.dcm"),
            "--truth", str(small_export / "truth.json")]  # fmt: skip
    code, out, err = run([*args, "--roi-mask", str(tmp_path / "roi.npz")], capsys)
    assert code == 0, err
    assert "region: roi.npz" in out  # (the 48^3 export registers too coarsely for success here)
    np.savez(tmp_path / "short.npz", mask=np.ones(volume.shape[1:], dtype=np.uint8))
    code, out, err = run([*args, "--roi-mask", str(tmp_path / "short.npz")], capsys)
    assert code == 2 and "short.npz: mask shape" in err
    code, out, err = run([*args, "--roi", "neck"], capsys)
    assert code == 2


@pytest.mark.parametrize("roi", [[], ["--roi", "cranium"], ["--roi", "none"]])
def test_register_says_which_region_it_follows(small_export: Path, tmp_path: Path, capsys, roi: list[str]) -> None:
    """By default (and with --roi cranium) the cranium: the skull base the phantom's export holds,
    the pixels that see mostly the neck below it left out, said on the terminal and in the JSON;
    --roi none: every pixel."""
    import json

    argv = ["register", "--volume", str(small_export / "volume"), "--image", str(small_export / "xa_fluoro.dcm")]
    code, out, err = run([*argv, *roi, "--out", str(tmp_path / "r.json")], capsys)
    assert code == 0, err
    doc = json.loads((tmp_path / "r.json").read_text())
    if roi[-1:] == ["none"]:
        assert "region: every pixel of the field (--roi none)" in out and "region" not in doc
        return
    assert "region: cranium: " in out and doc["region"]["source"] == "cranium"
    # the phantom's neck: its pixels left out, and whether skull and spine agree checked
    assert doc["region"]["skull_base_z_mm"] is not None
    (field,) = doc["region"]["fields"]
    assert 0 < field["left_out_px"] < field["field_px"] and "px see mostly what lies outside" in out
    assert "skull_spine" in doc


def test_register_on_a_region_says_whether_skull_and_spine_agree(small_export: Path, tmp_path: Path, capsys) -> None:
    """A mask leaving out the lower third of the phantom: the registration follows the rest,
    then the whole volume is searched near its estimate; the result says how far it moved."""
    import json

    volume = dicom.read_volume(small_export / "volume")
    mask = np.ones(volume.shape, dtype=np.uint8)
    mask[: volume.shape[0] // 3] = 0
    np.savez(tmp_path / "roi.npz", mask=mask)
    code, out, err = run(["register", "--volume", str(small_export / "volume"), "--image",
                          str(small_export / "xa_fluoro.dcm"), "--roi-mask", str(tmp_path / "roi.npz"),
                          "--out", str(tmp_path / "r.json")], capsys)  # fmt: skip
    assert code == 0, err
    assert "skull and spine agree" in out or "skull and spine DISAGREE" in out, out
    doc = json.loads((tmp_path / "r.json").read_text())
    assert doc["region"]["source"] == "roi.npz" and doc["region"]["left_out_ml"] > 0
    check = doc["skull_spine"]
    assert check["criterion"] == "in-plane" and check["drr_count"] > 0
    # agreement is the thresholds applied to what was measured
    assert check["agree"] == (check["shift_mm"] <= 1.0 and check["rotation_deg"] <= 1.5)
