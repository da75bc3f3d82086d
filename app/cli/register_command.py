"""``roadmap3d register``: a volume file to an X-ray file (or a biplane pair: two files of one
moment) or, with ``--pacs``, to series on a PACS (:func:`app.cli.net_commands.run_register_pacs`).

One run reads and checks its inputs (:func:`read_inputs`), registers (:func:`register_inputs`:
the region, the preparation, the plan, the optional geometry estimate, the skull-and-spine check
and the confidence), says what it found, and writes what was asked (:func:`write_outputs`). Every
output path is checked before the registration runs; files are written through temporary files.
"""

from __future__ import annotations

import os
import sys
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from app.cli.commands import (
    _format_offsets,
    _say,
    _show_warnings,
    _Stopwatch,
    check_writable,
    confidence_renderer,
    kernels_to_compile,
    parse_isocenter,
    prepare_for_registration,
    read_motion,
)
from app.cli.configs import Register
from app.cli.errors import UserError
from registration.io import dicom
from registration.io.isocenter import from_volume, resolve_isocenter
from registration.io.pacs_settings import ENV_URL
from registration.io.transforms import ITK_SUFFIXES, write_itk_transform


def run_register(options: Register) -> int:
    """``roadmap3d register``: from files, or with ``--pacs`` from a PACS."""
    if options.pacs is not None or os.environ.get(ENV_URL) and (options.study or options.store):
        if options.confidence or options.report is not None:
            raise UserError("--confidence and --report work on files only (not with --pacs) for now")
        if len(options.image) != 1:
            raise UserError(f"--pacs registers one image series; got {len(options.image)} --image values")
        from app.cli.net_commands import run_register_pacs

        return run_register_pacs(options, register_files)
    if options.study or options.store or options.ca_bundle:
        raise UserError("--study, --store and --ca-bundle need --pacs URL")
    if len(options.image) not in (1, 2):
        raise UserError(
            f"--image takes one X-ray file, or two (plane A and plane B of one moment); got {len(options.image)}"
        )
    return register_files(options)


def check_options(options: Register) -> None:
    """Refuse inconsistent options and unwritable outputs before any file is read."""
    from app.cli.report_commands import check_report_folder

    check_report_folder(options.report)
    n = len(options.image)
    if n not in (1, 2):
        raise ValueError(f"one X-ray image, or two (plane A and plane B of one moment), got {n}")
    if options.estimate_geometry and n != 2:
        raise ValueError(
            "--estimate-geometry needs two planes: one view cannot tell its source-image distance from the depth "
            "(give --sid-mm when it is known)"
        )
    if options.isocenter is not None and not from_volume(options.isocenter):
        parse_isocenter(options.isocenter)  # a bad value is refused before any file is read
    if options.geometry and len(options.geometry) != n:
        raise ValueError(f"--geometry: one side file per --image ({n}), got {len(options.geometry)}")
    if options.image_mask and len(options.image_mask) != n:
        raise ValueError(f"--image-mask: one mask per --image ({n}), got {len(options.image_mask)}")
    if options.out_transform is not None and Path(options.out_transform).suffix.lower() not in ITK_SUFFIXES:
        raise ValueError(
            f"{options.out_transform}: --out-transform takes an ITK transform file ({', '.join(ITK_SUFFIXES)})"
        )
    targets = (
        (options.out, "--out", "JSON"),
        (options.out_dicom, "--out-dicom", "DICOM"),
        (options.out_transform, "--out-transform", "ITK"),
    )
    for target, flag, kind in targets:
        if target is not None and Path(target).is_dir():
            raise ValueError(f"{target}: is a folder; {flag} takes a {kind} file name")
        check_writable(target, flag)  # before the registration runs, not after


@dataclass
class Inputs:
    """What a registration reads: the volume (``whole``; ``volume`` is the region it follows),
    the views, the iso-center, the start (from ``--initial-motion`` or ``--landmarks``) and the truth."""

    whole: Any
    volume: Any
    region: Any
    views: list
    #: The views with their whole fields (``views`` without the region's narrowing): the skull-and-spine check's.
    full_views: list
    isocenter: tuple[float, float, float]
    isocenter_from: str
    initial_motion: np.ndarray | None = None
    landmark_start: Any = None
    truth: np.ndarray | None = None
    vessel_points: np.ndarray | None = None
    #: What the region left out of each view's field (:class:`registration.core.roi.RegionField`).
    region_fields: list = field(default_factory=list)


