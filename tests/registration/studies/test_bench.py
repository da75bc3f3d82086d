"""``roadmap3d bench``'s registration block: the checks' price in the same process, per stage."""

from __future__ import annotations

import pytest

from registration.studies.bench import bench_registration, stage_costs


def test_stage_costs_are_medians_per_stage_in_order() -> None:
    runs = [
        {"stages": [{"stage": "a", "drrs": 10, "rays": 100, "seconds": 1.0},
                    {"stage": "b", "drrs": 4, "rays": 40, "seconds": 0.5}]},
        {"stages": [{"stage": "a", "drrs": 20, "rays": 300, "seconds": 3.0}]},
        {"stages": [{"stage": "a", "drrs": 30, "rays": 200, "seconds": 2.0}]},
    ]  # fmt: skip
    assert stage_costs(runs) == [
        {"stage": "a", "runs": 3, "drrs_median": 20.0, "rays_median": 200.0, "seconds_median": 2.0},
        {"stage": "b", "runs": 1, "drrs_median": 4.0, "rays_median": 40.0, "seconds_median": 0.5},
    ]


@pytest.mark.slow  # eight registrations of the phantom
def test_the_checks_price_is_measured_beside_them() -> None:
    reg = bench_registration(rounds=1)
    assert len(reg["runs"]) == 4 and reg["rounds"] == 1
    # Table I (27/27 cm fluoro) succeeds with and without the depth correction and rotation check
    assert reg["success_rate"] == 1.0 and reg["checks_off_success_rate"] == 1.0
    # the checks render more (DRR counts do not depend on the machine's load)
    assert reg["drr_count_median"] > reg["checks_off_drr_count_median"]
    assert reg["checks_ratio"]["min"] <= reg["checks_ratio"]["median"] and reg["checks_off_seconds_median"] > 0
    names = [s["stage"] for s in reg["stages"]]
    assert any(n.startswith("depth correction") for n in names) and any(n.startswith("rotation check") for n in names)
    # every stage renders but the rotation check, which takes the depth correction's screen of a
    # sharp estimate at no cost (Table I's are)
    assert all(s["runs"] == 4 and (s["drrs_median"] > 0 or n.startswith("rotation check"))
               for n, s in zip(names, reg["stages"], strict=True))  # fmt: skip


def test_the_confidence_cost_is_per_registration_ratios() -> None:
    from registration.studies.volume_bench import _confidence_cost

    records = [
        {"seconds": 1.0, "confidence_seconds": 0.2, "applied": True},
        {"seconds": 2.0, "confidence_seconds": 0.2, "applied": False},
        {"seconds": 0.5, "confidence_seconds": 0.25, "applied": True},
    ]
    # per case 0.2, 0.1 and 0.5 of the registration: the median and the least, not a ratio of medians
    assert _confidence_cost(records) == {
        "seconds_median": 0.2,
        "ratio_to_registration_median": 0.2,
        "ratio_to_registration_min": 0.1,
        "applied": 2,
    }


def test_drr_speedups_are_per_round_with_the_least_and_the_minima() -> None:
    from registration.studies.perf import round_ratios

    # round 1: 500 ms against a median of 2 ms (250x); round 2, loaded: 400 against 4 (100x);
    # round 3: 600 against 2 (300x); the minima: 400 ms and 1.5 ms
    ratios = round_ratios([500.0, 400.0, 600.0], [[1.5, 2.0, 3.0], [4.0], [2.0, 2.0]])
    assert ratios == {"speedup": 250.0, "speedup_min": 100.0, "speedup_of_minima": 266.7,
                      "speedup_rounds": [250.0, 100.0, 300.0]}  # fmt: skip
    with pytest.raises(ValueError, match="every round"):
        round_ratios([500.0], [[]])


def test_the_drr_bench_renders_like_the_reference_in_rounds(monkeypatch) -> None:
    from registration.studies import perf

    calls = []
    real = perf.render_reference
    monkeypatch.setattr(perf, "render_reference", lambda *a, **k: calls.append(1) or real(*a, **k))
    (row,) = perf.bench_drr(sizes=((32, 32),), repeats=4, rounds=2)
    # one untimed warm-up call of the reference (its first is the slowest), then one per round
    assert len(calls) == 3
    assert row["rounds"] == 2 and len(row["speedup_rounds"]) == 2
    assert row["speedup_min"] <= row["speedup"] and row["ms_min"] <= row["ms_median"]
    # Joseph's method against trilinear samples at half a voxel: the same line integrals within
    # the interpolation's difference (0.4-0.7 % of the maximum at 64-256 px; coarser at 32)
    assert row["max_rel_error"] < 0.02


def test_the_run_bench_reads_a_run_frame_by_frame_beside_decoding(tmp_path, monkeypatch) -> None:
    # A 6-frame run with a circular field and no geometry tags, as the shared real run has none:
    # the first frame apart, five frames read and decoded, the ratio per frame.
    import numpy as np
    import pydicom

    from registration.studies import run_bench
    from tests.registration.io.test_dicom import xa_file

    yy, xx = np.mgrid[0:128, 0:128]
    circle = np.hypot(yy - 63.5, xx - 63.5) < 60
    rng = np.random.default_rng(3)
    frames = np.where(circle, rng.integers(1500, 3000, (6, 128, 128)), rng.integers(0, 20, (6, 128, 128)))
    path = xa_file(tmp_path / "run.dcm", frames.astype(np.uint16), sid=None, imager_spacing=None)
    ds = pydicom.dcmread(path)
    ds.FrameTime = "66.7"
    ds.save_as(path)
    monkeypatch.setenv("ROADMAP3D_REAL_XA_RUN", str(path))
    out = run_bench.bench_real_run(frames=40)
    assert out["frames"] == 6 and out["pixels"] == [128, 128]
    assert 0 < out["frame_ms_min"] <= out["frame_ms_median"] and 0 < out["decode_ms_min"] <= out["decode_ms_median"]
    assert out["frame_to_decode_median"] > 0 and out["first_frame_ms"] > 0
    assert "dark outside" in out["field"]
    monkeypatch.setenv("ROADMAP3D_REAL_XA_RUN", str(tmp_path / "absent.dcm"))
    monkeypatch.setattr(run_bench, "REAL_RUN_RELATIVE", tmp_path / "nowhere.dcm")
    assert set(run_bench.bench_real_run()) == {"skipped"}
