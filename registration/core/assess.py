"""Whether to apply a registration's estimate: one policy for the command line, the app and the
studies (CONVENTIONS §7).

:func:`assess` vetoes an estimate that is not a registration (it ended at the search bounds, or
the measure found no overlap), measures the evidence of the others on the preparation's probe
levels (:meth:`registration.core.preparation.Preparation.probe_renderer`) and applies the
confidence rule (:data:`registration.core.confidence.DEFAULT_RULE`). Callers only format the
:class:`~registration.core.confidence.Assessment` it returns.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike

from registration.core.blas import with_one_blas_thread
from registration.core.confidence import DEFAULT_RULE, Assessment, ConfidenceRule, Evidence
from registration.core.drr import DRRRenderer
from registration.core.geometry import CArm, apply
from registration.core.images import XRayImage
from registration.core.landmarks import LandmarkStart
from registration.core.preparation import Preparation
from registration.core.register import RegistrationResult
from registration.core.register.beam_restart import FLAT_FAR_GAIN
from registration.core.register.result import SINGLE_PLANE_MAX_TURN_DEG, single_plane_turn_deg
from registration.core.volume import Volume

#: A single view's estimate whose search started this far (mm) from the machine-based pose, where
#: the image shift put the patient, is not applied automatically: beyond the clinical offsets the
#: depth along the beam may lie beyond the depth correction's reach, and one view cannot confirm it
#: (docs/decisions/2026-12-04-second-search.md).
SINGLE_PLANE_MAX_SHIFT_MM = 25.0
#: One view's estimate of a volume with a cervical spine is probed on the head alone
#: (:func:`registration.core.skull_spine.spine_pull`) when fewer than this fraction of its capture
#: runs agreed (docs/decisions/2026-12-05-spine-pull.md).
SPINE_PROBE_BELOW_AGREEMENT = 0.5
#: One view's applied estimate looks far along its beam (:func:`registration.core.depth.depth_far`)
#: when fewer than this fraction of its capture runs agreed and its measure's margin lies below
#: ``FAR_PROBE_BELOW_MARGIN`` (a flat peak; docs/decisions/2026-12-07-depth-far.md).
FAR_PROBE_BELOW_AGREEMENT = 0.5
FAR_PROBE_BELOW_MARGIN = 0.0025


def shifted_start_withheld(result: RegistrationResult) -> bool:
    """Whether ``result`` started from the image shift where its estimate cannot be confirmed:
    beyond the search box around the machine-based pose, or one view from a shift of
    ``SINGLE_PLANE_MAX_SHIFT_MM`` or more."""
    shift = getattr(result, "start_shift_mm", 0.0)
    one_view = "tz" not in tuple(getattr(result, "parameters", ("tz",)))  # one view does not search the depth
    return bool(shift) and (getattr(result, "beyond_box", True) or (one_view and shift >= SINGLE_PLANE_MAX_SHIFT_MM))


def depth_corrected(result: RegistrationResult) -> bool:
    """Whether the registration corrected its single-view estimate along the beam (its depth
    correction ran: ``depth_moves_mm``)."""
    return bool(getattr(result, "depth_moves_mm", ()))


def veto(result: RegistrationResult, landmarks: LandmarkStart | None = None) -> str | None:
    """Why ``result`` is not applied whatever its evidence (None: it is assessed): an estimate at
    the search bounds (inputs without information drift there), without a finite measure, one
    view's depth correction ending at its bound, started from the image shift where it cannot be
    confirmed (:func:`shifted_start_withheld`), reached by walking beyond the search box
    (:mod:`registration.core.register.walk`), one view's search run again from far along the beam and
    kept (:mod:`registration.core.register.beam_restart`) or not kept where the far look found the
    measure as high there (``FLAT_FAR_GAIN``), or one view's estimate turning the head more than
    ``SINGLE_PLANE_MAX_TURN_DEG``, or, registered from ``landmarks`` (the start they gave), an
    estimate that moves them further than their picks allow (:meth:`LandmarkStart.veto`) or that a
    second search held near them (:mod:`registration.core.register.landmark_hold`) found."""
    at_bounds = getattr(result, "at_bounds", ())  # a stand-in result may not say
    if at_bounds:
        return f"the estimate ended at the search bounds ({', '.join(at_bounds)})"
    if not math.isfinite(getattr(result, "similarity", 0.0)):
        return "no usable overlap between the DRR and the image"
    if getattr(result, "depth_at_bound", False):
        return (
            f"the depth correction ended at or beyond its bound ({result.depth_tz_mm:+.0f} mm along the beam): the "
            "patient may lie further along the beam than one view can tell; check the estimate by eye before "
            "applying it"
        )
    shift = getattr(result, "start_shift_mm", 0.0)
    if shifted_start_withheld(result):
        return (
            f"the search started {shift:.0f} mm from the machine-based pose, where the image shift put the "
            "patient: check the estimate by eye before applying it"
        )
    hops = getattr(result, "walk_hops", 0)
    if hops:
        return (
            f"the estimate lies beyond the search box around the machine-based pose (the search walked "
            f"{hops} time{'s' if hops > 1 else ''} from the bounds): check it by eye before applying it"
        )
    restart = getattr(result, "beam_restart", None)
    if restart is not None and restart.kept:
        return (
            f"one view's search ran again {abs(restart.tz_mm):.0f} mm along the beam and fit the image better there: "
            "one view cannot confirm a depth this far from the machine-based pose; check the estimate by eye before "
            "applying it"
        )
    if restart is not None and restart.measure_again is not None and restart.far_gain > FLAT_FAR_GAIN:
        return (
            f"the image fits nearly as well {abs(restart.tz_mm):.0f} mm along the beam as at the estimate, "
            "and one view cannot tell which depth is the patient's: check the estimate by eye before applying it"
        )
    turn = single_plane_turn_deg(result)
    if turn is not None and turn > SINGLE_PLANE_MAX_TURN_DEG:
        return (
            f"one view's estimate turns the head {turn:.0f} deg from where the search started, more than one view "
            "can confirm: check it by eye before applying it"
        )
    why = None if landmarks is None else landmarks.veto(result.patient_motion)
    if why is None and getattr(result, "held_by_landmarks", ""):
        return (
            "the images alone led the search away from the landmarks; held near them it found this estimate: "
            "check it by eye before applying it"
        )
    return why


@with_one_blas_thread
def assess(
    result: RegistrationResult,
    views: XRayImage | Sequence[XRayImage],
    preparation: Preparation,
    *,
    single_plane_motion: ArrayLike | None = None,
    rule: ConfidenceRule = DEFAULT_RULE,
    landmarks: LandmarkStart | None = None,
) -> Assessment:
    """The confidence in ``result`` (a registration of ``views`` with ``preparation``), the
    decision and why: :func:`assess_on` the preparation's probe levels."""
    why_not = veto(result, landmarks)
    if why_not is not None:
        return Assessment(0.0, False, why_not, Evidence(veto=why_not))
    renderer = preparation.probe_renderer()
    if renderer.has_level(0):  # the probes' level 0 written for these views before the probes run
        for view in (views,) if isinstance(views, XRayImage) else views:
            renderer.ready(view.geometry, result.patient_motion, level=0)
    from registration.core.depth import scan_level

    decided = assess_on(result, views, preparation.volume, renderer, single_plane_motion=single_plane_motion,
                        rule=rule, landmarks=landmarks, far_level=scan_level(preparation.renderer))  # fmt: skip
    probed, on_seconds = time.perf_counter(), decided.seconds
    pull = _spine_pull(result, views, preparation, decided.evidence, rule)
    if pull is None:
        return decided
    again = rule.assess(replace(decided.evidence, spine_pull_mm=pull.shift_mm))
    return replace(again, depth_probe=decided.depth_probe, depth_scan=decided.depth_scan, depth_far=decided.depth_far,
                   spine_pull=pull, seconds=on_seconds + time.perf_counter() - probed)  # fmt: skip


