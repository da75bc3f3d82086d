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