#: How ``register`` reads a volume (a worker reads through its memory of recent volumes); None:
#: :func:`registration.io.volume_cache.read_volume_cached` (a DICOM folder decoded once, kept on disk).
_volume_reader: list[Any] = [None]


def use_volume_reader(read: Any) -> None:
    """Have ``register`` read volumes with ``read`` (a path -> a volume, as :func:`dicom.read_volume`)."""
    _volume_reader[:] = [read]


def _read_volume(options: Register) -> Any:
    read = _volume_reader[0]
    if read is not None:
        return read(options.volume)
    from registration.io.volume_cache import read_volume_cached

    return read_volume_cached(options.volume, cache=not options.no_cache)


def _region_of_interest(vol: Any, roi: str, roi_mask: Path | None, *, cache: bool) -> Any:
    """The region the registration follows (None: the whole volume); a found cranium is kept in
    the preparation cache with the volume's preparation."""
    if roi_mask is not None:
        from registration.io.roi_masks import read_roi_mask

        return read_roi_mask(roi_mask, vol)
    from registration.core.roi import REGIONS, followed_region
    from registration.io.cache import PreparationCache

    if roi not in REGIONS:
        raise ValueError(f"--roi must be one of {', '.join(REGIONS)}, got {roi!r}")
    return followed_region(vol, roi, store=PreparationCache() if cache else None)


def _read_views(options: Register, iso: tuple[float, float, float]) -> list:
    """The X-ray image(s) as the engine's views; a biplane pair ordered plane A, plane B."""
    n = len(options.image)
    sides = list(options.geometry) or [None] * n
    masks = list(options.image_mask) or [None] * n
    views = [
        dicom.read_xray(path, frame=options.frame, isocenter_mm=iso, sid_mm=options.sid_mm, sod_mm=options.sod_mm,
                        pixel_mm=options.pixel_mm, geometry=side, image_mask=mask)
        for path, side, mask in zip(options.image, sides, masks, strict=True)
    ]  # fmt: skip
    if len(views) == 2:
        from registration.io.dicom.biplane import pair_views

        views = list(pair_views(views))
    return views


def _read_truth(path: Path, volume_for: str | None) -> tuple[np.ndarray, np.ndarray | None]:
    """The true motion and, when the truth file lists them, the vessel points its mTRE is taken at."""
    m_true, truth_doc = read_motion(path, what="truth", volume_frame_of_reference=volume_for)
    try:
        pts = np.asarray(truth_doc.get("vessel_points_mm", []), dtype=np.float64)
    except (TypeError, ValueError):
        pts = np.zeros((0, 3))
    ok = pts.ndim == 2 and pts.shape[1] == 3 and len(pts) and np.all(np.isfinite(pts))
    return m_true, pts if ok else None


