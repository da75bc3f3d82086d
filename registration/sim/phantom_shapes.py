"""The phantom's shapes: the :class:`HeadPhantom` type (an ordered list of primitives, each the
intersection of quadrics and half-spaces holding one HU value, evaluated exactly by
:mod:`registration.sim.phantom_kernels`) and the builder that paints primitives into one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core.geometry import check_rigid, invert_rigid, rotation_x, rotation_y, rotation_z
from registration.core.volume import MU_WATER_PER_MM
from registration.sim.phantom_kernels import (
    HU_AIR,
    bin_lines,
    bin_rays,
    line_integrals_kernel,
    source_terms,
    value_at_kernel,
    voxelize_kernel,
)

#: Most quadrics and half-spaces one primitive may intersect.
MAX_QUADRICS = 6


MAX_PLANES = 12


#: Point queries (:meth:`HeadPhantom.hu_at`, :meth:`HeadPhantom.vessel_mask_at`) treat every
#: primitive as a closed set: a point within this distance (mm) of a boundary belongs to it.
#: A vessel's centerline ends exactly on its end cap, so without it whether a tip is "inside"
#: depends on the last bit of floating-point rounding (seen differing between machines).
#: Half-space normals are unit vectors, so this is a distance; for a quadric it bounds the
#: rounding of ``|A (x - c)|^2`` near 1. Line integrals and voxels are unaffected.
POINT_TOLERANCE_MM = 1e-6


Float = NDArray[np.float64]


# --------------------------------------------------------------------------------------
# The phantom
# --------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class HeadPhantom:
    """An analytic head: ordered primitives painted one over another (module docstring).

    Arrays (P primitives): ``nq`` (P,) quadric counts, ``qcen`` (P, Q, 3) quadric
    centers (mm), ``qmat`` (P, Q, 3, 3) world-to-unit matrices (1/mm), ``npl`` (P,) plane
    counts, ``planes`` (P, K, 4) half-spaces ``n . x <= d``, ``hu`` (P,) the value inside each
    primitive, ``bsph`` (P, 4) bounding spheres (center, radius mm), ``tags`` (P,) tissue codes
    (``TAGS``). Later primitives are painted over earlier ones. ``paths`` holds the named artery
    centerlines (name, (N, 3) mm, radius mm).
    """

    nq: NDArray[np.int64]
    qcen: Float
    qmat: Float
    npl: NDArray[np.int64]
    planes: Float
    hu: Float
    bsph: Float
    tags: NDArray[np.int64]
    paths: tuple[tuple[str, Float, float], ...] = ()
    seed: int = 0
    contrast: bool = True
    facial: bool = True
    params: dict = field(default_factory=dict)

    @property
    def n_primitives(self) -> int:
        return int(self.nq.shape[0])

    @property
    def key(self) -> dict:
        """The parameters that define this phantom (for cache keys and labels)."""
        return {
            "phantom_seed": self.seed,
            "contrast": self.contrast,
            "facial": self.facial,
            "phantom_model": PHANTOM_MODEL_VERSION,
        }

    @property
    def mu_per_mm(self) -> Float:
        """Linear attenuation (1/mm) inside each primitive (``hu_to_mu_per_mm`` model)."""
        return np.maximum(MU_WATER_PER_MM * (1.0 + self.hu / 1000.0), 0.0)

    def _geometry(self) -> tuple:
        return (self.nq, self.qcen, self.qmat, self.npl, self.planes)

    # ----- line integrals ------------------------------------------------------------
    def line_integrals(self, sources_mm: ArrayLike, targets_mm: ArrayLike, motion: ArrayLike | None = None) -> Float:
        """Exact integral of ``mu`` (1/mm) along each segment source -> target.

        Parameters
        ----------
        sources_mm, targets_mm
            Segment end points, shape (N, 3) (or (3,)), broadcast against each other.
        motion
            Optional rigid 4x4 patient motion ``M`` (CONVENTIONS §4): integrate through the
            phantom moved by ``M``, i.e. along the segments mapped by ``inv(M)``.

        Returns
        -------
        (N,) float64 line integrals (dimensionless).
        """
        src, dst = _segments(sources_mm, targets_mm)
        if motion is not None:
            inv = invert_rigid(check_rigid(motion, name="motion"))
            src = src @ inv[:3, :3].T + inv[:3, 3]
            dst = dst @ inv[:3, :3].T + inv[:3, 3]
        src = np.ascontiguousarray(src)
        dst = np.ascontiguousarray(dst)
        if len(src) == 0:
            return np.zeros(0)
        order, tile_ptr, perm, cand_ptr, cand_idx = bin_rays(src, dst, self.bsph)
        pre = bool(np.all(src == src[0]))  # one common source: precompute its terms once
        qpre, ppre = source_terms(src[0] if pre else np.zeros(3), *self._geometry())
        return line_integrals_kernel(
            src,
            dst,
            order,
            tile_ptr,
            perm,
            cand_ptr,
            cand_idx,
            *self._geometry(),
            self.mu_per_mm,
            self.bsph,
            pre,
            qpre,
            ppre,
        )

    # ----- point values --------------------------------------------------------------
    def _values(self, points_mm: ArrayLike, values: Float, background: float) -> Float:
        pts = np.asarray(points_mm, dtype=np.float64)
        if pts.shape[-1:] != (3,):
            raise ValueError(f"points_mm must have shape (..., 3), got {pts.shape}")
        if not np.all(np.isfinite(pts)):
            raise ValueError("points_mm contains NaN or infinite values")
        flat = np.ascontiguousarray(pts.reshape(-1, 3))
        out = value_at_kernel(flat, *self._geometry(), values, float(background), self.bsph, POINT_TOLERANCE_MM)
        return out.reshape(pts.shape[:-1])

    def hu_at(self, points_mm: ArrayLike) -> NDArray[np.float32]:
        """HU at world points of shape (..., 3) (exact point values, no anti-aliasing)."""
        return self._values(points_mm, self.hu, HU_AIR).astype(np.float32)

    def vessel_mask_at(self, points_mm: ArrayLike) -> NDArray[np.bool_]:
        """True where a point lies inside an artery lumen or the aneurysm."""
        is_vessel = (self.tags == TAGS["vessel"]).astype(np.float64)
        return self._values(points_mm, is_vessel, 0.0) > 0.5

    def voxelize(
        self, shape: tuple[int, int, int], index_to_world: ArrayLike, *, supersample: int = 2
    ) -> NDArray[np.float32]:
        """HU on a voxel grid ``data[k, j, i]``, anti-aliased.

        Each voxel is the exact box average along the ``i`` axis (analytic chords) and the mean
        of ``supersample`` x ``supersample`` lines across ``j`` and ``k``.
        """
        shp = tuple(int(s) for s in shape)
        if len(shp) != 3 or min(shp) < 1:
            raise ValueError(f"shape must be three positive integers (k, j, i), got {shape}")
        if int(supersample) != supersample or supersample < 1:
            raise ValueError(f"supersample must be a positive integer, got {supersample}")
        aff = np.asarray(index_to_world, dtype=np.float64)
        if aff.shape != (4, 4) or not np.all(np.isfinite(aff)):
            raise ValueError("index_to_world must be a finite 4x4 matrix")
        if abs(np.linalg.det(aff[:3, :3])) < 1e-12:
            raise ValueError("index_to_world is singular")
        tile = 8
        ntj, perm, cand_ptr, cand_idx = bin_lines(shp, aff, self.bsph, tile)
        return voxelize_kernel(
            np.array(shp, dtype=np.int64),
            np.ascontiguousarray(aff),
            int(supersample),
            tile,
            perm,
            ntj,
            cand_ptr,
            cand_idx,
            *self._geometry(),
            self.hu,
            self.bsph,
        )

    # ----- vessels ---------------------------------------------------------------------
    def vessel_centerline_mm(self, *, step_mm: float = 1.0) -> Float:
        """Points along all artery centerlines, about ``step_mm`` apart, shape (N, 3)."""
        if not step_mm > 0:
            raise ValueError(f"step_mm must be positive, got {step_mm}")
        out = []
        for _name, pts, _radius in self.paths:
            out.append(_resample_polyline(pts, step_mm))
        return np.concatenate(out, axis=0) if out else np.zeros((0, 3))

    def path(self, name: str) -> tuple[Float, float]:
        """Centerline (N, 3) and radius (mm) of the named artery (for example "ica_r")."""
        for n, pts, r in self.paths:
            if n == name:
                return pts, r
        raise ValueError(f"no artery named {name!r}; known: {[p[0] for p in self.paths]}")

    @property
    def aneurysm(self) -> tuple[Float, float]:
        """Center (mm) and radius (mm) of the aneurysm."""
        return np.asarray(self.params["aneurysm_center_mm"]), float(self.params["aneurysm_radius_mm"])


TAGS = {"soft": 0, "bone": 1, "air": 2, "brain": 3, "vessel": 4, "fat": 5, "device": 6, "teeth": 7}


def _segments(sources_mm: ArrayLike, targets_mm: ArrayLike) -> tuple[Float, Float]:
    src = np.asarray(sources_mm, dtype=np.float64)
    dst = np.asarray(targets_mm, dtype=np.float64)
    if src.shape[-1:] != (3,) or dst.shape[-1:] != (3,):
        raise ValueError(f"sources and targets must have shape (N, 3), got {src.shape} and {dst.shape}")
    src, dst = np.broadcast_arrays(src.reshape(-1, 3), dst.reshape(-1, 3))
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise ValueError("sources and targets must be finite")
    return src, dst


def _resample_polyline(pts: Float, step_mm: float) -> Float:
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(2, int(math.ceil(s[-1] / step_mm)) + 1)
    si = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(si, s, pts[:, a]) for a in range(3)], axis=1)


# --------------------------------------------------------------------------------------
# Building primitives
# --------------------------------------------------------------------------------------
def _rot_to(axis: ArrayLike) -> Float:
    """A rotation whose third column is the unit vector ``axis``."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, a)
    x /= np.linalg.norm(x)
    y = np.cross(a, x)
    return np.column_stack([x, y, a])