def _depth_far(
    result: RegistrationResult,
    views: tuple[XRayImage, ...],
    renderer: DRRRenderer,
    volume_level: int,
    decided: Assessment,
    rule: ConfidenceRule,
) -> object | None:
    """One view's look far along its beam (:func:`registration.core.depth.depth_far` at
    ``volume_level``: the depth correction's level of the registration's own volume) for an
    estimate otherwise applied whose capture runs disagreed and whose peak is flat; None
    otherwise (it could not change the decision, or is not read)."""
    one_view = len(views) == 1 and "tz" not in tuple(result.parameters)
    e = decided.evidence
    flat = e.margin is not None and e.margin < FAR_PROBE_BELOW_MARGIN
    disagreed = e.agreement is not None and e.agreement < FAR_PROBE_BELOW_AGREEMENT
    if not (one_view and rule.far_weight and decided.applied and flat and disagreed):
        return None
    from registration.core.depth import depth_far

    return depth_far(renderer, views[0], result.patient_motion, volume_level=volume_level)


def _spine_pull(
    result: RegistrationResult,
    views: XRayImage | Sequence[XRayImage],
    preparation: Preparation,
    evidence: Evidence,
    rule: ConfidenceRule,
) -> object | None:
    """The head-alone probe of one view's estimate (:func:`registration.core.skull_spine.spine_pull`)
    when its capture runs disagreed and the volume is not a region already; None otherwise."""
    views = (views,) if isinstance(views, XRayImage) else tuple(views)
    one_view = len(views) == 1 and "tz" not in tuple(result.parameters)
    agreement = evidence.agreement
    if not (one_view and rule.spine_weight and agreement is not None and agreement < SPINE_PROBE_BELOW_AGREEMENT):
        return None
    if "roi" in preparation.volume.meta:  # a region's estimate: the skull-and-spine check's business
        return None
    from registration.core.skull_spine import spine_pull

    # a first search moving no more than the term's free pull decides it: the second is skipped
    return spine_pull(preparation.prepared, views[0], result.patient_motion, enough_mm=rule.spine_free_mm)


