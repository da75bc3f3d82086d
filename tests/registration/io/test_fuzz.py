"""Fuzzing the readers: >= 1,000 mutated files, each a DicomError/UploadError or a valid result.

A seeded mutator (``random.Random``, reproducible: the seed and the mutation are in every
failure message) builds the files from the project's own exports (XA image and run, CT
slice, Enhanced CT, .npz) and pydicom's bundled test files: byte flips, truncations,
deleted / duplicated / corrupted data elements, huge declared sizes, and every geometry tag
set to 0, negative, NaN, inf and 1e308. For each file, every reader that could be handed
it (``read_xray``, ``read_xray_run``, ``read_volume``, ``inspect``) must either raise a
``DicomError`` (``UploadError`` for archives) or return a result whose arrays are finite;
nothing else, under a second of CPU and no hang (CPU_S, HANG_S), and a tracemalloc peak under
MEMORY_BOUND.

Hostile zip uploads (zip-slip ``..`` names, absolute paths, symlinks, a 1 GB zero bomb,
10,000 tiny members, not a zip, a compressed-zeros .npz inside) go through the app's
upload handler, :func:`app.web.upload.read_upload`, in the same suite.

The default run (the CI suite) mutates DEFAULT_FILES files; ``pytest --fuzz-long`` mutates
LONG_FILES (and may be given ``--fuzz-seed``).
"""

from __future__ import annotations

import io
import math
import random
import resource
import struct
import time
import tracemalloc
import warnings
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pydicom
import pytest
from pydicom.data import get_testdata_file
from pydicom.dataset import Dataset

from registration.core.geometry import CArm
from registration.core.images import XRayImage
from registration.core.volume import Volume
from registration.io import dicom
from registration.io.dicom import DicomError, UploadError

#: Mutated files in the default run (the issue asks for at least 1,000 in CI) and with --fuzz-long.
DEFAULT_FILES = 1000
LONG_FILES = 20000
#: Each read must take under a second of this process's CPU time (the issue's bound; CPU, not
#: wall-clock time, so a busy shared machine cannot make the test flaky: refusals take 1-60 ms,
#: 4x that under tracemalloc) ...
CPU_S = 1.0
#: ... and under this much wall-clock time (a hang that does not spin: waiting on something).
HANG_S = 10.0
#: Peak traced memory of one read: the sources are at most a few hundred kB and their decoded
#: arrays a few MB; 64 MB is far below any blow-up (the hostile files used to take 1.35-5 GB).
MEMORY_BOUND = 64 * 1024**2
#: Every TRACE_EVERY-th mutant is read under tracemalloc (4x slower); all bound the peak RSS.
TRACE_EVERY = 4

#: Small pydicom test files (kB) of many encodings, volumes and X-ray-like images among them.
PYDICOM_FILES = (
    "CT_small.dcm",
    "MR_small.dcm",
    "MR_small_bigendian.dcm",
    "MR_small_implicit.dcm",
    "MR_small_RLE.dcm",
    "MR_small_jp2klossless.dcm",
    "MR_small_padded.dcm",
    "JPEG2000.dcm",
    "image_dfl.dcm",
    "rtdose_1frame.dcm",
    "rtdose.dcm",
    "liver_1frame.dcm",
    "no_meta.dcm",
    "ExplVR_BigEnd.dcm",
    "SC_rgb_small_odd.dcm",
    "badVR.dcm",
)

#: Tags the readers use for sizes and geometry: targets of the value mutations.
GEOMETRY_TAGS = (
    "PositionerPrimaryAngle",
    "PositionerSecondaryAngle",
    "DistanceSourceToDetector",
    "DistanceSourceToPatient",
    "ImagerPixelSpacing",
    "PixelSpacing",
    "ImagePositionPatient",
    "ImageOrientationPatient",
    "RescaleSlope",
    "RescaleIntercept",
    "FieldOfViewRotation",
    "PositionerPrimaryAngleIncrement",
    "PositionerSecondaryAngleIncrement",
    "RadiusOfCircularShutter",
    "CenterOfCircularShutter",
    "FrameTime",
    "SliceThickness",
)
SIZE_TAGS = ("Rows", "Columns", "NumberOfFrames", "BitsAllocated", "BitsStored", "HighBit", "SamplesPerPixel")
BAD_NUMBERS = ("0", "-1", "-0.5", "nan", "inf", "-inf", "1e308", "-1e308", "1e-308", "360", "7.5e3")
HUGE_SIZES = (0, 1, 2, 3, 255, 65535, 2**31 - 1, 2**32 - 1)


