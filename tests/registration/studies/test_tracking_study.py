"""validate tracking resumes: each case's outcome is saved as it finishes and reused by a rerun
of the same configuration (the full study's runs take most of an hour on 2 cores). No tracking
runs here: the case runner is replaced by one that counts its calls."""

import json
from dataclasses import asdict, replace
from pathlib import Path

import registration.studies.tracking as tracking
from registration.studies.tracking import TrackingConfig, run_tracking_study


def _fake_case(case, *, options=None, realtime=True, seed=0, log=None) -> dict:
    _fake_case.calls.append(case.name)
    frame = {"frame": 0, "t_s": 0.0, "status": "applied", "path": "capture", "confidence": 0.95,
             "latency_ms": 10.0, "cpu_ms": 5.0, "shown_error_mm": 0.1, "estimate_error_mm": 0.1,
             "right": True, "applied": True}  # fmt: skip
    return {
        "case": case.name,
        "case_config": {**asdict(case), "script": case.script.to_dict()},
        "frames": [frame],
        "skipped": [],
        "frame_count": 1,
        "timeline": {"error_mm": [0.1]},
        "realtime": realtime,
        "seed_seen": seed,
    }


def test_a_rerun_reuses_the_saved_cases_and_a_new_seed_does_not(tmp_path: Path, monkeypatch) -> None:
    _fake_case.calls = []
    monkeypatch.setattr(tracking, "run_tracking_case", _fake_case)
    config = TrackingConfig.full_config(0)
    names = [c.name for c in config.cases]
    first = run_tracking_study(config, out=tmp_path)
    assert _fake_case.calls == names
    assert sorted(p.stem for p in (tmp_path / "cases").glob("*.json")) == sorted(names)
    # an interrupted study: the last case's file lost; the rerun runs only that case
    (tmp_path / "cases" / f"{names[-1]}.json").unlink()
    again = run_tracking_study(config, out=tmp_path)
    assert _fake_case.calls == names + [names[-1]]
    assert again["summary"] == first["summary"]
    # a torn file is not trusted: rerun
    (tmp_path / "cases" / f"{names[0]}.json").write_text('{"key": ')
    run_tracking_study(config, out=tmp_path)
    assert _fake_case.calls[-1] == names[0] and len(_fake_case.calls) == len(names) + 2
    # another seed (or mode) is another study: every case runs again
    other = run_tracking_study(replace(config, seed=1), out=tmp_path)
    assert _fake_case.calls[-len(names) :] == names
    assert {c["seed_seen"] for c in other["cases"]} == {1}
    saved = json.loads((tmp_path / "cases" / f"{names[0]}.json").read_text())
    assert saved["key"]["seed"] == 1 and saved["key"]["realtime"] is True


def test_without_out_nothing_is_saved(tmp_path: Path, monkeypatch) -> None:
    _fake_case.calls = []
    monkeypatch.setattr(tracking, "run_tracking_case", _fake_case)
    run_tracking_study(TrackingConfig.quick_config(0))
    run_tracking_study(TrackingConfig.quick_config(0))
    assert _fake_case.calls == ["run20s", "run20s"]