def read_inputs(options: Register, clock: _Stopwatch) -> Inputs:
    """Read the volume, the region it follows, the views, the start and the truth."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        vol = _read_volume(options)
        clock.lap("reading the volume")
        region = _region_of_interest(vol, options.roi, options.roi_mask, cache=not options.no_cache)
        iso, iso_from = resolve_isocenter(options.isocenter, vol)
        views = _read_views(options, iso)
        clock.lap("reading the image" + ("s" if len(views) > 1 else ""))
    _show_warnings(caught)
    inputs = Inputs(whole=vol, volume=vol, region=region, views=views, full_views=views, isocenter=iso,
                    isocenter_from=iso_from)  # fmt: skip
    volume_for = str(vol.meta.get("frame_of_reference_uid") or "") or None
    if options.initial_motion is not None:
        inputs.initial_motion, _ = read_motion(
            options.initial_motion, what="initial motion", volume_frame_of_reference=volume_for
        )
    if options.landmarks is not None:
        if inputs.initial_motion is not None:
            raise ValueError("--landmarks and --initial-motion both give the start: use one")
        from registration.core.landmarks import landmark_start, read_landmarks

        inputs.landmark_start = landmark_start([v.geometry for v in views], read_landmarks(options.landmarks))
        inputs.initial_motion = inputs.landmark_start.patient_motion
    if options.truth is not None:
        inputs.truth, inputs.vessel_points = _read_truth(options.truth, volume_for)
    if region is not None:
        from registration.core.roi import region_views, region_volume

        if region.source != "cranium":  # a user's mask: its outside rendered as soft tissue too
            inputs.volume = region_volume(vol, region)
        inputs.views, inputs.region_fields = region_views(vol, region, views, inputs.initial_motion)
        clock.lap("the region's pixels")
    return inputs


def describe_inputs(options: Register, inputs: Inputs) -> None:
    """Say what is registered: the volume, each image, the geometry, the iso-center, the start, the region."""
    vol, views, iso = inputs.whole, inputs.views, inputs.isocenter
    _say(
        f"volume: {vol.label}  {vol.shape[2]}x{vol.shape[1]}x{vol.shape[0]} voxels, "
        f"{', '.join(f'{s:.3g}' for s in vol.spacing_mm)} mm"
    )
    for view in views:
        gv, plane = view.geometry, view.meta.get("plane") or ("PLANE A" if len(views) == 2 else "")
        _say(
            f"image:  {view.meta.get('source', options.image[0])} frame {view.meta.get('frame', 0)}"
            f"{f' ({plane})' if plane else ''}: {gv.cols}x{gv.rows} px, "
            f"primary {gv.primary_deg:+.1f} deg, secondary {gv.secondary_deg:+.1f} deg, "
            f"SID {gv.sid_mm:.0f} mm, SOD {gv.sod_mm:.0f} mm"
        )
    _say("geometry: nominal (the files' positioner angles and distances; no C-arm calibration is applied)")
    if len(views) == 2:
        _say("biplane: six parameters (tx, ty, tz, rx, ry, rz) in plane A's view frame")
    _say(f"iso-center: ({iso[0]:.2f}, {iso[1]:.2f}, {iso[2]:.2f}) mm, from {inputs.isocenter_from}")
    start = inputs.landmark_start
    if start is not None:
        left_out = int((~start.inliers).sum())
        _say(f"start: {options.landmarks}'s {len(start.inliers)} landmarks, reprojection error {start.rms_px:.1f} "
             "px rms" + (f" ({left_out} left out as disagreeing)" if left_out else "")
             + f": {_format_offsets(start.patient_motion, views[0].geometry)}")  # fmt: skip
    region = inputs.region
    _say("region: " + (region.describe() if region is not None else "every pixel of the field (--roi none)"))
    for view, found in zip(inputs.views, inputs.region_fields, strict=False):
        plane = f" ({view.meta.get('plane')})" if len(inputs.views) == 2 and view.meta.get("plane") else ""
        if found.kept_whole:
            _say(f"region{plane}: the image sees mostly what lies outside the region: its whole field is used")
        else:
            _say(f"region{plane}: {found.left_out_px:,} of the field's {found.field_px:,} px see mostly what lies "
                 "outside the region: left out of the measure")  # fmt: skip


@dataclass
class Outcome:
    """What a registration found: the result, the preparation it rendered, the views (with an
    estimated geometry when asked), and the optional geometry estimate, skull-and-spine check and
    assessment (the :func:`registration.studies.cases.assessment_fields` of :func:`assess`)."""

    result: Any
    prepared: Any
    views: list
    estimated: Any = None
    skull_spine: Any = None
    assessed: dict | None = None


def _region_left_something_out(inputs: Inputs) -> bool:
    """Whether the region narrowed a view's field or (a user's mask) rendered dense tissue as soft."""
    region = inputs.region
    rendered = region is not None and region.source != "cranium" and region.left_out_ml > 0
    return rendered or any(not f.kept_whole for f in inputs.region_fields)


def _skull_spine(inputs: Inputs, views: list, result: Any, prepared: Any, *, seed: int, cache: bool) -> Any:
    """Whether the whole volume (its spine included) fits where the region's estimate says
    (:func:`registration.core.skull_spine.skull_spine_check`). ``prepared``: the registration's
    preparation, searched again when it is of the whole volume (the cranium: prepared for the
    whole fields over the search, which holds the check's reach); a mask's soft-tissue volume
    has the whole one prepared here."""
    from registration.core.skull_spine import skull_spine_check

    whole, store = inputs.whole, None
    if inputs.volume is not whole or not _check_within_search(inputs, result):
        prepared, store = prepare_for_registration(whole, views, np.asarray(result.patient_motion), cache=cache)
    check = skull_spine_check(whole, views, result.patient_motion, renderer=prepared.renderer, seed=seed)
    if store is not None:
        store.flush()
    return check


def _check_within_search(inputs: Inputs, result: Any) -> bool:
    """Whether the skull-and-spine check's reach around ``result`` stays inside the search box the
    registration was prepared for (around the start, the machine-based pose by default)."""
    from registration.core.geometry import invert_rigid, matrix_to_offsets
    from registration.core.register import RegistrationOptions
    from registration.core.skull_spine import check_options

    box, reach = RegistrationOptions(), check_options()
    start = np.eye(4) if inputs.initial_motion is None else np.asarray(inputs.initial_motion, dtype=np.float64)
    moved = matrix_to_offsets(np.asarray(result.patient_motion) @ invert_rigid(start), inputs.views[0].geometry)
    shift_ok = np.all(np.abs(moved[:3]) <= box.bound_mm - reach.bound_mm)
    turn_ok = np.all(np.abs(moved[3:]) <= box.bound_deg - reach.bound_deg)
    return bool(shift_ok and turn_ok) and not getattr(result, "beyond_box", False)


def _estimate_geometry(result: Any, views: list, renderer: Any, inputs: Inputs) -> tuple[list, Any]:
    """Each plane's source-image distance estimated with the pose (the result updated in place,
    its residual too); the views with the estimated geometry, and the estimate."""
    from registration.core.intrinsics import estimate_geometry
    from registration.core.metrics import residuals

    estimated = estimate_geometry(inputs.volume, renderer, views, result.patient_motion, estimate=("sid",))
    result.patient_motion = estimated.patient_motion
    result.similarity = estimated.similarity
    if inputs.truth is not None:
        result.residual = residuals(estimated.patient_motion, inputs.truth, views[0].geometry, inputs.vessel_points,
                                    optimizes_tz=True)  # fmt: skip
    for view, found in zip(("PLANE A", "PLANE B"), estimated.intrinsics, strict=True):
        _say(f"geometry estimated ({view}): SID {found.sid_mm:.1f} mm ({100 * found.sid_change:+.2f} % of the file's)")
    _say(f"patient motion with the estimated geometry: {_format_offsets(estimated.patient_motion, views[0].geometry)}")
    return list(estimated.views), estimated


def register_inputs(options: Register, inputs: Inputs, clock: _Stopwatch) -> Outcome:
    """Prepare the volume for the views (cached), register, and run what was asked after it."""
    from registration.core.register import (
        RegistrationOptions,
        StartOptions,
        around_the_plan,
        register,
        registration_plan,
    )

    compiling = kernels_to_compile()
    clock.lap("loading the engine")
    if compiling:
        _say("compiling the engine's kernels (numba, once after an install or an update: up to a minute on "
             "2 cores; later runs load them from disk) ...", stream=sys.stderr)  # fmt: skip
    cache = not options.no_cache
    vol, views, m_init = inputs.volume, inputs.views, inputs.initial_motion
    # the volume prepared for these views once (cropped to the body the fields can reach, levels in mm);
    # a first run writes the prepared volume to disk while it registers (flushed below)
    # prepared for the whole fields: the assessment and the report see every pixel
    prepared, store = prepare_for_registration(vol, inputs.full_views, m_init, cache=cache)
    clock.lap("preparing the volume" + (" (cached)" if prepared.base_source == "disk" else ""))
    body = prepared.body_summary()
    if body["outside_body_ml"]:  # a CT's couch and head holder: not rendered, said so
        _say(f"body: the patient's body only; {body['outside_body_ml']:,.0f} ml of material away from it (a couch, "
             "a head holder) is not rendered")  # fmt: skip
    # a landmark start is not the machine-based pose: two views' estimate from it is fine-polished
    # and held near the poses the landmarks allow
    engine = RegistrationOptions(start=StartOptions(from_landmarks=inputs.landmark_start is not None))
    if options.explain:
        plan = registration_plan(vol, views, initial_motion=m_init, renderer=prepared.renderer, options=engine,
                                 landmarks=inputs.landmark_start)  # fmt: skip
        _say("plan:\n" + plan.describe() + "\naround it:\n" + around_the_plan(engine, len(views)))
    result = register(vol, views, initial_motion=m_init, seed=options.seed, truth=inputs.truth,
                      vessel_points_mm=inputs.vessel_points, renderer=prepared.renderer, options=engine,
                      landmarks=inputs.landmark_start)  # fmt: skip
    if store is not None:
        store.flush()
    clock.lap("registration")
    # what follows (the geometry estimate, the assessment, the report) sees the whole fields: the
    # confidence rule was calibrated on them
    outcome = Outcome(result=result, prepared=prepared, views=inputs.full_views)
    if options.estimate_geometry and not result.at_bounds:
        estimated_views, outcome.estimated = _estimate_geometry(result, views, prepared.renderer, inputs)
        outcome.views = [replace(full, geometry=v.geometry) for v, full in zip(estimated_views, inputs.full_views,
                                                                                strict=True)]  # fmt: skip
        clock.lap("estimating the geometry")
    _say(f"patient motion: {_format_offsets(result.patient_motion, views[0].geometry)}")
    _say(f"similarity {result.similarity:.4f}, {result.drr_count} DRRs, {result.seconds:.1f} s")
    if _region_left_something_out(inputs) and not result.at_bounds:
        outcome.skull_spine = _skull_spine(inputs, outcome.views, result, prepared, seed=options.seed, cache=cache)
        clock.lap("skull and spine")
        _say(outcome.skull_spine.message())
    say_result(result, len(views))
    if inputs.landmark_start is not None:
        moved = inputs.landmark_start.moved_mm(result.patient_motion)
        _say(f"landmarks: the estimate moves them {moved:.1f} mm (rms, at the iso-center) "
             "from where their picks put them")  # fmt: skip
    if (options.confidence or options.report is not None) and not result.at_bounds:
        from registration.core.assess import assess
        from registration.core.preparation import Preparation
        from registration.studies.cases import assessment_fields

        # the registration's prepared levels (cropped, in mm, cached), not a pyramid of the whole volume
        outcome.assessed = assessment_fields(assess(result, outcome.views, Preparation(vol, prepared, len(views)),
                                                    landmarks=inputs.landmark_start))  # fmt: skip
        clock.lap("confidence")
        pull = outcome.assessed.get("spine_pull")
        if pull is not None:
            _say(f"head alone (the capture runs disagreed): the fit without the spine moves {pull['shift_mm']:.2f} mm "
                 f"in the image plane, {pull['rotation_deg']:.2f} deg")  # fmt: skip
        decision = "applied" if outcome.assessed["applied"] else f"withheld: {outcome.assessed['withheld_reason']}"
        _say(f"confidence {outcome.assessed['confidence']:.2f} -> {decision}")
    return outcome


def say_result(result: Any, planes: int) -> None:
    """The intensities assumed, the residual against the truth, and where the search had to go."""
    from registration.core.assess import shifted_start_withheld

    for assumed in result.intensity:
        if assumed is not None:
            _say(assumed["note"])
    if result.residual is not None:
        r = result.residual
        verdict = "success" if r.success else "FAILURE"
        mtre = "" if r.mtre_mm is None else f", mTRE {r.mtre_mm:.2f} mm"
        criterion = "3-D" if planes == 2 else "in-plane"
        _say(
            f"residual vs truth: {r.translation_mm:.2f} mm total ({r.inplane_mm:.2f} mm in-plane, "
            f"{r.outofplane_mm:.2f} mm out-of-plane of plane A), {r.rotation_deg:.2f} deg{mtre} -> {verdict} "
            f"({criterion} criterion)"
        )
    if result.second_search:
        _say(f"{result.second_search}: the search ran again from the image shift and kept the better fit")
    if result.held_by_landmarks:
        _say(result.held_by_landmarks)
    if result.start_shift_mm:
        look = "; check the estimate by eye" if shifted_start_withheld(result) else ""
        _say(
            f"the image shows the patient {result.start_shift_mm:.0f} mm from the machine-based pose: the search "
            f"started there{look}"
        )
    if getattr(result, "translation_first", False):
        _say(
            "the estimate searched over the patient's translation alone from there fit the images better than the "
            "full search's: it was kept"
        )
    if getattr(result, "fine_polished", False):
        _say(
            "far from the machine-based pose, the estimate was polished on the full images and the finest volume level"
        )
    restart = getattr(result, "beam_restart", None)
    if restart is not None and restart.measure_again is not None:
        kept = "it fit better and was kept; check it by eye" if restart.kept else "the first estimate fit as well"
        _say(
            f"far from the machine-based pose with disagreeing capture runs, the search ran again "
            f"{abs(restart.tz_mm):.0f} mm along the beam: {kept}"
        )
    if result.walk_hops:
        _say(
            f"the search walked {result.walk_hops} time{'s' if result.walk_hops > 1 else ''} beyond its box around the "
            "machine-based pose: the patient is far from it; check the estimate by eye"
        )


def say_costs(clock: _Stopwatch, result: Any) -> None:
    """Where the time went, and each stage's DRRs, DRR pixels and seconds (on stderr)."""
    _say(clock.report(), stream=sys.stderr)
    _say("the registration's stages (DRRs, DRR pixels, seconds):", stream=sys.stderr)
    for cost in result.stages:
        _say(f"  {cost.drrs:6d} {cost.rays:11,d} {cost.seconds:6.2f} s  {cost.stage}", stream=sys.stderr)


