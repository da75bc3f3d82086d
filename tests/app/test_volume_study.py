"""``roadmap3d validate volume`` on the phantom's own 3DRA (a small, fast run of the real command)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from app.cli import main
from registration.io.dicom import write_npz
from registration.sim.phantom import make_head_phantom, registration_volume
from registration.studies.volume import SUMMARY_KEYS, head_isocenter_mm, mask_parts


@pytest.fixture(scope="module")
def phantom_3dra(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The phantom's 3DRA stand-in (128^3 over 27 cm, cached on disk) as a user's .npz."""
    path = tmp_path_factory.mktemp("volume-study") / "3dra.npz"
    write_npz(registration_volume(make_head_phantom(), 27.0, voxels=128), path)
    return path


def test_validate_volume_on_the_phantoms_3dra(
    phantom_3dra: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "study"
    with pytest.raises(SystemExit) as exit_:
        main(["validate", "volume", "--volume", str(phantom_3dra), "--isocenter", "volume-center",
              "--cases", "2", "--json", "--out", str(out)])  # fmt: skip
    assert exit_.value.code == 0
    captured = capsys.readouterr()
    summary = json.loads(captured.out)
    assert list(summary)[: len(SUMMARY_KEYS)] == list(SUMMARY_KEYS)
    assert summary["runs"] == 2
    # The phantom's 3DRA registers to its own simulated views at < 1 mm in-plane nearly always
    # (Table I and the clinical study); two cases at random offsets up to 25 mm / 10 deg: both.
    assert summary["success_rate"] == 1.0
    assert summary["inplane_residual_mm_median"] < 0.5 and summary["rotation_residual_deg_median"] < 1.0
    assert summary["seconds_median"] > 0 and summary["prepare_seconds"] > 0
    assert "best case" in summary["images"] and "Best case" in captured.err
    records = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert len(records) == 2 and all(r["views"] == 1 for r in records)
    assert "Best case" in (out / "report.md").read_text()
    assert json.loads((out / "summary.json").read_text())["runs"] == 2


def test_validate_volume_refuses_an_isocenter_outside_the_volume(
    phantom_3dra: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["validate", "volume", "--volume", str(phantom_3dra), "--isocenter", "500,0,0", "--cases", "1"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and "outside the volume" in err and "Traceback" not in err
    assert "--isocenter head" in err  # the way to aim at the head of a CT without the tag


def test_head_isocenter_is_the_middle_of_the_head() -> None:
    """A 'head' (sphere) above a wider 'neck and shoulders' block: the top 180 mm's largest tissue."""
    from registration.core.volume import Volume

    n, sp = 100, 3.0
    axis = (np.arange(n) - (n - 1) / 2) * sp  # +-148.5 mm
    z, y, x = np.meshgrid(axis, axis, axis, indexing="ij")
    hu = np.full(x.shape, -1000.0, np.float32)
    hu[(x - 10) ** 2 + (y + 5) ** 2 + (z - 60) ** 2 < 70**2] = 40.0  # head, center (10, -5, 60)
    hu[(z < -50) & (np.abs(x) < 140)] = 40.0  # shoulders, out of the top 180 mm
    iso = head_isocenter_mm(Volume.from_grid(hu, sp))
    # the head's box is cut at the top of the volume (z <= 148.5): its middle in z sits at
    # (-10 + 130) / 2 = 60 within a voxel; x, y within a voxel of the center
    assert iso == pytest.approx((10.0, -5.0, 60.0), abs=sp)


def test_bench_skips_the_real_ct_with_a_note_when_absent(monkeypatch: pytest.MonkeyPatch) -> None:
    import registration.studies.volume_bench as study

    monkeypatch.setattr(study, "find_real_ct", lambda: None)
    out = study.bench_real_volume(cases=1)
    assert set(out) == {"skipped"} and "real CT" in out["skipped"]


def test_validate_volume_biplane(phantom_3dra: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["validate", "volume", "--volume", str(phantom_3dra), "--isocenter", "volume-center",
              "--cases", "1", "--biplane", "--json", "--seed", "1"])  # fmt: skip
    assert exit_.value.code == 0
    summary = json.loads(capsys.readouterr().out)
    # two planes see all six offsets: the 3-D criterion (CONVENTIONS §6) holds for the phantom
    assert summary["config"]["biplane"] and "3-D" in summary["success_criterion"]
    assert summary["success_rate"] == 1.0 and summary["translation_residual_mm_median"] < 1.0


def test_validate_volume_with_clinical_images(
    phantom_3dra: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--realism``: the clean arm and a clinical one (blades, display chain, burned-in text) register the
    same case; the clinical images go through XA files read back as register reads them, each estimate
    gets a decision, the report has a row per arm."""
    out = tmp_path / "clinical"
    with pytest.raises(SystemExit) as exit_:
        main(["validate", "volume", "--volume", str(phantom_3dra), "--isocenter", "volume-center", "--cases", "1",
              "--realism", "clean,blades+display+text", "--strengths", "0.5", "--json", "--out", str(out)])  # fmt: skip
    assert exit_.value.code == 0
    captured = capsys.readouterr()
    summary = json.loads(captured.out)
    assert summary["runs"] == 2 and "clinical-looking" in summary["images"]
    arms = {a["arm"]: a for a in summary["arms"]}
    assert set(arms) == {"clean", "blades+display+text"}
    assert arms["clean"]["strength"] == 1.0 and arms["blades+display+text"]["strength"] == 0.5
    records = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert all("applied" in r for r in records)  # decisions for both arms
    clinical = next(r for r in records if r["arm"] == "blades+display+text")
    # the display chain wrote DISP: the reader says how it read the pixels
    assert "DISP" in (clinical["intensity_note"] or "") and clinical["mask_px"] > 0
    assert clinical["effects"] == ["blades", "display", "text"]
    report = (out / "report.md").read_text()
    assert "| blades+display+text | 0.5 | 1 |" in report
    # how the field was found: each part once, on the one image
    parts = arms["blades+display+text"]["mask_parts"]
    assert parts and set(parts.values()) == {1}
    assert all(f"{part} (1 of 1)" in report for part in parts)


def test_the_field_parts_are_counted_per_image_in_the_readers_order() -> None:
    found = ["dark outside, collimator blade x2, burned-in graphics",
             "dark outside, filter edge, collimator blade, burned-in graphics", None,
             "constant border, burned-in graphics"]  # fmt: skip
    parts = mask_parts(found)
    assert parts == {"constant border": 1, "dark outside": 2, "filter edge": 1, "collimator blade": 2,
                     "burned-in graphics": 3}  # fmt: skip
    assert list(parts)[-1] == "burned-in graphics"  # listed last by the reader, every time


def test_validate_volume_refuses_an_unknown_effect(phantom_3dra: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["validate", "volume", "--volume", str(phantom_3dra), "--isocenter", "volume-center",
              "--realism", "clean,shutters"])  # fmt: skip
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and "unknown effect 'shutters'" in err and "Traceback" not in err


def test_the_bench_resamples_a_ct_over_the_same_extent() -> None:
    from registration.core.volume import Volume
    from registration.studies.volume_bench import resampled

    rng = np.random.default_rng(0)
    data = rng.normal(0.0, 100.0, (6, 11, 9)).astype(np.float32)  # k, j, i
    affine = np.diag([1.0, -1.0, 3.0, 1.0])
    affine[:3, 3] = (5.0, 7.0, -20.0)
    vol = Volume(data, affine, label="ct")
    fine = resampled(vol, (0.5, 0.5, 2.5))
    assert fine.shape == (7, 21, 17)  # (6 - 1) * 3 / 2.5 + 1, (11 - 1) / 0.5 + 1, (9 - 1) / 0.5 + 1
    np.testing.assert_allclose(fine.spacing_mm, (0.5, 0.5, 15.0 / 6.0))
    # the first and last voxels stay in place, with their values (linear interpolation)
    np.testing.assert_allclose(fine.index_to_world[:3, 3], affine[:3, 3])
    np.testing.assert_allclose(fine.index_to_world @ [16, 20, 6, 1], affine @ [8, 10, 5, 1])
    assert fine.data[0, 0, 0] == pytest.approx(data[0, 0, 0], rel=1e-5)
    assert fine.data[-1, -1, -1] == pytest.approx(data[-1, -1, -1], rel=1e-5)
    assert fine.data[0, 0, 2] == pytest.approx(data[0, 0, 1], rel=1e-5)  # x index 2 of 0.5 mm is index 1 of 1 mm
