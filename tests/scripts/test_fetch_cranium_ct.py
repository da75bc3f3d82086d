"""The second real CT's reader: a Debian package holding an InVesalius project, built here."""

from __future__ import annotations

import importlib.util
import io
import lzma
import plistlib
import tarfile
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def fetch():
    spec = importlib.util.spec_from_file_location("fetch_cranium_ct", ROOT / "scripts" / "fetch_cranium_ct.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _tar(files: dict[str, bytes], mode: str) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode=mode) as tar:
        for name, payload in files.items():
            info = tarfile.TarInfo(name)
            info.size = len(payload)
            tar.addfile(info, io.BytesIO(payload))
    return buf.getvalue()


def _ar(members: dict[str, bytes]) -> bytes:
    out = b"!<arch>\n"
    for name, payload in members.items():
        header = f"{name + '/':<16}{0:<12}{0:<6}{0:<6}{'100644':<8}{len(payload):<10}`\n".encode()
        out += header + payload + (b"\n" if len(payload) % 2 else b"")
    return out


def _deb(data: np.ndarray, spacing: tuple[float, float, float]) -> bytes:
    main = {
        "matrix": {"dtype": "int16", "filename": "matrix.dat", "shape": list(data.shape)},
        "spacing": list(spacing),
        "name": "test CT",
    }
    inv3 = _tar({"tmp/main.plist": plistlib.dumps(main), "tmp/matrix.dat": data.astype(np.int16).tobytes()}, "w:gz")
    payload = lzma.compress(_tar({"./usr/share/doc/invesalius-examples/examples/Cranium.inv3": inv3}, "w"))
    return _ar({"debian-binary": b"2.0\n", "control.tar.xz": lzma.compress(_tar({}, "w")), "data.tar.xz": payload})


def test_the_ct_is_read_with_its_spacing_and_orientation(fetch) -> None:
    data = np.arange(3 * 4 * 5, dtype=np.int16).reshape(3, 4, 5) - 1000
    volume = fetch.cranium_from_deb(_deb(data, (0.5, 0.5, 1.5)), sha256=None)
    np.testing.assert_array_equal(volume.data, data)  # exact: int16 HU kept as float32
    # columns to the patient's left (+x), rows toward the face (-y), slices up (+z)
    np.testing.assert_allclose(volume.index_to_world, np.diag([0.5, -0.5, 1.5, 1.0]))
    assert "test CT" in volume.label


def test_a_package_with_another_checksum_is_refused(fetch) -> None:
    blob = _deb(np.zeros((2, 2, 2), np.int16), (1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="SHA-256"):
        fetch.cranium_from_deb(blob)
    with pytest.raises(ValueError, match="not a Debian package"):
        fetch.cranium_from_deb(b"<html>not found</html>", sha256=None)
