"""Volumes: an array in Hounsfield units plus the affine to world millimetres.

``data[k, j, i]`` (slice, row, column) and ``index_to_world`` mapping (i, j, k, 1) to world
millimetres, voxel centers at integer indices (CONVENTIONS.md §2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from registration.core.geometry import default_system

Array = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Volume:
    """A 3-D image in HU with its ``index_to_world`` affine.

    ``label`` says where the volume came from (for example "phantom resampled to the 3DRA
    grid (stand-in for a reconstruction)"); outputs repeat it so nobody mistakes a stand-in
    for a reconstruction.
    """

    data: NDArray[np.float32]
    index_to_world: Array
    label: str = ""
    meta: dict = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        data = np.asarray(self.data)
        if data.ndim != 3:
            raise ValueError(f"volume data must be 3-D (slice, row, column), got shape {data.shape}")
        if min(data.shape) < 2:
            raise ValueError(f"volume must have at least 2 voxels along each axis, got {data.shape}")
        if not np.issubdtype(data.dtype, np.number):
            raise ValueError(f"volume data must be numeric, got dtype {data.dtype}")
        with np.errstate(over="ignore"):  # values beyond float32 are reported below
            source, data = data, np.ascontiguousarray(data, dtype=np.float32)
        # the float64 sum of float32 values cannot overflow: it is finite iff every voxel is
        if not math.isfinite(float(np.sum(data, dtype=np.float64))):
            bad = ~np.isfinite(data)
            too_large = int(np.count_nonzero(bad & np.isfinite(source))) if source.dtype != np.float32 else 0
            if too_large:
                raise ValueError(
                    f"volume has {too_large} voxels beyond float32's range (|value| > "
                    f"{float(np.finfo(np.float32).max):.3g}): rescale the intensities"
                )
            raise ValueError(f"volume contains {int(np.count_nonzero(bad))} NaN or infinite voxels")
        affine = np.asarray(self.index_to_world, dtype=np.float64)
        if affine.shape != (4, 4) or not np.all(np.isfinite(affine)):
            raise ValueError("index_to_world must be a finite 4x4 matrix")
        if not np.allclose(affine[3], [0, 0, 0, 1]):
            raise ValueError("index_to_world must have last row (0, 0, 0, 1)")
        spacing = np.linalg.norm(affine[:3, :3], axis=0)
        if np.any(spacing <= 1e-9):
            raise ValueError(f"voxel spacing must be positive, got {spacing.tolist()} mm")
        if abs(np.linalg.det(affine[:3, :3])) < 1e-12:
            raise ValueError("index_to_world is singular (degenerate voxel axes)")
        object.__setattr__(self, "data", data)
        object.__setattr__(self, "index_to_world", affine)

    # ----- construction ------------------------------------------------------------
    @classmethod
    def from_grid(
        cls,
        data: ArrayLike,
        spacing_mm: float | tuple[float, float, float],
        *,
        center_mm: ArrayLike = (0.0, 0.0, 0.0),
        label: str = "",
    ) -> Volume:
        """An axis-aligned (LPS) volume centered at ``center_mm``; spacing as (x, y, z)."""
        arr = np.asarray(data)
        sp = np.broadcast_to(np.asarray(spacing_mm, dtype=np.float64), (3,))
        if not np.all(np.isfinite(sp)) or np.any(sp <= 0):
            raise ValueError(f"spacing_mm must be positive and finite, got {spacing_mm}")
        if arr.ndim != 3:
            raise ValueError(f"volume data must be 3-D, got shape {arr.shape}")
        nk, nj, ni = arr.shape
        affine = np.diag([sp[0], sp[1], sp[2], 1.0])
        half = (np.array([ni, nj, nk]) - 1) / 2.0 * sp
        affine[:3, 3] = np.asarray(center_mm, dtype=np.float64) - half
        return cls(data=arr, index_to_world=affine, label=label)

    def __repr__(self) -> str:
        """A line a notebook shows: the grid, the spacing, the values and the label (not the voxels)."""
        nk, nj, ni = self.shape
        spacing = ", ".join(f"{s:.3g}" for s in self.spacing_mm)
        label = f", label={self.label!r}" if self.label else ""
        return (f"{type(self).__name__}({ni}x{nj}x{nk} voxels (i, j, k), spacing ({spacing}) mm, "
                f"values {float(self.data.min()):.6g} to {float(self.data.max()):.6g}{label})")  # fmt: skip

    # ----- properties --------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.data.shape)  # type: ignore[return-value]

    @property
    def spacing_mm(self) -> Array:
        """Voxel spacing along (i, j, k) in mm."""
        return np.linalg.norm(self.index_to_world[:3, :3], axis=0)

    @property
    def index_from_world(self) -> Array:
        """World millimetres to voxel indices (i, j, k): the inverse of ``index_to_world``."""
        return np.linalg.inv(self.index_to_world)

    @property
    def center_mm(self) -> Array:
        nk, nj, ni = self.shape
        return self.index_to_world[:3, :3] @ (np.array([ni, nj, nk]) - 1) / 2.0 + self.index_to_world[:3, 3]

    def world_corners_mm(self) -> Array:
        """The 8 corner voxel centers in world mm, shape (8, 3)."""
        nk, nj, ni = self.shape
        idx = np.array([[i, j, k] for k in (0, nk - 1) for j in (0, nj - 1) for i in (0, ni - 1)], float)
        return idx @ self.index_to_world[:3, :3].T + self.index_to_world[:3, 3]

    def with_data(self, data: ArrayLike, *, label: str | None = None) -> Volume:
        return replace(self, data=np.asarray(data), label=self.label if label is None else label)

    # ----- resampling --------------------------------------------------------------
    def downsample(self, factor: int | tuple[int, int, int] = 2) -> Volume:
        """Average blocks of ``factor`` voxels along each axis (one number: ``factor``^3 blocks, a
        pyramid level; three: per axis, i j k); the affine keeps voxel centers exact."""
        fi, fj, fk = (factor,) * 3 if np.isscalar(factor) else tuple(factor)  # type: ignore[misc]
        if (fi, fj, fk) == (1, 1, 1):
            return self
        if min(fi, fj, fk) < 1 or any(int(f) != f for f in (fi, fj, fk)):
            raise ValueError(f"factor must be a positive integer, got {factor}")
        fi, fj, fk = int(fi), int(fj), int(fk)
        nk, nj, ni = self.shape[0] // fk, self.shape[1] // fj, self.shape[2] // fi
        if min(nk, nj, ni) < 2:
            raise ValueError(f"volume {self.shape} too small to downsample by {factor}: at least "
                             f"{2 * max(fi, fj, fk)} voxels along each axis are needed")  # fmt: skip
        d = self.data[: nk * fk, : nj * fj, : ni * fi]
        d = d.reshape(nk, fk, nj, fj, ni, fi).mean(axis=(1, 3, 5), dtype=np.float64)
        affine = self.index_to_world.copy()
        affine[:3, :3] = self.index_to_world[:3, :3] @ np.diag([fi, fj, fk]).astype(np.float64)
        shift = (np.array([fi, fj, fk], dtype=np.float64) - 1) / 2.0
        affine[:3, 3] = self.index_to_world[:3, :3] @ shift + self.index_to_world[:3, 3]
        return Volume(d.astype(np.float32), affine, label=self.label, meta=self.meta)

    def pyramid(self, levels: int) -> list[Volume]:
        """[full, /2, /4, ...] of length ``levels`` (fewer if the volume gets too small)."""
        out = [self]
        for _ in range(levels - 1):
            if min(out[-1].shape) < 8:
                break
            out.append(out[-1].downsample(2))
        return out

    def sample(self, points_mm: ArrayLike, *, order: int = 1, cval: float = -1000.0) -> NDArray[np.float32]:
        """Interpolate HU at world points (..., 3); outside the volume gives ``cval``."""
        pts = np.asarray(points_mm, dtype=np.float64)
        index_from_world = self.index_from_world
        idx = pts @ index_from_world[:3, :3].T + index_from_world[:3, 3]
        coords = idx[..., ::-1].reshape(-1, 3).T  # (k, j, i)
        out = ndimage.map_coordinates(self.data, coords, order=order, mode="constant", cval=cval)
        return out.reshape(pts.shape[:-1]).astype(np.float32)


def format_grid(
    volume_format_cm: float, *, voxels: int | None = None, center_mm: ArrayLike = (0.0, 0.0, 0.0)
) -> tuple[float, np.ndarray]:
    """Spacing (mm) and the world coordinates of voxel centers along one axis for a 3DRA format.

    A volume format f covers f x SOD / SID at the iso-center (assets/carm_system.txt).
    """
    system = default_system()
    n = voxels or system.volume_voxels
    fov = system.volume_fov_mm(volume_format_cm)
    spacing = fov / n
    axis = (np.arange(n) - (n - 1) / 2.0) * spacing
    return spacing, axis


#: Linear attenuation of water (1/mm) at the effective energy (~60 keV) that defines 0 HU: the
#: one value the phantom, the X-ray image model, the DRR and the FDK reconstruction share.
MU_WATER_PER_MM = 0.0206


def hu_to_mu_per_mm(hu: ArrayLike, *, mu_water_per_mm: float = MU_WATER_PER_MM) -> NDArray[np.float32]:
    """Linear attenuation (1/mm) from HU at an effective energy (default water at ~60 keV)."""
    # the same operations in the same order as mu_w * (1 + hu / 1000), in place: -1000 HU is 0 exactly
    mu = np.array(hu, dtype=np.float32)  # a copy: the input is left alone
    mu /= np.float32(1000.0)
    mu += np.float32(1.0)
    mu *= np.float32(mu_water_per_mm)
    np.maximum(mu, np.float32(0.0), out=mu)
    return mu if mu.ndim else mu[()]
