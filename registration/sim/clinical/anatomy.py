"""What the X-ray sees that the CT does not show the same way: the patient without the CT's couch,
bone that attenuates more, a neck that bends, and a static angiography table with its headrest.

All of it is formed here, apart from the engine: the couch is cut off by this module's own
segmentation (not the registration's body mask), the table is an analytic object traced by the
phantom's exact line integrals.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage
from scipy.spatial.transform import Rotation

from registration.core.geometry import invert_rigid, rigid
from registration.core.volume import Volume
from registration.sim.clinical.effects import BoneContrast, Neck, Table

#: Tissue threshold of the patient segmentation (HU): foam and air of a head holder lie below.
PATIENT_HU = -400.0
#: A couch or head board: a plate present in this fraction of the slices, wider than
#: ``PLATE_WIDTH_MM``, at most ``PLATE_MAX_MM`` thick.
PLATE_SLICE_FRACTION = 0.85
PLATE_WIDTH_MM = 100.0
PLATE_MAX_MM = 40.0
#: Opening radius (mm) that cuts the couch and head holder off where they touch the patient.
OPENING_MM = 6.0
#: Bone for finding the cervical spine (HU).
SPINE_BONE_HU = 250.0
# Materials of the angiography table (attenuation at the fluoroscopy's effective energy, 1/mm):
#: carbon-fibre skins of the table top and the headrest's polymer shell; the foam core.
CARBON_MU_PER_MM = 0.045
SHELL_MU_PER_MM = 0.026
FOAM_MU_PER_MM = 0.002
#: The table top: width (x), core thickness (y) and length (z) in mm.
TABLE_WIDTH_MM = 480.0
TABLE_CORE_MM = 22.0
TABLE_LENGTH_MM = 900.0


def patient_only(volume: Volume) -> tuple[Volume, NDArray[np.bool_]]:
    """The volume with everything but the patient set to air (-1000 HU), and the patient mask.

    A couch or head board is a flat plate behind the patient (posterior, +y) present in nearly
    every slice: the posterior-most run of image rows (y) where at least ``PLATE_SLICE_FRACTION``
    of the slices hold a run of tissue wider than ``PLATE_WIDTH_MM``, thinner than
    ``PLATE_MAX_MM`` and with much less tissue just in front of it, is cut off with everything
    behind it. Then tissue above ``PATIENT_HU`` opened by ``OPENING_MM`` (pieces of a head holder
    touch the patient over a few mm only) on a grid of about 2 mm, its largest component grown
    back and filled slice by slice (a voxel's rim kept for the skin's partial volume)."""
    spacing = volume.spacing_mm  # (x, y, z)
    tissue = volume.data > PATIENT_HU
    a = volume.index_to_world
    plate_rows = None
    if abs(a[1, 1]) > 0.9 * spacing[1] and abs(a[1, 0]) < 1e-6 and abs(a[1, 2]) < 1e-6:  # rows along y
        wide = tissue.sum(axis=2) * spacing[0] >= PLATE_WIDTH_MM  # (k, j)
        frac = wide.mean(axis=0)
        order = np.arange(volume.shape[1]) if a[1, 1] < 0 else np.arange(volume.shape[1])[::-1]  # posterior first
        run: list[int] = []
        for j in order:
            if frac[j] >= PLATE_SLICE_FRACTION:
                run.append(int(j))
            elif run:
                thin = len(run) * spacing[1] <= PLATE_MAX_MM
                if thin and frac[j] < PLATE_SLICE_FRACTION - 0.2:
                    plate_rows = run
                break
    cut = tissue.copy()
    if plate_rows is not None:
        front = plate_rows[-1]
        behind = np.arange(volume.shape[1]) >= front if a[1, 1] > 0 else np.arange(volume.shape[1]) <= front
        cut[:, behind, :] = False
    f = max(1, round(2.0 / float(min(spacing[0], spacing[1]))))  # in-plane factor to ~2 mm
    nk, nj, ni = cut.shape
    small = cut[:, : nj - nj % f, : ni - ni % f].reshape(nk, nj // f, f, ni // f, f).mean(axis=(2, 4)) >= 0.5
    radius = [max(1, round(OPENING_MM / spacing[2])), max(1, round(OPENING_MM / (spacing[1] * f))),
              max(1, round(OPENING_MM / (spacing[0] * f)))]  # fmt: skip
    ball = _ellipsoid(radius)
    opened = ndimage.binary_opening(small, structure=ball)
    labels, n = ndimage.label(opened)
    if n == 0:
        return volume, tissue
    largest = 1 + int(np.argmax(np.bincount(labels.ravel())[1:]))
    grown = ndimage.binary_dilation(labels == largest, structure=ball, iterations=2)
    full = np.zeros_like(cut)
    up = np.repeat(np.repeat(grown, f, axis=1), f, axis=2)
    full[:, : up.shape[1], : up.shape[2]] = up
    body = np.stack([ndimage.binary_fill_holes(s) for s in full & cut])
    keep = ndimage.binary_dilation(body, structure=np.ones((1, 3, 3), dtype=bool))  # the skin's partial volume
    data = np.where(keep, volume.data, np.float32(-1000.0)).astype(np.float32)
    meta = {
        **volume.meta,
        "couch_removed": {"plate_rows": None if plate_rows is None else [min(plate_rows), max(plate_rows)]},
    }
    return Volume(data, volume.index_to_world, label=volume.label, meta=meta), body


def _ellipsoid(radius: list[int]) -> NDArray[np.bool_]:
    g = np.ogrid[tuple(slice(-r, r + 1) for r in radius)]
    return sum((a / max(r, 1)) ** 2 for a, r in zip(g, radius, strict=True)) <= 1.0


def with_bone_contrast(volume: Volume, contrast: BoneContrast) -> Volume:
    """HU above the threshold scaled by ``contrast.ratio`` (bone/soft-tissue contrast)."""
    t = np.float32(contrast.threshold_hu)
    data = np.where(volume.data > t, t + np.float32(contrast.ratio) * (volume.data - t), volume.data)
    return Volume(data.astype(np.float32), volume.index_to_world, label=volume.label, meta=volume.meta)


# --------------------------------------------------------------------------------------
# The neck
# --------------------------------------------------------------------------------------
def neck_pivot_mm(volume: Volume, isocenter_mm: ArrayLike, neck: Neck) -> tuple[NDArray[np.float64], float]:
    """(C1/C2 pivot in world mm, the posterior limit's y) from the volume: the plane lies
    ``plane_below_iso_mm`` below the iso-center; the pivot is the middle of the bone within 15 mm
    of the iso-center's sagittal plane, behind it, in the 20 mm under the plane."""
    iso = np.asarray(isocenter_mm, dtype=np.float64)
    plane_z = iso[2] - neck.plane_below_iso_mm
    kk, jj, ii = np.nonzero(volume.data > SPINE_BONE_HU)
    idx = np.stack([ii, jj, kk], axis=1).astype(np.float64)
    pts = idx @ volume.index_to_world[:3, :3].T + volume.index_to_world[:3, 3]
    sel = (
        (np.abs(pts[:, 0] - iso[0]) < 15.0) & (pts[:, 1] > iso[1]) & (pts[:, 2] < plane_z) & (pts[:, 2] > plane_z - 20)
    )
    if sel.sum() < 20:  # no spine found: the pivot under the iso-center, 30 mm behind it
        pivot = np.array([iso[0], iso[1] + 30.0, plane_z - 10.0])
    else:
        pivot = np.array([iso[0], float(np.median(pts[sel, 1])), plane_z - 10.0])
    return pivot, float(pivot[1] - neck.anterior_cut_mm)


def neck_weight(points_mm: NDArray[np.float64], isocenter_mm: ArrayLike, pivot_mm: NDArray[np.float64],
                anterior_y_mm: float, neck: Neck) -> NDArray[np.float64]:  # fmt: skip
    """How much of the neck's own motion each point takes: 0 in the skull, 1 in the spine,
    smooth (logistic over ``blend_mm``) across the skull-base plane and the anterior cut."""
    iso = np.asarray(isocenter_mm, dtype=np.float64)
    plane_z = iso[2] - neck.plane_below_iso_mm
    w = neck.blend_mm / 4.0  # logistic scale: 10 % to 90 % over ~ blend_mm
    below = 1.0 / (1.0 + np.exp(np.clip((points_mm[..., 2] - plane_z) / w, -50, 50)))
    behind = 1.0 / (1.0 + np.exp(np.clip(-(points_mm[..., 1] - anterior_y_mm) / w, -50, 50)))
    return below * behind


def neck_transform(motion: ArrayLike, pivot_mm: NDArray[np.float64], neck: Neck) -> NDArray[np.float64]:
    """The spine's motion: ``follow`` of the patient motion (rotation vector and translation
    scaled) after the C1/C2 bend about the pivot."""
    m = np.asarray(motion, dtype=np.float64)
    rotvec = Rotation.from_matrix(m[:3, :3]).as_rotvec()
    part = rigid(Rotation.from_rotvec(neck.follow * rotvec).as_matrix(), neck.follow * m[:3, 3])
    bend = Rotation.from_euler("zx", [neck.rotation_deg, neck.flexion_deg], degrees=True).as_matrix()
    about = rigid(None, pivot_mm) @ rigid(bend, None) @ rigid(None, -pivot_mm)
    return part @ about


def bent_volume(volume: Volume, motion: ArrayLike, isocenter_mm: ArrayLike, neck: Neck) -> Volume:
    """The volume deformed so that, moved by ``motion``, its skull moves by ``motion`` and its
    neck by :func:`neck_transform`: the voxels below the skull-base plane resampled (trilinear)
    with the relative transform ``inv(motion) @ spine`` scaled by :func:`neck_weight` (rotation
    vector and translation about the pivot, inverted at each output point)."""
    m = np.asarray(motion, dtype=np.float64)
    pivot, anterior_y = neck_pivot_mm(volume, isocenter_mm, neck)
    relative = invert_rigid(m) @ neck_transform(m, pivot, neck)
    # relative transform about the pivot: x -> R (x - p) + p + t
    rot = relative[:3, :3]
    t = relative[:3, 3] - (pivot - rot @ pivot)
    rotvec = Rotation.from_matrix(rot).as_rotvec()
    iso = np.asarray(isocenter_mm, dtype=np.float64)
    a = volume.index_to_world
    nk, nj, ni = volume.shape
    z_of_k = a[2, 2] * np.arange(nk) + a[2, 3] + a[2, 0] * (ni - 1) / 2 + a[2, 1] * (nj - 1) / 2
    reach = iso[2] - neck.plane_below_iso_mm + 3 * neck.blend_mm
    ks = np.flatnonzero(z_of_k <= reach)
    if ks.size == 0 or (np.allclose(rotvec, 0) and np.allclose(t, 0)):
        return volume
    k0, k1 = int(ks.min()), int(ks.max()) + 1
    # rows (y) behind the anterior cut's blend only (the rest keeps weight ~ 0)
    y_of_j = a[1, 1] * np.arange(nj) + a[1, 3] + a[1, 0] * (ni - 1) / 2 + a[1, 2] * (nk - 1) / 2
    js = np.flatnonzero(y_of_j >= anterior_y - 3 * neck.blend_mm)
    if js.size == 0:
        return volume
    j0, j1 = int(js.min()), int(js.max()) + 1
    kk, jj, ii = np.meshgrid(np.arange(k0, k1), np.arange(j0, j1), np.arange(ni), indexing="ij")
    idx = np.stack([ii, jj, kk], axis=-1).reshape(-1, 3).astype(np.float64)
    pts = idx @ a[:3, :3].T + a[:3, 3]
    weight = neck_weight(pts, iso, pivot, anterior_y, neck)
    moving = weight > 1e-3
    p = pts[moving]
    wv = weight[moving][:, None]
    # inverse of the weighted transform at each output point: rotate back by -w*rotvec, shift back by w*t
    src = _rotate(p - pivot - wv * t, -wv * rotvec[None, :]) + pivot
    w2i = volume.index_from_world
    src_idx = src @ w2i[:3, :3].T + w2i[:3, 3]
    values = ndimage.map_coordinates(volume.data, src_idx[:, ::-1].T, order=1, mode="constant", cval=-1000.0)
    data = volume.data.copy()
    block = data[k0:k1, j0:j1].reshape(-1)
    block[moving] = values
    data[k0:k1, j0:j1] = block.reshape(k1 - k0, j1 - j0, ni)
    return Volume(data, a, label=volume.label, meta=volume.meta)


def _rotate(v: NDArray[np.float64], rotvec: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rodrigues' rotation of each row of ``v`` by the matching rotation vector."""
    angle = np.linalg.norm(rotvec, axis=1, keepdims=True)
    k = rotvec / np.maximum(angle, 1e-12)
    c, s = np.cos(angle), np.sin(angle)
    return v * c + np.cross(k, v) * s + k * np.sum(k * v, axis=1, keepdims=True) * (1 - c)


# --------------------------------------------------------------------------------------
# The table and the headrest
# --------------------------------------------------------------------------------------
def _interval(s: NDArray, d: NDArray, lo: NDArray, hi: NDArray) -> tuple[NDArray, NDArray]:
    """Parameter interval [t0, t1] (within [0, 1]) of the segments s + t d inside the box."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (lo[None, :] - s) / d
        tb = (hi[None, :] - s) / d
    t_lo = np.where(
        np.isfinite(ta) & np.isfinite(tb), np.minimum(ta, tb), np.where((s >= lo) & (s <= hi), -np.inf, np.inf)
    )
    t_hi = np.where(
        np.isfinite(ta) & np.isfinite(tb), np.maximum(ta, tb), np.where((s >= lo) & (s <= hi), np.inf, -np.inf)
    )
    return np.maximum(t_lo.max(axis=1), 0.0), np.minimum(t_hi.min(axis=1), 1.0)


def _box_length(s: NDArray, d: NDArray, lo: ArrayLike, hi: ArrayLike) -> NDArray:
    t0, t1 = _interval(s, d, np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64))
    return np.maximum(t1 - t0, 0.0) * np.linalg.norm(d, axis=1)


def _trough_length(
    s: NDArray, d: NDArray, center: NDArray, semi: tuple[float, float], z: tuple[float, float]
) -> NDArray:
    """Length of each segment inside the half elliptic cylinder (axis along z, the half y >= center y)."""
    a, b = semi
    px, py = (s[:, 0] - center[0]) / a, (s[:, 1] - center[1]) / b
    dx, dy = d[:, 0] / a, d[:, 1] / b
    qa = dx * dx + dy * dy
    qb = 2 * (px * dx + py * dy)
    qc = px * px + py * py - 1.0
    disc = qb * qb - 4 * qa * qc
    ok = (disc > 0) & (qa > 1e-18)
    root = np.sqrt(np.where(ok, disc, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        e0 = np.where(ok, (-qb - root) / (2 * qa), 1.0)
        e1 = np.where(ok, (-qb + root) / (2 * qa), 0.0)
    big = 1e9
    t0, t1 = _interval(s, d, np.array([-big, center[1], z[0]]), np.array([big, big, z[1]]))
    t0, t1 = np.maximum(t0, e0), np.minimum(t1, e1)
    return np.maximum(t1 - t0, 0.0) * np.linalg.norm(d, axis=1)


class StaticTable:
    """The angiography table top (carbon-fibre skins around a foam core) and a headrest (a polymer
    trough with a foam pad), exact line integrals of axis-aligned boxes and half elliptic
    cylinders; static: ``motion`` is ignored (the table does not move with the patient)."""

    def __init__(self, *, table_lo: NDArray, table_hi: NDArray, skin_mm: float, trough_center: NDArray | None,
                 trough_inner: tuple[float, float], shell_mm: float, trough_z: tuple[float, float],
                 scale: float) -> None:  # fmt: skip
        self.table_lo, self.table_hi, self.skin_mm = table_lo, table_hi, skin_mm
        self.trough_center, self.trough_inner, self.shell_mm, self.trough_z = (
            trough_center,
            trough_inner,
            shell_mm,
            trough_z,
        )
        self.scale = scale
        self.key = {"table": [table_lo.tolist(), table_hi.tolist()], "skin_mm": skin_mm, "scale": scale,
                    "headrest": None if trough_center is None else trough_center.tolist()}  # fmt: skip

    def line_integrals(self, sources_mm: ArrayLike, targets_mm: ArrayLike, motion: ArrayLike | None = None) -> NDArray:
        src = np.asarray(sources_mm, dtype=np.float64).reshape(-1, 3)
        dst = np.asarray(targets_mm, dtype=np.float64).reshape(-1, 3)
        src = np.broadcast_to(src, dst.shape)
        d = dst - src
        skin = np.array([0.0, self.skin_mm, 0.0]) + np.array([self.skin_mm, 0.0, 0.0])
        outer = _box_length(src, d, self.table_lo, self.table_hi)
        core = _box_length(src, d, self.table_lo + skin, self.table_hi - skin)
        total = CARBON_MU_PER_MM * (outer - core) + FOAM_MU_PER_MM * core
        if self.trough_center is not None:
            a, b = self.trough_inner
            t = self.shell_mm
            shell_out = _trough_length(src, d, self.trough_center, (a + t, b + t), self.trough_z)
            shell_in = _trough_length(src, d, self.trough_center, (a, b), self.trough_z)
            cradle = _trough_length(src, d, self.trough_center, (a - 10.0, b - 10.0), self.trough_z)
            total = total + SHELL_MU_PER_MM * (shell_out - shell_in) + FOAM_MU_PER_MM * (shell_in - cradle)
        return self.scale * total


def table_phantom(volume: Volume, isocenter_mm: ArrayLike, table: Table) -> tuple[StaticTable, dict]:
    """The angiography table top and headrest under the patient's head (world mm), from where the
    back of the head lies in ``volume`` (the patient only: :func:`patient_only`)."""
    iso = np.asarray(isocenter_mm, dtype=np.float64)
    a = volume.index_to_world
    kk, jj, ii = np.nonzero(volume.data > PATIENT_HU)
    pts = np.stack([ii, jj, kk], axis=1).astype(np.float64) @ a[:3, :3].T + a[:3, 3]
    head = pts[np.abs(pts[:, 2] - iso[2]) < 40.0]
    if len(head) == 0:
        raise ValueError("no tissue within 40 mm of the iso-center's height: cannot place the headrest")
    occiput_y = float(head[:, 1].max())  # the back of the head (posterior is +y)
    top_z = float(pts[:, 2].max())
    inner = (80.0, 55.0)
    center = np.array([iso[0], occiput_y + 6.0 - inner[1], 0.0])
    base_y = center[1] + inner[1] + table.shell_mm if table.headrest else occiput_y + 6.0
    y0 = base_y + 2.0
    y1 = y0 + TABLE_CORE_MM + 2 * table.skin_mm
    lo = np.array([iso[0] - TABLE_WIDTH_MM / 2, y0, top_z + 60.0 - TABLE_LENGTH_MM])
    hi = np.array([iso[0] + TABLE_WIDTH_MM / 2, y1, top_z + 60.0])
    static = StaticTable(table_lo=lo, table_hi=hi, skin_mm=table.skin_mm,
                         trough_center=center if table.headrest else None, trough_inner=inner,
                         shell_mm=table.shell_mm, trough_z=(iso[2] - 90.0, top_z + 30.0),
                         scale=table.attenuation_scale)  # fmt: skip
    placement = {"occiput_y_mm": occiput_y, "table_top_y_mm": float(y0), "headrest": table.headrest}
    return static, placement


def motion_magnitude(m: ArrayLike) -> tuple[float, float]:
    """(translation mm, rotation deg) of a rigid transform."""
    m = np.asarray(m, dtype=np.float64)
    angle = math.degrees(np.linalg.norm(Rotation.from_matrix(m[:3, :3]).as_rotvec()))
    return float(np.linalg.norm(m[:3, 3])), angle