def assess_on(
    result: RegistrationResult,
    views: XRayImage | Sequence[XRayImage],
    volume: Volume,
    renderer: DRRRenderer,
    *,
    single_plane_motion: ArrayLike | None = None,
    rule: ConfidenceRule = DEFAULT_RULE,
    landmarks: LandmarkStart | None = None,
    far_level: int | None = None,
) -> Assessment:
    """:func:`assess` with the probes rendered by ``renderer`` (of ``volume``).

    ``views``: the view, or the views of a biplane registration (margins and edges averaged over
    the planes); ``single_plane_motion``: plane A's own single-view estimate, whose in-plane
    disagreement with the biplane estimate is the planes' agreement. A single-plane
    (five-parameter) result that the registration did not correct along the beam
    (:func:`depth_corrected`) is also scanned (:func:`registration.core.depth.depth_scan`) and probed
    (:func:`~registration.core.depth.depth_probe`) there; both kept in the assessment, the probe's
    pose is not applied. ``far_level``: the level of ``renderer`` one view's far look renders at
    (the depth correction's level of the registration's volume,
    :func:`registration.core.depth.scan_level` of its renderer; None: no far look)."""
    start = time.perf_counter()
    views = (views,) if isinstance(views, XRayImage) else tuple(views)
    why_not = veto(result, landmarks)
    if why_not is not None:
        return Assessment(0.0, False, why_not, Evidence(veto=why_not))
    evidence, probe, scan = _evidence(result, views, volume, renderer, rule)
    if single_plane_motion is not None:
        disagreement = plane_a_disagreement_mm(result.patient_motion, single_plane_motion, views[0].geometry)
        evidence = replace(evidence, plane_disagreement_mm=disagreement)
    decided = rule.assess(evidence)
    far = None if far_level is None else _depth_far(result, views, renderer, far_level, decided, rule)
    if far is not None:
        decided = rule.assess(replace(evidence, depth_far_gain=far.gain))
    return replace(decided, depth_probe=probe, depth_scan=scan, depth_far=far, seconds=time.perf_counter() - start)


def plane_a_disagreement_mm(motion: ArrayLike, single_plane_motion: ArrayLike, geometry: CArm) -> float:
    """How far (mm) a two-view estimate ``motion`` and plane A's own single-view estimate put the
    iso-center apart across plane A's beam (``geometry``): the planes' disagreement."""
    iso = np.asarray(geometry.isocenter_mm)
    shift = apply(np.asarray(motion), iso) - apply(np.asarray(single_plane_motion), iso)
    inplane = shift - (shift @ geometry.direction) * geometry.direction
    return float(np.linalg.norm(inplane))


def _evidence(
    result: RegistrationResult,
    views: tuple[XRayImage, ...],
    volume: Volume,
    renderer: DRRRenderer,
    rule: ConfidenceRule,
) -> tuple[Evidence, object, object]:
    """The evidence of a registration (each view's, combined) and, for one plane's estimate that the
    registration did not correct along the beam, the depth scan and the depth probe (on corrected
    estimates their terms changed no decision: docs/decisions/2026-12-04-confidence-probes.md,
    docs/decisions/2026-12-06-confidence-scan-corrected.md)."""
    from registration.core.tracking import registration_evidence
    from registration.core.tracking.evidence import beam_margin, probe_measure

    motion = np.asarray(result.patient_motion)
    probe = scan = None
    one_view = len(views) == 1 and "tz" not in tuple(result.parameters)
    if one_view:
        from registration.core.depth import SCAN_STRIDE, depth_probe, depth_scan

        corrected = depth_corrected(result)
        if not corrected and (rule.depth_weight or rule.pull_weight):
            probe = depth_probe(renderer, views[0], motion)
        if not corrected:
            # the rule reads the scan only below its free distance: the scan stops once it cannot lie there
            below = rule.scan_free_mm if rule.scan_weight else None
            scan = depth_scan(renderer, views[0], motion, stride=SCAN_STRIDE, below_mm=below)
    probes = [probe_measure(volume, v, motion, renderer) for v in views]
    per_view = [
        registration_evidence(volume, v, motion, renderer=renderer, capture_motions=result.capture_motions,
                              depth=probe, agreement_in_plane=one_view, probe=p)  # single plane: captures keep tz
        for v, p in zip(views, probes, strict=True)
    ]  # fmt: skip
    check = result.rotation_check
    beam = beam_margin(volume, views, motion, renderer=renderer, probes=probes) if rule.beam_weight else None
    evidence = replace(
        per_view[0],
        margin=float(np.mean([e.margin for e in per_view])),
        # calibrated on single-plane registrations only (two views see the out-of-plane
        # rotations of each other's frame)
        rotation_margin=per_view[0].rotation_margin if len(per_view) == 1 else None,
        edges=float(np.mean([e.edges for e in per_view])),
        depth_scan_tz_mm=None if scan is None else float(scan.tz_mm),
        rival_gain=None if check is None or check.rival_gain is None else float(check.rival_gain),
        beam_margin=beam,
        planes_apart=None if len(views) < 2 else float(result.planes_disagreed),
    )
    return evidence, probe, scan
