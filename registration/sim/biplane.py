"""A simulated biplane angiography system (CONVENTIONS.md §6).

Plane A is the frontal C-arm (the default system: SID 1200 mm, SOD 810 mm, its bending and
``assets/calibration_table.json``); plane B is the lateral C-arm, a machine of its own: its own
SID, SOD, detector, image format, gravitational bending (another seed) and machine-based
calibration table, measured with the dodecahedron on a grid around the lateral position
(:func:`plane_b_calibration`, cached on disk). Both planes share the world frame and the
iso-center.

:func:`simulate_biplane` images the phantom moved by one patient motion through both planes'
true (bent) geometries with independent quantum noise (the two frames of one moment), and
returns the views the engine registers with: each image on its plane's machine-based
(calibrated) geometry, as a clinical system would deliver them.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike

from registration.core.geometry import DEFAULT_SID_MM, DEFAULT_SOD_MM, CArm
from registration.core.images import XRayImage
from registration.sim.calibration import (
    SYSTEM_BENDING_SEED,
    BendingModel,
    CalibrationTable,
    build_calibration_table,
    load_calibration_table,
)
from registration.sim.phantom import HeadPhantom
from registration.sim.xray import Attenuator, simulate_xray

#: Plane identification (DICOM Plane Identification 0018,9457).
PLANE_A, PLANE_B = "PLANE A", "PLANE B"

#: Seed of plane B's bending (plane A is the default system, seed SYSTEM_BENDING_SEED).
PLANE_B_BENDING_SEED = 1
#: Plane B's calibration grid: around the lateral position (LAO/RAO 90), degrees.
PLANE_B_PRIMARY_GRID_DEG = (50.0, 70.0, 90.0, 110.0, 130.0)
PLANE_B_SECONDARY_GRID_DEG = (-40.0, -20.0, 0.0, 20.0, 40.0)


@dataclass(frozen=True)
class PlaneSpec:
    """One C-arm of a biplane system: distances, detector mode and bending."""

    name: str
    sid_mm: float
    sod_mm: float
    image_format_cm: float
    pixels: int
    bending_seed: int

    def nominal(self, primary_deg: float, secondary_deg: float, *, pixels: int | None = None) -> CArm:
        """The plane's nominal view at the given angles (``pixels`` overrides the detector mode)."""
        n = int(pixels or self.pixels)
        pixel = self.image_format_cm * 10.0 / n
        return CArm(
            primary_deg=primary_deg,
            secondary_deg=secondary_deg,
            sid_mm=self.sid_mm,
            sod_mm=self.sod_mm,
            rows=n,
            cols=n,
            pixel_mm=(pixel, pixel),
        )

    @property
    def bending(self) -> BendingModel:
        return BendingModel(self.bending_seed)


def plane_a_spec(*, image_format_cm: float = 27.0, pixels: int = 512) -> PlaneSpec:
    """The frontal plane: the default system."""
    return PlaneSpec(PLANE_A, DEFAULT_SID_MM, DEFAULT_SOD_MM, image_format_cm, pixels, SYSTEM_BENDING_SEED)


def plane_b_spec(*, image_format_cm: float = 22.0, pixels: int = 384) -> PlaneSpec:
    """The lateral plane: a shorter arm with a smaller detector (its own machine)."""
    return PlaneSpec(PLANE_B, 1150.0, 760.0, image_format_cm, pixels, PLANE_B_BENDING_SEED)


_B_TABLES: dict[int, CalibrationTable] = {}


