"""``roadmap3d validate capture``: the offset sweeps, the capture radius and a small real run."""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from app.cli import main
from registration.studies.capture import (
    CaptureConfig,
    capture_radius,
    capture_report_md,
    capture_summary,
    capture_tasks,
    level_rates,
    pooled_records,
)


def _record(sweep: str, level: int, t: float, r: float, success: bool, applied: bool, n: int) -> dict:
    return {
        "case_id": f"{sweep}/{level}/{n}",
        "sweep": sweep,
        "level": level,
        "level_translation_mm": t,
        "level_rotation_deg": r,
        "success": success,
        "applied": applied,
        "single_success_inplane": success,
        "single_applied": applied,
        "image_source": "test",
        "volume_label": "test",
    }


def test_every_draw_sits_at_its_levels_offset() -> None:
    config = replace(CaptureConfig.quick_config(seed=3), registrations_per_level=2)
    tasks = capture_tasks(config)
    assert len(tasks) == 3 * 5 * 2 and len({t.case_id for t in tasks}) == len(tasks)
    for task in tasks:
        case, extra = task.case, task.extra
        t_mm, r_deg = config.level_offset(extra["sweep"], extra["level"])
        # the translation's length and the rotation's angle are the level's, exactly (a random direction)
        assert np.linalg.norm(case.translation_mm) == pytest.approx(t_mm, abs=1e-9)
        assert case.rotation_deg == r_deg
        if extra["sweep"] == "translation":
            assert r_deg == 0.0
        if extra["sweep"] == "rotation":
            assert t_mm == 0.0
    # the same seed draws the same moments; another seed draws others
    assert [t.case for t in capture_tasks(config)] == [t.case for t in tasks]
    other = capture_tasks(replace(config, seed=4))
    assert other[2].case.translation_mm != tasks[2].case.translation_mm  # level 1: 20 mm


def test_capture_radius_is_the_last_level_before_the_first_miss() -> None:
    # translation levels 0, 20, 40, 60: 20/20, 20/20, 19/20 (95 %: still captured), then 18/20
    records = []
    for level, (t, wins) in enumerate(((0.0, 20), (20.0, 20), (40.0, 19), (60.0, 18))):
        records += [_record("translation", level, t, 0.0, n < wins, n < wins, n) for n in range(20)]
    rows = level_rates(records, "translation", "biplane")
    assert [r["success_rate"] for r in rows] == [1.0, 1.0, 0.95, 0.9]
    assert capture_radius(rows, "translation_mm") == 40.0
    # a miss at a small offset ends the radius there even if larger offsets succeed again
    rows[1]["success_rate"] = 0.5
    assert capture_radius(rows, "translation_mm") == 0.0
    rows[0]["success_rate"] = 0.5
    assert capture_radius(rows, "translation_mm") is None


def test_each_level_carries_its_success_interval() -> None:
    """Wilson's 95 % score interval, checked against its closed form: 10 of 10 right is
    consistent with 72 %; 19 of 20 with 76-99 %."""
    records = [_record("translation", 0, 0.0, 0.0, True, True, n) for n in range(10)]
    records += [_record("translation", 1, 20.0, 0.0, n < 19, True, n) for n in range(20)]
    rows = level_rates(records, "translation", "single_plane")
    z = 1.959963984540054
    for row, (k, n) in zip(rows, ((10, 10), (19, 20)), strict=True):
        p = k / n
        centre = (p + z * z / (2 * n)) / (1 + z * z / n)
        half = z / (1 + z * z / n) * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
        assert row["successes"] == k
        assert row["success_interval_95"] == pytest.approx([centre - half, centre + half], abs=1e-4)  # rounded to 4
    assert rows[0]["success_interval_95"][0] == pytest.approx(0.7225, abs=1e-4)
    report = capture_report_md(
        capture_summary(records, config={"seed": 0}, wall_seconds=1.0) | {"volume_labels": ["t"], "image_source": "t"},
        "curves.png",
    )
    assert "| translation | 0 | 0 | 10 | 100.0 % | 72-100 % |" in report
    assert "| translation | 20 | 0 | 20 | 95.0 % | 76-99 % |" in report


