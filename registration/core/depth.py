"""The depth probe: does a single-plane estimate hold when the volume may move along the beam?

A single-plane registration searches the paper's five parameters and keeps tz (the offset along
the beam) where the initial pose put it (CONVENTIONS §4). A wrong tz is a wrong magnification:
the anatomy's projection grows or shrinks about the central ray (by ~2.5 % for 20 mm at the
iso-center of a 750 mm source distance), and the in-plane fit follows it part of the way (the
quick clinical study's two applied misses, 1.04 and 1.09 mm in-plane, had 17-20 mm out-of-plane
offsets). The gradient difference does see the magnification: released along the beam, a local
six-parameter polish from the estimate finds a better pose when tz is wrong.

:func:`depth_probe` runs that polish (Powell, :func:`registration.core.anneal.polish`, tz
bounded by ``bound_mm``: the prior that the initial pose is within the clinical offsets) at the
level of the registration's own polish, and reports how far the pose moves **in the plane**
(``shift_mm``, at the iso-center: the part of the estimate the unknown magnification makes
uncertain) and along the beam (``tz_mm``), and what the measure gained. The confidence
(:mod:`registration.core.confidence`, evidence ``depth_shift_mm``) withholds an estimate whose
in-plane part moves by more than a fraction of a millimetre once the volume may move along the
beam. The probe never replaces the estimate: its pose (``motion``) is reported for the
studies, which measure it beside the five-parameter result.

:func:`depth_scan` asks the narrower question where along the beam the measure peaks with the
rest of the estimate held (evidence ``depth_scan_tz_mm``), on the level-0 frame and DRR with
their low spatial frequencies removed (:func:`high_pass`). On the clinical study's FDK volumes
the plain measure peaks +5 to +20 mm toward the source even at the true pose
(docs/validation/clinical-200/scale_check.md), and it is not a resolution mismatch: blurring the
frame (or the DRR) moves that peak further toward the source, at every level. The bias lives in
the scales coarser than the reconstruction's voxel, where the truncated FDK volume (missing the
anatomy outside its cylinder, cupping) differs from the frame: with those scales removed the
peak at the true pose lies within 0-5 mm of it at level 0 (docs/validation/clinical-s6,
depth_scan.md). Released in the plane as well (the probe) the optimum drifts again: the
in-plane fit absorbs the magnification (0.05 mm per mm of tz, nearly the same for every
estimate), so only the held scan carries the information.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from registration.core.anneal import polish
from registration.core.drr import DRRRenderer
from registration.core.geometry import apply, check_rigid, invert_rigid, rotation_angle_deg
from registration.core.images import XRayImage
from registration.core.problem import LevelProblem
from registration.core.search import SIX_PARAMETERS, SearchSpace
from registration.core.similarity import GradientDifference

Array = NDArray[np.float64]

#: The probe's defaults: the registration's polish level (128 px, volume level 1), its support
#: margin, tz within the clinical offsets (25 mm), rotations within 5 degrees of the estimate,
#: Powell's first steps (tz's coarse: the measure changes slowly along the beam) and budget.
DEPTH_IMAGE_PX = 128
DEPTH_VOLUME_LEVEL = 1
DEPTH_MARGIN_MM = 4.0
DEPTH_BOUND_MM = 25.0
DEPTH_BOUND_DEG = 5.0
DEPTH_STEPS = (0.5, 0.5, 4.0, 0.3, 0.3, 0.3)
DEPTH_EVALUATIONS = 120
#: The scan: tz offsets from the estimate (mm, + toward the source), at level 0.
SCAN_TZ_MM = tuple(float(v) for v in np.arange(-24.0, 24.1, 2.0))
SCAN_IMAGE_PX = 256
SCAN_VOLUME_LEVEL = 0
#: The confidence's scan evaluates every sixth offset (12 mm apart), then climbs offset by offset
#: to the peak (:func:`depth_scan`'s ``stride``): the same peak as the full scan where the
#: measure has one (docs/decisions/2026-12-05-scan-stride.md).
SCAN_STRIDE = 6
#: The far look (:func:`depth_far`): offsets within ``FAR_NEAR_MM`` of the estimate, 8 mm apart,
#: and beyond it, 12 mm apart out to 76 mm either way (mm, + toward the source), at 128 px.
FAR_NEAR_MM = 24.0
_FAR_SIDE_MM = (28.0, 40.0, 52.0, 64.0, 76.0)
FAR_OFFSETS_MM = tuple(sorted((-24.0, -16.0, -8.0, 0.0, 8.0, 16.0, 24.0, *_FAR_SIDE_MM, *(-v for v in _FAR_SIDE_MM))))
FAR_IMAGE_PX = 128
#: The depth-corrected registration's scan (:func:`scan_level`): the prepared level whose voxel
#: is nearest this size (mm, in ratio), compared at about the polish's image size.
CORRECTION_VOXEL_MM = 1.0


def scan_level(renderer: DRRRenderer, voxel_mm: float = CORRECTION_VOXEL_MM) -> int:
    """The prepared level of ``renderer`` whose voxel (its largest spacing) is nearest
    ``voxel_mm`` in ratio (ties: the finer): a scan level chosen in millimetres, not by index.
    On the clinical study's 128^3 FDK volumes (level 0 of 1.2-1.4 mm voxels, prepared for one
    view's correction: :func:`registration.core.register.inputs.scans_level0`) that is level 0,
    where the high-passed scan was measured to see the offset
    (docs/validation/clinical-s6/depth_scan.md); on a CT or a 256^3 3DRA prepared by
    :func:`registration.core.prepare.prepare_volume` (levels 1 and 2 only) it is the polish's
    level 1 (1.2-2 mm), and rendering a 23.5 M-voxel level 0 is never asked for."""
    if not voxel_mm > 0:
        raise ValueError(f"voxel_mm must be positive, got {voxel_mm}")
    sizes = {
        k: float(renderer.level_volume(k).spacing_mm.max()) for k in range(renderer.n_levels) if renderer.has_level(k)
    }
    return min(sizes, key=lambda k: (abs(np.log(sizes[k] / voxel_mm)), k))


@dataclass(frozen=True)
class DepthProbe:
    """The outcome of :func:`depth_probe` (all at the frame view's iso-center)."""

    #: The six-parameter pose the probe found (4x4 patient motion).
    motion: Array
    #: In-plane shift of the iso-center from the estimate to the probe's pose (mm).
    shift_mm: float
    #: Its move along the beam (mm, signed: + toward the source, the view frame's z).
    tz_mm: float
    #: Rotation between the two poses (deg).
    rotation_deg: float
    #: The measure at the estimate and at the probe's pose, and the relative gain.
    similarity: float
    probe_similarity: float
    gain_relative: float
    drr_count: int

    def to_dict(self) -> dict:
        return {
            "motion": np.asarray(self.motion).tolist(),
            "shift_mm": self.shift_mm,
            "tz_mm": self.tz_mm,
            "rotation_deg": self.rotation_deg,
            "similarity": self.similarity,
            "probe_similarity": self.probe_similarity,
            "gain_relative": self.gain_relative,
            "drr_count": self.drr_count,
        }


def depth_probe(
    renderer: DRRRenderer,
    xray: XRayImage,
    motion: Array,
    *,
    image_px: int = DEPTH_IMAGE_PX,
    volume_level: int = DEPTH_VOLUME_LEVEL,
    margin_mm: float | None = DEPTH_MARGIN_MM,
    bound_mm: float = DEPTH_BOUND_MM,
    bound_deg: float = DEPTH_BOUND_DEG,
    evaluations: int = DEPTH_EVALUATIONS,
) -> DepthProbe:
    """Polish ``motion`` (a single-plane estimate for ``xray``) over all six parameters, tz
    included, and report how far it moves (see the module's docstring). Deterministic."""
    m = check_rigid(motion, name="motion")
    if not bound_mm > 0 or not bound_deg > 0:
        raise ValueError("bound_mm and bound_deg must be positive")
    g = xray.geometry
    count0 = renderer.count
    problem = LevelProblem.prepare(
        renderer, (xray,), image_px=image_px, volume_level=volume_level, motion=m, margin_mm=margin_mm
    )
    evaluate = problem.evaluator()
    space = SearchSpace(g, m, SIX_PARAMETERS, bound_mm, bound_deg)
    f0 = evaluate.similarity(m)
    result = polish(
        lambda x: -evaluate.similarity(space.motion(x)),
        space.start(),
        space.bounds,
        step=DEPTH_STEPS,
        max_evaluations=evaluations,
    )
    probe = space.motion(result.x) if -result.fun > f0 else m
    f1 = max(-result.fun, f0)
    iso = np.asarray(g.isocenter_mm, dtype=np.float64)
    err = probe @ invert_rigid(m)
    shift = apply(err, iso) - iso
    along = float(shift @ g.direction)
    inplane = shift - along * g.direction
    return DepthProbe(
        motion=probe,
        shift_mm=float(np.linalg.norm(inplane)),
        tz_mm=-along,  # the view frame's z is -d (toward the source)
        rotation_deg=rotation_angle_deg(err),
        similarity=float(f0),
        probe_similarity=float(f1),
        gain_relative=float((f1 - f0) / max(abs(f0), 1e-12)),
        drr_count=renderer.count - count0,
    )


def smooth(image: NDArray, sigma_px: float) -> NDArray[np.float64]:
    """``image`` (float64) smoothed by a Gaussian of ``sigma_px``: scipy's ``gaussian_filter``
    (its kernel out to 4 sigma, edges reflected), computed by OpenCV, about three times faster
    (the same values to 1e-15)."""
    import cv2

    radius = int(4.0 * float(sigma_px) + 0.5)
    size = 2 * radius + 1
    return cv2.GaussianBlur(np.asarray(image, dtype=np.float64), (size, size), sigmaX=float(sigma_px),
                            sigmaY=float(sigma_px), borderType=cv2.BORDER_REFLECT)  # fmt: skip


def high_pass(image: NDArray, mask: NDArray[np.bool_], sigma_px: float, weight: NDArray | None = None) -> NDArray:
    """``image`` less its Gaussian-smoothed self (``sigma_px``), both inside ``mask`` only: the
    smoothing is normalised by the smoothed mask (``weight``, computed when not given), so the
    field's edge does not leak in. Zero outside the mask."""
    m = np.asarray(mask, dtype=bool)
    if weight is None:
        weight = smooth(m.astype(np.float64), sigma_px)
    smoothed = smooth(np.where(m, image, 0.0), sigma_px)
    return np.where(m, image - smoothed / np.maximum(weight, 1e-6), 0.0)


@dataclass(frozen=True)
class DepthScan:
    """The outcome of :func:`depth_scan` (at the frame view's iso-center)."""

    #: Where along the beam the high-passed measure peaks, from the estimate (mm, + toward the
    #: source; parabola through the best offset and its neighbours).
    tz_mm: float
    #: The high-pass scale (level-0 pixels) and the offsets scanned with their measure.
    sigma_px: float
    offsets_mm: tuple[float, ...]
    similarity: tuple[float, ...]
    drr_count: int
    #: The scan stopped once its peak could no longer lie below the offset asked about: ``tz_mm``
    #: is then the best offset evaluated, and the peak lies no more than half a step below it.
    stopped: bool = False
    #: DRR pixels (rays) the scan rendered.
    rays: int = 0

    def to_dict(self) -> dict:
        return {
            "tz_mm": self.tz_mm,
            "stopped": self.stopped,
            "sigma_px": self.sigma_px,
            "offsets_mm": list(self.offsets_mm),
            "similarity": list(self.similarity),
            "drr_count": self.drr_count,
        }


def depth_scan(
    renderer: DRRRenderer,
    xray: XRayImage,
    motion: Array,
    *,
    offsets_mm: tuple[float, ...] = SCAN_TZ_MM,
    image_px: int = SCAN_IMAGE_PX,
    volume_level: int = SCAN_VOLUME_LEVEL,
    margin_mm: float | None = DEPTH_MARGIN_MM,
    sigma_px: float | None = None,
    pixel_at_iso_mm: float | None = None,
    stride: int = 1,
    below_mm: float | None = None,
) -> DepthScan:
    """The high-passed gradient difference of ``xray`` at ``motion`` moved along the beam by each
    of ``offsets_mm`` (nothing else moves), and where it peaks (see the module's docstring).

    ``sigma_px``: the high-pass scale; by default the volume level's voxel as the detector sees
    it at the iso-center, in the level's pixels (2.96 px for the clinical study's 22 cm patient:
    1.72 mm voxels, magnification 1.48, 0.86 mm pixels): the scales coarser than what the
    volume resolves are removed from both images. ``pixel_at_iso_mm``: compare at the block
    size whose pixel at the iso-center is nearest this without being coarser
    (:func:`registration.core.problem.matched_factor`) instead of ``image_px``'s rule.
    ``stride``: evaluate every ``stride``-th offset (the last too), then climb offset by offset
    from the best until it has both neighbours (the offsets and values kept are those evaluated).
    ``below_mm``: only a peak below it is wanted (the confidence reads no other): the scan stops
    once the strided scan's peak can no longer lie there (``stopped``), and is that scan's
    otherwise (:func:`_scanned`). Deterministic."""
    m = check_rigid(motion, name="motion")
    g = xray.geometry
    count0 = renderer.count
    problem = LevelProblem.prepare(
        renderer,
        (xray,),
        image_px=image_px,
        volume_level=volume_level,
        motion=m,
        margin_mm=margin_mm,
        pixel_at_iso_mm=pixel_at_iso_mm,
    )
    view = problem.views[0]
    if sigma_px is None:
        voxel_mm = float(renderer.level_volume(problem.volume_level).spacing_mm.max())
        sigma_px = voxel_mm * view.geometry.magnification / max(view.geometry.pixel_mm)
    if not sigma_px > 0:
        raise ValueError("sigma_px must be positive")
    weight = smooth(view.mask.astype(np.float64), sigma_px)
    measure = GradientDifference(high_pass(view.image, view.mask, sigma_px, weight), view.mask)
    out = np.empty((view.geometry.rows, view.geometry.cols), np.float32)
    d = np.asarray(g.direction, dtype=np.float64)

    def at(dz: float) -> float:
        shift = np.eye(4)
        shift[:3, 3] = -float(dz) * d  # + toward the source: against the beam's direction
        drr = renderer.render(view.geometry, shift @ m, level=problem.volume_level, mask=view.mask, out=out)
        return float(measure(high_pass(drr, view.mask, sigma_px, weight)))

    offsets_mm, values, stopped = _scanned(tuple(float(o) for o in offsets_mm), at, stride, below_mm)
    return DepthScan(
        tz_mm=scan_peak_mm(offsets_mm, values, stopped),
        sigma_px=float(sigma_px),
        offsets_mm=tuple(float(o) for o in offsets_mm),
        similarity=tuple(values),
        drr_count=renderer.count - count0,
        stopped=stopped,
        rays=(renderer.count - count0) * int(view.mask.sum()),
    )


@dataclass(frozen=True)
class DepthFar:
    """The outcome of :func:`depth_far` (at the frame view's iso-center)."""

    #: The best measure beyond ``near_mm`` of the estimate less the best within it (near 0 or
    #: above: the measure does not tell the estimate's depth from one far along the beam).
    gain: float
    #: Where the far best lies (mm from the estimate, + toward the source).
    far_tz_mm: float
    near_mm: float
    scan: DepthScan

    def to_dict(self) -> dict:
        return {"gain": self.gain, "far_tz_mm": self.far_tz_mm, "near_mm": self.near_mm, **self.scan.to_dict()}


def depth_far(
    renderer: DRRRenderer,
    xray: XRayImage,
    motion: Array,
    *,
    volume_level: int,
    offsets_mm: tuple[float, ...] = FAR_OFFSETS_MM,
    near_mm: float = FAR_NEAR_MM,
    image_px: int = FAR_IMAGE_PX,
) -> DepthFar:
    """Whether one view's measure tells the estimate ``motion`` from poses far along its beam:
    :func:`depth_scan`'s high-passed measure at every offset of ``offsets_mm`` (nothing else
    moves), the best beyond ``near_mm`` less the best within. A right estimate's peak stands
    out (-0.01 and below); where the in-plane fit absorbed a depth 50-90 mm off, the measure is
    as high far along the beam, often toward the truth (docs/decisions/2026-12-07-depth-far.md)."""
    offsets = tuple(sorted(float(o) for o in offsets_mm))
    o = np.asarray(offsets)
    near = np.abs(o) <= near_mm
    if near.all() or not near.any():
        raise ValueError(f"offsets_mm must lie both within and beyond +-{near_mm:g} mm")
    scan = depth_scan(renderer, xray, motion, offsets_mm=offsets, image_px=image_px, volume_level=volume_level)
    values = np.asarray(scan.similarity)
    far = int(np.flatnonzero(~near)[np.argmax(values[~near])])
    gain = float(values[far] - values[near].max())
    return DepthFar(gain=gain, far_tz_mm=float(o[far]), near_mm=float(near_mm), scan=scan)


def scan_peak_mm(offsets_mm: tuple[float, ...], values: list[float], stopped: bool = False) -> float:
    """Where a scan's ``values`` at ``offsets_mm`` peak: the best offset, moved by the parabola
    through it and its neighbours (at most half a step either way); a stopped scan's best offset
    as it is."""
    v = np.asarray(values)
    i = int(np.argmax(v))
    tz = float(offsets_mm[i])
    if 0 < i < len(v) - 1 and not stopped:
        curv = v[i - 1] - 2.0 * v[i] + v[i + 1]
        if curv < 0:
            h = 0.5 * (offsets_mm[i + 1] - offsets_mm[i - 1])
            tz += float(np.clip(0.5 * (v[i - 1] - v[i + 1]) / curv, -0.5, 0.5) * h)
    return tz


def _scanned(
    offsets: tuple[float, ...],
    at,  # noqa: ANN001
    stride: int,
    below_mm: float | None = None,
) -> tuple[tuple[float, ...], list[float], bool]:
    """``at`` evaluated on ``offsets`` (``stride`` 1), or on every ``stride``-th offset (the ends
    included) and then offset by offset uphill from the best until the best has both neighbours
    evaluated: the same peak and parabola as the full scan when the measure has one peak there.

    ``below_mm`` (ascending ``offsets``): only whether the peak lies below ``below_mm`` is wanted,
    and the peak itself when it does. The samples that could lead there come first, the climb
    tries its lower neighbour first, and the scan stops as soon as the strided scan's peak can no
    longer lie below ``below_mm`` (its parabola included); when it does lie below, the result is
    the strided scan's, bit for bit. Returns the offsets whose values decide the peak (in order),
    their values, and whether the scan stopped early (then only the best of them is meaningful)."""
    if int(stride) != stride or stride < 1:
        raise ValueError(f"stride must be a positive integer, got {stride}")
    n = len(offsets)
    cache: dict[int, float] = {}

    def value(k: int) -> float:
        if k not in cache:
            cache[k] = at(offsets[k])
        return cache[k]

    def best_of(seen: dict[int, float]) -> int:
        return max(seen, key=lambda k: (seen[k], -k))

    coarse = sorted({*range(0, n, stride), n - 1})
    if below_mm is not None:
        if any(b <= a for a, b in zip(offsets, offsets[1:], strict=False)):
            raise ValueError("below_mm needs ascending offsets")
        last_low = _last_low(offsets, below_mm)
        # coarse samples from which a climb could end at or below last_low (their lower
        # neighbours are the nearest samples under them)
        lower = [c for i, c in enumerate(coarse) if (coarse[i - 1] + 1 if i else 0) <= last_low]
        if lower != coarse:
            seen = {c: value(c) for c in lower}
            while True:
                best = best_of(seen)
                down, up = best - 1, best + 1
                if down >= 0 and down not in seen:
                    seen[down] = value(down)
                    if best_of(seen) != best:
                        continue
                # the climb only rises from here: it can end below only from a low best
                if best > last_low:
                    keys = sorted(seen)
                    return tuple(offsets[k] for k in keys), [seen[k] for k in keys], True
                if up < n and up not in seen:
                    seen[up] = value(up)
                    continue
                break
            # the peak of the lower samples lies below: the strided scan decides (its best
            # sample may lie higher), with the values already rendered
    seen = {c: value(c) for c in coarse}
    while True:
        best = best_of(seen)
        missing = [k for k in (best - 1, best + 1) if 0 <= k < n and k not in seen]
        if not missing:
            break
        for k in missing:
            seen[k] = value(k)
    keys = sorted(seen)
    return tuple(offsets[k] for k in keys), [seen[k] for k in keys], False


def _last_low(offsets: tuple[float, ...], below_mm: float) -> int:
    """The last index whose peak (its parabola may move it half a step either way) could lie
    below ``below_mm``; -1 when none can."""
    n = len(offsets)
    last = -1
    for k in range(n):
        half = 0.25 * (offsets[k + 1] - offsets[k - 1]) if 0 < k < n - 1 else 0.0
        if offsets[k] - half < below_mm:
            last = k
    return last