def plane_b_calibration(seed: int = PLANE_B_BENDING_SEED) -> CalibrationTable:
    """Plane B's machine-based registration table: the dodecahedron imaged and fitted on
    its grid with its own (bent) geometry; built once and cached on disk."""
    if seed not in _B_TABLES:
        from registration.io.cache import cached_arrays

        bending = BendingModel(seed)
        params = {"bending_seed": seed, "primary": PLANE_B_PRIMARY_GRID_DEG, "secondary": PLANE_B_SECONDARY_GRID_DEG}

        def build() -> dict[str, np.ndarray]:
            table = build_calibration_table(
                bending, primary_deg=PLANE_B_PRIMARY_GRID_DEG, secondary_deg=PLANE_B_SECONDARY_GRID_DEG, seed=seed
            )
            return {"deviations": table.deviations}

        arrays = cached_arrays("plane-b-calibration", params, build)
        _B_TABLES[seed] = CalibrationTable(
            np.array(PLANE_B_PRIMARY_GRID_DEG), np.array(PLANE_B_SECONDARY_GRID_DEG), arrays["deviations"],
            meta={"bending_seed": seed, "plane": PLANE_B},
        )  # fmt: skip
    return _B_TABLES[seed]


@dataclass(frozen=True)
class BiplaneSystem:
    """Two C-arms imaging one patient at the same moment."""

    plane_a: PlaneSpec = field(default_factory=plane_a_spec)
    plane_b: PlaneSpec = field(default_factory=plane_b_spec)

    def planes(self) -> tuple[PlaneSpec, PlaneSpec]:
        return (self.plane_a, self.plane_b)

    def true_geometry(self, plane: PlaneSpec, nominal: CArm) -> CArm:
        return plane.bending.true_geometry(nominal)

    def calibrated_geometry(self, plane: PlaneSpec, nominal: CArm) -> CArm:
        """The machine-based geometry the plane's own calibration table predicts."""
        table = load_calibration_table() if plane.name == PLANE_A else plane_b_calibration(plane.bending_seed)
        return table.geometry(nominal)


@dataclass(frozen=True)
class BiplaneShot:
    """The two frames of one moment: views on calibrated geometries, and the truth."""

    views: tuple[XRayImage, XRayImage]
    true_geometries: tuple[CArm, CArm]
    motion: np.ndarray


def simulate_biplane(
    phantom: HeadPhantom | Attenuator,
    angles_deg: tuple[tuple[float, float], tuple[float, float]] = ((0.0, 0.0), (90.0, 0.0)),
    *,
    motion: ArrayLike | None = None,
    system: BiplaneSystem | None = None,
    kind: str = "fluoro",
    seed: int = 0,
    pixels: tuple[int | None, int | None] = (None, None),
    calibrated: bool = True,
    isocenter_mm: ArrayLike | None = None,
) -> BiplaneShot:
    """Image ``phantom`` (or any :class:`~registration.sim.xray.Attenuator`, e.g. a CT's
    :class:`~registration.sim.volume_xray.VolumeAttenuator`) moved by ``motion`` through both
    planes at the same moment.

    ``angles_deg``: (primary, secondary) of plane A and of plane B. Each plane's image is
    formed with its true (bent) geometry (:func:`~registration.sim.xray.simulate_xray`: exact
    line integrals, Poisson noise) with its own noise stream; each view carries the plane's
    machine-based geometry when ``calibrated`` (else the true one) and ``meta["plane"]``.
    ``isocenter_mm``: both planes' iso-center in the world (default: the origin).
    """
    system = system or BiplaneSystem()
    m = np.eye(4) if motion is None else np.asarray(motion, dtype=np.float64)
    views, trues = [], []
    for plane, (primary, secondary), n in zip(system.planes(), angles_deg, pixels, strict=True):
        nominal = plane.nominal(primary, secondary, pixels=n)
        if isocenter_mm is not None:
            nominal = replace(nominal, isocenter_mm=tuple(float(v) for v in np.asarray(isocenter_mm).reshape(3)))
        true = system.true_geometry(plane, nominal)
        noise_seed = int((int(seed) * 1_000_003 + zlib.crc32(plane.name.encode())) % (2**31 - 1))
        image = simulate_xray(phantom, true, motion=m, kind=kind, seed=noise_seed)
        geometry = system.calibrated_geometry(plane, nominal) if calibrated else true
        meta = {**image.meta, "plane": plane.name, "true_geometry": true.to_dict()}
        views.append(XRayImage(image.image, image.mask, geometry, image.kind, meta))
        trues.append(true)
    return BiplaneShot((views[0], views[1]), (trues[0], trues[1]), m)
