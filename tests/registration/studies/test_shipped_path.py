"""The studies register on the path users run: the same case through the studies' function and
through ``roadmap3d register`` on the exported files gives the same pose and the same decision."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from app import cli
from app.cli import phantom_commands as pc
from registration.core.assess import assess
from registration.io import dicom
from registration.studies.cases import assessment_fields, register_prepared


def _run(argv: list[str]) -> int:
    with pytest.raises(SystemExit) as info:
        cli.main(argv)
    return int(info.value.code or 0)


@pytest.mark.slow
def test_study_and_cli_give_the_same_pose(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ROADMAP3D_CACHE", str(tmp_path / "cache"))
    export = tmp_path / "phantom"
    small = ["--voxels", "128", "--pixels", "128", "--volume-source", "resampled"]
    assert _run(["phantom", "--out", str(export), "--primary-deg", "15", "--offset", "T2", *small]) == 0
    volume_dir, image = export / pc.PHANTOM_VOLUME_DIR, export / pc.PHANTOM_FLUORO
    out = tmp_path / "result.json"
    # the phantom's studies follow the paper's protocol, the whole volume (register's default follows the cranium)
    argv = ["register", "--volume", str(volume_dir), "--image", str(image), "--seed", "3", "--confidence"]
    argv += ["--roi", "none"]
    assert _run([*argv, "--out", str(out), "--no-cache"]) == 0
    shipped = json.loads(out.read_text())
    # the studies' path on the same files
    volume, xray = dicom.read_volume(volume_dir), dicom.read_xray(image)
    result, preparation = register_prepared(volume, xray, seed=3)
    fields = assessment_fields(assess(result, xray, preparation))
    # 1e-9: the same arithmetic on the same data (the JSON holds float64 exactly)
    np.testing.assert_allclose(result.patient_motion, shipped["patient_motion"], rtol=0, atol=1e-9)
    assert result.drr_count == shipped["drr_count"]
    assert fields["applied"] == shipped["applied"] and fields["withheld_reason"] == shipped["withheld_reason"]
    assert fields["confidence"] == pytest.approx(shipped["confidence"], abs=1e-9)
