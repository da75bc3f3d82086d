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
