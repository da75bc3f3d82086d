"""Which simulated 3DRA: one recipe type for the registration volumes made of the head phantom.

A :class:`VolumeRecipe` names a registration volume completely (phantom variant, volume
format, grid, how it was made, where its grid is centered) and is the only place that turns
that into a volume: the studies (:mod:`registration.studies.cases`), ``roadmap3d phantom``
and the app all build their 3DRA through :meth:`VolumeRecipe.build`, so one recipe gives one
cache entry everywhere. Two ways to make one (:data:`VOLUME_SOURCES`):

- ``"fdk"``: the FDK reconstruction of a simulated rotational run with the calibrated
  geometry, as a real 3DRA (:func:`registration.sim.reconstruct.reconstruct_3dra`; minutes the
  first time, then cached);
- ``"resampled"``: the phantom voxelised on the 3DRA grid, smoothed, with noise, a quick
  stand-in (:func:`registration.sim.phantom.registration_volume`), labelled as such.

A grid centered away from the iso-center (``center_mm``) is a 3DRA made with the table moved,
as the paper's alternative 22 cm volume containing the facial structures.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING, Any

import numpy as np

from registration.core.geometry import rigid
from registration.core.volume import Volume, format_grid

if TYPE_CHECKING:
    from registration.sim.phantom import HeadPhantom

#: How a 3DRA of the phantom is made: reconstructed, or the phantom resampled (a stand-in).
VOLUME_SOURCES: tuple[str, ...] = ("fdk", "resampled")
FDK, RESAMPLED = VOLUME_SOURCES

#: The rotational run behind an off-center FDK volume (as :func:`reconstruct_3dra`'s defaults).
OFFCENTER_RUN = {"pixels": 256, "projections": 120, "kind": "exposure", "seed": 0}


@lru_cache(maxsize=4)
def _head_phantom(seed: int, contrast: bool, facial: bool) -> HeadPhantom:
    from registration.sim.phantom import make_head_phantom

    return make_head_phantom(seed=seed, contrast=contrast, facial=facial)


def _translation(t_mm: Sequence[float]) -> np.ndarray:
    return rigid(None, np.asarray(t_mm, dtype=np.float64))


@dataclass(frozen=True)
class VolumeRecipe:
    """A simulated 3DRA, completely specified (hashable: usable as a cache key in memory)."""

    phantom_seed: int = 0
    volume_format_cm: float = 27.0
    #: One of :data:`VOLUME_SOURCES`.
    source: str = FDK
    voxels: int = 256
    #: Contrast in the vessels of the imaged phantom.
    contrast: bool = True
    #: Facial structures in the phantom (the FDK volume is always made of the full phantom).
    facial: bool = True
    #: Center of the grid (world mm); not the origin: made with the table moved.
    center_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: Seed of the stand-in's added noise (``"resampled"`` only).
    noise_seed: int = 0

    def __post_init__(self) -> None:
        if self.source not in VOLUME_SOURCES:
            raise ValueError(f"volume source must be one of {VOLUME_SOURCES}, got {self.source!r}")
        fmt = float(self.volume_format_cm)
        if not math.isfinite(fmt) or fmt <= 0:
            raise ValueError(f"volume_format_cm must be positive, got {self.volume_format_cm}")
        if int(self.voxels) != self.voxels or self.voxels < 8:
            raise ValueError(f"voxels must be an integer >= 8, got {self.voxels}")
        if self.source == FDK and not self.facial:
            raise ValueError("the FDK 3DRA is reconstructed from the full phantom (facial=True)")
        if any(self.center_mm) and not self.facial:
            raise ValueError("an off-center 3DRA is made of the full phantom (facial=True)")
        center = tuple(float(c) for c in self.center_mm)
        if len(center) != 3 or not all(math.isfinite(c) for c in center):
            raise ValueError(f"center_mm must be three finite numbers, got {self.center_mm!r}")
        object.__setattr__(self, "volume_format_cm", fmt)
        object.__setattr__(self, "voxels", int(self.voxels))
        object.__setattr__(self, "center_mm", center)

    @property
    def offcenter(self) -> bool:
        return any(self.center_mm)

    @property
    def reconstructed(self) -> bool:
        """Made from a simulated rotational run (slow the first time), not resampled."""
        return self.source == FDK

    def describe(self) -> str:
        """What building it means, for progress messages."""
        if self.reconstructed:
            return (
                f"simulating the rotational run ({OFFCENTER_RUN['projections']} views) "
                f"and reconstructing it (FDK, {self.voxels}³)"
            )
        return f"voxelizing the phantom on the 3DRA grid ({self.voxels}³ voxels)"

    # ----- the cache ---------------------------------------------------------------------
    def cache_entry(self) -> tuple[str, dict[str, Any]]:
        """(kind, parameters) of the on-disk cache entry :meth:`build` loads or writes."""
        from registration.sim import phantom as ph
        from registration.sim.reconstruct import fdk_3dra_params

        if not self.offcenter:
            if self.reconstructed:
                fmt, voxels = self.volume_format_cm, self.voxels
                return "fdk-3dra", fdk_3dra_params(
                    self.phantom_seed, volume_format_cm=fmt, contrast=self.contrast, voxels=voxels
                )
            phantom = self._phantom()
            return "standin3dra", ph.standin_params(phantom, self.volume_format_cm, self.voxels, self.noise_seed)
        params = self._offcenter_params()
        if self.reconstructed:
            return "fdk-3dra-offcenter", {
                **params,
                "pixels": OFFCENTER_RUN["pixels"],
                "projections": OFFCENTER_RUN["projections"],
            }
        return "standin3dra-offcenter", {**params, "n_prims": self._phantom().n_primitives}

    def cache_key(self) -> str:
        from registration.io.cache import cache_key

        return cache_key(*self.cache_entry())

    def is_cached(self) -> bool:
        """Whether :meth:`build` would only load arrays from the cache."""
        from registration.io.cache import cache_dir

        return (cache_dir() / f"{self.cache_key()}.npz").exists()

    # ----- building -----------------------------------------------------------------------
    def _phantom(self) -> HeadPhantom:
        return _head_phantom(int(self.phantom_seed), bool(self.contrast), bool(self.facial))

    def build(self) -> Volume:
        """The volume (loaded from the on-disk cache when it was built before)."""
        if self.offcenter:
            return self._build_offcenter()
        if self.reconstructed:
            from registration.sim import reconstruct

            return reconstruct.reconstruct_3dra(
                self.phantom_seed, volume_format_cm=self.volume_format_cm, contrast=self.contrast, voxels=self.voxels
            )
        from registration.sim.phantom import registration_volume

        return registration_volume(self._phantom(), self.volume_format_cm, voxels=self.voxels, seed=self.noise_seed)

    def _offcenter_params(self) -> dict[str, Any]:
        from registration.sim.phantom import PHANTOM_MODEL_VERSION

        return {
            "phantom_model": PHANTOM_MODEL_VERSION,
            "phantom_seed": int(self.phantom_seed),
            "volume_format_cm": float(self.volume_format_cm),
            "center_mm": [float(c) for c in self.center_mm],
            "contrast": bool(self.contrast),
            "voxels": int(self.voxels),
            "source": self.source,
        }

    def _build_offcenter(self) -> Volume:
        """As on a real system, the rotational run is made with the table moved by ``-center_mm``
        (the phantom imaged moved by that translation, so ``center_mm`` sits at the iso-center
        of the run), reconstructed around the iso-center with the calibrated geometry, and put
        back into the world frame of the X-ray images by the known table shift. The stand-in
        voxelises the phantom on the shifted grid instead."""
        from registration.io.cache import cached_arrays
        from registration.sim.phantom import STAND_IN_LABEL, STAND_IN_NOISE_HU, STAND_IN_SMOOTH_VOXELS

        kind, params = self.cache_entry()
        center = np.asarray(self.center_mm, dtype=np.float64)
        phantom = self._phantom()
        voxels = self.voxels
        if not self.reconstructed:
            from scipy import ndimage

            spacing, axis = format_grid(self.volume_format_cm, voxels=voxels)
            affine = np.diag([spacing, spacing, spacing, 1.0])
            affine[:3, 3] = axis[0] + center

            def build_resampled() -> dict[str, np.ndarray]:
                hu = phantom.voxelize((voxels, voxels, voxels), affine, supersample=2)
                hu = ndimage.gaussian_filter(hu, STAND_IN_SMOOTH_VOXELS, mode="nearest")
                hu += np.random.default_rng(0).normal(0.0, STAND_IN_NOISE_HU, hu.shape).astype(np.float32)
                return {"data": hu.astype(np.float32)}

            data = cached_arrays(kind, params, build_resampled)
            return Volume(data["data"], affine, label=STAND_IN_LABEL + f", centered at {center.tolist()} mm")
        from registration.sim.reconstruct import RECONSTRUCTION_LABEL, reconstruct_run
        from registration.sim.rotational_run import rotational_run, view_seed
        from registration.sim.xray import simulate_xray

        table = _translation(-center)  # the phantom as the run sees it: moved by -center
        run_kind, seed = str(OFFCENTER_RUN["kind"]), int(OFFCENTER_RUN["seed"])
        projections = int(OFFCENTER_RUN["projections"])

        def imager(ph: object, geom: Any, index: int) -> tuple[np.ndarray, np.ndarray]:
            xr = simulate_xray(ph, geom, motion=table, kind=run_kind, seed=view_seed(seed, index))  # type: ignore[arg-type]
            return np.asarray(xr.image, np.float32), np.asarray(xr.mask, bool)

        def build_fdk() -> dict[str, np.ndarray]:
            run = rotational_run(
                phantom,
                image_format_cm=self.volume_format_cm,
                projections=projections,
                kind=run_kind,
                pixels=int(OFFCENTER_RUN["pixels"]),
                imager=imager,
            )
            vol = reconstruct_run(run, volume_format_cm=self.volume_format_cm, voxels=voxels)
            return {"data": vol.data, "index_to_world": _translation(center) @ vol.index_to_world}

        arrays = cached_arrays(kind, params, build_fdk)
        label = RECONSTRUCTION_LABEL.format(n=projections) + f", centered at {center.tolist()} mm"
        meta = {k: v for k, v in params.items() if k not in ("pixels", "projections")}
        return Volume(arrays["data"], arrays["index_to_world"], label=label, meta=meta)
