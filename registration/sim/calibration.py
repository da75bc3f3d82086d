"""The machine-based registration table: a grid of calibrated views, interpolated.

Calibrating a grid of views 20 degrees apart with the dodecahedron
(:mod:`registration.sim.dodecahedron`) and interpolating bilinearly between them gives the
machine-based registration (``assets/calibration_table.json``): :class:`CalibrationTable`,
:func:`build_calibration_table`, :func:`load_calibration_table`,
:func:`machine_based_geometry`; :func:`calibration_study` is ``roadmap3d validate
calibration``. The bending (:mod:`registration.sim.bending`) and the dodecahedron's names are
re-exported here, where the callers of the calibration have always found them.

Conventions (frames, angles, units) are those of ``shared/CONVENTIONS.md``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core.geometry import ASSETS, CArm
from registration.sim.bending import (
    DEVIATION_NAMES,
    ERROR_REGION_RADIUS_MM,
    SYSTEM_BENDING_SEED,
    BendingModel,
    default_bending,
    deviation_vector,
    error_region_points,
    machine_based_error_mm,
    with_deviation,
)
from registration.sim.dodecahedron import (
    CALIBRATION_FORMAT_CM,
    CALIBRATION_PHOTONS,
    CALIBRATION_PIXELS,
    LEAD_MU_PER_MM,
    CalibrationShot,
    DetectedSpheres,
    Dodecahedron,
    SpherePhantom,
    ViewCalibration,
    calibrate_true_view,
    calibrate_view,
    calibration_geometry,
    calibration_shot,
    detect_spheres,
    match_spheres,
    simulate_calibration_image,
    simulate_sphere_image,
)

Array = NDArray[np.float64]

#: The 20-degree calibration grid: rotation (primary) x angulation (secondary), degrees.
PRIMARY_GRID_DEG = tuple(float(a) for a in range(-120, 121, 20))
SECONDARY_GRID_DEG = tuple(float(b) for b in range(-60, 61, 20))

TABLE_PATH = ASSETS / "calibration_table.json"


# --------------------------------------------------------------------------------------
# The machine-based registration table
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CalibrationTable:
    """Deviation parameters measured on a grid of nominal angles, interpolated bilinearly.

    ``deviations[i, j]`` holds the nine parameters (:data:`DEVIATION_NAMES`) at
    ``primary_deg[i]``, ``secondary_deg[j]``.
    """

    primary_deg: Array
    secondary_deg: Array
    deviations: Array
    meta: dict = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        p = np.asarray(self.primary_deg, dtype=np.float64).reshape(-1)
        s = np.asarray(self.secondary_deg, dtype=np.float64).reshape(-1)
        d = np.asarray(self.deviations, dtype=np.float64)
        if p.size < 2 or s.size < 2 or np.any(np.diff(p) <= 0) or np.any(np.diff(s) <= 0):
            raise ValueError("grid angles must be strictly increasing with at least two values per axis")
        if d.shape != (p.size, s.size, 9) or not np.all(np.isfinite(d)):
            raise ValueError(f"deviations must be finite with shape {(p.size, s.size, 9)}, got {d.shape}")
        object.__setattr__(self, "primary_deg", p)
        object.__setattr__(self, "secondary_deg", s)
        object.__setattr__(self, "deviations", d)

    def deviation(self, primary_deg: float, secondary_deg: float) -> Array:
        """Bilinear interpolation of the nine parameters; ValueError outside the grid."""
        p, s = float(primary_deg), float(secondary_deg)
        eps = 1e-9
        if not (self.primary_deg[0] - eps <= p <= self.primary_deg[-1] + eps) or not (
            self.secondary_deg[0] - eps <= s <= self.secondary_deg[-1] + eps
        ):
            raise ValueError(
                f"angles ({p}, {s}) deg lie outside the calibrated range: primary "
                f"{self.primary_deg[0]}..{self.primary_deg[-1]}, secondary "
                f"{self.secondary_deg[0]}..{self.secondary_deg[-1]}"
            )
        i = int(np.clip(np.searchsorted(self.primary_deg, p) - 1, 0, self.primary_deg.size - 2))
        j = int(np.clip(np.searchsorted(self.secondary_deg, s) - 1, 0, self.secondary_deg.size - 2))
        tp = (p - self.primary_deg[i]) / (self.primary_deg[i + 1] - self.primary_deg[i])
        ts = (s - self.secondary_deg[j]) / (self.secondary_deg[j + 1] - self.secondary_deg[j])
        tp, ts = min(max(tp, 0.0), 1.0), min(max(ts, 0.0), 1.0)
        d = self.deviations
        return (
            (1 - tp) * (1 - ts) * d[i, j]
            + tp * (1 - ts) * d[i + 1, j]
            + (1 - tp) * ts * d[i, j + 1]
            + tp * ts * d[i + 1, j + 1]
        )

    def geometry(self, nominal: CArm) -> CArm:
        """The machine-based (calibrated, interpolated) geometry of a nominal view."""
        return with_deviation(nominal.nominal(), self.deviation(nominal.primary_deg, nominal.secondary_deg))

    def to_dict(self) -> dict[str, Any]:
        return {
            "description": (
                "Machine-based registration table: C-arm deviation parameters measured with the "
                "dodecahedron phantom on a grid of nominal angles; interpolate bilinearly."
            ),
            "parameters": list(DEVIATION_NAMES),
            "primary_deg": self.primary_deg.tolist(),
            "secondary_deg": self.secondary_deg.tolist(),
            "deviations": np.round(self.deviations, 5).tolist(),
            "meta": self.meta,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> CalibrationTable:
        try:
            if list(data["parameters"]) != list(DEVIATION_NAMES):
                raise ValueError(f"calibration table parameters {data['parameters']} != {DEVIATION_NAMES}")
            return cls(
                np.array(data["primary_deg"]),
                np.array(data["secondary_deg"]),
                np.array(data["deviations"]),
                meta=dict(data.get("meta", {})),
            )
        except KeyError as exc:
            raise ValueError(f"calibration table lacks the key {exc.args[0]!r}") from None

    def save(self, path: Path | str) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=1) + "\n")


def _view_seed(seed: int, primary_deg: float, secondary_deg: float) -> int:
    """Noise seed of a calibration view: fixed by the angles, whatever grid it belongs to."""
    key = [int(seed), int(round(primary_deg * 1000)) % 2**31, int(round(secondary_deg * 1000)) % 2**31]
    return int(np.random.SeedSequence(key).generate_state(1)[0])


def build_calibration_table(
    bending: BendingModel | None = None,
    *,
    primary_deg: ArrayLike = PRIMARY_GRID_DEG,
    secondary_deg: ArrayLike = SECONDARY_GRID_DEG,
    phantom: Dodecahedron | None = None,
    seed: int = 0,
) -> CalibrationTable:
    """Calibrate every grid view: image the dodecahedron with the true (bent) geometry,
    detect, match and fit (:func:`calibrate_true_view`). Deterministic for a given seed."""
    bending = bending or default_bending()
    phantom = phantom or Dodecahedron()
    p = np.asarray(primary_deg, dtype=np.float64)
    s = np.asarray(secondary_deg, dtype=np.float64)
    dev = np.zeros((p.size, s.size, 9))
    rms = []
    for i, a in enumerate(p):
        for j, b in enumerate(s):
            true = bending.true_geometry(calibration_geometry(a, b))
            result = calibrate_true_view(true, phantom=phantom, seed=_view_seed(seed, a, b))
            dev[i, j] = result.deviation
            rms.append(result.rms_px)
    meta = {
        "bending_seed": bending.seed,
        "noise_seed": seed,
        "format_cm": CALIBRATION_FORMAT_CM,
        "pixels": CALIBRATION_PIXELS,
        "max_rms_px": round(float(np.max(rms)), 4),
    }
    return CalibrationTable(p, s, dev, meta=meta)


_TABLES: dict[str, CalibrationTable] = {}


def load_calibration_table(path: Path | str | None = None) -> CalibrationTable:
    """The machine-based registration table (default ``assets/calibration_table.json``)."""
    key = str(path or TABLE_PATH)
    if key not in _TABLES:
        p = Path(key)
        if not p.exists():
            raise ValueError(f"calibration table {p} not found; build it with build_calibration_table().save(path)")
        _TABLES[key] = CalibrationTable.from_dict(json.loads(p.read_text()))
    return _TABLES[key]


def machine_based_geometry(
    primary_deg: float,
    secondary_deg: float,
    *,
    image_format_cm: float = 27.0,
    pixels: int = 512,
    nominal: CArm | None = None,
    table: CalibrationTable | None = None,
) -> CArm:
    """The machine-based registration: the geometry the calibration table predicts for the
    nominal angles, on the detector of ``nominal`` (default: ``image_format_cm``, ``pixels``)."""
    if nominal is None:
        nominal = CArm.for_format(image_format_cm, pixels=pixels)
    nominal = nominal.with_angles(primary_deg, secondary_deg)
    return (table or load_calibration_table()).geometry(nominal)


def calibration_study(*, samples: int = 50, seed: int = 0, table: CalibrationTable | None = None) -> dict[str, Any]:
    """Machine-based registration error at random nominal angles (uniform over the table's
    range) against the true geometry of the default system's bending."""
    if samples < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    table = table or load_calibration_table()
    bending = BendingModel(int(table.meta.get("bending_seed", SYSTEM_BENDING_SEED)))
    rng = np.random.default_rng(seed)
    records = []
    for _ in range(samples):
        a = float(rng.uniform(table.primary_deg[0], table.primary_deg[-1]))
        b = float(rng.uniform(table.secondary_deg[0], table.secondary_deg[-1]))
        nominal = CArm.for_format(27.0, primary_deg=a, secondary_deg=b)
        true = bending.true_geometry(nominal)
        uncorrected = machine_based_error_mm(true, nominal)
        error = machine_based_error_mm(true, table.geometry(nominal))
        records.append({"primary_deg": a, "secondary_deg": b, "error_mm": error, "uncorrected_mm": uncorrected})
    errors = [r["error_mm"] for r in records]
    return {
        "errors_mm": errors,
        "median_mm": float(np.median(errors)),
        "max_mm": float(np.max(errors)),
        "uncorrected_median_mm": float(np.median([r["uncorrected_mm"] for r in records])),
        "records": records,
        "region_radius_mm": ERROR_REGION_RADIUS_MM,
        "target_mm": 0.2,
    }


__all__ = [
    "CALIBRATION_FORMAT_CM", "CALIBRATION_PHOTONS", "CALIBRATION_PIXELS", "DEVIATION_NAMES", "ERROR_REGION_RADIUS_MM",
    "LEAD_MU_PER_MM", "PRIMARY_GRID_DEG", "SECONDARY_GRID_DEG", "SYSTEM_BENDING_SEED", "TABLE_PATH", "BendingModel",
    "CalibrationShot", "CalibrationTable", "DetectedSpheres", "Dodecahedron", "SpherePhantom", "ViewCalibration",
    "build_calibration_table", "calibrate_true_view", "calibrate_view", "calibration_geometry", "calibration_shot",
    "calibration_study", "default_bending", "detect_spheres", "deviation_vector", "error_region_points",
    "load_calibration_table", "machine_based_error_mm", "machine_based_geometry", "match_spheres",
    "simulate_calibration_image", "simulate_sphere_image", "with_deviation",
]  # fmt: skip