def result_document(options: Register, inputs: Inputs, outcome: Outcome) -> dict:
    """The result JSON (``--out``, and the report's numbers)."""
    views = outcome.views
    document = outcome.result.to_dict()
    document["volume"] = {"path": str(options.volume), "label": inputs.volume.label}
    described = [
        {"path": str(v.meta.get("source", p)), "frame": v.meta.get("frame", 0), "kind": v.kind}
        | ({"plane": v.meta.get("plane") or name} if len(views) == 2 else {})
        for v, p, name in zip(views, options.image, ("PLANE A", "PLANE B"), strict=False)
    ]
    document["image"] = described[0]
    if len(views) == 2:
        document["images"] = described
    if inputs.landmark_start is not None:
        document["landmark_start"] = inputs.landmark_start.report(outcome.result.patient_motion)
    document["body"] = outcome.prepared.body_summary()
    if inputs.region is not None:
        document["region"] = inputs.region.summary() | {"fields": [f.to_dict() for f in inputs.region_fields]}
    if outcome.skull_spine is not None:
        document["skull_spine"] = outcome.skull_spine.to_dict()
    if outcome.assessed is not None:
        keys = ("confidence", "applied", "withheld_reason", "confidence_evidence", "spine_pull")
        document.update({k: outcome.assessed[k] for k in keys if k in outcome.assessed})
    document["geometry_source"] = "nominal"  # the files' positioner tags, no calibration
    if outcome.estimated is not None:
        document["geometry_source"] = "estimated (source-image distance per plane, with the pose)"
        document["geometry_estimated"] = outcome.estimated.to_dict()
    document["conventions"] = "shared/CONVENTIONS.md: patient_motion is M with anatomy at X moved to M @ X"
    return document