def _write(path: Path, records: list[dict]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(json.dumps(r) + "\n" for r in records))
    return path


def test_pooled_runs_count_every_moment_per_level(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Two seeds' runs of 10 per level pooled: 20 per level, one miss in 20 passes the 95 % rule
    that it failed in its own run of 10."""
    base = {"pixels": [512, 384], "volume_format_cm": 27.0, "aimed": False}
    runs = []
    for seed in (1, 2):
        records = []
        for level, t in enumerate((0.0, 40.0)):
            for n in range(10):
                right = not (seed == 2 and level == 1 and n == 0)
                rec = _record("translation", level, t, 0.0, right, right, n) | base
                records.append(rec | {"case_id": f"{rec['case_id']}/s{seed}", "study_seed": seed, "revision": "abc"})
        runs.append(_write(tmp_path / f"s{seed}" / "results.jsonl", records))
    alone = capture_summary(pooled_records([runs[1]]), config={}, wall_seconds=0.0)
    assert alone["biplane"]["capture_radius_mm_95"] == 0.0  # 9 of 10 at 40 mm
    out = tmp_path / "pooled"
    with pytest.raises(SystemExit) as exit_:
        main(["validate", "capture", "--json", "--pool", str(runs[0].parent), str(runs[1]), "--out", str(out)])
    assert exit_.value.code == 0
    summary = json.loads(capsys.readouterr().out)
    for plane in ("biplane", "single_plane"):
        rows = summary[plane]["sweeps"]["translation"]
        assert [r["runs"] for r in rows] == [20, 20] and rows[1]["successes"] == 19
        assert summary[plane]["capture_radius_mm_95"] == 40.0
    assert summary["config"]["seeds"] == [1, 2] and summary["config"]["revisions"] == ["abc"]
    assert "Pooled from 2 runs: seeds 1, 2" in (out / "report.md").read_text()
    assert (out / "capture_curves.png").stat().st_size > 10_000
    assert not (out / "results.jsonl").exists()  # nothing registered, nothing copied


def test_pooling_refuses_what_does_not_belong_together(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    base = {"pixels": [512, 384], "volume_format_cm": 27.0, "aimed": False}
    one = _write(tmp_path / "a" / "results.jsonl", [_record("translation", 0, 0.0, 0.0, True, True, 0) | base])
    quick = _write(tmp_path / "b" / "results.jsonl",
                   [_record("translation", 0, 0.0, 0.0, True, True, 1) | base | {"pixels": [256, 192]}])  # fmt: skip
    other_ladder = _write(tmp_path / "c" / "results.jsonl", [_record("translation", 0, 5.0, 0.0, True, True, 2) | base])
    empty = _write(tmp_path / "d" / "results.jsonl", [{"case_id": "x"}])
    cases = [
        ([one, one], "was already pooled from"),
        ([one, quick], "pixels [256, 192] against [512, 384]"),
        ([one, other_ladder], "level 0 lies at another offset"),
        ([one, empty], "holds no moments of the capture study"),
        ([one, tmp_path / "missing"], "no such results file"),
    ]
    for paths, words in cases:
        with pytest.raises(ValueError, match=re.escape(words)):
            pooled_records(paths)
    # through the command: one line naming the file, exit 2, and --out may not be a pooled run's folder
    for argv, words in (
        (["--pool", str(one), str(quick), "--out", str(tmp_path / "p")], str(quick)),
        (["--pool", str(one), "--out", str(one.parent)], "is a pooled run's own folder"),
    ):
        with pytest.raises(SystemExit) as exit_:
            main(["validate", "capture", *argv])
        assert exit_.value.code == 2
        err = capsys.readouterr().err
        assert words in err and "Traceback" not in err
    assert one.read_text().count("\n") == 1  # the pooled run's records untouched


def test_summary_counts_applied_and_wrong_per_plane() -> None:
    records = [_record("rotation", 0, 0.0, 0.0, True, True, n) for n in range(3)]
    records += [_record("rotation", 1, 0.0, 30.0, False, n == 0, n) for n in range(3)]  # one wrong applied
    summary = capture_summary(records, config={"seed": 0}, wall_seconds=1.0)
    for plane in ("biplane", "single_plane"):
        s = summary[plane]
        assert s["capture_radius_deg_95"] == 0.0 and s["capture_radius_mm_95"] is None
        assert s["applied"] == 4 and s["applied_precision"] == pytest.approx(3 / 4)
        assert s["applied_wrong"] == ["rotation/1/0"] and s["runs"] == 6


def test_the_report_says_which_sweeps_did_not_run() -> None:
    """A run of the rotation sweep alone: its translation and combined radii are "not run", not
    "below the smallest level" (which a sweep that ran and missed at 0 would say)."""
    records = [_record("rotation", 0, 0.0, 0.0, n > 0, False, n) for n in range(3)]  # 2 of 3 at 0 deg
    summary = capture_summary(records, config={"seed": 0}, wall_seconds=1.0)
    summary |= {"volume_labels": ["test"], "image_source": "test"}
    report = capture_report_md(summary, "curves.png")
    assert "| capture radius, translation | not run | not run |" in report
    assert "| capture radius, rotation | below the smallest level | below the smallest level |" in report
    assert "| capture radius, both together | not run | not run |" in report


def test_validate_capture_runs_and_writes_its_report(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Two moments of the translation sweep on the quick phantom: at no offset both planes
    register (the phantom's own views; Table I succeeds 16/16 at 5-20 mm)."""
    out = tmp_path / "capture"
    with pytest.raises(SystemExit) as exit_:
        main(["validate", "capture", "--quick", "--json", "--sweep", "translation", "--registrations", "1",
              "--jobs", "1", "--out", str(out)])  # fmt: skip
    assert exit_.value.code == 0
    summary = json.loads(capsys.readouterr().out)
    for plane in ("single_plane", "biplane"):
        s = summary[plane]
        assert s["runs"] == 5 and s["sweeps"]["translation"][0]["translation_mm"] == 0.0
        assert s["sweeps"]["translation"][0]["success_rate"] == 1.0  # no offset: registered
        assert s["capture_radius_mm_95"] is not None and s["capture_radius_deg_95"] is None
        # the engine may fail far out, but what it applies must be right
        assert s["applied_precision"] == 1.0, s["applied_wrong"]
    assert (out / "capture_curves.png").stat().st_size > 10_000
    assert "Capture range" in (out / "report.md").read_text()


def test_validate_capture_refuses_bad_options(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["validate", "capture", "--registrations", "0"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "--registrations must be >= 1" in err and "Traceback" not in err
    with pytest.raises(SystemExit) as exit_:
        main(["validate", "capture", "--from-landmarks", "3"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "--from-landmarks takes 4 to 8" in err and "Traceback" not in err


def test_from_landmarks_the_same_moments_start_from_picks() -> None:
    from registration.studies.landmark_starts import LandmarkCase

    config = replace(CaptureConfig.quick_config(seed=3), registrations_per_level=1)
    plain = capture_tasks(config)
    picked = capture_tasks(replace(config, landmark_pairs=4, landmark_noise_mm=3.0))
    assert len(picked) == len(plain)
    for a, b in zip(plain, picked, strict=True):
        # the same moment, its own case id (a results file may hold both) and its own picks
        assert isinstance(b.case, LandmarkCase) and b.case.case == a.case and b.extra == a.extra
        assert b.case_id == a.case_id + "/landmarks-4x3mm-in-field"
    assert len({t.case.pick_seed for t in picked}) == len(picked)
    with pytest.raises(ValueError, match="four fix a pose"):
        replace(config, landmark_pairs=3)
    with pytest.raises(ValueError, match="picking error"):
        replace(config, landmark_noise_mm=-1.0)


def test_the_picks_lie_on_the_skulls_outline() -> None:
    from registration.core.volume import Volume
    from registration.studies.landmark_starts import outer_bone_points

    # a bone shell of radius 60 mm about (5, -3, 10) mm: its outermost points along the pick
    # directions lie 60 mm out along them (within the 1 mm voxel)
    z, y, x = np.mgrid[-80:81, -80:81, -80:81].astype(np.float64)
    r = np.sqrt(x**2 + y**2 + z**2)
    hu = np.where((r > 55) & (r <= 60), 1000.0, 0.0).astype(np.float32)
    volume = Volume.from_grid(hu, (1.0, 1.0, 1.0), label="shell")
    centre_index = np.array([80.0, 80.0, 80.0, 1.0])
    centre = (volume.index_to_world @ centre_index)[:3]
    points = outer_bone_points(volume, 4)
    assert np.all(np.abs(np.linalg.norm(points - centre, axis=1) - 60.0) < 1.0)
    with pytest.raises(ValueError, match="no bone"):
        outer_bone_points(Volume.from_grid(np.zeros((8, 8, 8), np.float32), (1.0, 1.0, 1.0), label="air"), 4)


def test_each_plane_picks_only_what_its_field_shows() -> None:
    from registration.core.geometry import CArm, apply
    from registration.core.images import XRayImage
    from registration.core.volume import Volume
    from registration.studies.landmark_starts import in_field, outer_bone_points, picked_landmarks, picks_per_plane

    z, y, x = np.mgrid[-70:71:2, -70:71:2, -70:71:2].astype(np.float64)
    r = np.sqrt(x**2 + y**2 + z**2)
    hu = np.where((r > 52) & (r <= 60), 1000.0, 0.0).astype(np.float32)
    volume = Volume.from_grid(hu, (2.0, 2.0, 2.0), label="shell")
    truth = np.eye(4)
    truth[:3, 3] = (10.0, -5.0, 4.0)
    geometry = CArm.for_format(27.0, pixels=96, primary_deg=0.0, secondary_deg=0.0)
    whole = np.ones((96, 96), dtype=bool)
    right_half = whole.copy()
    right_half[:, :48] = False  # a blade over the image's left half
    hidden = np.zeros((96, 96), dtype=bool)
    hidden[:2, :2] = True  # a field in the corner, off the skull
    views = [XRayImage(np.zeros((96, 96), np.float32), m, geometry) for m in (whole, right_half, hidden)]
    anatomy = outer_bone_points(volume, 8)
    seen = [[in_field(v, geometry.project(apply(truth, p))) for p in anatomy] for v in views]
    assert sum(seen[0]) == 8 and 0 < sum(seen[1]) < 8 and sum(seen[2]) == 0  # the setup holds what it says
    picks = picked_landmarks(volume, views, truth, pairs=4, noise_mm=0.0, rng=np.random.default_rng(1))
    # each plane its first four shown points (no error: exactly the outline's points and pixels)
    assert picks_per_plane(picks, 3) == [4, min(4, sum(seen[1])), 0]
    for plane, view in enumerate(views[:2]):
        expected = [p for p, ok in zip(anatomy, seen[plane], strict=True) if ok][:4]
        got = [lm for lm in picks if lm.plane == plane]
        np.testing.assert_allclose([lm.volume_mm for lm in got], expected, atol=1e-9)
        for lm in got:
            assert in_field(view, np.asarray(lm.image_px))
            np.testing.assert_allclose(lm.image_px, geometry.project(apply(truth, np.asarray(lm.volume_mm))),
                                       atol=1e-9)  # fmt: skip
    # wherever they project: the first four on every plane, whether the field shows them or not
    everywhere = picked_landmarks(volume, views, truth, pairs=4, noise_mm=0.0, rng=np.random.default_rng(1),
                                  visible=False)  # fmt: skip
    assert picks_per_plane(everywhere, 3) == [4, 4, 4]
    np.testing.assert_allclose([lm.volume_mm for lm in everywhere if lm.plane == 2], anatomy[:4], atol=1e-9)


def test_a_moment_without_four_picks_registers_from_the_machine_pose() -> None:
    """The summary counts the landmark starts and their success apart from the fallbacks."""
    base = {"case_id": "c", "sweep": "translation", "level": 0, "level_translation_mm": 80.0,
            "level_rotation_deg": 0.0, "image_source": "test", "volume_label": "test"}  # fmt: skip
    records = [
        {**base, "success": True, "applied": True, "landmark_start": True, "single_success_inplane": False,
         "single_applied": False, "single_landmark_start": True},
        {**base, "success": False, "applied": False, "landmark_start": True, "single_success_inplane": True,
         "single_applied": False, "single_landmark_start": False},
        {**base, "success": False, "applied": False, "landmark_start": False, "single_success_inplane": False,
         "single_applied": False, "single_landmark_start": False},
    ]  # fmt: skip
    summary = capture_summary(records, config={"landmark_pairs": 4, "landmark_noise_mm": 3.0}, wall_seconds=1.0)
    assert summary["biplane"]["landmark_starts"] == 2 and summary["biplane"]["landmark_start_success_rate"] == 0.5
    assert summary["single_plane"]["landmark_starts"] == 1
    assert summary["single_plane"]["landmark_start_success_rate"] == 0.0
    assert summary["biplane"]["success_rate"] == pytest.approx(1 / 3)  # every moment, the fallback's too
    report = capture_report_md(summary, "x.png")
    assert "| from landmarks" in report and "| 2, 50.0 % right | 1, 0.0 % right |" in report
    # a run from the machine-based pose has no such row
    plain = capture_summary([{k: v for k, v in r.items() if "landmark" not in k} for r in records], config={},
                            wall_seconds=1.0)  # fmt: skip
    assert "landmark_starts" not in plain["biplane"] and "| from landmarks" not in capture_report_md(plain, "x.png")


def test_a_moment_with_nothing_to_pick_registers_from_the_machine_pose(monkeypatch: pytest.MonkeyPatch) -> None:
    from registration.studies import landmark_starts

    config = replace(CaptureConfig.quick_config(seed=0), registrations_per_level=1, sweeps=("translation",),
                     landmark_pairs=4)  # fmt: skip
    task = next(t for t in capture_tasks(config) if t.extra["level_translation_mm"] == 0.0)
    monkeypatch.setattr(landmark_starts, "picked_landmarks", lambda *a, **k: [])  # no skull in either field
    record = landmark_starts.run_landmark_case(task.case)
    assert record["landmark_start"] is False and record["landmark_picks"] == [0, 0]
    assert record["single_landmark_start"] is False and record["single_landmark_picks"] == [0]
    assert "start_off_mm" not in record  # no landmark start to measure
    # the machine-based pose is the truth here (no offset): both register right from it
    assert record["success"] and record["single_success_inplane"], record


def test_a_moment_from_landmarks_registers_and_is_checked_against_them() -> None:
    """The quick phantom's 40 mm translation moment from four picks per plane 3 mm off: two views
    register (the landmarks put the start within a few mm; the biplane criterion: 3-D < 1 mm)."""
    from registration.studies.landmark_starts import run_landmark_case

    config = replace(CaptureConfig.quick_config(seed=0), registrations_per_level=1, sweeps=("translation",),
                     landmark_pairs=4)  # fmt: skip
    task = next(t for t in capture_tasks(config) if t.extra["level_translation_mm"] == 40.0)
    record = run_landmark_case(task.case)
    assert record["success"] and record["translation_residual_mm"] < 1.0, record
    # four picks 3 mm off start two views within a few mm of the patient (picked 3 mm off)
    assert record["start_off_mm"] < 6.0 and record["landmark_pairs"] == 4
    assert isinstance(record["single_success_inplane"], bool) and isinstance(record["single_applied"], bool)
    # one view 40 mm from the machine-based pose: never applied (it cannot confirm the depth)
    assert not record["single_applied"] and "cannot confirm the depth" in record["single_withheld_reason"]
    summary = capture_summary([{**record, **task.extra, "case_id": task.case_id}], config={"seed": 0,
                              "landmark_pairs": 4, "landmark_noise_mm": 3.0}, wall_seconds=1.0)  # fmt: skip
    assert summary["biplane"]["runs"] == 1


def test_aimed_moments_keep_the_head_in_both_fields() -> None:
    from registration.core.geometry import apply
    from registration.studies.biplane import AIM_MISS_MM, _offset_motion, case_views, study_volume

    config = replace(CaptureConfig.quick_config(seed=3), registrations_per_level=1, sweeps=("translation",))
    fixed, aimed = capture_tasks(config), capture_tasks(replace(config, aimed=True))
    for a, b in zip(fixed, aimed, strict=True):
        # the same moment (offset, angles, noise), its own case id, the record says which
        assert replace(b.case, aimed=False) == a.case and b.case.aimed and b.extra["aimed"]
        assert b.case_id == a.case_id.replace("-fluoro/", "-fluoro-aimed/")
    task = aimed[-1]  # 80 mm
    case = task.case
    volume = study_volume(case.ct_path, case.phantom_seed, case.volume_format_cm, case.volume_voxels)
    motion = _offset_motion(case)
    head = apply(motion, np.zeros(3))  # the phantom's centre (the unmoved iso-center), moved
    assert np.linalg.norm(head) == pytest.approx(80.0, abs=1e-6)
    views, _ = case_views(case, volume, motion)
    fixed_views, _ = case_views(replace(case, aimed=False), volume, motion)
    for view, still in zip(views, fixed_views, strict=True):
        # aimed: the iso-center is the moved head's centre, missed by the centring's 15 mm
        iso = np.asarray(view.geometry.isocenter_mm)
        assert np.linalg.norm(iso - head) == pytest.approx(AIM_MISS_MM, abs=1e-9)
        np.testing.assert_allclose(iso, views[0].geometry.isocenter_mm, atol=1e-12)  # one iso-center
        np.testing.assert_allclose(still.geometry.isocenter_mm, 0.0, atol=1e-12)
        # the aimed C-arm is the fixed one translated: the iso-center lands where the origin lands
        at = np.asarray(view.geometry.project(iso[None, :]))[0]
        np.testing.assert_allclose(at, np.asarray(still.geometry.project(np.zeros((1, 3))))[0], atol=1e-6)
        # and the head's image itself moves there: its line integrals' centroid is near the detector's
        # centre aimed, far from it in the fixed C-arm (the head moved 80 mm)
        mid = (np.asarray(view.image.shape) - 1) / 2
        off = [np.linalg.norm(np.average(np.indices(im.shape).reshape(2, -1), axis=1, weights=im.ravel()) - mid)
               for im in (view.image, still.image)]  # fmt: skip
        assert off[0] < off[1], off
    summary = capture_summary([], config={"aimed": True}, wall_seconds=0.0)
    assert "both C-arms aimed at the moved head" in capture_report_md(summary, "x.png")


def test_validate_capture_aimed_reaches_the_configuration() -> None:
    import tyro

    from app.cli.capture_commands import capture_config
    from app.cli.options import CaptureStudy

    args = tyro.cli(CaptureStudy, args=["--quick", "--aimed", "--from-landmarks", "4"])
    config = capture_config(args)
    assert config.aimed and config.landmark_pairs == 4 and config.quick
    assert not capture_config(tyro.cli(CaptureStudy, args=["--quick"])).aimed
