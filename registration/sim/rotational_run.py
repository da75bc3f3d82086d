"""The rotational run: a propeller rotation of the C-arm imaging the patient (paper section II.A).

The primary angle sweeps ~200 degrees (secondary 0) over ~120 projections. The images are
formed with the *true* (bent) geometry of each view
(:class:`registration.sim.bending.BendingModel`); the geometry a reconstruction may use is
the one *calibrated* from a dodecahedron run with the same angles
(:func:`registration.sim.dodecahedron.calibrate_true_view`), as on a real system. The FDK
reconstruction of a run is :mod:`registration.sim.reconstruct`.

:class:`RunRecipe` names a simulated run of the head phantom completely and caches its
images: what a viewer steps through (the app's calibration tab).

Conventions (frames, angles, units) are those of ``shared/CONVENTIONS.md``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core.geometry import CArm
from registration.sim.bending import BendingModel, default_bending, with_deviation
from registration.sim.dodecahedron import calibrate_true_view, calibration_geometry

Array = NDArray[np.float64]

#: The protocol of the project's rotational runs (the reconstruction's defaults).
RUN_PROJECTIONS = 120
RUN_ARC_DEG = 200.0


@dataclass(frozen=True)
class RotationalRun:
    """Images of a propeller run with the geometry they were formed with and the calibrated one.

    ``images[i]`` is the attenuation image (CONVENTIONS §5) of view i, ``masks[i]`` its
    collimated field; ``true_geometries`` formed the images, ``calibrated_geometries`` are what
    the dodecahedron calibration estimated (the reconstruction uses only those).
    """

    images: NDArray[np.float32]
    masks: NDArray[np.bool_]
    primary_deg: Array
    true_geometries: tuple[CArm, ...]
    calibrated_geometries: tuple[CArm, ...]
    kind: str = "exposure"

    def __len__(self) -> int:
        return int(self.images.shape[0])

    @property
    def nominal_geometries(self) -> tuple[CArm, ...]:
        return tuple(g.nominal() for g in self.true_geometries)


#: An image former: (phantom, true geometry, view index) -> (attenuation image, field mask).
Imager = Callable[[object, CArm, int], tuple[NDArray[np.float32], NDArray[np.bool_]]]


def view_seed(seed: int, index: int) -> int:
    """Noise seed of view ``index`` of a run simulated with ``seed`` (every run uses this)."""
    return seed * 100003 + index


class RunStopped(Exception):
    """A rotational run's ``progress`` callback asked to stop."""


#: Progress of a run being simulated: (views done, views in all) -> True to stop.
RunProgress = Callable[[int, int], bool]


def run_angles(projections: int, arc_deg: float) -> Array:
    """Nominal primary angles of a propeller run: ``projections`` evenly over ``arc_deg``,
    centered on the frontal view (0 degrees)."""
    if projections < 2:
        raise ValueError(f"projections must be >= 2, got {projections}")
    if not 180.0 < arc_deg <= 360.0:
        raise ValueError(f"arc_deg must exceed 180 (a short scan needs 180 + fan angle), got {arc_deg}")
    return np.linspace(-arc_deg / 2.0, arc_deg / 2.0, projections)


def calibrate_protocol(
    primary_deg: ArrayLike,
    *,
    bending: BendingModel | None = None,
    seed: int = 0,
    cache: bool = True,
) -> Array:
    """Deviation parameters (views x 9) of a rotational protocol, from a dodecahedron run.

    As on a real system the calibration run has the protocol's angles and is made once per
    system and protocol (here: cached by bending seed, angles and noise seed), then used for
    every 3D acquisition with that protocol. Each view is imaged with the true geometry and
    calibrated from its image alone (:func:`registration.sim.dodecahedron.calibrate_true_view`).
    """
    from registration.io.cache import cached_arrays

    bending = bending or default_bending()
    angles = np.asarray(primary_deg, dtype=np.float64).reshape(-1)

    def build() -> dict[str, np.ndarray]:
        dev = np.zeros((angles.size, 9))
        for i, a in enumerate(angles):
            true = bending.true_geometry(calibration_geometry(float(a), 0.0))
            dev[i] = calibrate_true_view(true, seed=seed * 7919 + i).deviation
        return {"deviations": dev}

    params = {
        "bending_seed": bending.seed,
        "bending": [bending.source_amplitude_mm, bending.detector_amplitude_mm, bending.tilt_amplitude_deg],
        "angles": np.round(angles, 6).tolist(),
        "seed": int(seed),
    }
    return cached_arrays("calibration-run", params, build, enabled=cache)["deviations"]


