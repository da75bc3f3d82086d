"""The read-ahead hints of ``roadmap3d register`` (app/cli/_perf.py): which files it names."""

from __future__ import annotations

import os
from pathlib import Path

from app.cli import _perf as prefetch


def test_inputs_are_the_series_files_and_the_images(tmp_path: Path) -> None:
    series = tmp_path / "series"
    series.mkdir()
    for name in ("b.dcm", "a.dcm", ".hidden"):
        (series / name).write_bytes(b"x")
    (series / "sub").mkdir()  # a series is read one level deep
    image = tmp_path / "xa.dcm"
    image.write_bytes(b"x")
    files = prefetch.input_files([series, image, tmp_path / "missing"])
    assert files == [series / "a.dcm", series / "b.dcm", image]


def test_prepared_entries_most_recent_first_within_the_budget(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(prefetch, "PREPARED_BYTES", 250)
    for n, size in enumerate((100, 100, 100)):
        p = tmp_path / f"prepared-levels-{n}.npz"
        p.write_bytes(b"x" * size)
        os.utime(p, (1000 + n, 1000 + n))
    (tmp_path / "clinical-patient-0.npz").write_bytes(b"x")  # not a prepared volume
    assert prefetch.prepared_files(tmp_path) == [tmp_path / "prepared-levels-2.npz", tmp_path / "prepared-levels-1.npz"]
    assert prefetch.prepared_files(tmp_path / "absent") == []


def test_read_ahead_runs_in_the_background_and_skips_what_it_cannot_open(tmp_path: Path) -> None:
    real = tmp_path / "a.bin"
    real.write_bytes(b"x" * 4096)
    thread = prefetch.read_ahead([tmp_path / "missing", real])
    if thread is not None:  # Linux: posix_fadvise
        assert thread.daemon
        thread.join(10)
        assert not thread.is_alive()
    assert prefetch.read_ahead([]) is None
