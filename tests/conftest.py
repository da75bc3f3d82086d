"""Fixtures shared across the test folders."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.orthanc import OrthancServer, missing, start_orthanc

#: The network tests' phantom export: small (48^3 resampled 3DRA, 96^2 XA images), seconds to make.
SMALL_EXPORT = ["--voxels", "48", "--pixels", "96", "--volume-source", "resampled", "--primary-deg", "15"]


@pytest.fixture(scope="session")
def small_export(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``roadmap3d phantom --out DIR`` with :data:`SMALL_EXPORT` (3DRA series, XA fluoro/exposure, truth)."""
    from app import cli

    out = tmp_path_factory.mktemp("network-export") / "phantom"
    with pytest.raises(SystemExit) as info:
        cli.main(["phantom", "--out", str(out), *SMALL_EXPORT])
    assert info.value.code == 0
    return out


@pytest.fixture(scope="session")
def orthanc(tmp_path_factory: pytest.TempPathFactory) -> Iterator[OrthancServer]:
    """A real Orthanc with DICOMweb on 127.0.0.1 (skipped with the reason when not installed)."""
    why = missing()
    if why:
        pytest.skip(why)
    server = start_orthanc(Path(tmp_path_factory.mktemp("orthanc")))
    yield server
    server.stop()


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("fuzz", "fuzzing of the readers (tests/registration/io/test_fuzz.py)")
    group.addoption(
        "--fuzz-long", action="store_true", default=False, help="mutate 20,000 files instead of the default 1,000"
    )
    group.addoption("--fuzz-seed", action="store", default="0", help="seed of the mutator (default 0)")
