"""The image-based registration pipeline (the paper's Fig. 2), for one or more views.

The machine-based pose (``initial_motion``, identity when the patient has not moved) is
refined by comparing DRRs of the volume with the X-ray images under gradient difference,
optimised by simulated annealing over offsets in the view frame of the first view
(:mod:`registration.core.search`). One view: the paper's five parameters (tx, ty, rx, ry, rz;
tz is kept, a view cannot see motion along its beam). Two views of the same moment (biplane,
CONVENTIONS.md §6): all six, in plane A's view frame, the measure being the mean of the
views' gradient differences (:mod:`registration.core.problem`).

A registration is a plan of stages (:func:`registration_plan`, :mod:`.plan`, built by
:mod:`.build`): coarse-to-fine annealing levels, each prepared once
(:class:`~registration.core.problem.LevelProblem`) and annealed by one or several capture runs
side by side (:mod:`.stages`); with two views first each plane's own capture (:mod:`.biplane`);
then local polishes; with one view the depth correction (:mod:`.depth`: the high-passed depth
scan estimates tz, the five parameters are polished again at it; the result's
``patient_motion`` holds that tz, ``depth_tz_mm``, which single-view success does not depend on,
CONVENTIONS §4) and the rotation check (:mod:`.rotation_check`). Options: :mod:`.options`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike

from registration.core.blas import with_one_blas_thread
from registration.core.checks import check_in_field, check_information, parameters_at_bounds
from registration.core.drr import DRRRenderer
from registration.core.geometry import invert_rigid, matrix_to_offsets
from registration.core.images import XRayImage
from registration.core.intensity import match_views
from registration.core.landmarks import LandmarkStart
from registration.core.metrics import residuals, vessel_points
from registration.core.problem import support_mask
from registration.core.register.beam_restart import FLAT_FAR_GAIN, beam_restart
from registration.core.register.biplane import (
    CROSS_START_MM,
    PLANE_CAPTURE_ROUNDS,
    PLANES_AGREE_DEG,
    PLANES_AGREE_MM,
    ROTATION_ACROSS_WEIGHT,
    combine_plane_estimates,
    plane_disagreement,
)
from registration.core.register.build import build_plan
from registration.core.register.depth import depth_resolvable
from registration.core.register.fine_polish import fine_polish
from registration.core.register.inputs import (
    Inputs,
    check_inputs,
    coarse_level,
    landmark_wall,
    prepared_renderer,
    prepared_volume,
    with_landmarks,
)
from registration.core.register.landmark_hold import held_by_landmarks
from registration.core.register.monitor import Monitor
from registration.core.register.options import (
    BiplaneOptions,
    DepthOptions,
    Level,
    PolishOptions,
    RegistrationOptions,
    RotationCheckOptions,
    StartOptions,
)
from registration.core.register.plan import PLANES_DISAGREE, Plan, Run, State
from registration.core.register.result import Progress, RegistrationResult, RotationCheck, StageCost
from registration.core.register.rotation_check import RIVAL_DISTINCT_DEG, rotation_check
from registration.core.register.shift_start import look_again, shifted_start
from registration.core.register.translation_first import translation_first
from registration.core.register.walk import walk_from_bounds
from registration.core.search import FIVE_PARAMETERS, SIX_PARAMETERS, SearchSpace
from registration.core.volume import Volume

#: Names of the five parameters of a single-view registration (mm, mm, deg, deg, deg).
PARAMETERS = FIVE_PARAMETERS

__all__ = [
    "CROSS_START_MM",
    "FIVE_PARAMETERS",
    "PARAMETERS",
    "PLANES_AGREE_DEG",
    "PLANES_AGREE_MM",
    "PLANE_CAPTURE_ROUNDS",
    "RIVAL_DISTINCT_DEG",
    "ROTATION_ACROSS_WEIGHT",
    "SIX_PARAMETERS",
    "StageCost",
    "StartOptions",
    "BiplaneOptions",
    "DepthOptions",
    "Inputs",
    "Level",
    "Monitor",
    "Plan",
    "PolishOptions",
    "Progress",
    "RegistrationOptions",
    "RegistrationResult",
    "RotationCheck",
    "RotationCheckOptions",
    "beyond_box",
    "check_inputs",
    "combine_plane_estimates",
    "depth_resolvable",
    "landmark_depth",
    "plane_disagreement",
    "prepared_renderer",
    "prepared_volume",
    "register",
    "registration_plan",
    "rotation_check",
    "support_mask",
]


@with_one_blas_thread
def register(
    volume: Volume,
    views: XRayImage | Sequence[XRayImage],
    *,
    initial_motion: ArrayLike | None = None,
    options: RegistrationOptions | None = None,
    seed: int = 0,
    callback: Callable[[Progress], bool | None] | None = None,
    truth: ArrayLike | None = None,
    vessel_points_mm: ArrayLike | None = None,
    renderer: DRRRenderer | None = None,
    landmarks: LandmarkStart | None = None,
) -> RegistrationResult:
    """Estimate the patient motion that aligns ``volume`` with the X-ray view(s).

    ``views``: one :class:`XRayImage` (image in attenuation line integrals, field mask,
    geometry) or several taken at the same moment (biplane: plane A first; offsets are in its
    view frame); ``initial_motion``: the machine-based pose as a 4x4 patient motion (identity by
    default); ``seed``: of the annealing's random generator (same seed, same result);
    ``callback``: called with a :class:`Progress` at every iteration, True stops; ``truth``: the
    true motion (the result then carries residuals and success); ``vessel_points_mm``: mTRE
    targets in volume world mm; ``renderer``: a :class:`DRRRenderer` of ``volume``, by default
    the volume prepared for the views and the search (:func:`prepared_renderer`, cached; the
    result's ``seconds`` excludes that preparation); ``landmarks``: the start picked landmarks
    gave (:func:`registration.core.landmarks.landmark_start`; ``initial_motion`` defaults to
    its pose): the estimate is fine-polished as one from away from the machine-based pose and,
    with two or more views, the search is held near the poses the landmarks allow
    (``StartOptions.landmark_wall``).
    """
    options = RegistrationOptions() if options is None else options
    _check_arguments(options, seed, callback, landmarks, renderer)
    if vessel_points_mm is not None:
        vessel_points_mm = _checked_points(vessel_points_mm)
    if landmarks is not None:
        options = replace(options, start=replace(options.start, from_landmarks=True))
        if initial_motion is None:
            initial_motion = landmarks.patient_motion
    inputs = with_landmarks(check_inputs(volume, views, initial_motion, truth, renderer, options), landmarks)
    options = landmark_depth(options, inputs)
    wall = landmark_wall(inputs, options)
    for view in inputs.views:
        check_information(inputs.volume, view)  # no edges, no registration (NoInformationError)
        check_in_field(inputs.volume, view, inputs.initial_motion, options.bound_mm)
    start = time.perf_counter()
    inputs, intensity = _matched_intensities(inputs, options)

    def once(
        inputs: Inputs, wall: Callable[[np.ndarray], float] | None = None, options: RegistrationOptions = options
    ) -> RegistrationResult:
        space = SearchSpace.for_views(inputs.views[0].geometry, inputs.initial_motion,
                                      optimize_tz=options.optimizes_tz(len(inputs.views)),
                                      bound_mm=options.bound_mm, bound_deg=options.bound_deg, wall=wall)  # fmt: skip
        run = Run(inputs, options, space, np.random.default_rng(seed), Monitor(space, callback, start))
        state = build_plan(inputs, options).run(State(run, space.start(), space))
        return _result(state, vessel_points_mm, time.perf_counter() - start)

    if not options.start.enabled:
        result = once(inputs)
    else:
        machine = inputs
        inputs, shift_mm = shifted_start(machine, options)
        far = far_start(options, len(inputs.views), shift_mm)
        result = walk_from_bounds(lambda i: once(i, None, far), inputs, options)
        result.start_shift_mm = shift_mm
        if shift_mm:  # the search started from the image shift: its translation-first rival
            result = translation_first(inputs, result, options, callback=callback, start_s=start,
                                       vessel_points_mm=vessel_points_mm)  # fmt: skip
        result = look_again(lambda i: walk_from_bounds(once, i, options), machine, result, options)
        result = beam_restart(lambda i: walk_from_bounds(once, i, options), machine, result, options)
        result = fine_polish(machine, result, options, callback=callback, start_s=start,
                             vessel_points_mm=vessel_points_mm)  # fmt: skip
        if wall is not None:  # from landmarks: searched again near them when the estimate left them

            def held() -> RegistrationResult:
                again = walk_from_bounds(lambda i: once(i, wall), machine, options)
                return fine_polish(machine, again, options, callback=callback, start_s=start,
                                   vessel_points_mm=vessel_points_mm, wall=wall)  # fmt: skip

            result = held_by_landmarks(held, machine, result)
        result.beyond_box = beyond_box(result, machine.initial_motion, options)
    # every search's stages are kept in order: a stage that ran only on the planes' disagreement
    result.planes_disagreed = any(c.stage.endswith(f"({PLANES_DISAGREE[0]})") for c in result.stages)
    result.intensity = intensity
    return result


def _check_arguments(options: object, seed: object, callback: object, landmarks: object, renderer: object) -> None:
    """TypeError or ValueError naming the argument of :func:`register` that is not what it takes."""
    if not isinstance(options, RegistrationOptions):
        hint = " (RegistrationOptions(**options) takes a dict's keywords)" if isinstance(options, dict) else ""
        raise TypeError(f"options must be a RegistrationOptions{hint}, got {type(options).__name__}")
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    if callback is not None and not callable(callback):
        raise TypeError(f"callback must be callable (it is called with a Progress), got {type(callback).__name__}")
    if landmarks is not None and not isinstance(landmarks, LandmarkStart):
        raise TypeError(f"landmarks must be a LandmarkStart (landmark_start(...)), got {type(landmarks).__name__}")
    if renderer is not None and not isinstance(renderer, DRRRenderer):
        raise TypeError(f"renderer must be a DRRRenderer, got {type(renderer).__name__}")


def _checked_points(points: ArrayLike) -> np.ndarray:
    """``vessel_points_mm`` as a finite (N, 3) float array, or ValueError."""
    p = vessel_points(points)
    if not len(p):
        raise ValueError(f"vessel_points_mm must be an (N, 3) array of points in mm, got shape {np.shape(points)}")
    if not np.isfinite(p).all():
        raise ValueError("vessel_points_mm holds NaN or infinite values")
    return p


def far_start(options: RegistrationOptions, n_views: int, shift_mm: float) -> RegistrationOptions:
    """``options`` for one view's search that starts from an image shift of at least
    ``DepthOptions.far_start_mm`` (an estimate the confidence withholds whatever it is): a scan
    along the beam after the capture level too (``scan_after_capture``); ``options`` itself
    otherwise."""
    d = options.depth
    if n_views != 1 or d.far_start_mm is None or not shift_mm or shift_mm < d.far_start_mm:
        return options
    return replace(options, depth=replace(d, scan_after_capture=True))


def around_the_plan(options: RegistrationOptions, n_views: int) -> str:
    """The rules that move the search's start or change its plan on the way (what
    ``register --explain`` prints after the plan): :meth:`StartOptions.describe` and
    :func:`far_start`'s."""
    lines = options.start.describe()
    far = options.depth.far_start_mm
    if n_views == 1 and far is not None and options.start.enabled and options.start.shift_mm is not None:
        lines += f"\none view from an image shift of {far:g} mm or more: a scan along the beam after the capture"
    d = options.depth
    if n_views == 1 and d.enabled and d.restart_beyond_mm is not None and options.start.enabled:
        lines += (
            f"\none view's estimate {d.restart_beyond_mm:g} mm or more from the machine-based pose, fewer than half of "
            f"its capture runs agreeing: a look along the beam to 76 mm and, unless the estimate's depth stands out "
            f"(gain {d.restart_far_gain:g} or less), the search again from the far side; its estimate kept when the "
            f"high-passed measure is {d.restart_gain:g} higher (then withheld for a look); the first estimate "
            f"withheld too when the look's gain is above {FLAT_FAR_GAIN:g}"
        )
    return lines


