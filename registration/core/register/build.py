"""The plan of one registration, built from its views and options (:class:`Plan`)."""

from __future__ import annotations

from registration.core.drr import DRRRenderer
from registration.core.register.biplane import PlaneCaptures
from registration.core.register.depth import depth_prescan_stage, depth_resolvable, depth_stage
from registration.core.register.inputs import Inputs
from registration.core.register.options import CAPTURE_64, Level, RegistrationOptions
from registration.core.register.plan import PLANES_AGREE, PLANES_DISAGREE, Plan, Stage
from registration.core.register.rotation_check import rotation_check_stage
from registration.core.register.stages import AnnealLevel, PlaneACapture, Polish, PolishBudget


def build_plan(inputs: Inputs, options: RegistrationOptions) -> Plan:
    """The stages a registration of ``inputs`` runs with ``options``, in order."""
    n_views = len(inputs.views)
    multi = n_views > 1 and options.optimizes_tz(n_views)
    pair = multi and options.biplane.plane_captures
    stages: list[Stage] = []
    single = n_views == 1 and not options.optimizes_tz(n_views)
    depth_runs = (options.polish.enabled and single and options.depth.enabled
                  and depth_resolvable(inputs.renderer, options.depth))  # fmt: skip
    if pair:
        stages += biplane_stages(options, inputs.renderer)
    else:
        levels = (capture_level(inputs.renderer, options, n_views), *options.levels[1:])
        if multi and options.biplane.plane_a_capture:
            stages.append(PlaneACapture(levels[0], options.margin_mm(0)))
        stages += [anneal(options, lv, n, n_views) for n, lv in enumerate(levels)]
        if depth_runs and options.depth.scan_first and options.depth.scan_after_capture and len(levels) > 1:
            stages.insert(len(stages) - len(levels) + 1, depth_prescan_stage(options, 1, after="the capture"))
    if options.polish.enabled:
        if depth_runs and options.depth.scan_first:
            stages.append(depth_prescan_stage(options, len(options.levels)))
        stages += polish_stages(options, pair)
        if depth_runs:
            depth = depth_stage(options, len(options.levels))
            stages.append(depth)
            if options.rotation_check.enabled:
                stages.append(rotation_check_stage(options, len(options.levels)))
    return Plan(tuple(stages))


def capture_level(renderer: DRRRenderer, options: RegistrationOptions, n_views: int) -> Level:
    """The capture level for ``n_views`` views (:meth:`RegistrationOptions.capture_level`), or the
    64 px capture (:data:`CAPTURE_64`) when ``renderer`` lacks its volume level (a volume too small
    for it: :func:`registration.core.register.inputs.supports_level`)."""
    level = options.capture_level(n_views)
    return level if renderer.has_level(level.volume_level) else CAPTURE_64


def anneal(options: RegistrationOptions, level: Level, margin_index: int, n_views: int,
           when: tuple | None = None) -> AnnealLevel:  # fmt: skip
    return AnnealLevel(level, options.margin_mm(margin_index), options.capture_runs(level, n_views), when)


def biplane_stages(options: RegistrationOptions, renderer: DRRRenderer) -> list[Stage]:
    """Each plane's own capture (each run then at the plane refinement's level); when the planes
    disagree the pair's capture level from each start and the levels after it; when they agree
    the pair's levels (by default none). A volume too small for the planes' capture level has
    them capture at the pair's capture level, without the refinement."""
    b, levels = options.biplane, options.levels
    last = len(levels) - 1
    capture = options.capture_level(2)
    plane, refine = b.plane_capture or capture, b.plane_refine
    if not renderer.has_level(plane.volume_level):
        plane, refine = capture, None
    refine_margin = options.margin_mm(1) if refine is not None else None
    stages: list[Stage] = [
        PlaneCaptures(plane, b.plane_capture_runs, options.margin_mm(0), refine, refine_margin),
        AnnealLevel(capture, options.margin_mm(0), None, PLANES_DISAGREE),
    ]
    if b.pair_levels is None:  # the levels after the capture, whatever the planes say
        return stages + [anneal(options, lv, n, 2) for n, lv in enumerate(levels[1:], 1)]
    stages += [anneal(options, lv, n, 2, PLANES_DISAGREE) for n, lv in enumerate(levels[1:], 1)]
    return stages + [anneal(options, lv, min(1 + n, last), 2, PLANES_AGREE) for n, lv in enumerate(b.pair_levels)]


def polish_stages(options: RegistrationOptions, pair: bool) -> list[Stage]:
    """The polish (the pair's own budget after the planes' captures, preceded by its coarse
    polish on the capture level's images)."""
    p, b, levels = options.polish, options.biplane, options.levels
    stages: list[Stage] = []
    if pair and b.coarse_polish_evaluations:
        coarse = PolishBudget(b.coarse_polish_evaluations, b.coarse_polish_reach_mm, b.coarse_polish_reach_deg,
                              b.polish_xtol, p.step_mm, p.step_deg)  # fmt: skip
        first = options.capture_level(2)
        stages.append(Polish("coarse polish", first.image_px, first.volume_level, options.margin_mm(len(levels) - 1),
                             coarse))  # fmt: skip
    if pair:
        evaluations = p.evaluations if b.polish_evaluations is None else b.polish_evaluations
        budget = PolishBudget(evaluations, b.polish_reach_mm, b.polish_reach_deg, b.polish_xtol, p.step_mm, p.step_deg)
    else:
        budget = PolishBudget(p.evaluations, p.reach_mm, p.reach_deg, p.xtol, p.step_mm, p.step_deg)
    stages.append(Polish("polish", p.image_px, p.volume_level, options.margin_mm(len(levels)), budget))
    return stages