@pytest.fixture(scope="module")
def fuzz_count(request: pytest.FixtureRequest) -> int:
    return LONG_FILES if request.config.getoption("--fuzz-long") else DEFAULT_FILES


@pytest.fixture(scope="module")
def fuzz_seed(request: pytest.FixtureRequest) -> int:
    return int(request.config.getoption("--fuzz-seed"))


# --------------------------------------------------------------------------------------
# Sources
# --------------------------------------------------------------------------------------
def _xray(size: int = 24, primary: float = 10.0, seed: int = 0) -> XRayImage:
    geometry = CArm.for_format(22, pixels=size, primary_deg=primary, secondary_deg=-5.0)
    rng = np.random.default_rng(seed)
    image = rng.uniform(0.0, 3.0, (size, size)).astype(np.float32)
    mask = geometry.field_mask()
    return XRayImage(image=np.where(mask, image, 0).astype(np.float32), mask=mask, geometry=geometry, kind="fluoro")


@pytest.fixture(scope="module")
def sources(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[bytes, str]]:
    """name -> (file bytes, suffix): the project's exports and pydicom's test files."""
    folder = tmp_path_factory.mktemp("fuzz-sources")
    rng = np.random.default_rng(0)
    volume = Volume(
        rng.normal(0.0, 300.0, (4, 12, 10)).astype(np.float32), np.diag([0.8, 0.7, 1.5, 1.0]), label="fuzz volume"
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = {
            "xa": dicom.write_xray(_xray(), folder / "xa.dcm"),
            "xa-run": dicom.write_xray([_xray(16, a, s) for s, a in enumerate((0.0, 5.0, 10.0))], folder / "run.dcm"),
            "enhanced-ct": dicom.write_enhanced(volume, folder / "enhanced.dcm"),
            "ct-slice": dicom.write_series(volume, folder / "series")[0],
            "npz": dicom.write_npz(volume, folder / "v.npz"),
        }
    found = {name: (path.read_bytes(), path.suffix) for name, path in out.items()}
    for name in PYDICOM_FILES:
        try:
            path = Path(get_testdata_file(name, download=False) or "")
        except Exception:  # a test file missing from this pydicom: fewer sources, same checks
            continue
        if path.is_file() and path.stat().st_size < 300_000:
            found[name] = (path.read_bytes(), ".dcm")
    return found


# --------------------------------------------------------------------------------------
# The mutator
# --------------------------------------------------------------------------------------
@dataclass
class Mutant:
    data: bytes
    suffix: str
    how: str


def _byte_flips(rng: random.Random, raw: bytes) -> tuple[bytes, str]:
    out = bytearray(raw)
    n = rng.choice((1, 2, 4, 16, 64))
    for _ in range(n):
        i = rng.randrange(len(out))
        out[i] = rng.randrange(256) if rng.random() < 0.7 else out[i] ^ (1 << rng.randrange(8))
    return bytes(out), f"{n} byte flips"


def _truncate(rng: random.Random, raw: bytes) -> tuple[bytes, str]:
    cut = rng.choice((0, 1, 128, 132, 200, len(raw) // 2, len(raw) - 1, rng.randrange(len(raw))))
    return raw[:cut], f"truncated to {cut} bytes"


def _dataset_mutation(rng: random.Random, raw: bytes) -> tuple[bytes, str] | None:
    """Tag-level edits through pydicom (None if pydicom cannot parse or write the source)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds = pydicom.dcmread(io.BytesIO(raw), force=True)
            ds.file_meta = getattr(ds, "file_meta", None) or pydicom.dataset.FileMetaDataset()
            how = _edit(rng, ds)
            buffer = io.BytesIO()
            ds.save_as(buffer, enforce_file_format=False)
    except Exception:
        return None
    return buffer.getvalue(), how


def _holder(ds: Dataset, keyword: str) -> Dataset | None:
    """The data set (top level or a functional-group item) that holds ``keyword``."""
    if keyword in ds:
        return ds
    for group in ("SharedFunctionalGroupsSequence", "PerFrameFunctionalGroupsSequence"):
        for item in ds.get(group) or []:
            for elem in item:
                if elem.VR == "SQ":
                    for sub in elem.value:
                        if keyword in sub:
                            return sub
    return None


def _edit(rng: random.Random, ds: Dataset) -> str:
    kind = rng.choice(("geometry", "geometry", "size", "delete", "duplicate", "corrupt", "pixels"))
    if kind == "geometry":
        keyword = rng.choice(GEOMETRY_TAGS)
        value = rng.choice(BAD_NUMBERS)
        holder = _holder(ds, keyword) or ds
        vm = {"ImagerPixelSpacing": 2, "PixelSpacing": 2, "CenterOfCircularShutter": 2, "ImagePositionPatient": 3}
        count = 6 if keyword == "ImageOrientationPatient" else vm.get(keyword, 1)
        values = [value] * count
        if keyword in ("RadiusOfCircularShutter", "CenterOfCircularShutter"):  # IS: integers only
            values = [
                str(int(float(value))) if math.isfinite(float(value)) and abs(float(value)) < 2**31 else "1"
            ] * count
        setattr(holder, keyword, values if count > 1 else values[0])
        return f"{keyword} = {value}"
    if kind == "size":
        keyword = rng.choice(SIZE_TAGS)
        value = rng.choice(HUGE_SIZES)
        if keyword == "NumberOfFrames":
            ds.NumberOfFrames = str(value)
        else:
            ds[keyword] = pydicom.DataElement(keyword, "US", value % 65536) if keyword in ds else None
            if ds.get(keyword) is None:
                setattr(ds, keyword, value % 65536)
        return f"{keyword} = {value}"
    elems = [e for e in ds.iterall() if e.tag != 0x7FE00010]
    if not elems:
        return "nothing to edit"
    elem = rng.choice(elems)
    if kind == "delete":
        holder = _holder(ds, elem.keyword) if elem.keyword else None
        if holder is not None:
            del holder[elem.tag]
        elif elem.tag in ds:
            del ds[elem.tag]
        return f"deleted {elem.keyword or elem.tag}"
    if kind == "duplicate":
        other = rng.choice(elems)
        if elem.VR == other.VR and elem.keyword and other.keyword:
            holder = _holder(ds, elem.keyword)
            if holder is not None:
                holder[elem.tag].value = other.value
        return f"{elem.keyword or elem.tag} = value of {other.keyword or other.tag}"
    if kind == "corrupt":
        junk = bytes(rng.randrange(256) for _ in range(rng.choice((0, 1, 3, 8, 33))))
        holder = (_holder(ds, elem.keyword) if elem.keyword else None) or ds
        if elem.tag in holder:
            holder[elem.tag] = pydicom.DataElement(elem.tag, "UN", junk)
        return f"{elem.keyword or elem.tag} = {len(junk)} junk bytes (UN)"
    # pixels: shorter, longer or empty PixelData
    if "PixelData" in ds and not ds["PixelData"].is_undefined_length:
        pixels = ds.PixelData
        choice = rng.choice(("empty", "half", "odd", "double"))
        ds.PixelData = {"empty": b"", "half": pixels[: len(pixels) // 2], "odd": pixels[:-1], "double": pixels * 2}[
            choice
        ]
        return f"PixelData {choice}"
    return "no native PixelData"


def _npz_mutation(rng: random.Random, raw: bytes) -> tuple[bytes, str]:
    how = rng.choice(("flip", "truncate", "shape", "dtype", "drop"))
    if how == "flip":
        return _byte_flips(rng, raw)
    if how == "truncate":
        return _truncate(rng, raw)
    with np.load(io.BytesIO(raw), allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    if how == "shape":
        arrays["data"] = np.zeros(rng.choice([(4, 4), (1, 1, 1), (0, 5, 5), (2, 2, 2, 2)]), np.float32)
    elif how == "dtype":
        arrays["data"] = arrays["data"].astype(rng.choice(["complex64", "bool", "<U3", "int8"]))
        arrays["index_to_world"] = rng.choice([np.eye(3), np.full((4, 4), np.nan), np.zeros((4, 4)), np.eye(4) * 1e308])
    else:
        arrays.pop(rng.choice(list(arrays)))
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    return buffer.getvalue(), f"npz {how}"


def mutants(sources: dict[str, tuple[bytes, str]], count: int, seed: int) -> list[tuple[str, Mutant]]:
    rng = random.Random(seed)
    names = sorted(sources)
    out: list[tuple[str, Mutant]] = []
    while len(out) < count:
        name = rng.choice(names)
        raw, suffix = sources[name]
        if suffix == ".npz":
            data, how = _npz_mutation(rng, raw)
        else:
            r = rng.random()
            made = _byte_flips(rng, raw) if r < 0.3 else _truncate(rng, raw) if r < 0.4 else _dataset_mutation(rng, raw)
            if made is None:
                made = _byte_flips(rng, raw)
            data, how = made
        out.append((name, Mutant(data, suffix, how)))
    return out


# --------------------------------------------------------------------------------------
# Reading a mutant
# --------------------------------------------------------------------------------------
def _valid_xray(image: XRayImage) -> None:
    assert np.all(np.isfinite(image.image)), "non-finite attenuation"
    assert image.mask.shape == image.image.shape and image.mask.any()


#: The readers a mutant of each project source is handed (pydicom's files get one of all, in turn).
READERS_OF = {
    "xa": ("read_xray",),
    "xa-run": ("read_xray_run", "read_xray"),
    "enhanced-ct": ("read_volume",),
    "ct-slice": ("read_volume",),
    "npz": ("read_volume",),
}
ALL_READERS = ("read_xray", "read_xray_run", "read_volume")
#: Every INSPECT_EVERY-th mutant is also handed to ``inspect`` (``roadmap3d info``), which reads it whole again.
INSPECT_EVERY = 5


def _readers(path: Path, source: str, n: int) -> list[tuple[str, Callable[[], None]]]:
    def xray() -> None:
        _valid_xray(dicom.read_xray(path, frame=0))

    def run() -> None:
        result = dicom.read_xray_run(path, frame_time_ms=33.3)
        assert len(result) >= 1
        _valid_xray(result[len(result) - 1])

    def volume() -> None:
        v = dicom.read_volume(path)
        assert np.all(np.isfinite(v.data)) and np.all(np.isfinite(v.index_to_world))

    def info() -> None:
        report = dicom.inspect(path)
        assert isinstance(report, dict)

    table = {"read_xray": xray, "read_xray_run": run, "read_volume": volume, "inspect": info}
    names = list(READERS_OF.get(source, (ALL_READERS[n % len(ALL_READERS)],)))
    if n % INSPECT_EVERY == 0:
        names.append("inspect")
    return [(name, table[name]) for name in names]


@dataclass
class Outcome:
    refused: int = 0
    accepted: int = 0
    slowest_s: float = 0.0
    peak_bytes: int = 0


def read_mutant(path: Path, source: str, n: int, label: str, outcome: Outcome, *, trace: bool = True) -> None:
    """The readers of ``source`` on ``path``: DicomError or a valid result; no hang; bounded memory.

    ``trace``: measure the peak with tracemalloc (it makes pydicom 4x slower, so the fuzz loop
    traces every TRACE_EVERY-th mutant and bounds the others by the process's peak RSS).
    """
    for reader_name, reader in _readers(path, source, n):
        if trace:
            tracemalloc.start()
        start, cpu_start = time.perf_counter(), time.process_time()
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                reader()
            outcome.accepted += 1
        except DicomError:
            outcome.refused += 1
        except Exception as exc:  # the bug this suite exists to find
            raise AssertionError(f"{label}: {reader_name} raised {type(exc).__name__}: {exc}") from exc
        finally:
            elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu_start
            peak = tracemalloc.get_traced_memory()[1] if trace else 0
            if trace:
                tracemalloc.stop()
        assert cpu < CPU_S, f"{label}: {reader_name} took {cpu:.2f} s of CPU"
        assert elapsed < HANG_S, f"{label}: {reader_name} took {elapsed:.1f} s (a hang)"
        assert peak < MEMORY_BOUND, f"{label}: {reader_name} peaked at {peak / 1e6:.0f} MB"
        outcome.slowest_s = max(outcome.slowest_s, cpu)
        outcome.peak_bytes = max(outcome.peak_bytes, peak)


def _peak_rss_bytes() -> int:
    """The process's peak resident memory so far (ru_maxrss is in kB on Linux)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def test_sources_are_read_cleanly(sources: dict[str, tuple[bytes, str]], tmp_path: Path) -> None:
    """The unmutated sources: the project's own exports are accepted, the others read or refused."""
    for name, (raw, suffix) in sources.items():
        path = tmp_path / f"{name}{suffix}"
        path.write_bytes(raw)
        read_mutant(path, name, 0, name, Outcome())
    path = tmp_path / "own.dcm"
    path.write_bytes(sources["xa"][0])
    assert dicom.read_xray(path).image.shape == (24, 24)


def test_fuzz_mutated_files(
    sources: dict[str, tuple[bytes, str]], tmp_path: Path, fuzz_count: int, fuzz_seed: int
) -> None:
    outcome = Outcome()
    rss_before = _peak_rss_bytes()
    for n, (name, mutant) in enumerate(mutants(sources, fuzz_count, fuzz_seed)):
        path = tmp_path / f"m{n % 8}{mutant.suffix}"
        path.write_bytes(mutant.data)
        label = f"seed {fuzz_seed} mutant {n} ({name}: {mutant.how})"
        read_mutant(path, name, n, label, outcome, trace=n % TRACE_EVERY == 0)
    rss_growth = _peak_rss_bytes() - rss_before
    print(
        f"\n{fuzz_count} mutated files (seed {fuzz_seed}): {outcome.refused} refusals, {outcome.accepted} valid "
        f"results; slowest read {outcome.slowest_s * 1000:.0f} ms of CPU, traced peak "
        f"{outcome.peak_bytes / 1e6:.1f} MB, peak RSS grew {rss_growth / 1e6:.0f} MB"
    )
    assert rss_growth < MEMORY_BOUND  # no untraced mutant allocated more than the traced bound either
    assert outcome.refused > fuzz_count // 2  # most mutants are broken: the readers must notice
    assert outcome.accepted > 0  # and some survive (a reader refusing everything would pass otherwise)


def test_fuzz_series_with_one_mutated_slice(sources: dict[str, tuple[bytes, str]], tmp_path: Path) -> None:
    """A slice series where one slice is mutated: the folder reader refuses or reads it."""
    rng_volume = np.random.default_rng(1)
    volume = Volume(rng_volume.normal(0, 300, (4, 8, 8)).astype(np.float32), np.diag([0.8, 0.8, 1.5, 1.0]))
    folder = tmp_path / "series"
    files = dicom.write_series(volume, folder)
    originals = [p.read_bytes() for p in files]
    outcome = Outcome()
    slice_sources = {"slice": (originals[1], ".dcm")}
    for n, (_name, mutant) in enumerate(mutants(slice_sources, 40, 7)):
        files[1].write_bytes(mutant.data)
        tracemalloc.start()
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                dicom.read_volume(folder)
            outcome.accepted += 1
        except DicomError:
            outcome.refused += 1
        except Exception as exc:
            raise AssertionError(f"series mutant {n} ({mutant.how}): {type(exc).__name__}: {exc}") from exc
        finally:
            _, peak = tracemalloc.get_traced_memory()
            tracemalloc.stop()
        assert peak < MEMORY_BOUND
    assert outcome.refused > 0 and outcome.accepted > 0


# --------------------------------------------------------------------------------------
# Hostile uploads through the app's upload handler
# --------------------------------------------------------------------------------------
def _zip(entries: list[tuple[str | zipfile.ZipInfo, bytes]], compression: int = zipfile.ZIP_DEFLATED) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=compression) as archive:
        for name, payload in entries:
            archive.writestr(name, payload)
    return buffer.getvalue()


def _symlink(name: str, target: str) -> tuple[zipfile.ZipInfo, bytes]:
    info = zipfile.ZipInfo(name)
    info.external_attr = (0o120777 << 16) | 0x20
    return info, target.encode()


def deflated_zeros(size: int, prefix: bytes = b"") -> tuple[bytes, int]:
    """A raw deflate stream of ``prefix`` + ``size`` zero bytes and its CRC-32, built in milliseconds.

    After a full flush the compressor references nothing before it, so one compressed 4 MB
    block of zeros can be repeated: a 1 GB bomb costs one 4 MB compression, not 1 GB of it.
    """
    block = 1 << 22
    assert size % block == 0
    compressor = zlib.compressobj(9, zlib.DEFLATED, -zlib.MAX_WBITS)
    head = compressor.compress(prefix) + compressor.flush(zlib.Z_FULL_FLUSH)
    zeros = bytes(block)
    chunk = compressor.compress(zeros) + compressor.flush(zlib.Z_FULL_FLUSH)
    tail = compressor.flush(zlib.Z_FINISH)
    crc = zlib.crc32(prefix)
    for _ in range(size // block):
        crc = zlib.crc32(zeros, crc)
    return head + chunk * (size // block) + tail, crc


def one_member_zip(name: str, payload: bytes, crc: int, size: int, *, declared_size: int | None = None) -> bytes:
    """A zip with one deflated member, written by hand (``declared_size``: a lying header)."""
    declared = size if declared_size is None else declared_size
    encoded = name.encode()
    local = struct.pack("<IHHHHHIIIHH", 0x04034B50, 20, 0, 8, 0, 0, crc, len(payload), declared, len(encoded), 0)
    central = struct.pack(
        "<IHHHHHHIIIHHHHHII", 0x02014B50, 20, 20, 0, 8, 0, 0, crc, len(payload), declared, len(encoded), 0, 0, 0, 0,
        0o100644 << 16, 0,
    )  # fmt: skip
    body = local + encoded + payload
    directory = central + encoded
    end = struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, 1, 1, len(directory), len(body), 0)
    return body + directory + end


def _zero_bomb(size: int, *, lying: bool = False) -> bytes:
    """A zip whose one member inflates to ``size`` zero bytes (about size / 1000 compressed)."""
    payload, crc = deflated_zeros(size)
    return one_member_zip("volume/zeros.dcm", payload, crc, size, declared_size=1000 if lying else None)


def _npz_zeros_upload(xa: bytes) -> bytes:
    """A valid XA and an .npz of compressed zeros (512^3 float32: 512 MB) inside a zip."""
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f4", "fortran_order": False, "shape": (512,) * 3})
    payload, crc = deflated_zeros(512**3 * 4, header.getvalue())
    data_member = one_member_zip("data.npy", payload, crc, 512**3 * 4 + len(header.getvalue()))
    affine = io.BytesIO()
    np.save(affine, np.eye(4))
    # the npz: its data member as built, plus index_to_world appended by zipfile
    npz = io.BytesIO(data_member)
    with zipfile.ZipFile(npz, "a", compression=zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("index_to_world.npy", affine.getvalue())
    return _zip([("v.npz", npz.getvalue()), ("xa.dcm", xa)], compression=zipfile.ZIP_STORED)


@pytest.fixture(scope="module")
def upload_config():
    from tests.app.conftest import TEST_CONFIG

    return TEST_CONFIG


def _hostile_uploads(xa: bytes) -> list[tuple[str, str, bytes, str]]:
    """(case, file name, content, a word the refusal must contain)."""
    many = _zip([(f"f{i}.txt", b"x") for i in range(10_000)], compression=zipfile.ZIP_STORED)
    lying = _zero_bomb(1 << 30, lying=True)
    return [
        ("zip-slip", "a.zip", _zip([("../escape.dcm", xa)]), "'..'"),
        ("zip-slip nested", "a.zip", _zip([("ok/../../escape.dcm", xa)]), "'..'"),
        ("absolute", "a.zip", _zip([("/etc/escape.dcm", xa)]), "absolute"),
        ("windows absolute", "a.zip", _zip([("C:\\escape.dcm", xa)]), "absolute"),
        ("symlink", "a.zip", _zip([_symlink("link", "/etc/passwd"), ("xa.dcm", xa)]), "symbolic link"),
        ("1 GB zero bomb", "bomb.zip", _zero_bomb(1 << 30), "limit"),
        ("1 GB zero bomb declaring 1 kB", "bomb.zip", lying, "cannot unpack"),  # zipfile reads 1 kB: bad CRC
        ("10,000 tiny members", "many.zip", many, "members"),
        ("not a zip", "a.zip", b"PK\x03\x04 this is not really a zip" + bytes(100), "not a readable zip"),
        ("empty", "a.zip", b"", "not a readable zip"),
        ("not .zip", "volume.dcm", xa, "expected"),
        ("no image", "a.zip", _zip([("readme.txt", b"hello")]), "found no"),
        ("compressed-zeros npz", "npz.zip", _npz_zeros_upload(xa), "compressed"),
    ]


def test_hostile_uploads_are_refused_by_the_app_handler(
    sources: dict[str, tuple[bytes, str]], upload_config, tmp_path: Path
) -> None:
    from app.web.upload import read_upload

    for case, name, content, needle in _hostile_uploads(sources["xa"][0]):
        tracemalloc.start()
        try:
            with pytest.raises((UploadError, DicomError)) as info:
                read_upload(name, content, max_bytes=64 * 1024**2, config=upload_config)
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        assert needle in str(info.value), f"{case}: {info.value}"
        # the archive itself is in memory (up to ~1 MB for the bomb); unpacking must not add much
        assert peak < len(content) + MEMORY_BOUND, f"{case}: peak {peak / 1e6:.0f} MB"
    assert not (tmp_path.parent / "escape.dcm").exists()


def test_fuzz_mutated_uploads(sources: dict[str, tuple[bytes, str]], upload_config, fuzz_seed: int) -> None:
    """A valid upload (XA + Enhanced CT), its bytes mutated: refused with a message or read."""
    from app.web.upload import read_upload

    valid = _zip([("ct/enhanced.dcm", sources["enhanced-ct"][0]), ("xa.dcm", sources["xa"][0])])
    read_upload("ok.zip", valid, max_bytes=16 * 1024**2, config=upload_config)  # the unmutated upload reads
    rng = random.Random(fuzz_seed)
    accepted = refused = 0
    for n in range(30):
        data, how = _byte_flips(rng, valid) if rng.random() < 0.7 else _truncate(rng, valid)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                read_upload("m.zip", data, max_bytes=16 * 1024**2, config=upload_config)
            accepted += 1
        except (UploadError, DicomError):
            refused += 1
        except Exception as exc:
            raise AssertionError(f"upload mutant {n} ({how}): {type(exc).__name__}: {exc}") from exc
    assert refused > 0


def test_mutator_is_reproducible(sources: dict[str, tuple[bytes, str]]) -> None:
    a = [(n, m.how, m.data[:64]) for n, m in mutants(sources, 30, 123)]
    b = [(n, m.how, m.data[:64]) for n, m in mutants(sources, 30, 123)]
    assert a == b
