"""One view far from the machine-based pose: the search again from far along the beam.

One view sees the patient's depth only through magnification. Where the patient moved far, the
in-plane search can settle 30-50 mm off along the beam with a wrong in-plane offset and turn
taking up the magnification, and the depth correction, scanning from there, finds its peak near
that estimate: the measure there is well below the truth's, but nothing near it is better. Its
capture runs then disagree. For such an estimate (``DepthOptions.restart_beyond_mm`` or more from
the machine-based pose at the iso-center, fewer than half of its capture runs agreeing) the far
look (:func:`registration.core.depth.depth_far`) finds the side along the beam where the measure
holds up best; unless the estimate's peak stands out (``DepthOptions.restart_far_gain``), the
whole search runs again from the estimate moved there. Its estimate is kept
when the depth scan's high-passed measure (unbiased along the beam) is higher by at least
``DepthOptions.restart_gain``; a kept estimate lies far along the beam from where one view can
confirm the depth, so :func:`registration.core.assess.veto` withholds it for a look. Estimates near
the machine-based pose, or whose capture runs agreed, are untouched and cost nothing more.
Decision record: ``docs/decisions/2026-12-07-beam-restart.md``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from registration.core.confidence import capture_agreement
from registration.core.register.fine_polish import far_from_machine
from registration.core.register.inputs import Inputs, prepared_renderer
from registration.core.register.options import RegistrationOptions
from registration.core.register.result import RegistrationResult, StageCost

#: The search runs again only when fewer than this fraction of the capture runs agreed.
RESTART_BELOW_AGREEMENT = 0.5
#: A search again not kept leaves the first estimate withheld when the far look found the measure
#: there within this much of the estimate's (a flat look: one view cannot tell which depth is the
#: patient's; :func:`registration.core.assess.veto`, docs/decisions/2026-12-08-flat-far-look.md).
FLAT_FAR_GAIN = -0.02


@dataclass(frozen=True)
class BeamRestart:
    """What :func:`beam_restart` did: where along the beam the search ran again from (mm from the
    first estimate, + toward the source), the far look's gain there, both estimates' high-passed
    measure, and whether the second estimate was kept."""

    tz_mm: float
    far_gain: float
    #: None: the search did not run again (the far look found the estimate's depth standing out).
    measure_first: float | None
    measure_again: float | None
    kept: bool

    def to_dict(self) -> dict:
        return {
            "tz_mm": self.tz_mm,
            "far_gain": self.far_gain,
            "measure_first": self.measure_first,
            "measure_again": self.measure_again,
            "kept": self.kept,
        }


def restart_wanted(inputs: Inputs, result: RegistrationResult, options: RegistrationOptions) -> bool:
    """Whether one view's ``result`` is searched again from far along the beam (see the module)."""
    beyond = options.depth.restart_beyond_mm
    if len(inputs.views) != 1 or beyond is None or result.stopped or not options.depth.enabled:
        return False
    if inputs.landmarks is not None or not far_from_machine(result, inputs.initial_motion, beyond):
        return False
    g = inputs.views[0].geometry
    motions = [np.asarray(m, dtype=np.float64) for m in result.capture_motions]
    return capture_agreement(motions, result.patient_motion, g.isocenter_mm, g.direction) < RESTART_BELOW_AGREEMENT


def beam_restart(
    register_once: Callable[[Inputs], RegistrationResult],
    inputs: Inputs,
    result: RegistrationResult,
    options: RegistrationOptions,
) -> RegistrationResult:
    """``result``, or the search run again from far along the beam when that fits better (see the
    module); ``inputs`` start at the machine-based pose. The result keeps both searches' costs
    (the far look as a stage of its own) and, when the search ran again, ``beam_restart``."""
    if not restart_wanted(inputs, result, options):
        return result
    from registration.core.depth import depth_far, depth_scan, scan_level

    renderer = inputs.renderer
    level = scan_level(renderer, options.depth.voxel_mm)
    if float(renderer.level_volume(level).spacing_mm.max()) > options.depth.max_voxel_mm:
        return result  # no level fine enough to tell depths apart (the depth correction did not run either)
    view = inputs.views[0]
    px = options.depth.image_px
    t0, count0 = time.perf_counter(), renderer.count
    far = depth_far(renderer, view, result.patient_motion, volume_level=level, image_px=px)

    def measure(motion: np.ndarray) -> float:
        scan = depth_scan(renderer, view, motion, offsets_mm=(0.0,), image_px=px, volume_level=level)
        return float(scan.similarity[0])

    look = StageCost(
        f"beam restart: far look along the beam ({len(far.scan.offsets_mm)} offsets to "
        f"+-{max(abs(o) for o in far.scan.offsets_mm):g} mm, {px} px)",
        renderer.count - count0,
        far.scan.rays,
        time.perf_counter() - t0,
    )
    if far.gain <= options.depth.restart_far_gain:  # the estimate's depth stands out: not in doubt
        result.beam_restart = BeamRestart(far.far_tz_mm, far.gain, None, None, False)
        result.drr_count += look.drrs
        result.seconds += look.seconds
        result.stages = result.stages + (look,)
        return result
    first = measure(result.patient_motion)
    shift = np.eye(4)
    shift[:3, 3] = -far.far_tz_mm * np.asarray(view.geometry.direction, dtype=np.float64)  # + toward the source
    start = shift @ np.asarray(result.patient_motion, dtype=np.float64)
    again = register_once(replace(inputs, initial_motion=start,
                                  renderer=prepared_renderer(inputs.volume, inputs.views, start, options)))  # fmt: skip
    measured = None if again.stopped else measure(again.patient_motion)
    kept = again if measured is not None and measured >= first + options.depth.restart_gain else result
    kept.beam_restart = BeamRestart(far.far_tz_mm, far.gain, first, measured, kept is again)
    kept.drr_count = result.drr_count + (renderer.count - count0) + again.drr_count
    kept.seconds = max(result.seconds, again.seconds)  # both timed from the registration's start
    kept.similarity_trace = list(result.similarity_trace) + list(again.similarity_trace)
    kept.stages = (result.stages + (look,)
                   + tuple(replace(c, stage=f"beam restart: {c.stage}") for c in again.stages))  # fmt: skip
    return kept
