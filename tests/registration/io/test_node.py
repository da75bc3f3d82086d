"""The DICOM node (registration/io/node.py) with pynetdicom's StoreSCU as the C-arm.

A C-STORE from an allowed AE title is answered only once the file is complete in the private
folder, so the image is readable the moment the sender sees success (well within the second
the issue asks for, without a clock in the test); an unknown calling AE title is refused at
association; nothing is written for a refused peer.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

import numpy as np
import pytest
from pynetdicom import AE
from pynetdicom.sop_class import Verification, XRayAngiographicImageStorage  # type: ignore[attr-defined]

from registration.io import dicom
from registration.io.node import DicomNode, NodeError, Received, private_folder


def _scu(title: str) -> AE:
    ae = AE(ae_title=title)
    ae.add_requested_context(Verification)
    ae.add_requested_context(XRayAngiographicImageStorage)
    ae.acse_timeout = ae.dimse_timeout = ae.network_timeout = 10
    return ae


@pytest.fixture()
def node(tmp_path: Path):
    got: list[Received] = []
    with DicomNode(tmp_path / "received", allowed=["CARM"], port=0, on_received=got.append) as n:
        n.got = got  # type: ignore[attr-defined]
        yield n


def test_store_from_an_allowed_ae_is_readable_at_once(node: DicomNode, small_export: Path) -> None:
    assert node.host == "127.0.0.1" and node.port > 0
    assoc = _scu("CARM").associate("127.0.0.1", node.port, ae_title="ROADMAP3D")
    assert assoc.is_established
    try:
        assert assoc.send_c_echo().Status == 0x0000
        sent = dicom.read_dataset(small_export / "xa_fluoro.dcm")
        status = assoc.send_c_store(sent)
        assert status.Status == 0x0000
        # The answer came after the file was renamed into place and reported: no waiting.
        (item,) = node.got  # type: ignore[attr-defined]
        assert item.calling_ae == "CARM" and item.role == "xray" and item.modality == "XA"
        assert item.path == node.folder / sent.StudyInstanceUID / sent.SeriesInstanceUID / f"{sent.SOPInstanceUID}.dcm"
        got = dicom.read_xray(item.path)
        want = dicom.read_xray(small_export / "xa_fluoro.dcm")
        assert np.array_equal(got.image, want.image) and got.geometry == want.geometry
    finally:
        assoc.release()
    # private: the folder tree 0700, the file 0600, no temporary leftovers
    assert stat.S_IMODE(node.folder.stat().st_mode) == 0o700
    assert stat.S_IMODE(item.path.parent.stat().st_mode) == 0o700
    assert stat.S_IMODE(item.path.stat().st_mode) == 0o600
    assert [p.name for p in item.path.parent.iterdir()] == [item.path.name]


def test_unknown_calling_ae_title_is_refused(node: DicomNode, small_export: Path) -> None:
    assoc = _scu("INTRUDER").associate("127.0.0.1", node.port, ae_title="ROADMAP3D")
    assert assoc.is_rejected and not assoc.is_established
    # calling the node by another name is refused too
    assoc = _scu("CARM").associate("127.0.0.1", node.port, ae_title="SOMEONE")
    assert assoc.is_rejected
    assert node.got == []  # type: ignore[attr-defined]
    assert [p.name for p in node.folder.iterdir()] == [".incoming"] and not any((node.folder / ".incoming").iterdir())


def test_configuration_is_checked(tmp_path: Path) -> None:
    with pytest.raises(NodeError, match="--allow"):
        DicomNode(tmp_path / "a", allowed=[])
    assert not (tmp_path / "a").exists()  # nothing made for a refused configuration
    with pytest.raises(NodeError, match="16 printable"):
        DicomNode(tmp_path / "b", allowed=["A-VERY-LONG-AE-TITLE"])
    shared = tmp_path / "shared"
    shared.mkdir(mode=0o755)
    shared.chmod(0o755)
    with pytest.raises(NodeError, match="chmod 700"):
        private_folder(shared)
    made = private_folder(tmp_path / "new" / "folder")
    assert stat.S_IMODE(made.stat().st_mode) == 0o700 and made.stat().st_uid == os.getuid()