def write_outputs(options: Register, inputs: Inputs, outcome: Outcome, clock: _Stopwatch) -> None:
    """The result JSON, the report folder, the DICOM Spatial Registration and the ITK transform, as asked."""
    result, views = outcome.result, outcome.views
    document = result_document(options, inputs, outcome) if options.out or options.report else {}
    if options.out is not None:
        dicom.write_text_atomic(options.out, dicom.json_dumps(document))
        _say(f"wrote {options.out}")
    if options.report is not None:
        from app.cli.report_commands import write_register_report

        write_register_report(
            options.report, document=document, assessed=outcome.assessed, volume=inputs.volume, views=list(views),
            renderer=confidence_renderer(outcome.prepared, planes=len(views)), initial_motion=inputs.initial_motion,
            identify=options.report_identify,
        )  # fmt: skip
        clock.lap("report")
        _say(f"wrote {options.report}/ (open {Path(options.report) / 'report.html'})")
    if options.out_dicom is not None:
        description = f"roadmap3d: similarity {result.similarity:.4f}, {result.drr_count} DRRs"
        dicom.write_registration(options.out_dicom, result.patient_motion, volume=inputs.volume, xray=views[0],
                                 description=description)  # fmt: skip
        _say(f"wrote {options.out_dicom} (DICOM Spatial Registration: volume frame of reference -> X-ray image)")
    if options.out_transform is not None:
        write_itk_transform(result.patient_motion, options.out_transform)
        _say(
            f"wrote {options.out_transform} (ITK transform, LPS: inverse of the patient motion; fixed = the patient "
            "as imaged)"
        )


def register_files(options: Register) -> int:
    """Register, print a summary, and write the outputs asked for; exit code 2 when the estimate
    ended at the search bounds (the inputs hold no information to register by: nothing written)."""
    clock = _Stopwatch()
    check_options(options)
    inputs = read_inputs(options, clock)
    describe_inputs(options, inputs)
    outcome = register_inputs(options, inputs, clock)
    if options.verbose:
        say_costs(clock, outcome.result)
    if outcome.result.at_bounds:
        print(f"error: cannot register: the estimate ended at the search bounds "
              f"({', '.join(outcome.result.at_bounds)}); no result written", file=sys.stderr)  # fmt: skip
        return 2
    write_outputs(options, inputs, outcome, clock)
    return 0
