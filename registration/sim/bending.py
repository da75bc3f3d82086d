"""C-arm bending: the true geometry of a nominal view, and how far a geometry is from the truth.

Sections II.A and II.B of Homan et al.: the angle sensors of a C-arm report only the *nominal*
geometry (:meth:`registration.core.geometry.CArm.nominal`); gravity bends the arm so that the
true source and detector deviate from it by a few millimetres and a small detector tilt,
depending on the angles. :class:`BendingModel` simulates that (seeded, smooth in the angles);
the nine deviation parameters (:data:`DEVIATION_NAMES`) map a nominal view to a true one
(:func:`with_deviation`). :func:`machine_based_error_mm` is the error measure of ``roadmap3d
validate calibration``: how far an estimated geometry projects the iso-center region from the
true one. Measuring the deviations is :mod:`registration.sim.dodecahedron`; the grid of
measured views is :mod:`registration.sim.calibration`.

Conventions (frames, angles, units) are those of ``shared/CONVENTIONS.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core.geometry import CArm

Array = NDArray[np.float64]

#: Names of the nine deviation parameters of a true geometry, in vector order.
DEVIATION_NAMES = (
    "source_dx_mm",
    "source_dy_mm",
    "source_dz_mm",
    "detector_dx_mm",
    "detector_dy_mm",
    "detector_dz_mm",
    "detector_tilt_x_deg",
    "detector_tilt_y_deg",
    "detector_tilt_z_deg",
)

#: Seed of the default system's bending (the C-arm that ``assets/calibration_table.json``
#: was measured on).
SYSTEM_BENDING_SEED = 0

#: Radius (mm) of the iso-center region over which the machine-based error is measured.
ERROR_REGION_RADIUS_MM = 50.0


# --------------------------------------------------------------------------------------
# Deviation parameters <-> CArm
# --------------------------------------------------------------------------------------
def deviation_vector(geometry: CArm) -> Array:
    """The nine deviation parameters (:data:`DEVIATION_NAMES`) of a geometry."""
    return np.array([*geometry.source_shift_mm, *geometry.detector_shift_mm, *geometry.detector_tilt_deg])


def with_deviation(nominal: CArm, deviation: ArrayLike) -> CArm:
    """``nominal`` with its deviation fields set from a 9-vector (:data:`DEVIATION_NAMES`).

    Source and detector shifts are world millimetres; the tilt is in degrees about the view
    frame's axes (see :class:`~registration.core.geometry.CArm`).
    """
    x = np.asarray(deviation, dtype=np.float64).reshape(-1)
    if x.shape != (9,) or not np.all(np.isfinite(x)):
        raise ValueError(f"deviation must be nine finite numbers {DEVIATION_NAMES}, got {deviation}")
    return replace(
        nominal,
        source_shift_mm=tuple(x[0:3]),
        detector_shift_mm=tuple(x[3:6]),
        detector_tilt_deg=tuple(x[6:9]),
    )


# --------------------------------------------------------------------------------------
# C-arm mechanics
# --------------------------------------------------------------------------------------
def _basis(primary_deg: float, secondary_deg: float) -> Array:
    """Smooth angular basis: harmonics up to order 2 in the rotation, 1 in the angulation."""
    a, b = math.radians(primary_deg), math.radians(secondary_deg)
    return np.array(
        [
            1.0,
            math.cos(a),
            math.sin(a),
            math.cos(2 * a),
            math.sin(2 * a),
            math.cos(b),
            math.sin(b),
            math.cos(a) * math.sin(b),
            math.sin(a) * math.sin(b),
        ]
    )


#: Relative weight of each basis function in the random part (higher harmonics smaller).
_BASIS_WEIGHTS = np.array([0.5, 1.0, 1.0, 0.35, 0.35, 0.5, 0.6, 0.4, 0.4])


@dataclass(frozen=True)
class BendingModel:
    """Simulated gravitational bending of a C-arm, fixed per system by ``seed``.

    The deviation of the true from the nominal geometry is, for each of the nine parameters
    (:data:`DEVIATION_NAMES`), a smooth function of the nominal angles:

    - a *gravity sag* of the source and the detector toward the floor (world +y for the supine
      patient), largest when the source-detector axis is horizontal: amplitude x (1 - d_y^2)
      with d the nominal central-ray direction;
    - a seeded random combination of low angular harmonics (:func:`_basis`: up to order 2 in
      the rotation, 1 in the angulation), standing for the arm's and the bearings' compliance.

    Sizes: source shifts up to ~``source_amplitude_mm``, detector shifts up to
    ~``detector_amplitude_mm`` per axis, detector tilts ~0.1-0.5 degrees.
    """

    seed: int = SYSTEM_BENDING_SEED
    source_amplitude_mm: float = 2.0
    detector_amplitude_mm: float = 3.0
    tilt_amplitude_deg: float = 0.3
    _coefficients: Array = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in ("source_amplitude_mm", "detector_amplitude_mm", "tilt_amplitude_deg"):
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"{name} must be finite and >= 0, got {value}")
        rng = np.random.default_rng(np.random.SeedSequence([int(self.seed), 0xC0A4]))
        amplitude = np.array(
            [self.source_amplitude_mm] * 3 + [self.detector_amplitude_mm] * 3 + [self.tilt_amplitude_deg] * 3
        )
        # random part: 9 parameters x 9 basis functions, ~half the amplitude in RMS
        coeffs = rng.normal(size=(9, _BASIS_WEIGHTS.size)) * _BASIS_WEIGHTS
        coeffs *= (0.5 * amplitude / np.sqrt(np.sum(_BASIS_WEIGHTS**2) / 2.0))[:, None]
        object.__setattr__(self, "_coefficients", coeffs)

    def deviation(self, primary_deg: float, secondary_deg: float) -> Array:
        """The nine deviation parameters (:data:`DEVIATION_NAMES`) at nominal angles."""
        if not (math.isfinite(primary_deg) and math.isfinite(secondary_deg)):
            raise ValueError(f"angles must be finite, got {primary_deg}, {secondary_deg}")
        dev = self._coefficients @ _basis(primary_deg, secondary_deg)
        d = CArm(primary_deg=primary_deg, secondary_deg=secondary_deg).direction
        sag = 1.0 - d[1] ** 2  # 0 with a vertical beam, 1 with a horizontal one
        dev[1] += 0.8 * self.source_amplitude_mm * sag
        dev[4] += 0.8 * self.detector_amplitude_mm * sag
        return dev

    def true_geometry(self, nominal: CArm) -> CArm:
        """The true (bent) geometry of a nominal view: same angles, deviation fields set."""
        return with_deviation(nominal, self.deviation(nominal.primary_deg, nominal.secondary_deg))


def default_bending() -> BendingModel:
    """The bending of the default system (seed :data:`SYSTEM_BENDING_SEED`)."""
    return BendingModel(SYSTEM_BENDING_SEED)


# --------------------------------------------------------------------------------------
# The error measure
# --------------------------------------------------------------------------------------
def _fibonacci_sphere(n: int) -> Array:
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    r = np.sqrt(1.0 - z * z)
    theta = math.pi * (1.0 + math.sqrt(5.0)) * k
    return np.column_stack([r * np.cos(theta), r * np.sin(theta), z])


def error_region_points(radius_mm: float = ERROR_REGION_RADIUS_MM) -> Array:
    """The iso-center, 100 points on the sphere of ``radius_mm`` and 50 on half that radius."""
    return np.vstack([np.zeros((1, 3)), radius_mm * _fibonacci_sphere(100), 0.5 * radius_mm * _fibonacci_sphere(50)])


def machine_based_error_mm(true: CArm, estimate: CArm, *, radius_mm: float = ERROR_REGION_RADIUS_MM) -> float:
    """Displacement at the iso-center region between two geometries of one view, in mm.

    For the iso-center and points filling a sphere of ``radius_mm`` around it
    (:func:`error_region_points`), the distance on the detector between their projections with
    ``true`` and with ``estimate`` is scaled back to the iso-center plane (divided by the
    nominal magnification SID/SOD); the error is the largest of these distances. It is the
    misregistration a machine-based overlay shows for anatomy near the iso-center.
    """
    if (true.rows, true.cols, true.pixel_mm) != (estimate.rows, estimate.cols, estimate.pixel_mm):
        raise ValueError("true and estimate must share the detector (rows, cols, pixel_mm)")
    pts = error_region_points(radius_mm) + np.asarray(true.isocenter_mm)
    diff_px = true.project(pts) - estimate.project(pts)
    diff_mm = diff_px * np.array([true.pixel_mm[1], true.pixel_mm[0]])
    return float(np.max(np.linalg.norm(diff_mm, axis=1)) / true.magnification)
