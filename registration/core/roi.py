"""The part of the volume a registration should follow: the cranium, not the neck.

The roadmap's target is the head's vessels. The skull moves as a rigid body; the cervical spine
follows it only partly (flexion, rotation at C1/C2), and its edges are among the strongest in a
frontal or lateral image: a rigid fit pulled by the spine is wrong where it matters.

A :class:`RegionOfInterest` marks the voxels that drive the registration. Outside it,
:func:`roi_volume` turns everything denser than soft tissue into soft tissue: the DRR keeps the
neck's outline and air spaces but shows no spine, so the spine's edges in the X-ray image find
nothing to pull on (gradient difference bounds what one unmatched edge can cost).

:func:`cranium_region`: found automatically, the cervical spine below the skull base (the bone
column tracked slice by slice from the bottom of the scan up to where it joins the wide bone of
the skull base) left out, everything else in. :func:`read_roi_mask`: a label mask the user gives
(:func:`registration.io.roi_masks.read_roi_mask`: NumPy ``.npz`` or NIfTI on the volume's grid).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from registration.core.geometry import CArm
from registration.core.images import XRayImage
from registration.core.prepare.prepared import recall_for_volume, remember_for_volume
from registration.core.volume import Volume

if TYPE_CHECKING:
    from registration.core.drr import DRRRenderer
    from registration.core.prepare.store import PreparationStore

#: Voxels above this HU are bone for the spine's tracking.
BONE_HU = 250.0
#: Outside the region, voxels above this HU are set to it (soft tissue: muscle ~40 HU).
SOFT_TISSUE_HU = 40.0
#: The spine is tracked within this distance (mm, across a slice) of its centre in the slice below.
TRACK_RADIUS_MM = 30.0
#: What is left out around the tracked centre (mm across): the vertebra with its processes.
COLUMN_RADIUS_MM = 40.0
#: The skull base: the first slice (going up) where the bone the spine joins is wider than this (mm).
SKULL_BASE_WIDTH_MM = 100.0
#: At least this much bone (mm^2) in a slice's tracking disc to count as the spine there.
MIN_SPINE_AREA_MM2 = 40.0


@dataclass(frozen=True)
class RegionOfInterest:
    """Voxels (``mask[k, j, i]``, the volume's grid) that drive the registration; ``source``:
    "cranium" (found automatically) or the mask's file; ``skull_base_z_mm``: the world z of the
    skull base the automatic region found (None for a user's mask); ``left_out_ml``: the volume
    of dense tissue (above ``SOFT_TISSUE_HU``) left out."""

    mask: NDArray[np.bool_]
    source: str
    skull_base_z_mm: float | None = None
    left_out_ml: float = 0.0
    #: Why the automatic region is the whole volume ("no spine found", "oblique slices"), else "".
    note: str = ""

    def summary(self) -> dict:
        """For the result JSON: the automatic cranium by its skull base (the pixels that see
        mostly the neck below it are left out: :func:`region_views`), a mask by its voxels."""
        if self.source == "cranium":
            out: dict = {"source": self.source, "skull_base_z_mm": self.skull_base_z_mm}
        else:
            out = {"source": self.source, "left_out_ml": round(float(self.left_out_ml), 1),
                   "voxels": int(self.mask.sum())}  # fmt: skip
        return out | ({"note": self.note} if self.note else {})

    def describe(self) -> str:
        """One line: what the registration follows."""
        if self.source == "cranium":
            if self.skull_base_z_mm is None:
                return f"cranium: the whole volume ({self.note or 'no spine found'})"
            return f"cranium: the head above the skull base at z {self.skull_base_z_mm:.0f} mm"
        return f"{self.source}: {int(self.mask.sum()):,} voxels ({self.left_out_ml:.0f} ml of dense tissue left out)"


class ObliqueSlices(ValueError):
    """The volume's slices are not axial: the automatic cranium cannot track the spine."""


def _axial(volume: Volume) -> tuple[NDArray[np.float64], float, float]:
    """Slice z (world mm, per k), the in-slice pixel sizes (mm); refuses oblique grids."""
    a = volume.index_to_world
    if abs(a[2, 0]) > 1e-6 or abs(a[2, 1]) > 1e-6 or abs(a[0, 2]) > 1e-6 or abs(a[1, 2]) > 1e-6:
        raise ObliqueSlices("the automatic cranium needs axial slices (the volume's k axis along the patient's z)")
    z = a[2, 2] * np.arange(volume.shape[0]) + a[2, 3]
    return z, float(np.hypot(a[0, 0], a[1, 0])), float(np.hypot(a[0, 1], a[1, 1]))


#: The regions a registration follows by name: "none" (the whole volume) or "cranium" (found).
REGIONS = ("none", "cranium")
#: Bump when the automatic cranium's rule changes (stored regions are found again).
CRANIUM_VERSION = 1


def followed_region(volume: Volume, roi: str, *, store: PreparationStore | None = None) -> RegionOfInterest | None:
    """The region named by ``roi`` (``REGIONS``): the cranium found in ``volume`` (the whole
    volume, with a note, when it has no spine or is not axial), or None for "none". ``store``:
    where a found cranium is kept by the volume's content (:mod:`registration.core.prepare.store`)."""
    if roi == "none":
        return None
    if roi != "cranium":
        raise ValueError(f"the region must be one of {', '.join(REGIONS)}, got {roi!r}")
    region = recall_for_volume(_FOUND, (id(volume),), volume)
    if region is not None:
        return region
    try:
        region = cranium_region(volume, store=store)
    except ObliqueSlices:  # no automatic cranium
        region = RegionOfInterest(np.ones(volume.shape, dtype=bool), "cranium", None, 0.0,
                                  note="oblique slices: the spine is tracked on axial slices only")  # fmt: skip
    remember_for_volume(_FOUND, (id(volume),), (volume, region))
    return region


#: The cranium found for the volumes seen last (by identity, the volume kept alive with it): a
#: process that registers one volume many times (the app, a worker, a study) finds it once.
_FOUND: OrderedDict[tuple, tuple[Volume, RegionOfInterest]] = OrderedDict()


def region_volume(volume: Volume, roi: RegionOfInterest | None) -> Volume:
    """What the registration renders: ``volume`` itself when ``roi`` is None or leaves nothing
    dense out (the same voxels, the same stored preparation), else :func:`roi_volume`."""
    if roi is None or roi.left_out_ml <= 0:
        return volume
    return roi_volume(volume, roi)


def cranium_region(volume: Volume, *, store: PreparationStore | None = None) -> RegionOfInterest:
    """The volume without its cervical spine below the skull base (see the module). When no
    spine is found (a cranium-only 3DRA) the whole volume. ``store``: the tracked column is kept
    there by the volume's content and read back instead of tracked again."""
    key = None
    if store is not None:
        from registration.core.prepare.store import volume_digest

        rule = [BONE_HU, TRACK_RADIUS_MM, COLUMN_RADIUS_MM, SKULL_BASE_WIDTH_MM, MIN_SPINE_AREA_MM2]
        key = {"volume_sha256": volume_digest(volume), "version": CRANIUM_VERSION, "rule": rule}
        found = store.load("cranium", key)
        if found is not None and found.get("column") is not None and found["column"].ndim == 2:
            base = float(found["skull_base_z_mm"][0])
            return _region_of_column(volume, [tuple(c) for c in found["column"]], None if np.isnan(base) else base)
    column, base_z = _spine_column(volume)
    region = _region_of_column(volume, column, base_z)
    if store is not None and key is not None:
        store.save("cranium", key, {"column": np.asarray(column, dtype=np.float64).reshape(-1, 3),
                                    "skull_base_z_mm": np.array([np.nan if base_z is None else base_z])})  # fmt: skip
    return region


def _region_of_column(volume: Volume, column: list, base_z: float | None) -> RegionOfInterest:
    """The region that leaves out ``column`` (slice k, centre i, centre j) below ``base_z``."""
    _, di, dj = _axial(volume)
    data = volume.data
    keep = np.ones(data.shape, dtype=bool)
    if base_z is None or len(column) < 3:
        return RegionOfInterest(keep, "cranium", None, 0.0, note="no spine found")
    nj, ni = data.shape[1:]
    voxel_ml = di * dj * abs(volume.index_to_world[2, 2]) / 1000.0
    ri, rj = COLUMN_RADIUS_MM / di, COLUMN_RADIUS_MM / dj
    left = 0
    for k, ci, cj in column:  # each slice's disc, within its bounding box
        i0, i1 = max(0, int(np.floor(ci - ri))), min(ni, int(np.ceil(ci + ri)) + 1)
        j0, j1 = max(0, int(np.floor(cj - rj))), min(nj, int(np.ceil(cj + rj)) + 1)
        jj, ii = np.mgrid[j0:j1, i0:i1]
        out = ((ii - ci) * di) ** 2 + ((jj - cj) * dj) ** 2 <= COLUMN_RADIUS_MM**2
        keep[int(k), j0:j1, i0:i1] &= ~out
        left += int((out & (data[int(k), j0:j1, i0:i1] > SOFT_TISSUE_HU)).sum())
    return RegionOfInterest(keep, "cranium", base_z, left * voxel_ml)


def _spine_column(volume: Volume) -> tuple[list[tuple[int, float, float]], float | None]:
    """The cervical spine tracked from the bottom of the scan up: (slice k, centre i, centre j)
    per slice, and the world z of the skull base where the tracking stopped (None: not reached)."""
    z, di, dj = _axial(volume)
    order = np.argsort(z)  # from the feet up
    data = volume.data
    nk, nj, ni = data.shape
    jj, ii = np.mgrid[0:nj, 0:ni]
    center: tuple[float, float] | None = None
    column: list[tuple[int, float, float]] = []
    base_z: float | None = None
    for k in order:
        bone = data[k] > BONE_HU
        if center is None:
            tissue = data[k] > -300.0
            if not tissue.any() or not bone.any():
                continue
            # the spine at the bottom: the bone component nearest the tissue's centre line
            labels, n = ndimage.label(bone)
            sizes = np.bincount(labels.ravel())[1:] * di * dj
            mid_i = float(ii[tissue].mean())
            mid_j = float(jj[tissue].mean())
            best, dist = 0, np.inf
            for lab in range(1, n + 1):
                if sizes[lab - 1] < MIN_SPINE_AREA_MM2:
                    continue
                ci, cj = ii[labels == lab].mean(), jj[labels == lab].mean()
                d = abs(ci - mid_i) * di + 0.25 * abs(cj - mid_j) * dj
                if d < dist:
                    best, dist = lab, d
            if best == 0:
                continue
            center = (float(ii[labels == best].mean()), float(jj[labels == best].mean()))
        disc = ((ii - center[0]) * di) ** 2 + ((jj - center[1]) * dj) ** 2 <= TRACK_RADIUS_MM**2
        inside = bone & disc
        if inside.sum() * di * dj < MIN_SPINE_AREA_MM2:
            if column:
                column.append((int(k), center[0], center[1]))
            continue
        # the bone this part of the column belongs to in the slice: wide at the skull base
        labels, _ = ndimage.label(bone)
        joined = np.isin(labels, np.unique(labels[inside]))
        cols = np.nonzero(joined.any(axis=0))[0]
        if column and (cols.max() - cols.min() + 1) * di > SKULL_BASE_WIDTH_MM:
            base_z = float(z[k])
            break
        center = (float(ii[inside].mean()), float(jj[inside].mean()))
        column.append((int(k), center[0], center[1]))
    return column, base_z


def dense_left_out_ml(volume: Volume, mask: NDArray[np.bool_]) -> float:
    """The volume (ml) of what lies outside ``mask`` and is denser than soft tissue."""
    voxel_ml = abs(float(np.linalg.det(volume.index_to_world[:3, :3]))) / 1000.0
    return float(((~mask) & (volume.data > SOFT_TISSUE_HU)).sum()) * voxel_ml


def roi_volume(volume: Volume, roi: RegionOfInterest) -> Volume:
    """``volume`` with what lies outside ``roi`` and is denser than soft tissue set to
    ``SOFT_TISSUE_HU`` (a new volume; labelled so)."""
    if roi.mask.shape != volume.shape:
        raise ValueError(f"the region's mask {roi.mask.shape} does not match the volume {volume.shape}")
    data = soft_outside(volume.data, roi.mask)
    meta = dict(volume.meta) | {"roi": roi.summary()}
    return Volume(data, volume.index_to_world, label=f"{volume.label} (region: {roi.source})",
                  meta=meta)  # fmt: skip


def soft_outside(data: NDArray, mask: NDArray[np.bool_]) -> NDArray[np.float32]:
    """``data`` (HU) with what lies outside ``mask`` and is denser than soft tissue set to
    ``SOFT_TISSUE_HU``."""
    return np.where(~mask & (data > SOFT_TISSUE_HU), np.float32(SOFT_TISSUE_HU), data).astype(np.float32)


def region_on_grid(roi: RegionOfInterest, volume: Volume, grid: Volume) -> NDArray[np.bool_]:
    """``roi`` (on ``volume``'s grid) on ``grid``'s voxels, nearest voxel; what lies outside
    ``volume`` is in the region."""
    m = np.linalg.inv(volume.index_to_world) @ grid.index_to_world  # grid index -> volume index
    nk, nj, ni = grid.shape
    if np.allclose(m[:3, :3] - np.diag(np.diag(m[:3, :3])), 0.0, atol=1e-9):
        axes = [np.rint(m[a, a] * np.arange(n) + m[a, 3]).astype(np.int64) for a, n in enumerate((ni, nj, nk))]
        inside = [(ax >= 0) & (ax < size) for ax, size in zip(axes, roi.mask.shape[::-1], strict=True)]
        clipped = [np.clip(ax, 0, size - 1) for ax, size in zip(axes, roi.mask.shape[::-1], strict=True)]
        out = roi.mask[np.ix_(clipped[2], clipped[1], clipped[0])].copy()
        out |= ~(inside[2][:, None, None] & inside[1][None, :, None] & inside[0][None, None, :])
        return out
    kk, jj, ii = np.meshgrid(np.arange(nk), np.arange(nj), np.arange(ni), indexing="ij")
    idx = np.stack([ii, jj, kk], axis=-1).reshape(-1, 3) @ m[:3, :3].T + m[:3, 3]
    coords = idx[:, ::-1].T.reshape(3, nk, nj, ni)  # (k, j, i)
    return ndimage.map_coordinates(roi.mask.astype(np.uint8), coords, order=0, cval=1).astype(bool)


#: A pixel whose ray meets more than this share of its attenuation outside the region (the neck
#: below the skull base, for the cranium) is left out of the measure.
OUTSIDE_SHARE = 0.5
#: The pixels left out are grown by this much (mm at the iso-center): the patient moved from the start.
OUTSIDE_GROW_MM = 4.0
#: The share is taken on a coarse copy of the volume with voxels about this size (mm).
OUTSIDE_VOXEL_MM = 4.0
#: A view keeps its whole field when the region would leave less than this share of it.
MIN_FIELD_SHARE = 0.25


@dataclass(frozen=True)
class RegionField:
    """What the region left out of one view's field: ``left_out_px`` of its ``field_px``
    usable pixels (0 with ``kept_whole`` when too little would have been left)."""

    left_out_px: int
    field_px: int
    kept_whole: bool = False

    def to_dict(self) -> dict:
        return {"left_out_px": self.left_out_px, "field_px": self.field_px, "kept_whole": self.kept_whole}


def outside_voxels(volume: Volume, roi: RegionOfInterest) -> NDArray[np.bool_]:
    """The voxels whose edges the image should not be matched on: for the automatic cranium the
    whole slab below the skull base (spine, neck muscles, airway and skin all move with the neck);
    none for a user's mask (its outside is rendered as soft tissue instead, :func:`roi_volume`)."""
    if roi.source != "cranium" or roi.skull_base_z_mm is None:
        return np.zeros(volume.shape, dtype=bool)
    z, _, _ = _axial(volume)
    return np.broadcast_to((z < roi.skull_base_z_mm)[:, None, None], volume.shape)


def region_views(
    volume: Volume,
    roi: RegionOfInterest | None,
    views: XRayImage | tuple[XRayImage, ...] | list[XRayImage],
    motion: NDArray[np.float64] | None = None,
) -> tuple[list[XRayImage], list[RegionField]]:
    """``views`` with the pixels that see mostly what lies outside ``roi`` left out of their
    fields: where more than ``OUTSIDE_SHARE`` of a ray's attenuation, with the volume moved by
    ``motion`` (the start), lies in :func:`outside_voxels`, grown by ``OUTSIDE_GROW_MM``. The
    rest of the volume is rendered as it is: the head's edges seen through the neck still count.
    Views unchanged (and no fields) when ``roi`` is None or leaves nothing out."""
    views = [views] if isinstance(views, XRayImage) else list(views)
    renderers = None if roi is None else _outside_renderers(volume, roi)
    if renderers is None:
        return views, []
    narrowed, fields = [], []
    for view in views:
        g = view.geometry
        rows, cols = max(1, g.rows // 2), max(1, g.cols // 2)
        small = g.resized(rows, cols)
        seen_out, seen_in = (r.render(small, motion) for r in renderers)
        away = seen_out > OUTSIDE_SHARE * np.maximum(seen_out + seen_in, 1e-6)
        away = ndimage.zoom(away.astype(np.uint8), (g.rows / rows, g.cols / cols), order=0).astype(bool)
        away = away[: g.rows, : g.cols]
        grow = int(round(OUTSIDE_GROW_MM / _pixel_mm_at_iso(g)))
        if grow > 0 and away.any():
            away = ndimage.binary_dilation(away, iterations=grow)
        field = np.asarray(view.mask, dtype=bool)
        left = field & away
        kept = field & ~away
        if kept.sum() < MIN_FIELD_SHARE * field.sum():
            narrowed.append(view)
            fields.append(RegionField(0, int(field.sum()), kept_whole=True))
            continue
        narrowed.append(replace(view, mask=kept))
        fields.append(RegionField(int(left.sum()), int(field.sum())))
    return narrowed, fields


#: The coarse outside and inside of the regions used last: (volume, (region, renderers or None)).
_PARTS: OrderedDict[tuple, tuple[Volume, tuple[RegionOfInterest, tuple[DRRRenderer, DRRRenderer] | None]]] = (
    OrderedDict()
)


def _outside_renderers(volume: Volume, roi: RegionOfInterest) -> tuple[DRRRenderer, DRRRenderer] | None:
    """Renderers of what lies outside ``roi`` and what lies inside, on a coarse copy of
    ``volume`` (``OUTSIDE_VOXEL_MM``); None when nothing lies outside. Kept for the last few."""
    from registration.core.drr import DRRRenderer

    key = (id(volume), id(roi))
    hit = recall_for_volume(_PARTS, key, volume)
    if hit is not None and hit[0] is roi:
        return hit[1]
    outside = outside_voxels(volume, roi)
    renderers = None
    if outside.any():
        step = np.maximum(1, np.rint(OUTSIDE_VOXEL_MM / np.asarray(volume.spacing_mm[::-1]))).astype(int)  # k, j, i
        sl = tuple(slice(None, None, int(n)) for n in step)
        coarse, away = volume.data[sl], outside[sl]
        affine = volume.index_to_world @ np.diag([step[2], step[1], step[0], 1.0]).astype(np.float64)
        air = np.float32(-1000.0)
        parts = (np.where(away, coarse, air), np.where(away, air, coarse))
        renderers = tuple(DRRRenderer(Volume(p.astype(np.float32), affine, label=n), levels=1)
                          for p, n in zip(parts, ("outside", "inside"), strict=True))  # fmt: skip
    remember_for_volume(_PARTS, key, (volume, (roi, renderers)))
    return renderers


def _pixel_mm_at_iso(g: CArm) -> float:
    """A detector pixel's size at the iso-center (mm)."""
    return float(min(g.pixel_mm)) * g.sod_mm / g.sid_mm