def _euler(rx: float = 0.0, ry: float = 0.0, rz: float = 0.0) -> Float:
    """Rz @ Ry @ Rx (degrees)."""
    return rotation_z(rz) @ rotation_y(ry) @ rotation_x(rx)


@dataclass
class _Prim:
    quads: list[tuple[Float, Float]]  # (center, matrix)
    planes: list[tuple[Float, float]]  # (normal, d): inside where n . x <= d
    hu: float
    sphere: tuple[Float, float]
    group: str
    tag: str


class PhantomBuilder:
    """Collects primitives; each one is painted over those before it."""

    def __init__(self) -> None:
        self.prims: list[_Prim] = []

    # ----- shapes (return the region description, add nothing) -----------------------
    @staticmethod
    def ellipsoid(center: ArrayLike, semi: ArrayLike, rot: Float | None = None) -> dict:
        c = np.asarray(center, dtype=np.float64)
        s = np.broadcast_to(np.asarray(semi, dtype=np.float64), (3,))
        r = np.eye(3) if rot is None else rot
        m = np.diag(1.0 / s) @ r.T
        return {"quads": [(c, m)], "planes": [], "sphere": (c, float(s.max()))}

    @staticmethod
    def cylinder(p0: ArrayLike, p1: ArrayLike, semi: ArrayLike) -> dict:
        """Elliptic cylinder from p0 to p1 with flat caps; ``semi`` = (a, b) across the axis."""
        a0 = np.asarray(p0, dtype=np.float64)
        a1 = np.asarray(p1, dtype=np.float64)
        axis = a1 - a0
        length = float(np.linalg.norm(axis))
        axis = axis / length
        r = _rot_to(axis)
        s = np.broadcast_to(np.asarray(semi, dtype=np.float64), (2,))
        m = np.diag([1.0 / s[0], 1.0 / s[1], 0.0]) @ r.T
        mid = (a0 + a1) / 2
        planes = [(-axis, float(-axis @ a0)), (axis, float(axis @ a1))]
        return {
            "quads": [(mid, m)],
            "planes": planes,
            "sphere": (mid, math.hypot(length / 2, float(s.max()))),
        }

    @staticmethod
    def clip(region: dict, normal: ArrayLike, point: ArrayLike) -> dict:
        """Keep the part of ``region`` on the side ``normal . (x - point) <= 0``."""
        n = np.asarray(normal, dtype=np.float64)
        n = n / np.linalg.norm(n)
        out = dict(region)
        out["planes"] = [*region["planes"], (n, float(n @ np.asarray(point, dtype=np.float64)))]
        return out

    # ----- painting ----------------------------------------------------------------
    def paint(self, region: dict, hu: float, group: str, tag: str) -> None:
        """Make ``region`` ``hu`` HU, over whatever was painted there before."""
        if len(region["quads"]) > MAX_QUADRICS or len(region["planes"]) > MAX_PLANES:
            raise ValueError("primitive too complex")  # a builder bug, never user input
        c, r = region["sphere"]
        self.prims.append(_Prim(list(region["quads"]), list(region["planes"]), float(hu), (c, r), group, tag))

    def tube(self, pts: Float, radius: float, hu: float, group: str, tag: str = "vessel") -> None:
        """A tube of constant radius along a polyline: mitred cylinders with exact joints."""
        n = len(pts)
        dirs = np.diff(pts, axis=0)
        lengths = np.linalg.norm(dirs, axis=1)
        dirs = dirs / lengths[:, None]
        for i in range(n - 1):
            a0, a1 = pts[i], pts[i + 1]
            axis = dirs[i]
            m = np.diag([1.0 / radius, 1.0 / radius, 0.0]) @ _rot_to(axis).T
            # end planes: bisectors with the neighbouring segments (flat caps at the ends)
            n0 = -(axis + dirs[i - 1]) if i > 0 else -axis
            n1 = axis + dirs[i + 1] if i < n - 2 else axis
            n0 = n0 / np.linalg.norm(n0)
            n1 = n1 / np.linalg.norm(n1)
            # how far a mitred end reaches beyond the axis end point
            over = radius / max(min(abs(float(n0 @ axis)), abs(float(n1 @ axis))), 0.2)
            mid = (a0 + a1) / 2
            region = {
                "quads": [(mid, m)],
                "planes": [(n0, float(n0 @ a0)), (n1, float(n1 @ a1))],
                "sphere": (mid, math.hypot(lengths[i] / 2 + over, radius)),
            }
            self.paint(region, hu, group, tag)

    # ----- finishing ---------------------------------------------------------------
    def build(self, **kwargs) -> HeadPhantom:
        n = len(self.prims)
        nq = np.zeros(n, np.int64)
        qcen = np.zeros((n, MAX_QUADRICS, 3))
        qmat = np.zeros((n, MAX_QUADRICS, 3, 3))
        npl = np.zeros(n, np.int64)
        planes = np.zeros((n, MAX_PLANES, 4))
        hu = np.zeros(n)
        bsph = np.zeros((n, 4))
        tags = np.zeros(n, np.int64)
        for i, p in enumerate(self.prims):
            nq[i] = len(p.quads)
            for q, (c, m) in enumerate(p.quads):
                qcen[i, q] = c
                qmat[i, q] = m
            npl[i] = len(p.planes)
            for k, (nv, d) in enumerate(p.planes):
                planes[i, k, :3] = nv
                planes[i, k, 3] = d
            hu[i] = p.hu
            bsph[i, :3] = p.sphere[0]
            bsph[i, 3] = p.sphere[1]
            tags[i] = TAGS[p.tag]
        for arr in (nq, qcen, qmat, npl, planes, hu, bsph, tags):
            arr.flags.writeable = False  # phantoms are shared (cached): keep them immutable
        return HeadPhantom(
            nq=nq,
            qcen=qcen,
            qmat=qmat,
            npl=npl,
            planes=planes,
            hu=hu,
            bsph=bsph,
            tags=tags,
            **kwargs,
        )


#: Bump when the anatomy changes (it is part of every cache key).
PHANTOM_MODEL_VERSION = 3