def landmark_depth(options: RegistrationOptions, inputs: Inputs) -> RegistrationOptions:
    """``options`` with one view's depth correction reaching ``StartOptions.landmark_depth_mm``
    from a landmark start (never less than its own bound); ``options`` itself otherwise."""
    reach = options.start.landmark_depth_mm
    if inputs.landmarks is None or len(inputs.views) != 1 or reach is None or reach <= options.depth.bound_mm:
        return options
    return replace(options, depth=replace(options.depth, bound_mm=float(reach)))


def beyond_box(result: RegistrationResult, machine_motion: np.ndarray, options: RegistrationOptions) -> bool:
    """Whether ``result``'s estimate lies beyond the search box around the machine-based pose
    (its searched translations beyond ``bound_mm`` or a rotation beyond ``bound_deg``)."""
    offsets = matrix_to_offsets(np.asarray(result.patient_motion) @ invert_rigid(machine_motion), result.geometry)
    searched = [i for i, name in enumerate(("tx", "ty", "tz")) if name in result.parameters]
    return bool(np.any(np.abs(offsets[searched]) > options.bound_mm) or np.any(np.abs(offsets[3:]) > options.bound_deg))


def _matched_intensities(inputs: Inputs, options: RegistrationOptions) -> tuple[Inputs, tuple[dict | None, ...]]:
    """The views with their intensities matched to the DRR's as ``options.intensity`` asks
    (:mod:`registration.core.intensity`), and what each assumed (None: as read)."""
    level = coarse_level(inputs.renderer, options, len(inputs.views))
    margin = options.margin_mm(0) or 0.0
    views, infos = match_views(
        inputs.renderer, inputs.views, inputs.initial_motion, options.intensity, level=level,
        support=lambda g: support_mask(inputs.renderer.volume, g, inputs.initial_motion, margin),
    )  # fmt: skip
    if all(i is None for i in infos):
        return inputs, ()
    return replace(inputs, views=views), tuple(None if i is None else i.to_dict() | {"note": i.note()} for i in infos)


