"""The global start: a search box that walks when the estimate ends on its bounds.

The annealing searches a box around the machine-based pose (``bound_mm``, ``bound_deg``). A
patient moved further than that pulls the estimate onto the box's walls: the measure still
improves toward the true pose, the box stops it. The walk starts the whole plan again from that
estimate, with the box (and the volume's preparation) centred there, until an estimate ends
inside its box or :attr:`StartOptions.walk_hops` restarts are spent. It runs only when needed: a
registration that ends inside its first box is exactly the registration without it.

An estimate reached by walking lies outside the box around the machine-based pose, where the
confidence's probes were not prepared: :func:`registration.core.assess.veto` withholds it (it
is shown, never applied automatically). ``docs/validation/capture.md`` measures the walk.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from registration.core.geometry import offsets_to_matrix
from registration.core.register.inputs import Inputs, prepared_renderer
from registration.core.register.options import RegistrationOptions
from registration.core.register.result import RegistrationResult


def walk_from_bounds(
    register_once: Callable[[Inputs], RegistrationResult], inputs: Inputs, options: RegistrationOptions
) -> RegistrationResult:
    """``register_once(inputs)``, started again from its estimate while that ends at the search
    bounds (at most ``options.start.walk_hops`` times). The result is the last run's, with the
    DRRs and similarity trace of every run and ``walk_hops`` set to the restarts made."""
    result = register_once(inputs)
    drr_count, trace, hops, stages = result.drr_count, list(result.similarity_trace), 0, list(result.stages)
    while result.at_bounds and not result.stopped and hops < options.start.walk_hops:
        start = _start_at(result, inputs)
        renderer = prepared_renderer(inputs.volume, inputs.views, start, options)
        inputs = replace(inputs, initial_motion=start, renderer=renderer)
        result = register_once(inputs)
        hops += 1
        drr_count += result.drr_count
        trace += result.similarity_trace
        stages += [replace(c, stage=f"walk {hops}: {c.stage}") for c in result.stages]
    result.drr_count, result.similarity_trace, result.walk_hops = drr_count, trace, hops
    result.stages = tuple(stages)
    return result


def _start_at(result: RegistrationResult, inputs: Inputs) -> np.ndarray:
    """The next start: the estimate's searched offsets from this run's start (one view: without
    the depth correction's tz, which a search lost beyond its box does not support)."""
    offsets = dict(zip(result.parameters, np.asarray(result.offsets, dtype=np.float64), strict=True))
    six = [offsets.get(name, 0.0) for name in ("tx", "ty", "tz", "rx", "ry", "rz")]
    return offsets_to_matrix(six, result.geometry) @ inputs.initial_motion
