"""What the app shows, prepared once: phantom, registration volumes, renderers, surface meshes.

Everything expensive is built on first use, reported through a ``progress(message, fraction)``
callback, and cached on disk by :mod:`registration.cache` (under the user's cache dir), keyed by
its parameters, so a warm start only loads arrays.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh

from app import _standins  # TEMPORARY
from registration.cache import cached_arrays
from registration.drr import DRRRenderer
from registration.volume import Volume

_standins.install()

try:  # TEMPORARY until registration.phantom / registration.xray land
    from registration.xray import XRayImage, simulate_xray

    from registration.phantom import HeadPhantom, make_head_phantom, registration_volume
except ImportError:  # pragma: no cover
    from registration.xray import XRayImage, simulate_xray

    from app._standins import (  # type: ignore[assignment]
        HeadPhantom,
        make_head_phantom,
        registration_volume,
    )

__all__ = ["AppConfig", "PhantomData", "XRayImage", "simulate_xray", "ProgressFn"]

ProgressFn = Callable[[str, float], None]


def _quiet(_message: str, _fraction: float) -> None:
    pass


@dataclass(frozen=True)
class AppConfig:
    """Sizes of what the app computes; smaller values start faster (tests use them)."""

    voxels: int = 256
    """Registration volume grid (voxels per axis)."""
    pixels: int = 512
    """X-ray image size (pixels per side)."""
    display_px: int = 384
    """Size of each 2-D tile in the panel."""
    seed: int = 0

    @classmethod
    def from_env(cls) -> AppConfig:
        """Overrides from ROADMAP3D_APP_VOXELS / ROADMAP3D_APP_PIXELS (for tests and slow machines)."""
        voxels = int(os.environ.get("ROADMAP3D_APP_VOXELS", cls.voxels))
        pixels = int(os.environ.get("ROADMAP3D_APP_PIXELS", cls.pixels))
        if not 32 <= voxels <= 512 or not 64 <= pixels <= 2048:
            raise ValueError(
                f"ROADMAP3D_APP_VOXELS must lie in 32..512 and _PIXELS in 64..2048, got {voxels}, {pixels}"
            )
        return cls(voxels=voxels, pixels=pixels)


def _mesh_arrays(meshes: dict[str, trimesh.Trimesh]) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    for name, mesh in meshes.items():
        out[f"{name}.vertices"] = np.asarray(mesh.vertices, dtype=np.float32)
        out[f"{name}.faces"] = np.asarray(mesh.faces, dtype=np.int32)
    return out


def _meshes_from_arrays(arrays: dict[str, np.ndarray]) -> dict[str, trimesh.Trimesh]:
    names = sorted({key.rsplit(".", 1)[0] for key in arrays})
    return {name: trimesh.Trimesh(arrays[f"{name}.vertices"], arrays[f"{name}.faces"], process=False) for name in names}


def surface_meshes(volume: Volume) -> dict[str, trimesh.Trimesh]:
    """The vessel and bone surfaces of ``volume`` (the engine's, or a private fallback)."""
    try:
        from registration.meshes import surface_meshes as engine_meshes
    except ImportError:
        return _fallback_meshes(volume)
    return engine_meshes(volume)


def _fallback_meshes(volume: Volume) -> dict[str, trimesh.Trimesh]:
    """Marching cubes of bone (> 600 HU) and contrast-filled vessels (250..900 HU, away from bone)."""
    from scipy import ndimage
    from skimage.measure import marching_cubes

    vol = volume.downsample(2) if max(volume.shape) > 160 else volume
    hu = vol.data
    bone = hu > 600.0
    near_bone = ndimage.binary_dilation(bone, iterations=2)
    vessels = (hu > 250.0) & (hu < 900.0) & ~near_bone
    labels, n = ndimage.label(vessels)
    if n:
        sizes = ndimage.sum_labels(vessels, labels, index=np.arange(1, n + 1))
        keep = np.flatnonzero(sizes >= max(20, sizes.max() * 0.02)) + 1
        vessels = np.isin(labels, keep)
    out: dict[str, trimesh.Trimesh] = {}
    for name, mask in (("bone", bone), ("vessels", vessels)):
        if mask.sum() < 8:
            continue
        field = ndimage.gaussian_filter(mask.astype(np.float32), 0.8)
        verts, faces, _, _ = marching_cubes(field, 0.5)
        ijk = verts[:, ::-1]  # (k, j, i) -> (i, j, k)
        world = ijk @ vol.index_to_world[:3, :3].T + vol.index_to_world[:3, 3]
        if np.linalg.det(vol.index_to_world[:3, :3]) < 0:
            faces = faces[:, ::-1]
        out[name] = trimesh.Trimesh(world, faces[:, ::-1], process=False)
    return out


class PhantomData:
    """The built-in head phantom and what is derived from it, built lazily and cached."""

    def __init__(self, config: AppConfig, progress: ProgressFn = _quiet) -> None:
        self.config = config
        self.progress = progress
        self._lock = threading.RLock()
        self._phantoms: dict[bool, HeadPhantom] = {}
        self._volumes: dict[float, Volume] = {}
        self._renderers: dict[float, DRRRenderer] = {}
        self._meshes: dict[float, dict[str, trimesh.Trimesh]] = {}
        self._vessel_points: np.ndarray | None = None

    def phantom(self, contrast: bool = True) -> HeadPhantom:
        with self._lock:
            if contrast not in self._phantoms:
                self.progress(f"Building the head phantom ({'with' if contrast else 'without'} contrast)", 0.05)
                self._phantoms[contrast] = make_head_phantom(seed=self.config.seed, contrast=contrast)
            return self._phantoms[contrast]

    def volume(self, volume_format_cm: float) -> Volume:
        """The registration volume (3DRA stand-in) of one volume format."""
        with self._lock:
            if volume_format_cm not in self._volumes:
                params = {"format_cm": volume_format_cm, "voxels": self.config.voxels, "seed": self.config.seed}

                def build() -> dict[str, np.ndarray]:
                    self.progress(
                        f"Voxelizing the phantom: {volume_format_cm:g} cm volume, {self.config.voxels}³ voxels",
                        0.2,
                    )
                    vol = registration_volume(self.phantom(True), volume_format_cm, voxels=self.config.voxels)
                    return {"data": vol.data, "index_to_world": vol.index_to_world, "label": np.array(vol.label)}

                self.progress(f"Loading the {volume_format_cm:g} cm volume", 0.15)
                arrays = cached_arrays("app-volume", params, build)
                self._volumes[volume_format_cm] = Volume(
                    arrays["data"], arrays["index_to_world"], label=str(arrays["label"])
                )
            return self._volumes[volume_format_cm]

    def renderer(self, volume_format_cm: float) -> DRRRenderer:
        with self._lock:
            if volume_format_cm not in self._renderers:
                volume = self.volume(volume_format_cm)
                self.progress("Preparing the DRR renderer", 0.6)
                self._renderers[volume_format_cm] = DRRRenderer(volume, levels=3)
            return self._renderers[volume_format_cm]

    def meshes(self, volume_format_cm: float) -> dict[str, trimesh.Trimesh]:
        with self._lock:
            if volume_format_cm not in self._meshes:
                volume = self.volume(volume_format_cm)
                params = {"format_cm": volume_format_cm, "voxels": self.config.voxels, "seed": self.config.seed}

                def build() -> dict[str, np.ndarray]:
                    self.progress("Extracting skull and vessel surfaces (marching cubes)", 0.4)
                    return _mesh_arrays(surface_meshes(volume))

                self.progress("Loading surface meshes", 0.35)
                self._meshes[volume_format_cm] = _meshes_from_arrays(cached_arrays("app-meshes", params, build))
            return self._meshes[volume_format_cm]

    def vessel_points_mm(self) -> np.ndarray:
        with self._lock:
            if self._vessel_points is None:
                self._vessel_points = np.asarray(self.phantom(True).vessel_centerline_mm(), dtype=np.float64)
            return self._vessel_points