def rotational_run(
    phantom: object,
    *,
    image_format_cm: float,
    projections: int = RUN_PROJECTIONS,
    arc_deg: float = RUN_ARC_DEG,
    kind: str = "exposure",
    bending: BendingModel | None = None,
    pixels: int = 512,
    seed: int = 0,
    imager: Imager | None = None,
    calibrate: bool = True,
    calibration_seed: int = 0,
    supersample: int | None = None,
    progress: RunProgress | None = None,
) -> RotationalRun:
    """Simulate a rotational run of ``phantom`` and calibrate its geometry.

    Each view's image is formed with the true (bent) geometry by ``imager`` (default:
    :func:`registration.sim.xray.simulate_xray` with ``kind`` and a per-view seed). The calibrated
    geometries come from a dodecahedron run with the same nominal angles
    (:func:`calibrate_protocol`, noise seed ``calibration_seed``); with ``calibrate=False``
    they are the nominal geometries (what an uncalibrated system would use). ``supersample``
    (default: simulate_xray's) sets the default imager's sub-pixel rays; ``progress`` is called
    after each view and may stop the run (:class:`RunStopped` is raised).
    """
    bending = bending or default_bending()
    angles = run_angles(projections, arc_deg)
    if imager is None:
        from registration.sim.xray import SUPERSAMPLE, simulate_xray

        rays = SUPERSAMPLE if supersample is None else supersample

        def imager(ph: object, geom: CArm, index: int) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
            xr = simulate_xray(ph, geom, kind=kind, seed=view_seed(seed, index), supersample=rays)  # type: ignore[arg-type]
            return np.asarray(xr.image, np.float32), np.asarray(xr.mask, bool)

    deviations = calibrate_protocol(angles, bending=bending, seed=calibration_seed) if calibrate else None
    images, masks, true_geoms, cal_geoms = [], [], [], []
    for index, angle in enumerate(angles):
        nominal = CArm.for_format(image_format_cm, pixels=pixels, primary_deg=float(angle))
        true = bending.true_geometry(nominal)
        image, mask = imager(phantom, true, index)
        images.append(np.asarray(image, np.float32))
        masks.append(np.asarray(mask, bool))
        true_geoms.append(true)
        cal_geoms.append(nominal if deviations is None else with_deviation(nominal, deviations[index]))
        if progress is not None and progress(index + 1, len(angles)):
            raise RunStopped(f"the rotational run was stopped after {index + 1} of {len(angles)} views")
    return RotationalRun(
        images=np.stack(images),
        masks=np.stack(masks),
        primary_deg=angles,
        true_geometries=tuple(true_geoms),
        calibrated_geometries=tuple(cal_geoms),
        kind=kind,
    )


@dataclass(frozen=True)
class RunRecipe:
    """A simulated rotational run of the head phantom, images only (no calibration), cached by
    every field. The views use :func:`view_seed` and the default bending, as every run."""

    phantom_seed: int = 0
    image_format_cm: float = 27.0
    projections: int = RUN_PROJECTIONS
    arc_deg: float = RUN_ARC_DEG
    pixels: int = 256
    kind: str = "exposure"
    contrast: bool = True
    seed: int = 0
    supersample: int = 2

    def angles(self) -> Array:
        """Nominal primary angles of the views."""
        return run_angles(self.projections, self.arc_deg)

    def nominal_geometry(self, index: int) -> CArm:
        return CArm.for_format(self.image_format_cm, pixels=self.pixels, primary_deg=float(self.angles()[index]))

    def cache_entry(self) -> tuple[str, dict]:
        """(kind, parameters) of the on-disk cache entry of :meth:`images`."""
        from registration.sim.phantom import PHANTOM_MODEL_VERSION

        return "rotational-run", {
            "phantom_seed": int(self.phantom_seed),
            "phantom_model": PHANTOM_MODEL_VERSION,
            "contrast": bool(self.contrast),
            "image_format_cm": float(self.image_format_cm),
            "projections": int(self.projections),
            "arc_deg": float(self.arc_deg),
            "pixels": int(self.pixels),
            "kind": self.kind,
            "seed": int(self.seed),
            "supersample": int(self.supersample),
            "bending_seed": default_bending().seed,
        }

    def is_cached(self) -> bool:
        """Whether :meth:`images` would only load arrays from the cache."""
        from registration.io.cache import cache_dir, cache_key

        return (cache_dir() / f"{cache_key(*self.cache_entry())}.npz").exists()

    def images(
        self, *, progress: RunProgress | None = None, cache: bool = True
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """(images, masks) of the run's views, simulated (``progress`` per view) or loaded."""
        from registration.io.cache import cached_arrays

        def build() -> dict[str, np.ndarray]:
            from registration.sim.phantom import make_head_phantom

            run = rotational_run(
                make_head_phantom(seed=self.phantom_seed, contrast=self.contrast),
                image_format_cm=self.image_format_cm,
                projections=self.projections,
                arc_deg=self.arc_deg,
                kind=self.kind,
                pixels=self.pixels,
                seed=self.seed,
                calibrate=False,
                supersample=self.supersample,
                progress=progress,
            )
            return {"images": run.images, "masks": run.masks}

        arrays = cached_arrays(*self.cache_entry(), build, enabled=cache)
        return arrays["images"], arrays["masks"].astype(bool)
