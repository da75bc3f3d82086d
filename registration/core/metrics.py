"""Residual errors of a registration against the truth (CONVENTIONS.md §4).

E = M_est @ inv(M_true). The translational residual is E's displacement of the iso-center
(mm), split into the part in the detector plane (in-plane) and along the central ray
(out-of-plane); the rotational residual is E's rotation angle (degrees). mTRE is the mean
displacement of target points (vessel centerline) under E.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import ArrayLike

from registration.core.geometry import CArm, apply, check_rigid, invert_rigid, rotation_angle_deg

#: Success criterion of the paper: translation below 1 mm and rotation below 3 degrees.
SUCCESS_TRANSLATION_MM = 1.0
SUCCESS_ROTATION_DEG = 3.0


@dataclass(frozen=True)
class Residual:
    """Residual error of one registration, in millimetres and degrees."""

    translation_mm: float
    inplane_mm: float
    outofplane_mm: float
    rotation_deg: float
    mtre_mm: float | None
    #: Success by the registration's criterion: the in-plane part and the rotation when tz
    #: was not optimised (single view), the total translation when it was (biplane).
    success: bool
    #: Success on the total translation, the paper's strict criterion.
    success_total: bool

    def to_dict(self) -> dict:
        return asdict(self)

    def readout(self) -> str:
        """The one-line form the app shows."""
        return (
            f"Residual: {self.inplane_mm:.2f} mm in-plane, {self.translation_mm:.2f} mm total, "
            f"{self.rotation_deg:.2f}° rotation"
        )


def vessel_points(points: ArrayLike) -> np.ndarray:
    """``points`` as an (N, 3) float array of mm (N may be 0), or ValueError naming the shape."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.size and (pts.ndim != 2 or pts.shape[1] != 3):
        raise ValueError(f"vessel_points_mm must be an (N, 3) array of points in mm, got shape {pts.shape}")
    return pts.reshape(-1, 3)


def residuals(
    estimate: ArrayLike,
    truth: ArrayLike,
    geometry: CArm,
    vessel_points_mm: ArrayLike | None = None,
    *,
    optimizes_tz: bool = False,
) -> Residual:
    """Residual of ``estimate`` against ``truth`` (both 4x4 patient motions) in ``geometry``'s view.

    ``success`` is judged on the in-plane part when tz was not optimised (a single view,
    CONVENTIONS §4) and on the whole translation when it was (biplane, §6).
    """
    if not isinstance(geometry, CArm):
        raise TypeError(f"geometry must be a CArm (an image's .geometry), got {type(geometry).__name__}")
    for name, motion in (("estimate", estimate), ("truth", truth)):
        if not isinstance(motion, np.ndarray | list | tuple):
            raise TypeError(f"{name} must be a 4x4 patient motion (a result's .patient_motion), "
                            f"got {type(motion).__name__}")  # fmt: skip
    m_est = check_rigid(estimate, name="estimated motion")
    m_true = check_rigid(truth, name="true motion")
    err = m_est @ invert_rigid(m_true)
    iso = np.asarray(geometry.isocenter_mm, dtype=np.float64)
    shift = apply(err, iso) - iso
    d = geometry.direction
    out_of_plane = float(shift @ d)
    in_plane = float(np.linalg.norm(shift - out_of_plane * d))
    total = float(np.linalg.norm(shift))
    rot = rotation_angle_deg(err)
    mtre = None
    if vessel_points_mm is not None:
        pts = vessel_points(vessel_points_mm)
        if len(pts):
            # Points of the 3DRA sit at M_true @ X in the image; the estimate puts them at M_est @ X.
            moved_true = apply(m_true, pts)
            mtre = float(np.mean(np.linalg.norm(apply(err, moved_true) - moved_true, axis=1)))
    return Residual(
        translation_mm=total,
        inplane_mm=in_plane,
        outofplane_mm=abs(out_of_plane),
        rotation_deg=rot,
        mtre_mm=mtre,
        success=(total if optimizes_tz else in_plane) < SUCCESS_TRANSLATION_MM and rot < SUCCESS_ROTATION_DEG,
        success_total=total < SUCCESS_TRANSLATION_MM and rot < SUCCESS_ROTATION_DEG,
    )