def registration_plan(
    volume: Volume,
    views: XRayImage | Sequence[XRayImage],
    *,
    initial_motion: ArrayLike | None = None,
    options: RegistrationOptions | None = None,
    renderer: DRRRenderer | None = None,
    landmarks: LandmarkStart | None = None,
) -> Plan:
    """The plan :func:`register` runs for these inputs (``.describe()``: one line per stage)."""
    options = options or RegistrationOptions()
    inputs = with_landmarks(check_inputs(volume, views, initial_motion, None, renderer, options), landmarks)
    return build_plan(inputs, landmark_depth(options, inputs))


def _result(state: State, vessel_points_mm: ArrayLike | None, seconds: float) -> RegistrationResult:
    run, x = state.run, state.x
    m_est = state.motion
    res = None
    if run.inputs.truth is not None:
        res = residuals(m_est, run.inputs.truth, run.space.frame, vessel_points_mm,
                        optimizes_tz=run.space.optimizes_tz)  # fmt: skip
    return RegistrationResult(
        patient_motion=m_est,
        similarity=-state.f,
        similarity_trace=run.monitor.trace,
        drr_count=run.monitor.drr_count,
        stages=tuple(run.monitor.stages),
        seconds=seconds,
        stopped=run.monitor.stopped,
        offsets=x,
        geometry=run.space.frame,
        volume_label=run.inputs.volume.label,
        residual=res,
        parameters=run.space.names,
        views=tuple(v.geometry for v in run.inputs.views),
        capture_motions=tuple(run.monitor.captures),
        at_bounds=tuple(run.space.names[i] for i in parameters_at_bounds(x, run.space.bounds)),
        depth_tz_mm=state.tz_mm,
        depth_moves_mm=state.depth_moves_mm or (),
        depth_at_bound=state.tz_mm is not None
        and abs(state.tz_mm) > run.options.depth.bound_mm - run.options.depth.scan_step_mm,
        rotation_check=state.check,
    )
