"""The view-independent part of a preparation, kept across processes by the volume's content."""

from __future__ import annotations

import hashlib
import json
import threading
import weakref
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from registration.core.prepare.body import ProbeBlocks
from registration.core.prepare.params import (
    AIR_HU,
    BODY_HU,
    BODY_KEEP_MM,
    BODY_MIN_SHARE,
    BODY_OPENING_MM,
    BODY_PART_SHARE,
    CROP_PROBE_MM,
    PREPARE_VERSION,
    SNAP_TOLERANCE,
    TISSUE_HU,
)
from registration.core.volume import Volume

Array = NDArray[np.float64]


class PreparationStore(Protocol):
    """Where prepared bases outlive a process (:class:`registration.io.cache.PreparationCache`).

    ``load`` returns the arrays stored under ``key`` (a JSON-ready dict), or None when there
    are none or they cannot be read (a store never raises for a damaged entry: the preparation
    is then built again and saved over it); ``save`` stores them (atomically).
    """

    def load(self, kind: str, key: dict) -> dict[str, np.ndarray] | None: ...

    def save(self, kind: str, key: dict, arrays: dict[str, np.ndarray]) -> None: ...


@dataclass(frozen=True)
class PreparedBase:
    """What a preparation computes whatever the views: the probe blocks and, per pyramid
    level, the volume's box of needed tissue (the body's, all views alike) on the level's grid,
    set to air outside the body. A view's levels are slices of these (:func:`_slice_level`).
    ``source``: "built", or "memory" / "disk" where it was found."""

    blocks: ProbeBlocks
    levels: dict[int, Volume]
    box_lo: NDArray[np.int64]
    box_hi: NDArray[np.int64]
    source: str = "built"


#: Each volume's digest, computed once per volume object (the engine never changes a volume's
#: voxels in place: a changed volume is a new one).
_DIGESTS: weakref.WeakKeyDictionary[Volume, str] = weakref.WeakKeyDictionary()
_DIGESTS_LOCK = threading.Lock()


def volume_digest(volume: Volume) -> str:
    """SHA-256 of the volume's voxels (float32, C order), shape and affine: what a stored
    preparation belongs to (hashing its 94 MB takes ~0.05-0.1 s; decoding the series 0.2-0.4 s).
    Computed once per volume: the cranium's store and the preparation's ask for it in turn."""
    with _DIGESTS_LOCK:
        known = _DIGESTS.get(volume)
    if known is not None:
        return known
    digest = _sha256(volume)
    with _DIGESTS_LOCK:
        _DIGESTS[volume] = digest
    return digest


def remember_digest(volume: Volume, digest: str) -> None:
    """Take ``digest`` as ``volume``'s (:func:`volume_digest`): its voxels were hashed before,
    when they were kept on disk with it (:mod:`registration.io.volume_cache`)."""
    with _DIGESTS_LOCK:
        _DIGESTS[volume] = digest


def _sha256(volume: Volume) -> str:
    h = hashlib.sha256()
    h.update(json.dumps([list(volume.shape), str(volume.data.dtype)]).encode())
    h.update(np.ascontiguousarray(volume.index_to_world, dtype=np.float64).tobytes())
    h.update(memoryview(np.ascontiguousarray(volume.data)).cast("B"))
    return h.hexdigest()


def _blocks_key(digest: str, body: bool) -> dict:
    return {
        "volume_sha256": digest,
        "prepare_version": PREPARE_VERSION,
        "body": body,
        "thresholds_hu": [TISSUE_HU, BODY_HU, AIR_HU],
        "probe_mm": CROP_PROBE_MM,
        "body_mm": [BODY_OPENING_MM, BODY_KEEP_MM],
        "body_shares": [BODY_PART_SHARE, BODY_MIN_SHARE],
    }


def _levels_key(blocks_key: dict, targets: dict[int, float], margin_mm: float) -> dict:
    return blocks_key | {
        "targets_mm": [[lv, round(t, 9)] for lv, t in sorted(targets.items())],
        "margin_mm": round(margin_mm, 9),
        "snap_tolerance": SNAP_TOLERANCE,
    }


def _blocks_arrays(blocks: ProbeBlocks) -> dict[str, np.ndarray]:
    out = {"step": np.asarray(blocks.step, dtype=np.int64), "tissue": np.asarray(blocks.tissue, dtype=bool)}
    if blocks.body is not None:
        out["body"] = np.asarray(blocks.body, dtype=bool)
    return out


def _blocks_from(arrays: dict[str, np.ndarray], volume: Volume) -> ProbeBlocks | None:
    """The stored probe blocks, None unless they fit ``volume`` (a foreign or damaged entry)."""
    try:
        step = np.asarray(arrays["step"])
        tissue = np.asarray(arrays["tissue"])
        body = arrays.get("body")
        if step.shape != (3,) or step.dtype != np.int64 or np.any(step < 1) or tissue.dtype != bool:
            return None
        shape = tuple(-(-n // int(s)) for n, s in zip(volume.shape, step[::-1], strict=True))
        if tissue.shape != shape or (body is not None and (body.dtype != bool or body.shape != shape)):
            return None
    except (KeyError, TypeError, ValueError):
        return None
    return ProbeBlocks(step, tissue, None if body is None else np.asarray(body))


def _base_arrays(base: PreparedBase) -> dict[str, np.ndarray]:
    out = {"box": np.stack([base.box_lo, base.box_hi]).astype(np.int64)}
    for lv, v in base.levels.items():
        out[f"level{lv}"] = v.data
        out[f"affine{lv}"] = v.index_to_world
    return out


def _base_from(
    arrays: dict[str, np.ndarray], volume: Volume, blocks: ProbeBlocks, levels: Sequence[int]
) -> PreparedBase | None:
    """The stored levels, None unless they are those of ``levels`` for ``volume``'s grid."""
    try:
        box = np.asarray(arrays["box"])
        if box.shape != (2, 3) or box.dtype != np.int64:
            return None
        built = {}
        for lv in levels:
            data, affine = np.asarray(arrays[f"level{lv}"]), np.asarray(arrays[f"affine{lv}"])
            if data.dtype != np.float32 or data.ndim != 3 or affine.shape != (4, 4) or affine.dtype != np.float64:
                return None
            level = Volume(data, affine, label=volume.label, meta=volume.meta)
            a = volume.index_from_world @ level.index_to_world  # the level keeps the volume's axes
            if np.abs(a[:3, :3] - np.diag(np.diag(a[:3, :3]))).max() > 1e-6 * np.abs(a[:3, :3]).max():
                return None
            built[int(lv)] = level
    except (KeyError, TypeError, ValueError):
        return None
    return PreparedBase(blocks, built, box[0], box[1], source="disk")
