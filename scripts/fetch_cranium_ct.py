"""A second real head CT for the studies: InVesalius's example "Cranium" (ProMED CT 0051).

Debian ships it in the package ``invesalius-examples`` (GPL-2, © CTI Renato Archer). This script
downloads that package from Debian's archive (or takes a ``.deb`` already downloaded), checks its
SHA-256, reads the CT out of the InVesalius project inside it and writes a NIfTI volume:

    python scripts/fetch_cranium_ct.py --out data/cranium-ct.nii.gz [--deb invesalius-examples.deb]

The CT: 256 x 256 pixels of 0.957 mm, 108 slices 1.5 mm apart, int16 Hounsfield units, from the
upper jaw to the vertex, with the scanner's curved head holder behind the head. The project
stores it as InVesalius reads DICOM: slices from feet to head, rows from the back of the head
to the face; columns are taken to run from the patient's right to left (the usual DICOM display).
Nothing of it is kept in the project's repository.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import lzma
import plistlib
import sys
import tarfile
import urllib.request
from pathlib import Path

import numpy as np

from registration.core.volume import Volume
from registration.io.volume_files import write_volume_file
from registration.studies.volume import head_isocenter_mm

DEB_URL = "http://deb.debian.org/debian/pool/main/i/invesalius/invesalius-examples_3.1.99998-4_all.deb"
DEB_SHA256 = "f2f14bdfef6dc3812eafc5013d133c6c18370aaab5666b78d54af2e7db432f97"
MEMBER = "./usr/share/doc/invesalius-examples/examples/Cranium.inv3"


def ar_members(blob: bytes) -> dict[str, bytes]:
    """The members of a Debian package (a Unix ``ar`` archive)."""
    if not blob.startswith(b"!<arch>\n"):
        raise ValueError("not a Debian package (no ar header)")
    out: dict[str, bytes] = {}
    pos = 8
    while pos + 60 <= len(blob):
        header = blob[pos : pos + 60]
        name = header[:16].decode().strip().rstrip("/")
        size = int(header[48:58].decode().strip())
        out[name] = blob[pos + 60 : pos + 60 + size]
        pos += 60 + size + (size % 2)
    return out


def cranium_from_deb(blob: bytes, sha256: str | None = DEB_SHA256) -> Volume:
    """The CT inside the package (its SHA-256 checked unless ``sha256`` is None)."""
    digest = hashlib.sha256(blob).hexdigest()
    if sha256 is not None and digest != sha256:
        raise ValueError(f"the package's SHA-256 is {digest}, expected {sha256}")
    members = ar_members(blob)
    data_tar = next((v for k, v in members.items() if k.startswith("data.tar")), None)
    if data_tar is None:
        raise ValueError("the package has no data archive")
    raw = lzma.decompress(data_tar) if data_tar[:6] == b"\xfd7zXZ\x00" else data_tar
    with tarfile.open(fileobj=io.BytesIO(raw)) as outer:
        project = outer.extractfile(MEMBER)
        if project is None:
            raise ValueError(f"the package has no {MEMBER}")
        inv3 = project.read()
    with tarfile.open(fileobj=io.BytesIO(inv3), mode="r:gz") as inner:
        files = {Path(m.name).name: m for m in inner.getmembers() if m.isfile()}
        main = plistlib.loads(inner.extractfile(files["main.plist"]).read())
        matrix = main["matrix"]
        data = np.frombuffer(inner.extractfile(files[matrix["filename"]]).read(), dtype=matrix["dtype"])
    nk, nj, ni = matrix["shape"]
    data = data.reshape(nk, nj, ni)
    sx, sy, sz = (float(s) for s in main["spacing"])
    # columns: patient right -> left (+x); rows: back of the head -> face (-y); slices: up (+z)
    affine = np.diag([sx, -sy, sz, 1.0])
    return Volume(data.astype(np.float32), affine, label=f"InVesalius example CT ({main.get('name', 'Cranium')})")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True, help="NIfTI file to write (.nii.gz)")
    ap.add_argument("--deb", type=Path, help="the invesalius-examples .deb, already downloaded")
    args = ap.parse_args()
    try:
        if args.deb is not None:
            blob = args.deb.read_bytes()
        else:
            print(f"downloading {DEB_URL} (18.7 MB)", file=sys.stderr)
            with urllib.request.urlopen(DEB_URL, timeout=120) as response:
                blob = response.read()
        volume = cranium_from_deb(blob)
    except (OSError, ValueError, KeyError, tarfile.TarError) as exc:
        print(f"error: {args.deb or DEB_URL}: {exc}", file=sys.stderr)
        return 2
    path = write_volume_file(volume, args.out)
    shape = "x".join(str(n) for n in volume.data.shape[::-1])
    iso = ",".join(f"{v:.1f}" for v in head_isocenter_mm(volume))
    print(f"wrote {path}: {shape} voxels; an iso-center inside the skull: {iso}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
