"""What the app's session holds besides its data: the C-arm controls' settings and the state of a
registration run (in progress, or the last one)."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.web.data import XRayImage
from registration.core.geometry import (
    DEFAULT_SID_MM,
    CArm,
    default_system,
)
from registration.core.register import Progress, RegistrationResult
from registration.sim.biplane import plane_b_spec

Array = np.ndarray

#: Plane B's angles when biplane mode starts: lateral (LAO 90), as a neuro suite's plane B.
PLANE_B_PRIMARY_DEG = 90.0


@dataclass(frozen=True)
class CArmSettings:
    """What the C-arm controls set."""

    primary_deg: float = 0.0
    secondary_deg: float = 0.0
    sid_mm: float = DEFAULT_SID_MM
    image_format_cm: float = 27.0
    volume_format_cm: float = 27.0
    kind: str = "fluoro"
    contrast: bool = True
    catheter: bool = False
    #: Biplane mode: plane B (the lateral C-arm, its own machine: sim.biplane.plane_b_spec)
    #: images the patient at the same moment; registration then searches all six offsets.
    biplane: bool = False
    primary_b_deg: float = PLANE_B_PRIMARY_DEG
    secondary_b_deg: float = 0.0

    def plane_a(self) -> tuple:
        """What plane A's image depends on (plane B's controls do not re-form it)."""
        return (self.primary_deg, self.secondary_deg, self.sid_mm, self.image_format_cm, self.kind, self.contrast,
                self.catheter)  # fmt: skip

    def geometry_b(self, pixels: int) -> CArm:
        """Plane B's nominal view: its own SID, SOD and image format (sim.biplane), ``pixels`` square."""
        return plane_b_spec().nominal(self.primary_b_deg, self.secondary_b_deg, pixels=pixels)

    def geometry(self, pixels: int) -> CArm:
        """The nominal view these settings describe (raises ValueError if impossible)."""
        pixel_mm = self.image_format_cm * 10.0 / pixels
        return CArm(
            primary_deg=self.primary_deg,
            secondary_deg=self.secondary_deg,
            sid_mm=self.sid_mm,
            sod_mm=default_system().sod_mm,
            rows=pixels,
            cols=pixels,
            pixel_mm=(pixel_mm, pixel_mm),
        )


@dataclass
class RunState:
    """A registration in progress (or the last one)."""

    running: bool = False
    iterations: list[int] | None = None
    similarity: list[float] | None = None
    temperature: list[float] | None = None
    progress: Progress | None = None
    result: RegistrationResult | None = None
    error: str | None = None
    started_s: float = 0.0
    stop_requested_s: float | None = None
    stop_latency_s: float | None = None
    #: set by Stop; the optimizer's callback reads it (one event per run)
    stop: threading.Event = field(default_factory=threading.Event)
    #: Stop came before the optimizer's first iteration: the run was let go (its result is dropped)
    abandoned: bool = False
    #: The estimate's confidence and decision (CONVENTIONS §7: ``confidence``, ``applied``,
    #: ``withheld_reason``), None while running, for a stopped run, or when it could not be assessed
    assessment: dict | None = None
    #: The roadmap's pose when the run started (the correction is measured from it) and the
    #: iso-center it is measured at (mm, world); who started the run ("Register", "Auto-correct").
    initial_motion: Array | None = None
    #: The views the run registered (plane A first); the Evidence tab and the report use them.
    views: list[XRayImage] | None = None
    isocenter_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    trigger: str = "Register"
    #: After a registration on the user's region: whether the whole volume, spine included, fits
    #: where the region's estimate says (:mod:`registration.core.skull_spine`); None otherwise.
    skull_spine: Any = None
