"""The search space of a registration: which offsets are optimised, their bounds, and the map
from a parameter vector to a patient motion.

Parameters are offsets in the view frame of one X-ray view (the *frame view*: the only view
of a single-plane registration, plane A of a biplane one; CONVENTIONS.md §4 and §6):
translations in mm, rotations in degrees about the iso-center, composed as
``M = offsets_to_matrix((tx, ty, tz, rx, ry, rz), frame) @ initial_motion``. The paper's
single-view search has five parameters (tz is kept: one view cannot see motion along its
beam); a biplane search has all six.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core.geometry import (
    OFFSET_NAMES,
    CArm,
    invert_rigid,
    matrix_to_offsets,
    rigid,
    rotation_x,
    rotation_y,
    rotation_z,
)

Array = NDArray[np.float64]

#: The paper's five parameters (mm, mm, deg, deg, deg): tz is not optimised.
FIVE_PARAMETERS = ("tx", "ty", "rx", "ry", "rz")
#: All six offsets (mm, mm, mm, deg, deg, deg), as in Table I.
SIX_PARAMETERS = OFFSET_NAMES

_TRANSLATIONS = ("tx", "ty", "tz")


@dataclass(frozen=True)
class SearchSpace:
    """Which offsets a registration optimises, in ``frame``'s view frame, and their bounds.

    ``initial_motion`` (the machine-based pose, 4x4 rigid, checked by the caller) is where
    the parameter vector 0 lies; the bounds are +- ``bound_mm`` / ``bound_deg`` around it.
    ``held_tz_mm``: a five-parameter space's offset along the beam (mm, the view frame's tz), held
    while the others are searched (0: the initial pose's; :meth:`holding_tz`).
    ``wall``: a soft limit inside the box, the cost a patient motion adds to the registration's
    (for example :meth:`registration.core.landmarks.LandmarkStart.wall`); None: the box alone.
    """

    frame: CArm
    initial_motion: Array
    names: tuple[str, ...] = FIVE_PARAMETERS
    bound_mm: float = 30.0
    bound_deg: float = 15.0
    held_tz_mm: float = 0.0
    wall: Callable[[Array], float] | None = field(default=None, repr=False, compare=False)
    _frames: tuple[Array, Array] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.names not in (FIVE_PARAMETERS, SIX_PARAMETERS):
            raise ValueError(f"parameters must be {FIVE_PARAMETERS} or {SIX_PARAMETERS}, got {self.names}")
        if not self.bound_mm > 0 or not self.bound_deg > 0:
            raise ValueError("bound_mm and bound_deg must be positive")
        if self.held_tz_mm != 0.0 and "tz" in self.names:
            raise ValueError("a six-parameter space searches tz: it cannot hold it")
        object.__setattr__(self, "_frames", (self.frame.world_from_view, self.frame.view_from_world))

    @classmethod
    def for_views(
        cls,
        frame: CArm,
        initial_motion: Array,
        *,
        optimize_tz: bool,
        bound_mm: float,
        bound_deg: float,
        wall: Callable[[Array], float] | None = None,
    ) -> SearchSpace:
        names = SIX_PARAMETERS if optimize_tz else FIVE_PARAMETERS
        return cls(frame, initial_motion, names, bound_mm, bound_deg, wall=wall)

    def holding_tz(self, tz_mm: float) -> SearchSpace:
        """This space's five parameters with tz held at ``tz_mm`` (the depth correction's)."""
        return replace(self, names=FIVE_PARAMETERS, held_tz_mm=float(tz_mm))

    @property
    def size(self) -> int:
        return len(self.names)

    @property
    def optimizes_tz(self) -> bool:
        return "tz" in self.names

    def is_translation(self) -> NDArray[np.bool_]:
        """Per parameter: True for a translation (mm), False for a rotation (deg)."""
        return np.array([n in _TRANSLATIONS for n in self.names])

    @property
    def bounds(self) -> Array:
        """(n, 2) lower and upper bounds of the parameters."""
        half = np.where(self.is_translation(), self.bound_mm, self.bound_deg)
        return np.stack([-half, half], axis=1)

    def start(self) -> Array:
        """The parameter vector of the initial motion (all zeros)."""
        return np.zeros(self.size)

    def per_parameter(self, values: ArrayLike) -> Array:
        """Values given for the five parameters (tx, ty, rx, ry, rz), or for all of ours.

        A six-parameter search takes tz's value from tx's (both translations in mm).
        """
        v = np.asarray(values, dtype=np.float64).reshape(-1)
        if v.size == self.size:
            return v
        if v.size == len(FIVE_PARAMETERS) and self.optimizes_tz:
            return np.insert(v, 2, v[0])
        raise ValueError(f"expected {self.size} or 5 values for the parameters {self.names}, got {v.size}")

    def offsets(self, x: ArrayLike) -> Array:
        """The six view-frame offsets (tx, ty, tz, rx, ry, rz) of a parameter vector."""
        x = np.asarray(x, dtype=np.float64)
        if self.optimizes_tz:
            return x.copy()
        return np.array([x[0], x[1], self.held_tz_mm, x[2], x[3], x[4]])

    def motion(self, x: ArrayLike) -> Array:
        """Patient motion (4x4, world mm) of a parameter vector.

        Same arithmetic as :func:`registration.core.geometry.offsets_to_matrix` (bit for bit),
        with the frame's transforms computed once.
        """
        o = self.offsets(x)
        world_from_view, view_from_world = self._frames
        rot = rotation_z(o[5]) @ rotation_y(o[4]) @ rotation_x(o[3])
        return world_from_view @ rigid(rot, o[:3]) @ view_from_world @ self.initial_motion

    def from_offsets(self, offsets: ArrayLike) -> Array:
        """The parameter vector of six view-frame offsets (tz dropped by a five-parameter space)."""
        o = np.asarray(offsets, dtype=np.float64).reshape(6)
        return o.copy() if self.optimizes_tz else o[[0, 1, 3, 4, 5]].copy()

    def from_motion(self, motion: ArrayLike) -> Array:
        """The parameter vector nearest a patient motion (4x4): its offsets from the initial
        motion in the frame's view frame (tz dropped by a five-parameter space)."""
        relative = np.asarray(motion, dtype=np.float64) @ invert_rigid(self.initial_motion)
        return self.from_offsets(matrix_to_offsets(relative, self.frame))

    def as_dict(self, x: ArrayLike) -> dict[str, float]:
        """The parameter vector by name (the JSON form of a result's offsets)."""
        return dict(zip(self.names, np.asarray(x, dtype=np.float64).tolist(), strict=True))
