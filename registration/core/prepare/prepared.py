"""The prepared volume of some views: built, sliced from the base, cached; its crop, recropped."""

from __future__ import annotations

import math
import threading
import time
import weakref
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core.drr import DRRRenderer
from registration.core.geometry import CArm, check_rigid, invert_rigid
from registration.core.prepare.body import ProbeBlocks, _crop, mask_outside_body, needed_box, probe_blocks
from registration.core.prepare.params import (
    CACHE_ENTRIES,
    DEFAULT_LEVELS,
    MIN_LEVEL0_MM,
    SNAP_TOLERANCE,
)
from registration.core.prepare.reach import (
    Reach,
    _axes_and_spacing,
    field_extent_mm,
    level_spacing_mm,
)
from registration.core.prepare.resample import _snap_factor, resample_isotropic
from registration.core.prepare.store import (
    PreparationStore,
    PreparedBase,
    _base_arrays,
    _base_from,
    _blocks_arrays,
    _blocks_from,
    _blocks_key,
    _levels_key,
    volume_digest,
)
from registration.core.volume import Volume

Array = NDArray[np.float64]


@dataclass
class PreparedVolume:
    """A volume cropped and resampled for the views and search it was prepared for.

    ``levels[L]`` is pyramid level L (None when it was not prepared); ``renderer`` renders
    them and keeps ``volume`` (the original) as its identity.
    """

    volume: Volume
    levels: tuple[Volume | None, ...]
    spacing_mm: tuple[float | None, ...]
    #: Index box of the original volume that was kept ((i, j, k) low and high, inclusive).
    box_lo: tuple[int, int, int]
    box_hi: tuple[int, int, int]
    reach: Reach
    geometries: tuple[CArm, ...]
    seconds: float
    renderer: DRRRenderer = field(repr=False)
    #: Whether the levels hold only the body (what lies outside it set to air, ``probe_blocks``).
    body: bool = False
    #: Where the view-independent part came from: "built", "memory" or "disk" (a store).
    base_source: str = "built"
    #: What the levels hold (:class:`Crop`; also :func:`crop_of` the renderer).
    crop: Crop | None = field(default=None, repr=False)
    #: Renderers built on these levels and kept with them (the confidence's probe levels, by planes).
    derived: dict = field(default_factory=dict, repr=False, compare=False)
    #: The volume's probe blocks the levels were masked with (the body; None: not kept).
    blocks: ProbeBlocks | None = field(default=None, repr=False, compare=False)

    @property
    def voxels_per_level(self) -> list[int | None]:
        return [None if v is None else int(np.prod(v.shape)) for v in self.levels]

    def summary(self) -> dict:
        """JSON-ready description (spacing, shape and voxels per level, crop, time)."""
        return {
            "spacing_mm": list(self.spacing_mm),
            "shape_per_level": [None if v is None else list(v.shape[::-1]) for v in self.levels],
            "voxels_per_level": self.voxels_per_level,
            "source_voxels": int(np.prod(self.volume.shape)),
            "box_lo": list(self.box_lo),
            "box_hi": list(self.box_hi),
            "reach": {"translation_mm": self.reach.translation_mm, "rotation_deg": self.reach.rotation_deg},
            "body_only": self.body,
            "base_source": self.base_source,
            "prepare_seconds": self.seconds,
            "complete": None if self.crop is None else self.crop.complete,
        }

    def body_summary(self) -> dict:
        """What the body mask left out (JSON-ready): ``body_only``, and ``outside_body_ml``, the
        volume of the probe blocks holding tissue away from the patient's body (a CT's couch
        and head holder), None when the blocks were not kept or no single body was found."""
        blocks = self.blocks
        if not self.body or blocks is None or blocks.body is None:
            return {"body_only": bool(self.body), "outside_body_ml": None}
        voxel_mm3 = abs(float(np.linalg.det(self.volume.index_to_world[:3, :3])))
        block_ml = float(np.prod(blocks.step)) * voxel_mm3 / 1000.0
        outside = int((blocks.tissue & ~blocks.body).sum())
        return {"body_only": True, "outside_body_ml": round(outside * block_ml, 1)}


def _field_key(geometry: CArm) -> tuple:
    """What the crop and the spacing depend on: the projection of the whole field (not the
    number of pixels it is sampled with)."""
    g = geometry.resized(64, 64)
    return tuple(np.round(g.projection_matrix.ravel() / np.linalg.norm(g.projection_matrix[2, :3]), 5))


