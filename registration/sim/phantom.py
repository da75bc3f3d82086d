"""Analytic head phantom in Hounsfield units, and the stand-in registration volume.

The phantom is a FORBILD-like, ordered list of primitives in world millimetres
(CONVENTIONS.md §1: LPS, the circle of Willis near the iso-center). Each primitive is the
intersection of up to ``MAX_QUADRICS`` quadrics ``|A (x - c)|^2 <= 1`` (an ellipsoid, or an
elliptic cylinder when a row of ``A`` is zero) and up to ``MAX_PLANES`` half-spaces
``n . x <= d``, and holds one tissue value in HU. Later primitives are painted over earlier
ones (the scalp, then the skull, then the sinuses carved into it, then the arteries), so a
sinus is exactly air whatever lay there, and no point is ever below air (-1000 HU).

Everything is evaluated exactly: a point takes the value of the newest primitive holding it,
and the line integral of ``mu`` along a segment is the sum over the visible pieces of each
primitive's chord (painter's algorithm along the ray, newest first) times its attenuation
``mu = MU_WATER_PER_MM (1 + HU / 1000)`` per mm (:func:`registration.core.volume.hu_to_mu_per_mm`, air 0).
No sampling, no grid: the phantom is resolution independent. The compiled kernels that do
this (and the ray culling) are :mod:`registration.sim.phantom_kernels`; this module holds the
:class:`HeadPhantom` type, the anatomy that builds it and the stand-in volume.

Anatomy (world mm; +x left, +y posterior, +z superior): scalp over a skull of outer table,
diploe and inner table whose floor is a bowl (anterior fossa ~ z -5, posterior fossa ~ z -45);
brain with ventricles; sphenoid body with sinus, sella turcica, dorsum, clinoids and greater
wings; clivus; petrous bones with inner ear and internal auditory canal; mastoids with air
cells; ear canals; frontal sinuses; the facial skeleton (orbits with fat and globes, zygoma
and arches, maxillary sinuses, ethmoid cells, nasal cavity, septum, turbinates, nasal bones,
hard palate, maxillary and mandibular arches, 28 teeth with enamel crowns); cervical spine,
spinal cord, airway and hyoid; and the arteries (internal carotids, vertebrals, basilar,
circle of Willis, ACA/MCA/PCA with branches) with a ~7 mm aneurysm at the left MCA
bifurcation. The circle of Willis lies around the origin (the ICA termini at x = +-14 mm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from registration.core.geometry import check_rigid, invert_rigid, rotation_x, rotation_y, rotation_z
from registration.core.volume import MU_WATER_PER_MM, Volume, format_grid
from registration.io.cache import cached_arrays
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

#: Bump when the anatomy changes (it is part of every cache key).
PHANTOM_MODEL_VERSION = 3

#: Length of the straight pieces that make up an artery (mm). Neighbouring pieces meet on
#: their bisecting plane (a mitre joint), which joins tubes of one radius without gap or
#: overlap; the arteries bend by at most ~45 degrees per joint.
VESSEL_STEP_MM = 4.0

#: Label every output of :func:`registration_volume` carries.
STAND_IN_LABEL = "phantom resampled to the 3DRA grid (stand-in for a reconstruction)"

# Tissue values (HU) of the phantom (air, HU_AIR, is the kernels' background).
HU_SOFT = 40.0  # scalp, muscle, neck
HU_FAT = -80.0  # orbital fat
HU_EYE = 10.0
HU_BRAIN = 35.0
HU_CSF = 5.0
HU_CORTICAL = 1700.0  # inner and outer tables
HU_DIPLOE = 600.0
HU_PETROUS = 2000.0
HU_FACIAL_BONE = 1100.0
HU_ENAMEL = 2800.0
HU_BLOOD = 40.0
HU_CONTRAST = 540.0  # iodine-filled lumen (~ +500 HU over blood)

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


class _Builder:
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


# --------------------------------------------------------------------------------------
# The anatomy
# --------------------------------------------------------------------------------------
def _catmull_rom(ctrl: Float, step_mm: float = 2.5) -> Float:
    """A smooth curve through the control points, sampled about ``step_mm`` apart."""
    ctrl = np.asarray(ctrl, dtype=np.float64)
    if len(ctrl) == 2:
        return _resample_polyline(ctrl, step_mm)
    p = np.vstack([2 * ctrl[0] - ctrl[1], ctrl, 2 * ctrl[-1] - ctrl[-2]])
    out = [ctrl[:1]]
    for i in range(1, len(p) - 2):
        p0, p1, p2, p3 = p[i - 1], p[i], p[i + 1], p[i + 2]
        n = max(1, int(math.ceil(np.linalg.norm(p2 - p1) / step_mm)))
        t = (np.arange(1, n + 1) / n)[:, None]
        seg = 0.5 * (
            2 * p1 + (-p0 + p2) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t**2 + (-p0 + 3 * p1 - 3 * p2 + p3) * t**3
        )
        out.append(seg)
    return np.vstack(out)


class _Variation:
    """Seeded anatomical variation; seed 0 is the canonical phantom (no variation)."""

    def __init__(self, seed: int) -> None:
        self.on = seed != 0
        rng = np.random.default_rng(seed)
        self.rng = rng
        self.scale = 1.0 + (rng.normal(0.0, 0.03, 3) if self.on else np.zeros(3))
        # a smooth displacement field for vessel paths (mm): three random plane waves
        self.k = rng.normal(0.0, 2 * math.pi / 70.0, (3, 3))
        self.phase = rng.uniform(0, 2 * math.pi, 3)
        self.amp = rng.normal(0.0, 1.5, (3, 3)) if self.on else np.zeros((3, 3))

    def pos(self, p: ArrayLike) -> Float:
        return np.asarray(p, dtype=np.float64) * self.scale

    def size(self, s: ArrayLike, rel: float = 0.0) -> Float:
        s = np.asarray(s, dtype=np.float64)
        jitter = 1.0 + (self.rng.normal(0.0, rel) if (self.on and rel > 0) else 0.0)
        if s.shape == (3,):
            return s * self.scale * jitter
        return s * float(np.mean(self.scale)) * jitter

    def jitter(self, sigma: float, n: int = 3) -> Float:
        return self.rng.normal(0.0, sigma, n) if self.on else np.zeros(n)

    def vessel(self, pts: ArrayLike) -> Float:
        p = self.pos(pts)
        disp = np.zeros_like(p)
        for w in range(3):
            disp += np.sin(p @ self.k[w] + self.phase[w])[:, None] * self.amp[w]
        return p + disp


def _mirror(p: ArrayLike, side: float) -> Float:
    q = np.array(p, dtype=np.float64)
    q[..., 0] *= side
    return q


def make_head_phantom(*, seed: int = 0, contrast: bool = True, facial: bool = True) -> HeadPhantom:
    """The analytic head phantom (HU), world mm, circle of Willis near the origin.

    Parameters
    ----------
    seed
        Anatomical variant: 0 is the canonical head; other seeds perturb sizes (~3 %),
        positions and vessel paths (~1.5 mm) slightly.
    contrast
        Iodine in the arteries (lumen ~ +540 HU) or plain blood (~ 40 HU).
    facial
        Include the facial skeleton: orbits, maxilla, zygoma, nasal cavity and maxillary and
        ethmoid sinuses, mandible and teeth.

    Returns
    -------
    HeadPhantom
        About 150 mm left-right, 190 mm anterior-posterior, 220 mm from vertex to chin, plus
        a neck with the cervical spine and airway.
    """
    if int(seed) != seed or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed}")
    return _cached_phantom(int(seed), bool(contrast), bool(facial))


_PHANTOMS: dict[tuple[int, bool, bool], HeadPhantom] = {}


def _cached_phantom(seed: int, contrast: bool, facial: bool) -> HeadPhantom:
    key = (seed, contrast, facial)
    if key not in _PHANTOMS:
        if len(_PHANTOMS) > 8:
            _PHANTOMS.clear()
        _PHANTOMS[key] = _build_phantom(seed, contrast, facial)
    return _PHANTOMS[key]


def _build_phantom(seed: int, contrast: bool, facial: bool) -> HeadPhantom:
    var = _Variation(seed)
    # texture: irregular small structure (air cells), fixed for a seed, canonical for seed 0
    texture = np.random.default_rng(1000 + seed)
    b = _Builder()
    E, C = b.ellipsoid, b.cylinder
    P, S = var.pos, var.size

    # ----- envelope: cranium, face, neck (soft tissue) --------------------------------
    cran_c = P([0.0, 5.0, 18.0])
    cran_s = S([75.0, 96.0, 90.0])
    b.paint(E(cran_c, cran_s), HU_SOFT, "head", "soft")
    b.paint(E(P([0.0, -38.0, -52.0]), S([63.0, 58.0, 62.0])), HU_SOFT, "head", "soft")
    b.paint(C(P([0.0, 12.0, -300.0]), P([0.0, 12.0, -40.0]), S([56.0, 58.0])), HU_SOFT, "neck", "soft")
    b.paint(E(P([0.0, -99.0, -45.0]), S([9.0, 12.0, 19.0]), _euler(rx=-15)), HU_SOFT, "face", "soft")  # nose

    # ----- skull vault: nested ellipsoids above the cranial floor -----------------------
    # The cranial floor is the bowl of a large ellipsoid: high in front (anterior fossa,
    # orbital roofs), low at the back (posterior fossa), curving down laterally (middle fossa).
    bowl_c = P([0.0, 40.0, 75.0]) + var.jitter(1.0)
    bowl_s = S([125.0, 160.0, 120.0])

    def vault(semi_minus: float, floor_minus: float) -> dict:
        region = E(cran_c, cran_s - semi_minus)
        bowl = E(bowl_c, bowl_s - floor_minus)
        return {"quads": region["quads"] + bowl["quads"], "planes": [], "sphere": region["sphere"]}

    b.paint(vault(5.0, 0.0), HU_CORTICAL, "skull", "bone")  # outer table
    b.paint(vault(7.0, 1.5), HU_DIPLOE, "skull", "bone")  # diploe
    b.paint(vault(10.5, 3.5), HU_CORTICAL, "skull", "bone")  # inner table
    b.paint(vault(12.5, 5.0), HU_BRAIN, "skull", "brain")  # brain

    # ventricles (CSF)
    for side in (-1.0, 1.0):
        b.paint(
            E(P(_mirror([9.0, 2.0, 24.0], side)), S([5.0, 26.0, 8.0], 0.1), _euler(rz=side * 8)),
            HU_CSF,
            "brain",
            "brain",
        )
    b.paint(E(P([0.0, 4.0, 4.0]), S([1.8, 11.0, 8.0])), HU_CSF, "brain", "brain")
    b.paint(E(P([0.0, 40.0, -28.0]), S([6.0, 4.0, 5.0])), HU_CSF, "brain", "brain")

    # ----- skull base: sphenoid, sella, clivus, foramen magnum, petrous, mastoid --------
    b.paint(E(P([0.0, -6.0, -40.0]), S([18.0, 19.0, 13.0])), 800.0, "sphenoid", "bone")  # sphenoid body
    b.paint(E(P([0.0, -14.0, -41.0]), S([12.5, 9.5, 8.5], 0.1)), HU_AIR, "sphenoid", "air")  # sphenoid sinus
    b.paint(E(P([0.0, 3.0, -27.0]), S([7.0, 6.0, 5.5])), HU_SOFT, "sphenoid", "soft")  # pituitary fossa (sella)
    b.paint(E(P([0.0, 10.5, -22.0]), S([7.0, 2.2, 7.0]), _euler(rx=15)), 1500.0, "sphenoid", "bone")  # dorsum
    for side in (-1.0, 1.0):  # anterior clinoid processes
        b.paint(E(P(_mirror([9.0, -8.0, -21.0], side)), S([4.0, 7.0, 2.5])), 1500.0, "sphenoid", "bone")
    b.paint(C(P([0.0, 9.0, -30.0]), P([0.0, 30.0, -60.0]), S([10.0, 5.0])), 1300.0, "clivus", "bone")
    for side in (-1.0, 1.0):
        # greater wings of the sphenoid: oblique plates from the sphenoid body to the temple
        # (the innominate lines of a frontal view)
        wing = E(P(_mirror([30.0, -30.0, -27.0], side)), S([2.5, 21.0, 14.0]), _euler(rz=side * 40.0))
        b.paint(wing, 1200.0, "sphenoid", "bone")
        # styloid processes, pointing down and forward from under the petrous bones
        b.paint(
            C(P(_mirror([40.0, 16.0, -50.0], side)), P(_mirror([34.0, 2.0, -82.0], side)), 1.6),
            1300.0,
            "clivus",
            "bone",
        )
    b.paint(E(P([0.0, 85.0, -20.0]), S([10.0, 5.0, 7.0])), 1500.0, "skull", "bone")  # occipital protuberance
    fm = C(P([0.0, 46.0, -55.0]), P([0.0, 46.0, -38.0]), S([15.0, 18.0]))
    b.paint(fm, HU_BRAIN, "clivus", "brain")  # foramen magnum: medulla through the floor plate
    for side in (-1.0, 1.0):
        g = f"petrous_{'l' if side > 0 else 'r'}"
        apex = P(_mirror([13.0, 3.0, -31.0], side))
        base = P(_mirror([55.0, 28.0, -40.0], side))
        axis = base - apex
        center = (apex + base) / 2
        half = float(np.linalg.norm(axis)) / 2 + 3.0
        b.paint(E(center, [10.0, 7.0, half], _rot_to(axis)), HU_PETROUS, g, "bone")
        b.paint(E(P(_mirror([36.0, 15.0, -35.0], side)), 2.6), HU_CSF, g, "soft")  # cochlea/vestibule
        b.paint(
            C(P(_mirror([20.0, 8.0, -32.0], side)), P(_mirror([33.0, 13.0, -34.5], side)), 2.2),
            HU_CSF,
            g,
            "soft",
        )  # internal auditory canal
        # mastoid process with air cells
        mc = P(_mirror([53.0, 30.0, -50.0], side))
        b.paint(E(mc, S([10.0, 13.0, 16.0])), 1000.0, g, "bone")
        _air_cells(b, mc, S([8.0, 11.0, 14.0]), 26, (1.6, 3.4), texture, g)
        ear = P(_mirror([48.0, 17.0, -40.0], side))
        b.paint(C(ear, P(_mirror([80.0, 17.0, -41.0], side)), 3.5), HU_AIR, g, "air")  # ear canal
        b.paint(E(ear, S([3.0, 4.0, 5.0])), HU_AIR, g, "air")  # middle ear

    # ----- frontal sinus (walls first, then air so the two lobes join) -----------------
    fs = [(P(_mirror([7.0, -80.0, 8.0], side)), S([8.0, 6.0, 11.0], 0.1)) for side in (-1.0, 1.0)]
    for c, s in fs:
        b.paint(E(c, s + 2.0), 1400.0, "frontal", "bone")
    for c, s in fs:
        b.paint(E(c, s), HU_AIR, "frontal", "air")

    # ----- cervical spine and airway --------------------------------------------------
    b.paint(C(P([0.0, 28.0, -67.0]), P([0.0, 28.0, -58.0]), S([22.0, 19.0])), 1000.0, "spine", "bone")  # C1
    b.paint(C(P([0.0, 14.0, -90.0]), P([0.0, 14.0, -56.0]), S(5.0)), 1100.0, "spine", "bone")  # dens
    for level in range(6):
        z = -90.0 - 18.0 * level
        b.paint(C(P([0.0, 14.0, z - 7.0]), P([0.0, 14.0, z + 7.0]), S([10.0, 8.5])), 900.0, "spine", "bone")
        b.paint(E(P([0.0, 40.0, z + 2.0]), S([17.0, 15.0, 5.0])), 900.0, "spine", "bone")  # arch
    b.paint(C(P([0.0, 34.0, -300.0]), P([0.0, 34.0, -56.0]), S([8.0, 7.0])), HU_BRAIN, "spine", "brain")  # cord
    airway = _catmull_rom(P([[0.0, -26.0, -50.0], [0.0, -12.0, -72.0], [0.0, -9.0, -130.0], [0.0, -14.0, -300.0]]))
    b.tube(airway, float(S(7.0)), HU_AIR, "airway", "air")
    for side in (-1.0, 1.0):  # occipital condyles, resting on the atlas
        b.paint(E(P(_mirror([13.0, 36.0, -58.0], side)), S([6.0, 10.0, 5.0])), 1300.0, "spine", "bone")
    hyoid = np.stack([20.0 * (u := np.linspace(-1.0, 1.0, 9)), -38.0 + 26.0 * u**2, np.full_like(u, -125.0)], axis=1)
    b.tube(P(hyoid), float(S(2.2)), 1000.0, "spine", "bone")

    if facial:
        _facial_skeleton(b, var, texture)

    aneurysm_c, aneurysm_r, paths = _arteries(b, var, contrast)
    return b.build(
        paths=tuple(paths),
        seed=seed,
        contrast=contrast,
        facial=facial,
        params={"aneurysm_center_mm": aneurysm_c.tolist(), "aneurysm_radius_mm": aneurysm_r},
    )


def _air_cells(
    b: _Builder, center: Float, semi: Float, count: int, radii: tuple[float, float], rng, group: str
) -> None:
    """``count`` air cells of random radius at random places inside an ellipsoid."""
    placed = 0
    while placed < count:
        off = rng.uniform(-1.0, 1.0, 3)
        if off @ off > 1.0:
            continue
        radius = rng.uniform(*radii)
        b.paint(b.ellipsoid(center + off * semi, radius), HU_AIR, group, "air")
        placed += 1


def _facial_skeleton(b: _Builder, var: _Variation, texture: np.random.Generator) -> None:
    E, C = b.ellipsoid, b.cylinder
    P, S = var.pos, var.size
    # orbits: bony cone (walls) behind the rim, fat, globe
    for side in (-1.0, 1.0):
        g = f"orbit_{'l' if side > 0 else 'r'}"
        axis = np.array([side * math.sin(math.radians(20)), -math.cos(math.radians(20)), -0.05])
        c = P(_mirror([33.0, -62.0, -30.0], side))
        rot = _rot_to(axis)
        semi = S([16.5, 16.5, 24.0], 0.05)
        rim = c + axis * 17.0  # the orbital opening
        b.paint(b.clip(E(c, semi + 2.5, rot), axis, rim), HU_FACIAL_BONE, g, "bone")
        b.paint(E(c, semi, rot), HU_FAT, g, "fat")
        b.paint(E(c + axis * 15.0, S(12.0)), HU_EYE, g, "soft")
        # zygoma and zygomatic arch
        b.paint(E(P(_mirror([48.0, -60.0, -44.0], side)), S([8.0, 9.0, 13.0])), HU_FACIAL_BONE, g, "bone")
        b.paint(
            C(P(_mirror([50.0, -55.0, -44.0], side)), P(_mirror([60.0, -2.0, -40.0], side)), [4.0, 3.0]),
            1200.0,
            g,
            "bone",
        )
    # maxillary sinuses (walls first)
    ms = [(P(_mirror([29.0, -57.0, -50.0], side)), S([13.0, 17.0, 15.0], 0.08)) for side in (-1.0, 1.0)]
    for i, (c, s) in enumerate(ms):
        b.paint(E(c, s + 2.0), HU_FACIAL_BONE, f"maxilla_{i}", "bone")
    for i, (c, s) in enumerate(ms):
        b.paint(E(c, s), HU_AIR, f"maxilla_{i}", "air")
    # ethmoid labyrinth: a block of thin septa with air cells
    ec = P([0.0, -52.0, -29.0])
    b.paint(E(ec, S([11.0, 22.0, 10.0])), 300.0, "ethmoid", "bone")
    _air_cells(b, ec, S([8.5, 19.0, 7.5]), 30, (1.8, 3.2), texture, "ethmoid")
    for side in (-1.0, 1.0):  # nasal bones at the bridge of the nose
        b.paint(
            E(P(_mirror([4.0, -92.0, -30.0], side)), S([2.5, 2.0, 10.0]), _euler(rx=-20.0)),
            1100.0,
            "nasal",
            "bone",
        )
    # nasal cavity, septum, turbinates, hard palate
    b.paint(E(P([0.0, -58.0, -55.0]), S([12.0, 31.0, 14.0])), HU_AIR, "nasal", "air")
    b.paint(E(P([0.0, -58.0, -53.0]), S([1.2, 28.0, 13.0])), 600.0, "nasal", "bone")
    for side in (-1.0, 1.0):
        b.paint(E(P(_mirror([9.0, -55.0, -60.0], side)), S([2.5, 22.0, 4.0])), 300.0, "nasal", "soft")
        b.paint(E(P(_mirror([9.5, -52.0, -50.0], side)), S([2.0, 17.0, 3.0])), 300.0, "nasal", "soft")
    b.paint(E(P([0.0, -52.0, -71.0]), S([21.0, 30.0, 3.0])), 1300.0, "nasal", "bone")
    # upper dental arch (alveolar bone) and mandible, as tubes along parabolic arches
    s_up = np.linspace(-0.78, 0.78, 25)
    up = np.stack([45.0 * s_up, -79.0 + 70.0 * s_up**2, np.full_like(s_up, -71.0)], axis=1)
    b.tube(P(up), float(S(6.5)), HU_FACIAL_BONE, "jaw", "bone")
    s_lo = np.linspace(-1.0, 1.0, 33)
    for z in (-104.0, -94.0):
        lo = np.stack([47.0 * s_lo, -77.0 + 77.0 * s_lo**2, np.full_like(s_lo, z)], axis=1)
        b.tube(P(lo), float(S(6.0)), 1300.0, "jaw", "bone")
    for side in (-1.0, 1.0):
        ramus = _catmull_rom(P(_mirror([[47.0, 0.0, -100.0], [48.5, 6.0, -72.0], [50.0, 12.0, -48.0]], side)))
        b.tube(ramus, float(S(5.0)), 1300.0, "jaw", "bone")
        coronoid = _catmull_rom(P(_mirror([[46.0, -14.0, -95.0], [45.0, -20.0, -60.0]], side)))
        b.tube(coronoid, float(S(3.5)), 1300.0, "jaw", "bone")
        b.paint(E(P(_mirror([50.0, 12.0, -45.0], side)), S([9.0, 5.0, 5.0])), 1300.0, "jaw", "bone")  # condyle
    # teeth: 7 per side per jaw (incisors to molars); enamel crowns and roots
    s_teeth = [0.05, 0.16, 0.27, 0.38, 0.48, 0.59, 0.7]
    crowns = [
        (3.3, 2.2, 4.5),
        (3.0, 2.2, 4.5),
        (3.0, 3.3, 5.0),
        (3.2, 3.5, 4.0),
        (3.3, 3.6, 4.0),
        (4.8, 5.0, 3.8),
        (4.6, 4.8, 3.6),
    ]
    for side in (-1.0, 1.0):
        for s, crown in zip(s_teeth, crowns, strict=True):
            for jaw_z, root_dz, arch in (
                (-79.0, 8.0, (45.0, -79.0, 70.0)),
                (-88.0, -8.0, (47.0, -77.0, 77.0)),
            ):
                x = side * arch[0] * s * 0.93
                y = arch[1] + arch[2] * s**2 + 3.0
                c = P([x, y, jaw_z])
                b.paint(
                    E(c + [0.0, 0.0, root_dz], S([crown[0] * 0.55, crown[1] * 0.55, 7.0])),
                    1700.0,
                    "teeth",
                    "teeth",
                )
                b.paint(E(c, S(crown)), HU_ENAMEL, "teeth", "teeth")


def _arteries(b: _Builder, var: _Variation, contrast: bool) -> tuple[Float, float, list]:
    """Internal carotids, vertebrals, basilar, circle of Willis, ACA/MCA/PCA, aneurysm."""
    lumen_hu = HU_CONTRAST if contrast else HU_BLOOD
    paths: list[tuple[str, Float, float]] = []

    def vessel(name: str, ctrl: list, radius: float) -> Float:
        pts = _catmull_rom(var.vessel(ctrl), VESSEL_STEP_MM)
        r = float(var.size(radius))
        b.tube(pts, r, lumen_hu, "vessels", "vessel")
        paths.append((name, pts, r))
        return pts

    for side, tag in ((-1.0, "r"), (1.0, "l")):
        m = lambda pts, s=side: _mirror(pts, s)  # noqa: E731
        vessel(
            f"ica_{tag}",
            m(
                [
                    [22, 8, -160],
                    [23, 9, -110],
                    [25, 10, -72],
                    [25, 9, -55],
                    [22, 2, -46],
                    [17, -6, -40],
                    [16, -10, -33],
                    [15, -18, -27],
                    [14, -21, -18],
                    [13, -14, -10],
                    [13, -8, -4],
                    [14, -4, 0],
                ]
            ),
            2.0,
        )
        vessel(
            f"vert_{tag}",
            m(
                [
                    [26, 22, -170],
                    [26, 24, -110],
                    [27, 26, -88],
                    [36, 30, -78],
                    [30, 40, -68],
                    [14, 36, -60],
                    [4, 26, -56],
                    [0.0, 23, -54],
                ]
            ),
            1.5,
        )
        vessel(f"a1_{tag}", m([[14, -4, 0], [9, -13, 2], [3.5, -20, 4]]), 1.0)
        vessel(
            f"a2_{tag}",
            m(
                [
                    [3.5, -20, 4],
                    [3, -30, 12],
                    [3, -40, 25],
                    [4, -45, 40],
                    [4, -36, 55],
                    [4, -12, 64],
                    [4, 18, 64],
                    [5, 40, 56],
                ]
            ),
            0.9,
        )
        vessel(f"callosomarginal_{tag}", m([[3, -40, 28], [8, -58, 40], [8, -55, 60], [9, -30, 78]]), 0.75)
        vessel(f"m1_{tag}", m([[14, -4, 0], [25, -6, 0], [37, -8, 2], [45, -8, 4]]), 1.4)
        vessel(f"m2_sup_{tag}", m([[45, -8, 4], [50, -12, 15], [55, -6, 30], [58, 6, 45], [55, 20, 58]]), 1.0)
        vessel(f"m2_inf_{tag}", m([[45, -8, 4], [52, -3, -3], [57, 10, 0], [60, 25, 8], [58, 42, 18]]), 1.0)
        vessel(f"m3_{tag}", m([[55, -6, 30], [62, -20, 35], [64, -35, 30]]), 0.75)
        vessel(f"m3b_{tag}", m([[57, 10, 0], [63, 15, 20], [62, 12, 40]]), 0.75)
        vessel(f"pcom_{tag}", m([[13, -8, -4], [11, 0, -6], [8, 8, -7]]), 0.75)
        vessel(f"p1_{tag}", m([[0, 10, -9], [8, 8, -7]]), 1.1)
        vessel(
            f"p2_{tag}",
            m([[8, 8, -7], [18, 16, -5], [22, 32, 0], [18, 48, 5], [12, 66, 10], [8, 82, 16]]),
            1.0,
        )
        vessel(f"sca_{tag}", m([[0, 12, -13], [12, 16, -15], [18, 28, -17], [14, 42, -18]]), 0.75)
    vessel("basilar", [[0.0, 23, -54], [0.0, 19, -40], [0.0, 14, -25], [0.0, 10, -9]], 1.5)
    vessel("acom", [[-3.5, -20, 4], [3.5, -20, 4]], 0.75)
    # aneurysm at the left MCA bifurcation, bulging on along the M1 direction
    m1 = var.vessel(_mirror([[37, -8, 2], [45, -8, 4]], 1.0))
    direction = (m1[1] - m1[0]) / np.linalg.norm(m1[1] - m1[0])
    radius = 3.5 + (var.rng.uniform(-0.3, 0.3) if var.on else 0.0)
    center = m1[1] + direction * (radius - 1.0)  # the neck overlaps the bifurcation by 1 mm
    b.paint(b.ellipsoid(center, radius), lumen_hu, "vessels", "vessel")
    return center, radius, paths


# --------------------------------------------------------------------------------------
# The stand-in registration volume
# --------------------------------------------------------------------------------------
#: Gaussian smoothing (voxels) and noise (HU) that make the resampled phantom look like a
#: reconstruction (a 3DRA has a soft point spread function and quantum noise).
STAND_IN_SMOOTH_VOXELS = 0.6
STAND_IN_NOISE_HU = 20.0


def standin_params(phantom: HeadPhantom, volume_format_cm: float, voxels: int, noise_seed: int) -> dict:
    """The cache parameters of :func:`registration_volume` (kind ``"standin3dra"``)."""
    return {
        **phantom.key,
        "volume_format_cm": float(volume_format_cm),
        "voxels": int(voxels),
        "noise_seed": int(noise_seed),
        "smooth": STAND_IN_SMOOTH_VOXELS,
        "noise_hu": STAND_IN_NOISE_HU,
        "n_prims": phantom.n_primitives,
    }


def registration_volume(
    phantom: HeadPhantom | int,
    volume_format_cm: float,
    *,
    voxels: int = 256,
    seed: int = 0,
    cache: bool = True,
) -> Volume:
    """The stand-in 3DRA: the phantom voxelised on the 3DRA grid, smoothed, with noise.

    Parameters
    ----------
    phantom
        A :class:`HeadPhantom`, or a phantom seed (contrast and facial structures on).
    volume_format_cm
        3DRA volume format; the cube spans ``f x SOD / SID`` at the iso-center.
    voxels
        Grid size along each axis.
    seed
        Seed of the added noise.
    cache
        Keep the result in the on-disk cache (keyed by every parameter).

    Returns
    -------
    Volume
        Axis-aligned LPS grid centered at the iso-center, labelled ``STAND_IN_LABEL``.
    """
    if not isinstance(phantom, HeadPhantom):
        phantom = make_head_phantom(seed=int(phantom))
    fmt = float(volume_format_cm)
    if not math.isfinite(fmt) or fmt <= 0:
        raise ValueError(f"volume_format_cm must be positive, got {volume_format_cm}")
    if int(voxels) != voxels or voxels < 8:
        raise ValueError(f"voxels must be an integer >= 8, got {voxels}")
    voxels = int(voxels)
    spacing, axis = format_grid(fmt, voxels=voxels)
    data_shape = (voxels, voxels, voxels)
    affine = np.diag([spacing, spacing, spacing, 1.0])
    affine[:3, 3] = axis[0]

    def build() -> dict[str, np.ndarray]:
        hu = phantom.voxelize(data_shape, affine, supersample=2)
        hu = ndimage.gaussian_filter(hu, STAND_IN_SMOOTH_VOXELS, mode="nearest")
        rng = np.random.default_rng(seed)
        hu += rng.normal(0.0, STAND_IN_NOISE_HU, hu.shape).astype(np.float32)
        return {"data": hu.astype(np.float32)}

    params = standin_params(phantom, fmt, voxels, seed)
    data = cached_arrays("standin3dra", params, build, enabled=cache)["data"]
    return Volume(data, affine, label=STAND_IN_LABEL, meta={"source": "phantom", **params})
