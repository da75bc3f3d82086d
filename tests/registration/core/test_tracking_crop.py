"""The tracker's crop (issue 13 follow-up): a volume prepared for a run (cropped to what the field
reaches over one capture's search from the initial pose) is prepared again around the applied pose
when a capture from there would search beyond the crop's reach; a crop that holds the whole body,
and a still patient's, never are.

The volume is a tall "CT" of the analytic phantom (head and neck down to 330 mm below the
iso-center, 2 x 2 x 3 mm voxels). With the default capture search (+-30 mm, +-15 deg) even
that is kept whole; the runs here use a narrow search (+-10 mm, +-4 deg) so that the crop is
partial (the neck below ~ -110 mm is cut at a 15 cm format). Frames are formed from the
analytic phantom by the honest image model, not by the renderer that scores them."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from registration.core.drr import DRRRenderer
from registration.core.geometry import CArm, rigid
from registration.core.images import XRayImage
from registration.core.metrics import residuals
from registration.core.prepare import Reach, crop_of, prepare_volume, recrop
from registration.core.register import RegistrationOptions
from registration.core.tracking import TrackingOptions, light_capture, track_run
from registration.core.volume import Volume

PIXELS = 64
FORMAT_CM = 15.0
#: The narrow capture search that leaves this volume's crop partial.
BOUND_MM, BOUND_DEG = 10.0, 4.0
CAPTURE = light_capture(RegistrationOptions(bound_mm=BOUND_MM, bound_deg=BOUND_DEG))
OPTIONS = TrackingOptions(image_px=PIXELS, volume_voxels=64, capture=CAPTURE)
FPS = 15.0


@pytest.fixture(scope="module")
def tall():
    from registration.sim.phantom import make_head_phantom

    anatomy = make_head_phantom(seed=0, contrast=False)
    spacing = np.array([2.0, 2.0, 3.0])
    affine = np.diag([*spacing, 1.0])
    affine[:3, 3] = (-100.0, -110.0, -330.0)
    hu = anatomy.voxelize((151, 111, 101), affine, supersample=1)
    return Volume(hu.astype(np.float32), affine, label="tall phantom CT (test)"), anatomy


def _geometry() -> CArm:
    return CArm.for_format(FORMAT_CM, pixels=PIXELS)


def _prepared(volume: Volume, bound_mm: float = BOUND_MM, bound_deg: float = BOUND_DEG):
    reach = Reach.of_search(bound_mm, bound_deg, translations=2)  # one plane: tx, ty searched
    return prepare_volume(volume, [_geometry()], reach=reach, levels=[1, 2], cache=False)


def _frames(anatomy, motions: list[np.ndarray]) -> list[XRayImage]:
    from registration.sim.xray import simulate_xray

    return [
        simulate_xray(anatomy, _geometry(), motion=m, kind="fluoro", catheter=False, seed=100 + n)
        for n, m in enumerate(motions)
    ]


def _walk(frames_still: int, steps: int, step_mm: float) -> list[np.ndarray]:
    """Still, then a steady drift toward the head (+z: the field sees more of the neck), then still."""
    out = [np.eye(4)] * frames_still
    out += [rigid(None, (0.0, 0.0, step_mm * (k + 1))) for k in range(steps)]
    out += [out[-1]] * frames_still
    return out


def test_recrop_holds_what_a_moved_pose_needs(tall) -> None:
    """Ground truth for the fault: a DRR at a pose 80 mm headward of the start, rendered from the
    crop prepared at the start, misses the neck at the field's lower edge (the whole body's
    levels render it); the crop prepared again around that pose renders it exactly."""
    volume, _ = tall
    prepared = _prepared(volume)
    crop = prepared.crop
    assert crop is not None and crop_of(prepared.renderer) is crop
    assert not crop.complete  # the neck far below the field is cut away
    level = prepared.renderer.level_nearest(64)
    whole = DRRRenderer(volume, levels=[None] + [crop.base.levels[k] for k in (1, 2)])
    g = _geometry()
    mask = g.field_mask()
    moved = rigid(None, (0.0, 0.0, 80.0))
    truth = whole.render(g, moved, level=level)
    old = prepared.renderer.render(g, moved, level=level)
    # measured: 50 % of the largest line integral missing; 15 % of the field's pixels off by > 1 %
    missing = np.abs(truth - old)[mask] / truth[mask].max()
    assert missing.max() > 0.1 and (missing > 0.01).mean() > 0.05
    search = Reach.of_search(BOUND_MM, BOUND_DEG, translations=2)
    mm, deg = crop.margin(moved, search)
    assert mm < 0  # the tracker's test says so before any DRR is rendered
    again = recrop(crop, moved, search)
    # the same grids (slices of the same base levels): the same DRR wherever both hold the anatomy
    np.testing.assert_allclose(again.renderer.render(g, moved, level=level)[mask], truth[mask], rtol=0, atol=1e-5)
    assert again.crop.margin(moved, search) == pytest.approx((0.0, 0.0), abs=1e-9)
    assert again.spacing_mm == prepared.spacing_mm


def test_complete_crop_never_reprepares(tall) -> None:
    """With the default search (+-30 mm, +-15 deg) the crop of this head and neck holds the whole
    body: its margin is infinite and a tracker never prepares it again."""
    volume, _ = tall
    prepared = _prepared(volume, 30.0, 15.0)
    assert prepared.crop.complete
    assert prepared.crop.margin(rigid(None, (0.0, 0.0, 80.0)), Reach.of_search(30.0, 15.0)) == (np.inf, np.inf)


@pytest.mark.slow
def test_drift_past_the_crop_reprepares_and_keeps_tracking(tall) -> None:
    volume, anatomy = tall
    prepared = _prepared(volume)
    # 3 still frames, a 24 mm drift at 0.6 mm per frame (9 mm/s: faster than a patient's <= 1
    # mm/s, to cross the crop's 14 mm reach in a short run), 3 still frames
    motions = _walk(3, 40, 0.6)
    frames = _frames(anatomy, motions)
    times = np.arange(len(frames)) / FPS
    result = track_run(volume, [frames], times, options=OPTIONS, renderer=prepared.renderer, realtime=False, seed=1)
    re = [f for f in result.frames if f.reprepared]
    assert len(re) >= 1 and result.summary()["reprepared"] == len(re)
    for f in re:  # swapped in at the frame after the one that started it (a replay waits for it)
        assert f.crop["started_frame"] == f.frame - 1 and f.crop["box_lo"] != list(prepared.box_lo)
    # the crop followed the patient: at the end, a capture from the applied pose is covered again
    last = result.frames[-1]
    assert last.crop_margin_mm is not None and last.crop_margin_mm > -OPTIONS.reprepare_tolerance_mm
    g = _geometry()
    errors = [residuals(f.estimate, motions[f.frame], g).inplane_mm for f in result.frames if f.status == "applied"]
    assert errors
    # issue 13's targets for applied frames: median <= 0.5 mm, none worse than 2 mm (in-plane at
    # the iso-center, one plane: CONVENTIONS §4)
    assert np.median(errors) <= 0.5 and max(errors) < 2.0, errors
    shown = residuals(last.patient_motion, motions[-1], g)
    assert shown.inplane_mm < 1.0 and shown.rotation_deg < 3.0, shown
    # the same seed gives the same decisions, re-preparations included
    again = track_run(volume, [frames], times, options=OPTIONS, renderer=prepared.renderer, realtime=False, seed=1)
    assert [(f.status, f.reprepared) for f in again.frames] == [(f.status, f.reprepared) for f in result.frames]
    for fa, fb in zip(again.frames, result.frames, strict=True):
        np.testing.assert_array_equal(fa.patient_motion, fb.patient_motion)
    # and with re-preparation off, the crop stays the initial one
    off = track_run(volume, [frames], times, options=replace(OPTIONS, reprepare=False), renderer=prepared.renderer,
                    realtime=False, seed=1)  # fmt: skip
    assert not any(f.reprepared for f in off.frames)


def test_still_run_never_reprepares(tall) -> None:
    volume, anatomy = tall
    prepared = _prepared(volume)
    frames = _frames(anatomy, [np.eye(4)] * 12)
    result = track_run(volume, [frames], np.arange(12) / FPS, options=OPTIONS, renderer=prepared.renderer,
                       realtime=False)  # fmt: skip
    assert [f.status for f in result.frames] == ["unchanged"] * 12
    assert not any(f.reprepared for f in result.frames)
    # the applied pose never moved: the crop leaves a capture from it its whole reach
    assert all(f.crop_margin_mm == pytest.approx(0.0, abs=1e-6) for f in result.frames)


def test_live_run_keeps_processing_frames_while_the_crop_is_prepared(tall, monkeypatch) -> None:
    """Off the critical path: in a live run (frames at their times, skipped when busy) the new
    crop is prepared in a thread; the tracker goes on processing frames with the old one and
    swaps the new one in at the first frame after it is ready."""
    import threading

    import registration.core.tracking.crop_watch as tracking

    volume, anatomy = tall
    prepared = _prepared(volume)
    motions = _walk(3, 12, 0.6)
    frames = _frames(anatomy, motions)
    release, finished = threading.Event(), threading.Event()
    real_recrop = tracking.recrop

    def slow_recrop(*args, **kwargs):  # a preparation that takes until the test releases it
        release.wait(60.0)
        try:
            return real_recrop(*args, **kwargs)
        finally:
            finished.set()

    monkeypatch.setattr(tracking, "recrop", slow_recrop)
    seen: list = []

    def on_frame(est) -> None:
        seen.append(est)
        short = -OPTIONS.reprepare_tolerance_mm
        started = [f for f in seen if f.crop_margin_mm is not None and f.crop_margin_mm < short]
        if started and est.frame == started[0].frame + 3:
            release.set()
            assert finished.wait(60.0)  # ready before the next frame: it is swapped in there

    ticks = iter(np.arange(0.0, 1000.0, 1.0 / FPS))  # every frame "takes" one frame time: none skipped
    result = track_run(volume, [frames], np.arange(len(frames)) / FPS, options=OPTIONS, renderer=prepared.renderer,
                       realtime=True, clock=lambda: next(ticks), on_frame=on_frame, seed=1)  # fmt: skip
    (first,) = [f for f in result.frames if f.reprepared][:1]
    start = first.crop["started_frame"]
    # the three frames after the one that started it were processed with the old crop meanwhile
    assert first.frame == start + 4, (start, first.frame)
    assert [f.frame for f in result.frames if start < f.frame < first.frame] == [start + 1, start + 2, start + 3]
    assert not result.skipped


@pytest.mark.slow
def test_real_ct_crop_holds_the_whole_body() -> None:
    """The shared head CT (23.5 M voxels; skipped without ../shared) as ``roadmap3d track``
    prepares it (register's default search from the initial pose): the crop is the body's box
    whole, so no motion can take the anatomy out of it (a DRR 60 mm and 10 deg away equals the
    whole body's) and a tracker never prepares it again."""
    from registration.core.register import prepared_volume
    from registration.io import dicom
    from registration.studies.runs import axis_angle_matrix
    from registration.studies.volume import find_real_ct

    path = find_real_ct()
    if path is None:
        pytest.skip("the real head CT is not here (../shared/data/real-ct/head-neck-ct)")
    volume = dicom.read_volume(path)
    iso = (247.5, -276.0, -90.0)  # the studies' iso-center inside the skull
    g = replace(CArm.for_format(27.0, pixels=128, primary_deg=20.0, secondary_deg=-10.0), isocenter_mm=iso)
    image = XRayImage(np.zeros((g.rows, g.cols), np.float32), g.field_mask(), g, "fluoro", {})
    prepared = prepared_volume(volume, (image,), np.eye(4), RegistrationOptions())
    crop = prepared.crop
    assert crop is not None and crop.complete, prepared.summary()
    c = np.asarray(iso)
    far = rigid(None, (0.0, 20.0, 60.0)) @ rigid(None, c) @ axis_angle_matrix((1.0, 0.0, 0.0), 10.0) @ rigid(None, -c)
    assert crop.margin(far, Reach.of_search(30.0, 15.0)) == (np.inf, np.inf)
    level = prepared.renderer.level_nearest(64)
    whole = DRRRenderer(volume, levels=[None] + [crop.base.levels[k] for k in range(1, level + 1)])
    small = g.resized(64, 64)
    np.testing.assert_allclose(prepared.renderer.render(small, far, level=level), whole.render(small, far, level=level),
                               rtol=0, atol=1e-5)  # fmt: skip


def test_biplane_recrop_holds_both_planes(tall) -> None:
    """Two planes (frontal and lateral): the crop and its re-preparation hold what both fields
    reach (a capture of two planes searches tz too: three translations)."""
    volume, _ = tall
    a, b = _geometry(), CArm.for_format(FORMAT_CM, pixels=PIXELS, primary_deg=90.0)
    search = Reach.of_search(BOUND_MM, BOUND_DEG, translations=3)
    prepared = prepare_volume(volume, [a, b], reach=search, levels=[1, 2], cache=False)
    crop = prepared.crop
    assert not crop.complete and len(crop.geometries) == 2
    level = prepared.renderer.level_nearest(64)
    whole = DRRRenderer(volume, levels=[None] + [crop.base.levels[k] for k in (1, 2)])
    moved = rigid(None, (0.0, 0.0, 80.0))
    again = recrop(crop, moved, search)
    for g in (a, b):
        mask = g.field_mask()
        truth = whole.render(g, moved, level=level)[mask]
        assert np.abs(truth - prepared.renderer.render(g, moved, level=level)[mask]).max() > 0.1 * truth.max()
        np.testing.assert_allclose(again.renderer.render(g, moved, level=level)[mask], truth, rtol=0, atol=1e-5)
