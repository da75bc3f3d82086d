"""Simulated annealing: reproducibility, accounting, a known optimum, the stop callback."""

import numpy as np
import pytest

from registration.core.anneal import Schedule, anneal

BOUNDS = np.array([[-30.0, 30.0]] * 2 + [[-15.0, 15.0]] * 3)
OPTIMUM = np.array([7.0, -4.0, 3.0, -2.0, 5.0])


def rugged(x):
    """A quadratic bowl with ripples: local minima everywhere, the global one at OPTIMUM."""
    d = np.asarray(x) - OPTIMUM
    return float(np.sum(d**2) + 4.0 * np.sum(1 - np.cos(2 * d)))


def test_same_seed_same_result():
    a = anneal(rugged, np.zeros(5), BOUNDS, rng=np.random.default_rng(3))
    b = anneal(rugged, np.zeros(5), BOUNDS, rng=np.random.default_rng(3))
    np.testing.assert_array_equal(a.x, b.x)
    assert a.fun == b.fun and a.nfev == b.nfev
    c = anneal(rugged, np.zeros(5), BOUNDS, rng=np.random.default_rng(4))
    assert not np.array_equal(a.x, c.x)


def test_finds_known_optimum():
    schedule = Schedule(step=(4, 4, 2, 2, 2), stages=40, moves_per_stage=40, cooling=0.85)
    res = anneal(rugged, np.zeros(5), BOUNDS, rng=np.random.default_rng(0), schedule=schedule)
    # The ripples have period pi; landing in the right basin means |x - opt| < pi/2 per axis,
    # and the end of the schedule (tiny steps) brings it well inside: 0.3 leaves room for
    # the last steps' size.
    np.testing.assert_allclose(res.x, OPTIMUM, atol=0.3)
    assert res.success


def test_evaluations_counted():
    calls = []

    def cost(x):
        calls.append(1)
        return rugged(x)

    schedule = Schedule(stages=5, moves_per_stage=7, probes=4)
    res = anneal(cost, np.zeros(5), BOUNDS, rng=np.random.default_rng(1), schedule=schedule)
    assert res.nfev == len(calls) == schedule.max_evaluations
    assert res.nit == 5 * 7 == len(res.trace)
    assert all(a >= b for a, b in zip(res.trace, res.trace[1:], strict=False))  # best never worsens


def test_callback_stops_run():
    seen = []

    def callback(state):
        seen.append(state)
        return state.nit >= 10

    res = anneal(rugged, np.zeros(5), BOUNDS, rng=np.random.default_rng(2), callback=callback)
    assert res.nit == 10 and len(seen) == 10
    assert res.message == "stopped by the callback"
    assert seen[-1].temperature > 0 and seen[-1].best_fun <= seen[0].fun


def test_stays_in_bounds():
    res = anneal(lambda x: -float(np.sum(x)), np.zeros(5), BOUNDS, rng=np.random.default_rng(0))
    assert np.all(res.x <= BOUNDS[:, 1]) and np.all(res.x >= BOUNDS[:, 0])


@pytest.mark.parametrize(
    "x0, bounds, message",
    [
        (np.zeros(5), np.zeros((5, 2)), "lower < upper"),
        (np.zeros(5), np.ones((4, 2)), "shape"),
        (np.full(5, 100.0), BOUNDS, "outside"),
    ],
)
def test_bad_arguments(x0, bounds, message):
    with pytest.raises(ValueError, match=message):
        anneal(rugged, x0, bounds, rng=np.random.default_rng(0))


def test_bad_schedule():
    with pytest.raises(ValueError, match="cooling"):
        Schedule(cooling=1.5)


def test_nonfinite_cost_at_start():
    res = anneal(lambda x: float("nan"), np.zeros(5), BOUNDS, rng=np.random.default_rng(0))
    assert not res.success and "not finite" in res.message
