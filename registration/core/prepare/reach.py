"""What the search can reach: the reach of a search, the crop box of the tissue rays can meet."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core.geometry import CArm, check_rigid, rotation_angle_deg
from registration.core.prepare.params import (
    LEVEL0_PIXELS,
)
from registration.core.volume import Volume

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Reach:
    """How far the search may move anatomy from where the volume shows it.

    Every point X moves by at most ``translation_mm + 2 sin(rotation_deg / 2) |X - c|`` with
    c the iso-center: a rigid motion within the reach is a rotation of at most
    ``rotation_deg`` about c followed by a translation of at most ``translation_mm``.
    """

    translation_mm: float
    rotation_deg: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.translation_mm) and self.translation_mm >= 0):
            raise ValueError(f"reach translation must be finite and >= 0 mm, got {self.translation_mm}")
        if not (math.isfinite(self.rotation_deg) and 0 <= self.rotation_deg <= 180):
            raise ValueError(f"reach rotation must lie in [0, 180] degrees, got {self.rotation_deg}")

    @classmethod
    def of_search(
        cls,
        bound_mm: float,
        bound_deg: float,
        *,
        initial_motion: ArrayLike | None = None,
        isocenter_mm: ArrayLike = (0.0, 0.0, 0.0),
        translations: int = 3,
    ) -> Reach:
        """The reach of a search of +-``bound_mm`` on ``translations`` view-frame axes and
        +-``bound_deg`` on three rotation angles about the iso-center, around ``initial_motion``."""
        t_search = bound_mm * math.sqrt(translations)
        # three Euler angles of at most b each compose to a rotation of at most ~ sqrt(3) b
        theta_search = min(180.0, bound_deg * math.sqrt(3.0) * 1.05)
        search = cls(t_search, theta_search)
        return search if initial_motion is None else search.around(initial_motion, isocenter_mm)

    def around(self, motion: ArrayLike, isocenter_mm: ArrayLike = (0.0, 0.0, 0.0)) -> Reach:
        """The reach of this search started at ``motion`` instead of at the volume's pose: the
        motion's shift of the iso-center c and its rotation added (and the search's rotation of
        the moved iso-center)."""
        return self._moved(check_rigid(motion, name="initial motion"), isocenter_mm)

    def _moved(self, m: Array, isocenter_mm: ArrayLike) -> Reach:
        c = np.asarray(isocenter_mm, dtype=np.float64)
        t_init = float(np.linalg.norm(m[:3, :3] @ c + m[:3, 3] - c))
        theta_init = rotation_angle_deg(m)
        # the search rotates the moved iso-center
        lever = 2.0 * math.sin(math.radians(self.rotation_deg) / 2.0) * t_init
        return Reach(self.translation_mm + t_init + lever, min(180.0, self.rotation_deg + theta_init))

    def grown(self, translation_mm: float, rotation_deg: float) -> Reach:
        """This reach with some slack added."""
        return Reach(self.translation_mm + translation_mm, min(180.0, self.rotation_deg + rotation_deg))

    def covers(self, other: Reach) -> bool:
        return self.translation_mm >= other.translation_mm - 1e-9 and self.rotation_deg >= other.rotation_deg - 1e-9

    def displacement_mm(self, distance_mm: ArrayLike) -> NDArray[np.float64]:
        """The largest displacement of points at ``distance_mm`` from the iso-center."""
        lever = 2.0 * math.sin(math.radians(self.rotation_deg) / 2.0)
        return self.translation_mm + lever * np.asarray(distance_mm, dtype=np.float64)


def _axes_and_spacing(volume: Volume) -> tuple[Array, Array]:
    lin = volume.index_to_world[:3, :3]
    spacing = np.linalg.norm(lin, axis=0)
    return lin / spacing, spacing


def field_extent_mm(geometry: CArm) -> float:
    """Diameter of the collimated field at the iso-center (mm)."""
    return geometry.field_diameter_mm / geometry.magnification


def level_spacing_mm(extent_mm: float, level: int) -> float:
    """Voxel size (mm) of pyramid ``level`` for an image showing ``extent_mm`` at the iso-center:
    the pixel of a ``256 / 2**level``-pixel image of it."""
    if not math.isfinite(extent_mm) or extent_mm <= 0:
        raise ValueError(f"extent must be positive, got {extent_mm} mm")
    if isinstance(level, bool) or int(level) != level or level < 0:
        raise ValueError(f"level must be an integer >= 0, got {level}")
    return float(extent_mm) * 2**level / LEVEL0_PIXELS


def _reach_mask(points: Array, geometries: Sequence[CArm], reach: Reach, margin_mm: float) -> NDArray[np.bool_]:
    """Points (N, 3) that a ray through some view's field meets under a motion within ``reach``."""
    needed = np.zeros(len(points), dtype=bool)
    for g in geometries:
        iso = np.asarray(g.isocenter_mm)
        delta = reach.displacement_mm(np.linalg.norm(points - iso, axis=1)) + margin_mm
        p = g.projection_matrix
        h = points @ p[:, :3].T + p[:, 3]
        depth = h[:, 2]  # distance from the source along the detector normal (mm)
        ahead = depth > delta + 1.0
        safe = np.where(ahead, depth, 1.0)
        col, row = h[:, 0] / safe, h[:, 1] / safe
        x = (col - (g.cols - 1) / 2.0) * g.pixel_mm[1]
        y = (row - (g.rows - 1) / 2.0) * g.pixel_mm[0]
        r_det = np.hypot(x, y)
        focal = g.sid_mm  # source to detector (nominal; calibrated shifts are sub-millimetre)
        # a displacement delta at depth a moves the projection by at most delta * focal / (a - delta)
        slack = delta * focal / np.maximum(safe - delta, 1.0) * (1.0 + r_det / focal)
        needed |= ahead & (r_det - slack <= g.field_diameter_mm / 2.0)
    return needed
