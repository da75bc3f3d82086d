"""Decoded volumes kept on disk (``registration.io.volume_cache``): loaded only while every file
of the series is as it was, never half-written, never an exception."""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np
import pytest

from registration.core.prepare.store import volume_digest
from registration.core.volume import Volume
from registration.io import dicom
from registration.io.volume_cache import DecodedVolumes, files_state, read_volume_cached


@pytest.fixture
def series(tmp_path: Path) -> Path:
    k, j, i = np.mgrid[0:6, 0:7, 0:8].astype(np.float32)
    data = (100.0 * i + 10.0 * j + k - 500.0).astype(np.float32)
    affine = np.diag([0.8, 0.7, 2.5, 1.0])
    affine[:3, 3] = (-3.0, 4.0, -7.5)
    dicom.write_series(Volume(data, affine, label="ramp"), tmp_path / "series", uid_seed="cache-test")
    return tmp_path / "series"


class CountingReader:
    """``dicom.read_volume``, counted."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, path: Path) -> Volume:
        self.calls += 1
        return dicom.read_volume(path)


def _same(a: Volume, b: Volume) -> None:
    np.testing.assert_array_equal(np.asarray(a.data), np.asarray(b.data))
    np.testing.assert_array_equal(a.index_to_world, b.index_to_world)
    assert a.label == b.label and json.dumps(a.meta, default=str) == json.dumps(b.meta, default=str)


def test_a_series_decoded_once_loads_the_same_volume(series: Path, tmp_path: Path) -> None:
    store, read = DecodedVolumes(tmp_path / "cache"), CountingReader()
    plain = dicom.read_volume(series)
    first = store.read(series, read)
    assert read.calls == 1 and len(store.entries()) == 1
    again = store.read(series, read)
    assert read.calls == 1  # loaded, not decoded
    _same(again, plain)
    _same(first, plain)
    # the digest kept with it is the voxels' own (a prepared volume on disk is found by it)
    assert volume_digest(again) == volume_digest(Volume(plain.data.copy(), plain.index_to_world))
    # the loaded voxels are a private copy-on-write map: writing to them leaves the entry alone
    np.asarray(again.data)[0, 0, 0] = 12345.0
    _same(store.read(series, read), plain)
    assert read.calls == 1
    # reached by another path to the same folder: the volume says the path it was given
    other = Path(os.path.relpath(series))
    assert store.read(other, read).meta["source"] == str(other) and read.calls == 1
    # the same through the command line's reader (the cache folder from ROADMAP3D_CACHE)
    os.environ["ROADMAP3D_CACHE"] = str(tmp_path / "cache")
    try:
        _same(read_volume_cached(series), plain)
        _same(read_volume_cached(series, cache=False), plain)
    finally:
        del os.environ["ROADMAP3D_CACHE"]


def test_any_change_to_the_files_decodes_again(series: Path, tmp_path: Path) -> None:
    store, read = DecodedVolumes(tmp_path / "cache"), CountingReader()
    store.read(series, read)
    first = sorted(series.iterdir())[0]
    before = files_state(series, identity=True)
    # the same bytes written again, its times put back: the change time still moves
    st = first.stat()
    first.write_bytes(first.read_bytes())
    os.utime(first, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert files_state(series, identity=True) != before
    store.read(series, read)
    assert read.calls == 2
    (series / "notes.txt").write_text("a file added to the folder")
    store.read(series, read)
    assert read.calls == 3
    (series / "notes.txt").unlink()  # the files as they were at the second read: its entry
    store.read(series, read)
    assert read.calls == 3


def test_a_change_in_a_subfolder_decodes_again(series: Path, tmp_path: Path) -> None:
    # the reader reads the folder's subfolders too: their files are part of the key
    outer = tmp_path / "outer"
    outer.mkdir()
    series.rename(outer / "series")
    store, read = DecodedVolumes(tmp_path / "cache"), CountingReader()
    store.read(outer, read)
    store.read(outer, read)
    assert read.calls == 1
    nested = sorted((outer / "series").iterdir())[-1]
    nested.write_bytes(nested.read_bytes())
    store.read(outer, read)
    assert read.calls == 2


def test_a_damaged_entry_is_decoded_again_without_an_error(series: Path, tmp_path: Path) -> None:
    store, read = DecodedVolumes(tmp_path / "cache"), CountingReader()
    plain = store.read(series, read)
    voxels = store.entries()[0]
    for damage in (
        lambda: voxels.write_bytes(voxels.read_bytes()[:100]),  # cut short
        lambda: voxels.with_suffix(".json").write_text("{not json"),
        lambda: voxels.with_suffix(".json").write_text(
            json.dumps({**json.loads(voxels.with_suffix(".json").read_text()), "key": {"folder": "elsewhere"}})
        ),  # another folder's entry under this name
    ):
        damage()
        calls = read.calls
        _same(store.read(series, read), plain)
        assert read.calls == calls + 1 and len(store.entries()) == 1  # removed, decoded, written anew
        _same(store.read(series, read), plain)
        assert read.calls == calls + 1


def test_nothing_is_kept_when_the_cache_is_off(series: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ROADMAP3D_NO_CACHE", "1")
    store, read = DecodedVolumes(tmp_path / "cache"), CountingReader()
    store.read(series, read)
    store.read(series, read)
    assert read.calls == 2 and not (tmp_path / "cache").exists()
    # a single file is read by the reader alone
    monkeypatch.delenv("ROADMAP3D_NO_CACHE")
    one = sorted(series.iterdir())[0]
    with pytest.raises(dicom.DicomError):  # one slice is not a volume: the reader's own message
        DecodedVolumes(tmp_path / "cache").read(one, dicom.read_volume)
    assert not list((tmp_path / "cache").glob("decoded-*"))


def test_the_readers_warnings_are_said_on_every_load(series: Path, tmp_path: Path) -> None:
    store = DecodedVolumes(tmp_path / "cache")

    def read_with_a_warning(path: Path) -> Volume:
        warnings.warn(f"{path}: slices unevenly spaced", stacklevel=1)
        return dicom.read_volume(path)

    for _ in range(2):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            store.read(series, read_with_a_warning)
        assert [str(w.message) for w in caught] == [f"{series}: slices unevenly spaced"]


def test_the_least_recently_used_entries_go_first(tmp_path: Path) -> None:
    folders = []
    for n in range(3):
        data = np.full((4, 5, 6), float(n), dtype=np.float32)
        dicom.write_series(Volume(data, np.eye(4), label=f"v{n}"), tmp_path / f"s{n}", uid_seed=f"lru{n}")
        folders.append(tmp_path / f"s{n}")
    store = DecodedVolumes(tmp_path / "cache")
    for n, folder in enumerate(folders):
        store.read(folder, dicom.read_volume)
        entry = store.entries()[-1] if n == 0 else max(store.entries(), key=lambda p: p.stat().st_mtime_ns)
        os.utime(entry, (1_000_000 + n, 1_000_000 + n))  # older first
    size = store.entries()[0].stat().st_size
    store.max_bytes = 2 * size
    store.prune()
    kept = {json.loads(p.with_suffix(".json").read_text())["label"] for p in store.entries()}
    assert kept == {"v1", "v2"}
