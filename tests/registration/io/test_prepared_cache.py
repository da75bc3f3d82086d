"""The prepared volume on disk (registration.io.cache.PreparationCache): the same voxels and
DRRs as a fresh preparation, rebuilt when damaged or foreign, keyed by the volume's content."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from registration.core import prepare
from registration.core.geometry import CArm, offsets_to_matrix
from registration.core.prepare import PreparedVolume, Reach, prepare_volume, volume_digest
from registration.core.volume import Volume
from registration.io.cache import PreparationCache

ISO = np.array([4.0, -3.0, 2.0])
REACH = Reach(10.0, 4.0)


def _head(spacing_xyz: tuple[float, float, float] = (2.0, 2.0, 3.0)) -> Volume:
    """A textured ellipsoid ('head') with a couch-like plate below, on a scanner-like grid."""
    sp = np.asarray(spacing_xyz)
    n = np.round(np.array([220.0, 220.0, 200.0]) / sp).astype(int)
    axes = [ISO[a] + (np.arange(n[a]) - (n[a] - 1) / 2.0) * sp[a] for a in range(3)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    d = np.sqrt(((x - ISO[0]) / 70.0) ** 2 + ((y - ISO[1]) / 80.0) ** 2 + ((z - ISO[2]) / 75.0) ** 2)
    texture = 300.0 * np.sin(x / 9.0) * np.cos(y / 11.0) * np.sin(z / 7.0)
    hu = np.where(d < 1.0, 200.0 + texture, -1000.0)
    hu[np.abs(y - ISO[1] - 100.0) < 4.0] = 300.0  # a plate 100 mm behind: not body
    return Volume.from_grid(hu.astype(np.float32), tuple(sp), center_mm=ISO)


def _view(primary: float = 0.0, secondary: float = 0.0) -> CArm:
    return replace(CArm.for_format(27.0, pixels=48, primary_deg=primary, secondary_deg=secondary),
                   isocenter_mm=tuple(ISO))  # fmt: skip


def _prepared(volume: Volume, view: CArm, store: PreparationCache | None) -> PreparedVolume:
    prepare.clear_cache()  # a new process: nothing in memory
    return prepare_volume(volume, view, reach=REACH, store=store)


def _assert_same(a: PreparedVolume, b: PreparedVolume, view: CArm) -> None:
    """Bit-identical levels (voxels and grids) and DRRs."""
    assert a.spacing_mm == b.spacing_mm and (a.box_lo, a.box_hi) == (b.box_lo, b.box_hi)
    for va, vb in zip(a.levels, b.levels, strict=True):
        assert (va is None) == (vb is None)
        if va is not None:
            np.testing.assert_array_equal(va.data, vb.data)
            np.testing.assert_array_equal(va.index_to_world, vb.index_to_world)
    motion = offsets_to_matrix([3.0, -2.0, 1.0, 2.0, -1.0, 3.0], view)
    for level in (1, 2):
        np.testing.assert_array_equal(a.renderer.render(view, motion, level=level),
                                      b.renderer.render(view, motion, level=level))  # fmt: skip


@pytest.fixture
def store(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> PreparationCache:
    monkeypatch.delenv("ROADMAP3D_NO_CACHE", raising=False)
    return PreparationCache(tmp_path / "cache")


def test_round_trip_is_bit_identical_and_serves_other_views(store: PreparationCache) -> None:
    vol, view = _head(), _view()
    built = _prepared(vol, view, store)
    assert built.base_source == "built" and len(store.entries()) == 2  # probe blocks, levels
    again = _prepared(vol, view, store)
    assert again.base_source == "disk"
    _assert_same(built, again, view)
    fresh = prepare_volume(vol, view, reach=REACH, cache=False)  # nothing remembered or stored
    assert fresh.base_source == "built"
    _assert_same(fresh, again, view)
    # another C-arm angle of the same volume: its crop of the same stored levels
    oblique = _view(35.0, -20.0)
    from_disk = _prepared(vol, oblique, store)
    assert from_disk.base_source == "disk"
    _assert_same(prepare_volume(vol, oblique, reach=REACH, cache=False), from_disk, oblique)
    prepare.clear_cache()


@pytest.mark.parametrize("damage", ["garbage", "truncated", "foreign"])
def test_a_damaged_or_foreign_entry_is_rebuilt(store: PreparationCache, damage: str) -> None:
    vol, view = _head(), _view()
    built = _prepared(vol, view, store)
    levels_file = next(p for p in store.entries() if p.name.startswith("prepared-levels-"))
    blocks_file = next(p for p in store.entries() if p.name.startswith("prepared-blocks-"))
    if damage == "garbage":
        levels_file.write_bytes(b"not an npz at all" * 100)
    elif damage == "truncated":
        levels_file.write_bytes(levels_file.read_bytes()[: levels_file.stat().st_size // 2])
    else:  # a valid entry of another key under this name (the blocks' file)
        levels_file.write_bytes(blocks_file.read_bytes())
    rebuilt = _prepared(vol, view, store)  # no exception: built again and saved over it
    assert rebuilt.base_source == "built"
    _assert_same(built, rebuilt, view)
    assert _prepared(vol, view, store).base_source == "disk"
    prepare.clear_cache()


def test_stored_arrays_that_do_not_fit_the_volume_are_rebuilt(store: PreparationCache) -> None:
    """An entry with the right key but wrong contents (a level of another dtype, probe blocks of
    another shape) is not used."""
    vol, view = _head(), _view()
    _prepared(vol, view, store)
    digest = volume_digest(vol)
    key = prepare._blocks_key(digest, True)
    store.save("prepared-blocks", key, {"step": np.array([1, 1, 1]), "tissue": np.zeros((2, 2, 2), bool)})
    assert prepare._blocks_from(store.load("prepared-blocks", key), vol) is None
    assert _prepared(vol, view, store).body  # the blocks were probed again
    prepare.clear_cache()


def test_a_changed_volume_changes_the_key(store: PreparationCache) -> None:
    vol, view = _head(), _view()
    _prepared(vol, view, store)
    data = vol.data.copy()
    data[data.shape[0] // 2, data.shape[1] // 2, data.shape[2] // 2] += 1.0  # one voxel of one slice
    changed = vol.with_data(data)
    assert volume_digest(changed) != volume_digest(vol)
    moved = Volume(vol.data, vol.index_to_world @ np.diag([1.0, 1.0, 1.0001, 1.0]))  # another slice spacing
    assert volume_digest(moved) != volume_digest(vol)
    assert _prepared(changed, view, store).base_source == "built"
    assert _prepared(vol, view, store).base_source == "disk"  # the original's entry is still there
    prepare.clear_cache()


def test_a_volume_is_hashed_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """The cranium's store and the preparation's both key by the digest: one hash per volume."""
    from registration.core.prepare import store as store_module

    hashed: list[int] = []
    real = store_module._sha256
    monkeypatch.setattr(store_module, "_sha256", lambda v: hashed.append(id(v)) or real(v))
    vol = _head()
    first = volume_digest(vol)
    assert volume_digest(vol) == first and hashed == [id(vol)]
    twin = Volume(vol.data.copy(), vol.index_to_world)  # the same voxels in another volume
    assert volume_digest(twin) == first and len(hashed) == 2


def test_size_bound_and_switch(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("ROADMAP3D_NO_CACHE", raising=False)
    small = PreparationCache(tmp_path / "small", max_bytes=1)  # keeps only the entry just written
    vol, view = _head(), _view()
    _prepared(vol, view, small)
    assert len(small.entries()) == 1
    monkeypatch.setenv("ROADMAP3D_NO_CACHE", "1")
    off = PreparationCache(tmp_path / "off")
    assert _prepared(vol, view, off).base_source == "built"
    assert _prepared(vol, view, off).base_source == "built" and off.entries() == []
    prepare.clear_cache()


def test_background_writes_are_the_same_entries(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``roadmap3d register`` writes the prepared volume from threads while it registers: after
    :meth:`flush` the entries are on disk and a later process reads the same voxels from them."""
    monkeypatch.delenv("ROADMAP3D_NO_CACHE", raising=False)
    vol, view = _head(), _view()
    background = PreparationCache(tmp_path / "cache", background=True)
    built = _prepared(vol, view, background)
    background.flush()
    assert built.base_source == "built" and len(background.entries()) == 2  # the blocks and the levels
    later = _prepared(vol, view, PreparationCache(tmp_path / "cache"))
    assert later.base_source == "disk"
    _assert_same(built, later, view)
    prepare.clear_cache()
