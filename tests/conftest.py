"""Fixtures shared across the test folders."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.orthanc import OrthancServer, missing, start_orthanc


@pytest.fixture(scope="session")
def orthanc(tmp_path_factory: pytest.TempPathFactory) -> Iterator[OrthancServer]:
    """A real Orthanc with DICOMweb on 127.0.0.1 (skipped with the reason when not installed)."""
    why = missing()
    if why:
        pytest.skip(why)
    server = start_orthanc(Path(tmp_path_factory.mktemp("orthanc")))
    yield server
    server.stop()
