"""``roadmap3d phantom-run`` and ``roadmap3d track`` end to end: a simulated run written as a
multi-frame XA with its frame times, read back and tracked; the per-frame list of CONVENTIONS §7."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from app import cli
from app.cli import track_commands as tc
from registration.io import dicom

SMALL = ["--pixels", "64", "--voxels", "128", "--volume-source", "resampled", "--seconds", "2", "--sudden-moves", "1"]


def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as info:
        cli.main(argv)
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return int(info.value.code or 0), out, err


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("run") / "phantom-run"
    with pytest.raises(SystemExit) as info:
        cli.main(["phantom-run", "--out", str(out), *SMALL])
    assert info.value.code == 0
    return out


def test_run_file_has_frame_times_and_truth(exported: Path) -> None:
    run_ = dicom.read_xray_run(exported / tc.RUN_FILE)
    truth = json.loads((exported / tc.RUN_TRUTH).read_text())
    assert len(run_) == len(truth["frames"]) == 30  # 2 s at 15 frames/s
    # frame times survive the file (FrameTime of 66.7 ms: DICOM keeps it to a few digits)
    np.testing.assert_allclose(run_.times_s, [f["t_s"] for f in truth["frames"]], atol=1e-3)


def test_track_writes_the_per_frame_list(exported: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "track.json"
    code, stdout, _ = run(
        ["track", "--volume", str(exported / "volume"), "--run", str(exported / tc.RUN_FILE),
         "--truth", str(exported / tc.RUN_TRUTH), "--out", str(out), "--every-frame"], capsys,
    )  # fmt: skip
    assert code == 0, stdout
    doc = json.loads(out.read_text())
    assert len(doc["frames"]) == 30 and doc["skipped"] == []  # --every-frame processes every frame
    for f in doc["frames"]:
        assert f["status"] in ("applied", "withheld", "unchanged")
        assert np.asarray(f["patient_motion"]).shape == (4, 4)
        assert f["latency_ms"] > 0 and "shown_error_mm" in f
    s = doc["summary"]
    for key in ("frames", "ms_per_frame_median", "ms_per_frame_p95", "applied", "withheld", "skipped"):
        assert key in s
    # the roadmap at the end of the run is right (single plane: in-plane < 1 mm)
    assert doc["frames"][-1]["shown_error_mm"] < 1.0
    assert "latency: median" in stdout


def test_track_bad_input(exported: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    junk = tmp_path / "junk.dcm"
    junk.write_bytes(b"not a dicom file")
    code, _, err = run(["track", "--volume", str(exported / "volume"), "--run", str(junk)], capsys)
    assert code == 2 and "error:" in err and "junk.dcm" in err
    bad_truth = tmp_path / "truth.json"
    bad_truth.write_text(json.dumps({"frames": [{"patient_motion": np.eye(4).tolist()}]}))
    code, _, err = run(
        ["track", "--volume", str(exported / "volume"), "--run", str(exported / tc.RUN_FILE), "--truth",
         str(bad_truth)], capsys,
    )  # fmt: skip
    assert code == 2 and "truth.json" in err and "30 frames" in err