def _anatomy_extent_mm(volume: Volume, lo: NDArray[np.int64], hi: NDArray[np.int64], geometry: CArm) -> float:
    """Largest extent of the box across the beam (mm), projected to the iso-center plane."""
    idx = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])], float)
    corners = idx @ volume.index_to_world[:3, :3].T + volume.index_to_world[:3, 3]
    view = corners @ geometry.view_from_world[:3, :3].T + geometry.view_from_world[:3, 3]
    return float(max(np.ptp(view[:, 0]), np.ptp(view[:, 1])))


def _build_levels(
    volume: Volume, targets: dict[int, float], lo: NDArray[np.int64], hi: NDArray[np.int64], blocks: ProbeBlocks
) -> tuple[dict[int, Volume], NDArray[np.int64], NDArray[np.int64]]:
    """The levels of ``targets`` (level -> spacing) over the index box ``lo..hi``, set to air
    outside the body; and the box they cover (aligned for block averages)."""
    nk, nj, ni = volume.shape
    top = np.array([ni - 1, nj - 1, nk - 1], dtype=np.int64)
    _, spacing = _axes_and_spacing(volume)
    snaps = {lv: _snap_factor(spacing, t) for lv, t in targets.items()}
    largest = max([f for f in snaps.values() if f is not None], default=1)
    if largest > 1:  # crop on block boundaries, so block averages are the volume's own pyramid's
        lo = (lo // largest) * largest
        span = np.maximum(-(-(hi - lo + 1) // largest) * largest, 2 * largest)
        hi = np.minimum(lo + span - 1, top)
    base = _crop(volume, lo, hi) if any(f is not None for f in snaps.values()) else None
    built: dict[int, Volume] = {}
    for lv in sorted(targets):  # finest first
        finer = built.get(lv - 1)
        if snaps[lv] is not None and base is not None:
            built[lv] = base.downsample(snaps[lv]) if snaps[lv] > 1 else base
        elif finer is not None and abs(targets[lv] / float(finer.spacing_mm[0]) - 2.0) < 1e-6 and min(finer.shape) >= 4:
            built[lv] = finer.downsample(2)
        elif finer is not None and abs(targets[lv] - float(finer.spacing_mm[0])) < 1e-6:
            built[lv] = finer
        else:
            built[lv] = resample_isotropic(volume, targets[lv], lo, hi)
    # outside the body: air
    return {lv: mask_outside_body(v, volume, blocks) for lv, v in built.items()}, lo, hi


def _slice_level(level: Volume, volume: Volume, lo: NDArray[np.int64], hi: NDArray[np.int64]) -> Volume:
    """The voxels of ``level`` (a grid of ``volume``'s axes) that span the source index box
    ``lo..hi``: from the voxel nearest its low face to the one nearest its high face (the box
    holds the crop's margin of two coarsest voxels; at least two voxels along each axis)."""
    a = volume.index_from_world @ level.index_to_world  # level index -> source index (diagonal)
    scale, offset = np.diag(a)[:3], a[:3, 3]
    n = np.array(level.shape[::-1], dtype=np.int64)  # (i, j, k)
    g_lo = np.round((lo - offset) / scale).astype(np.int64)
    g_hi = np.round((hi - offset) / scale).astype(np.int64)
    g_lo = np.clip(g_lo, 0, n - 2)
    g_hi = np.clip(np.maximum(g_hi, g_lo + 1), 1, n - 1)
    if np.all(g_lo == 0) and np.all(g_hi == n - 1):
        return level
    data = level.data[g_lo[2] : g_hi[2] + 1, g_lo[1] : g_hi[1] + 1, g_lo[0] : g_hi[0] + 1]
    affine = level.index_to_world.copy()
    affine[:3, 3] = level.index_to_world[:3, :3] @ g_lo + level.index_to_world[:3, 3]
    return Volume(np.ascontiguousarray(data), affine, label=level.label, meta=level.meta)


_BLOCKS: OrderedDict[tuple, tuple[Volume, ProbeBlocks]] = OrderedDict()
_BASES: OrderedDict[tuple, tuple[Volume, PreparedBase]] = OrderedDict()


def remember_for_volume(table: OrderedDict, key: tuple, value: tuple) -> None:
    """Keep ``value`` (``(volume, what was computed for it)``) under ``key`` in ``table``, the
    ``CACHE_ENTRIES`` used last (thread-safe)."""
    with _CACHE_LOCK:
        table[key] = value
        table.move_to_end(key)
        while len(table) > CACHE_ENTRIES:
            table.popitem(last=False)


def recall_for_volume(table: OrderedDict, key: tuple, volume: Volume):  # noqa: ANN202
    """What :func:`remember_for_volume` kept under ``key`` for this very ``volume`` (None: nothing)."""
    with _CACHE_LOCK:
        hit = table.get(key)
        if hit is None or hit[0] is not volume:
            return None
        table.move_to_end(key)
        return hit[1]


class _Digest:
    """The volume's digest, computed once and only when a store asks for it."""

    def __init__(self, volume: Volume) -> None:
        self.volume, self._value = volume, None

    def __call__(self) -> str:
        if self._value is None:
            self._value = volume_digest(self.volume)
        return self._value


def _probe(volume: Volume, body: bool, store: PreparationStore | None, remember: bool, digest: _Digest) -> ProbeBlocks:
    key = (weakref.ref(volume), body)
    blocks = recall_for_volume(_BLOCKS, key, volume) if remember else None
    if blocks is not None:
        return blocks
    if store is not None:
        stored = store.load("prepared-blocks", _blocks_key(digest(), body))
        blocks = None if stored is None else _blocks_from(stored, volume)
    if blocks is None:
        blocks = probe_blocks(volume, body=body)
        if store is not None:
            store.save("prepared-blocks", _blocks_key(digest(), body), _blocks_arrays(blocks))
    if remember:
        remember_for_volume(_BLOCKS, key, (volume, blocks))
    return blocks


def _base(
    volume: Volume, blocks: ProbeBlocks, targets: dict[int, float], margin_mm: float, body: bool,
    store: PreparationStore | None, remember: bool, digest: _Digest,
) -> PreparedBase:  # fmt: skip
    """The base levels of ``targets``: remembered, stored, or built over the needed tissue's box."""
    key = (weakref.ref(volume), body, tuple(sorted(targets.items())), round(margin_mm, 9))
    base = recall_for_volume(_BASES, key, volume) if remember else None
    if base is not None:
        return PreparedBase(base.blocks, base.levels, base.box_lo, base.box_hi, source="memory")
    if store is not None:
        stored = store.load("prepared-levels", _levels_key(_blocks_key(digest(), body), targets, margin_mm))
        base = None if stored is None else _base_from(stored, volume, blocks, sorted(targets))
    if base is None:
        nk, nj, ni = volume.shape
        full = (np.zeros(3, dtype=np.int64), np.array([ni - 1, nj - 1, nk - 1], dtype=np.int64))
        lo, hi = _tissue_box(volume, blocks, margin_mm) or full
        levels, lo, hi = _build_levels(volume, targets, lo, hi, blocks)
        base = PreparedBase(blocks, levels, lo, hi)
        if store is not None:
            store.save("prepared-levels", _levels_key(_blocks_key(digest(), body), targets, margin_mm),
                       _base_arrays(base))  # fmt: skip
    if remember:
        remember_for_volume(_BASES, key, (volume, base))
    return base


def _tissue_box(
    volume: Volume, blocks: ProbeBlocks, margin_mm: float
) -> tuple[NDArray[np.int64], NDArray[np.int64]] | None:
    """Index box (lo, hi inclusive, (i, j, k)) of the needed blocks (tissue of the body) grown
    by ``margin_mm``: what any view's crop (:func:`needed_box`) lies within."""
    _, spacing = _axes_and_spacing(volume)
    nk, nj, ni = volume.shape
    si, sj, sk = (int(x) for x in blocks.step)
    kk, jj, ii = np.nonzero(blocks.needed)
    if kk.size == 0:
        return None
    pad = np.ceil(margin_mm / spacing).astype(np.int64)
    lo = np.array([ii.min() * si, jj.min() * sj, kk.min() * sk], dtype=np.int64) - pad
    hi = np.array([(ii.max() + 1) * si - 1, (jj.max() + 1) * sj - 1, (kk.max() + 1) * sk - 1], dtype=np.int64) + pad
    return np.maximum(lo, 0), np.minimum(hi, np.array([ni - 1, nj - 1, nk - 1]))


def _prepare(
    volume: Volume, geometries: tuple[CArm, ...], reach: Reach, levels: tuple[int, ...], body: bool,
    store: PreparationStore | None = None, remember: bool = True,
) -> PreparedVolume:  # fmt: skip
    start = time.perf_counter()
    digest = _Digest(volume)
    _, spacing = _axes_and_spacing(volume)
    nk, nj, ni = volume.shape
    full = (np.zeros(3, dtype=np.int64), np.array([ni - 1, nj - 1, nk - 1], dtype=np.int64))
    # the coarsest level's voxels plus a voxel of the source for interpolation at the crop's faces
    extent_guess = max(field_extent_mm(g) for g in geometries)
    margin = 2.0 * level_spacing_mm(extent_guess, max(levels)) + float(spacing.max())
    blocks = _probe(volume, body, store, remember, digest)
    lo, hi = needed_box(volume, geometries, reach, margin_mm=margin, blocks=blocks) or full
    extent = min(extent_guess, max(_anatomy_extent_mm(volume, lo, hi, g) for g in geometries))
    # level 0 never finer than the volume's own finest spacing (resampling cannot add detail)
    # nor, on a scanner's anisotropic grid (a CT's slices), than MIN_LEVEL0_MM: its fine in-plane
    # spacing costs rays and samples, not accuracy; an isotropic 3DRA keeps its own pyramid
    anisotropic = float(spacing.max()) > (1.0 + SNAP_TOLERANCE) * float(spacing.min())
    base_mm = max(level_spacing_mm(extent, 0), float(spacing.min()), MIN_LEVEL0_MM if anisotropic else 0.0)
    targets = {lv: base_mm * 2**lv for lv in levels}
    base = _base(volume, blocks, targets, margin, body, store, remember, digest)
    return _assemble(volume, geometries, reach, np.eye(4), levels, base, margin, lo, hi, start)


def _assemble(
    volume: Volume, geometries: tuple[CArm, ...], reach: Reach, center: Array, levels: tuple[int, ...],
    base: PreparedBase, margin_mm: float, lo: NDArray[np.int64], hi: NDArray[np.int64], start: float,
) -> PreparedVolume:  # fmt: skip
    """The view's crop ``lo..hi``: the base levels' voxels that cover it, their renderer, and
    the :class:`Crop` that says what they hold (kept for :func:`crop_of`)."""
    sliced = {lv: _slice_level(v, volume, lo, hi) for lv, v in base.levels.items()}
    pyramid = tuple(sliced.get(lv) for lv in range(max(levels) + 1))
    renderer = DRRRenderer(volume, levels=list(pyramid))
    tissue = _tissue_box(volume, base.blocks, margin_mm)
    complete = tissue is None or bool(np.all(lo <= tissue[0]) and np.all(hi >= tissue[1]))
    crop = Crop(
        volume=volume, geometries=geometries, reach=reach, center_motion=np.array(center, dtype=np.float64),
        levels=levels, box_lo=tuple(int(x) for x in lo), box_hi=tuple(int(x) for x in hi),  # type: ignore[arg-type]
        complete=complete, margin_mm=float(margin_mm), base=base,
    )  # fmt: skip
    with _CACHE_LOCK:
        _CROPS[renderer] = crop
    return PreparedVolume(
        volume=volume,
        levels=pyramid,
        spacing_mm=tuple(None if v is None else float(v.spacing_mm.max()) for v in pyramid),
        box_lo=crop.box_lo,
        box_hi=crop.box_hi,
        reach=reach,
        geometries=geometries,
        seconds=time.perf_counter() - start,
        renderer=renderer,
        body=base.blocks.body is not None,
        base_source=base.source,
        crop=crop,
        blocks=base.blocks,
    )


@dataclass(frozen=True, eq=False)
class Crop:
    """What a preparation's levels hold: the tissue of the volume's index box ``box_lo..box_hi``
    ((i, j, k), inclusive), which holds everything a ray through ``geometries`` meets while the
    patient's motion is ``S @ center_motion`` with S within ``reach`` (about the views'
    iso-center, CONVENTIONS §4). Outside that the levels may lack anatomy: a DRR at such a
    motion can be missing tissue at the field's edge. ``complete``: the box holds all of the
    body's tissue (no motion can need more). ``base``: the levels it was sliced from (a new
    crop is sliced from them too: :func:`recrop`)."""

    volume: Volume = field(repr=False)
    geometries: tuple[CArm, ...]
    reach: Reach
    center_motion: Array
    levels: tuple[int, ...]
    box_lo: tuple[int, int, int]
    box_hi: tuple[int, int, int]
    complete: bool
    margin_mm: float
    base: PreparedBase = field(repr=False)

    def margin(self, motion: ArrayLike, search: Reach) -> tuple[float, float]:
        """What is left of the crop's reach (mm at the iso-center, degrees) when a search of
        ``search`` starts at the patient motion ``motion``; negative: that search can render
        anatomy the crop lacks. Infinite for a complete crop."""
        if self.complete:
            return math.inf, math.inf
        # a tracker asks after every applied frame: its poses are rigid already (no check_rigid)
        moved = np.asarray(motion, dtype=np.float64) @ invert_rigid(self.center_motion)
        need = search._moved(moved, self.geometries[0].isocenter_mm)
        return self.reach.translation_mm - need.translation_mm, self.reach.rotation_deg - need.rotation_deg


#: The crop behind each prepared renderer (weak: a renderer no longer used is forgotten).
_CROPS: weakref.WeakKeyDictionary[DRRRenderer, Crop] = weakref.WeakKeyDictionary()


def crop_of(renderer: DRRRenderer) -> Crop | None:
    """The :class:`Crop` of a renderer made by :func:`prepare_volume` or :func:`recrop` (None
    for any other renderer, e.g. a pyramid of the whole volume: nothing is missing from it)."""
    with _CACHE_LOCK:
        return _CROPS.get(renderer)


def recrop(crop: Crop, center_motion: ArrayLike, reach: Reach) -> PreparedVolume:
    """The crop's levels again, around the patient motion ``center_motion`` and for ``reach``
    about it: the same grids (slices of the same base levels, so a DRR of anatomy both crops
    hold is the same), another box. Not cached. Used by a tracker whose patient moved toward
    the crop's edge (:mod:`registration.core.tracking`)."""
    start = time.perf_counter()
    center = check_rigid(center_motion, name="center motion")
    volume = crop.volume
    found = needed_box(volume, crop.geometries, reach, margin_mm=crop.margin_mm, blocks=crop.base.blocks,
                       center_motion=center)  # fmt: skip
    if found is None:  # no tissue within reach of the fields: keep all of it
        found = _tissue_box(volume, crop.base.blocks, crop.margin_mm)
    if found is None:
        found = (np.asarray(crop.box_lo, dtype=np.int64), np.asarray(crop.box_hi, dtype=np.int64))
    lo, hi = found
    return _assemble(volume, crop.geometries, reach, center, crop.levels, crop.base, crop.margin_mm, lo, hi, start)


_CACHE: OrderedDict[tuple, tuple[Volume, PreparedVolume]] = OrderedDict()
_CACHE_LOCK = threading.Lock()


def prepare_volume(
    volume: Volume,
    geometries: CArm | Sequence[CArm],
    *,
    reach: Reach | None = None,
    levels: Sequence[int] = DEFAULT_LEVELS,
    cache: bool = True,
    body: bool = True,
    store: PreparationStore | None = None,
) -> PreparedVolume:
    """The cropped, resampled pyramid of ``volume`` for ``geometries`` (cached per volume).

    ``reach``: how far the search may move the anatomy (default: the default search of
    +-30 mm and +-15 degrees, :meth:`Reach.of_search`). ``levels``: the pyramid levels to
    prepare. ``body``: keep only the patient's body (:func:`probe_blocks`: a CT's couch, head
    rest and the air around set to air). A cached preparation of the same volume object for the same fields and levels
    whose reach covers ``reach`` is returned as it is (its ``seconds`` are those of its making).
    ``store``: where the view-independent part (:class:`PreparedBase`) is looked up by the
    volume's content and saved (``PreparedVolume.base_source`` says "disk" when it came from
    there). ``cache=False``: nothing remembered, looked up or stored.
    """
    if not isinstance(volume, Volume):
        raise ValueError(f"volume must be a Volume, got {type(volume).__name__}")
    views = (geometries,) if isinstance(geometries, CArm) else tuple(geometries)
    if not views or not all(isinstance(g, CArm) for g in views):
        raise ValueError("geometries must be one or more CArm views")
    levels_t = tuple(sorted({int(lv) for lv in levels}))
    if not levels_t or levels_t[0] < 0:
        raise ValueError(f"levels must be integers >= 0, got {list(levels)}")
    reach = reach or Reach.of_search(30.0, 15.0)
    key = (weakref.ref(volume), tuple(_field_key(g) for g in views), levels_t, bool(body))
    if cache:
        with _CACHE_LOCK:
            hit = _CACHE.get(key)
            if hit is not None and hit[0] is volume and hit[1].reach.covers(reach):
                _CACHE.move_to_end(key)
                return hit[1]
    prepared = _prepare(volume, views, reach, levels_t, bool(body), store if cache else None, remember=cache)
    if cache:
        remember_for_volume(_CACHE, key, (volume, prepared))
    return prepared


def clear_cache() -> None:
    """Forget every cached preparation (and the remembered bases and probe blocks)."""
    with _CACHE_LOCK:
        _CACHE.clear()
        _BASES.clear()
        _BLOCKS.clear()
