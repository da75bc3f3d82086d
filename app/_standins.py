"""TEMPORARY stand-ins for engine modules that have not landed yet (deleted once they do)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from registration.drr import DRRRenderer
from registration.geometry import CArm
from registration.volume import Volume, format_grid


@dataclass
class HeadPhantom:
    seed: int = 0
    contrast: bool = True

    def vessel_centerline_mm(self) -> np.ndarray:
        t = np.linspace(-40, 40, 60)
        return np.stack([t, 0 * t + 5, 0.3 * t], axis=1)


def make_head_phantom(*, seed: int = 0, contrast: bool = True) -> HeadPhantom:
    return HeadPhantom(seed, contrast)


def registration_volume(phantom: HeadPhantom, volume_format_cm: float, *, voxels: int = 256, seed: int = 0) -> Volume:
    spacing, axis = format_grid(volume_format_cm, voxels=voxels)
    z, y, x = np.meshgrid(axis, axis, axis, indexing="ij")
    r = np.sqrt((x / 75) ** 2 + (y / 90) ** 2 + (z / 70) ** 2)
    hu = np.full(x.shape, -1000.0, np.float32)
    hu[r < 1.08] = 40
    hu[(r > 0.92) & (r < 1.0)] = 1200
    hu[(np.abs(z + 30) < 6) & (np.abs(x) < 50) & (np.abs(y) < 40)] = 900
    if phantom.contrast:
        d = np.sqrt((y - 5) ** 2 + (z - 0.3 * x) ** 2)
        hu[(d < 3) & (np.abs(x) < 40)] = 500
    return Volume.from_grid(hu, spacing, label="stand-in phantom")


@dataclass
class XRayImage:
    image: np.ndarray
    mask: np.ndarray
    geometry: CArm
    kind: str = "fluoro"
    meta: dict = field(default_factory=dict)


_CACHE: dict = {}


def simulate_xray(
    phantom: HeadPhantom, geometry: CArm, *, motion=None, kind: str = "fluoro", catheter: bool = False, seed: int = 0
) -> XRayImage:
    key = (phantom.contrast,)
    if key not in _CACHE:
        _CACHE[key] = DRRRenderer(registration_volume(phantom, 27.0, voxels=96))
    img = _CACHE[key].render(geometry, motion)
    rng = np.random.default_rng(seed)
    img = img + rng.normal(0, 0.05 if kind == "fluoro" else 0.02, img.shape).astype(np.float32)
    mask = geometry.field_mask()
    return XRayImage(np.where(mask, img, 0).astype(np.float32), mask, geometry, kind)


def _downsample(self: XRayImage, factor: int) -> XRayImage:
    r, c = self.image.shape[0] // factor, self.image.shape[1] // factor
    img = self.image[: r * factor, : c * factor].reshape(r, factor, c, factor).mean(axis=(1, 3))
    mask = self.mask[: r * factor, : c * factor].reshape(r, factor, c, factor).all(axis=(1, 3))
    return XRayImage(img.astype(np.float32), mask, self.geometry.resized(r, c), self.kind)


XRayImage.downsample = _downsample  # type: ignore[attr-defined]


def install() -> None:
    """Register this module as registration.xray when the real one is missing."""
    import sys
    import types

    try:
        import registration.xray  # noqa: F401
    except ImportError:
        mod = types.ModuleType("registration.xray")
        mod.XRayImage = XRayImage  # type: ignore[attr-defined]
        mod.simulate_xray = simulate_xray  # type: ignore[attr-defined]
        sys.modules["registration.xray"] = mod
