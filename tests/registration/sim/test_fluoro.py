"""Simulated fluoroscopy runs: the patient's script keeps its limits; frames are honest images."""

import numpy as np
import pytest

from registration.core.geometry import CArm, apply, invert_rigid, rotation_angle_deg
from registration.sim.fluoro import RunScript, motion_trajectory, simulate_biplane_run, wire_lengths_mm


def _step(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Translation of the iso-center (mm) and rotation (deg) from pose a to pose b."""
    d = b @ invert_rigid(a)
    return float(np.linalg.norm(apply(d, np.zeros(3)))), rotation_angle_deg(d)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_script_limits(seed):
    script = RunScript(duration_s=40.0, seed=seed, sudden_moves=3, breathing_mm=0.0)
    times, motions, phases = motion_trajectory(script)
    assert len(times) == 600 and np.allclose(np.diff(times), 1 / 15)
    assert phases[0] == "still" and set(phases) <= {"still", "drift", "move", "settled"}
    fps = script.fps
    for n in range(1, len(times)):
        t_mm, r_deg = _step(motions[n - 1], motions[n])
        if phases[n] == "still" and phases[n - 1] == "still":
            assert t_mm < 1e-9 and r_deg < 1e-4  # still means still (acos near 1: ~1e-6 deg rounding)
        if phases[n] == "drift" and phases[n - 1] == "drift":
            assert t_mm * fps <= script.drift_mm_per_s + 1e-9  # drift speed <= 1 mm/s
    # every sudden move: at most 25 mm / 10 deg, within 0.5 s
    starts = [n for n in range(1, len(times)) if phases[n] == "move" and phases[n - 1] != "move"]
    assert len(starts) == 3
    for n in starts:
        end = n
        while phases[end] == "move":
            end += 1
        # frames labelled "move" span the 0.5 s of the move (one frame of sampling slack)
        assert (end - n) / fps <= script.move_s + 1 / fps + 1e-9
        t_mm, r_deg = _step(motions[n - 1], motions[end])
        assert script.min_move_mm * 0.5 < t_mm + 10 * r_deg  # it is a real move
        # rotations turn about the iso-center: the iso-center moves by the translation alone
        assert t_mm <= script.max_move_mm + 1e-6 and r_deg <= script.max_move_deg + 1e-6


def test_still_script_and_breathing():
    _, motions, phases = motion_trajectory(RunScript.still(2.0))
    assert set(phases) == {"still"} and np.allclose(motions, np.eye(4))
    _, motions, _ = motion_trajectory(RunScript(duration_s=8.0, sudden_moves=0, drift=False, breathing_mm=0.3))
    z = motions[:, 2, 3]
    assert 0.25 < z.max() <= 0.3 + 1e-12 and -0.3 - 1e-12 <= z.min() < -0.25  # the oscillation's amplitude
    assert np.allclose(motions[:, :3, :3], np.eye(3))


def test_wire_advances_and_script_checks():
    w = wire_lengths_mm(RunScript(duration_s=4.0))
    assert w[0] == 120.0 and w[-1] == 200.0 and np.all(np.diff(w) > 0)
    with pytest.raises(ValueError, match="duration_s"):
        RunScript(duration_s=0.0)
    with pytest.raises(ValueError, match="too long"):
        RunScript(duration_s=1000.0)


def test_biplane_frames_share_motion_with_own_noise():
    from registration.sim.phantom import make_head_phantom

    anatomy = make_head_phantom(seed=0, contrast=False)
    script = RunScript(duration_s=0.2, sudden_moves=0, drift=False, catheter=False)
    a = CArm.for_format(27.0, pixels=32)
    b = CArm.for_format(27.0, pixels=32, primary_deg=90.0)
    run_a, run_b = simulate_biplane_run(anatomy, [a, b], script, cache=False)
    assert (run_a.plane, run_b.plane) == ("PLANE A", "PLANE B")
    np.testing.assert_array_equal(run_a.truth, run_b.truth)
    np.testing.assert_array_equal(run_a.times_s, run_b.times_s)
    assert len(run_a) == 3 and run_a[1].meta["t_s"] == pytest.approx(1 / 15)
    # a still patient: the frames of one plane differ only by their noise
    d = run_a.images[1] - run_a.images[0]
    assert 0 < np.abs(d[run_a.mask]).mean() < 0.2
    assert not np.allclose(run_a.images[0], run_b.images[0])


def test_glitch_frames_show_no_anatomy():
    from registration.sim.phantom import make_head_phantom

    anatomy = make_head_phantom(seed=0, contrast=False)
    script = RunScript(duration_s=0.2, sudden_moves=0, drift=False, catheter=False, glitch_times_s=(1 / 15,))
    run = simulate_biplane_run(anatomy, [CArm.for_format(27.0, pixels=32)], script, cache=False)[0]
    assert run.phases == ("still", "glitch", "still")
    inside = run.mask
    # the anatomy's frames carry its contrast; the glitch is a flat field with its noise only
    assert run.images[1][inside].std() < 0.1 < run.images[0][inside].std()
