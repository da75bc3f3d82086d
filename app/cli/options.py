"""The options of ``roadmap3d validate`` (what tyro turns into flags), shared by the command line
and the runners of :mod:`app.cli.study_commands`. Light: importing it loads no engine module.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal


@dataclass
class Table1:
    """Reproduce Table I: T1-T4, fluoro and exposure, formats 27/27 and 48/48 cm."""

    json: bool = False
    """Print one JSON object {"records": [...], "summary": {...}} on stdout."""
    seed: int = 0
    """Seed of the phantom, image noise and annealing."""


@dataclass
class PhantomStudy:
    """Table II-III and Fig. 6: every volume x image format, T1-T4, fluoro and exposure."""

    out: Path = Path("validation-phantom")
    """Output folder (results.jsonl, plots, report.md/html); a rerun resumes."""
    quick: bool = False
    """A reduced grid that finishes in a few minutes."""
    json: bool = False
    """Print the summary as one JSON object."""
    seed: int = 0
    jobs: int | None = None
    """Parallel processes (default: all cores)."""
    scheduler: str | None = None
    """Run on a Dask cluster, e.g. tcp://HOST:PORT."""
    volume_source: Literal["fdk", "resampled"] = "fdk"
    """Registration volume: the FDK 3DRA, or the phantom resampled to its grid (faster)."""


@dataclass
class ClinicalStudy:
    """Fig. 7: 10 virtual patients, 100 random registrations each against their own 3DRA."""

    out: Path = Path("validation-clinical")
    quick: bool = False
    json: bool = False
    seed: int = 0
    jobs: int | None = None
    scheduler: str | None = None
    registrations: int | None = None
    """Registrations per patient (default: 100; quick 20, its 2 patients): the first N draws of the seed."""


@dataclass
class BiplaneStudy:
    """Biplane (six parameters) beside single-plane registration at clinical offsets."""

    out: Path = Path("validation-biplane")
    """Output folder (results.jsonl, histograms, report.md/html); a rerun resumes."""
    quick: bool = False
    """One patient, 12 moments, smaller images and volume: a few minutes."""
    json: bool = False
    """Print the summary as one JSON object."""
    seed: int = 0
    jobs: int | None = None
    """Parallel processes (default: all cores)."""
    scheduler: str | None = None
    """Run on a Dask cluster, e.g. tcp://HOST:PORT."""
    ct: Path | None = None
    """A DICOM CT folder to register instead of the phantom's 3DRAs (images formed from the CT itself)."""
    registrations: int | None = None
    """Moments per patient (default: 50, quick 12)."""


@dataclass
class GeometryStudy:
    """Registration on files whose C-arm geometry is wrong, with and without estimating it (biplane, phantom)."""

    out: Path = Path("validation-geometry")
    """Output folder (results.jsonl, report.md, summary.json); a rerun resumes."""
    quick: bool = False
    """The quick biplane study's 12 moments, smaller images and volume: minutes."""
    json: bool = False
    """Print the summary as one JSON object."""
    seed: int = 0
    jobs: int | None = None
    """Parallel processes (default: all cores)."""
    scheduler: str | None = None
    """Run on a Dask cluster, e.g. tcp://HOST:PORT."""
    registrations: int | None = None
    """Moments (default: 50, quick 12)."""
    sid_error: float = 0.05
    """The images' source-image distance is 1 + this times the files' (0.05: the files say 5 % short)."""
    shift_px: float = 0.0
    """The files' principal point moved by this many pixels, in a random direction per plane."""


@dataclass
class CaptureStudy:
    """Capture range: success against the initial offset (translation 0-80 mm, rotation 0-40 deg)."""

    out: Path = Path("validation-capture")
    """Output folder (results.jsonl, capture_curves.png, report.md/html); a rerun resumes."""
    quick: bool = False
    """Five levels per sweep, three moments each, smaller images and volume: minutes."""
    json: bool = False
    """Print the summary as one JSON object {"single_plane": {...}, "biplane": {...}, ...}."""
    seed: int = 0
    jobs: int | None = None
    """Parallel processes (default: all cores)."""
    scheduler: str | None = None
    """Run on a Dask cluster, e.g. tcp://HOST:PORT."""
    ct: Path | None = None
    """A DICOM CT folder to register instead of the phantom's 3DRA (images formed from the CT itself)."""
    registrations: int | None = None
    """Moments per offset level (default: 10, quick 3)."""
    sweep: tuple[Literal["translation", "rotation", "combined"], ...] = ("translation", "rotation", "combined")
    """Which sweeps to run: the translation alone, the rotation alone, or both growing together."""
    from_landmarks: int | None = None
    """Start each registration from this many landmarks per plane (4-8, on the skull's outline) picked
    with --landmark-error-mm instead of from the machine-based pose."""
    landmark_error_mm: float = 3.0
    """The landmarks' picking error, mm (volume and image)."""
    aimed: bool = False
    """Aim both C-arms at the moved head (the table panned back to the anatomy, centred within 15 mm): the
    head stays in both fields while the machine-based pose is off by the whole offset."""
    pool: tuple[Path, ...] = ()
    """Register nothing: report on the moments of earlier runs together (their results.jsonl files or
    folders, e.g. several seeds of one design), levels pooled by offset, into --out."""


@dataclass
class CalibrationStudy:
    """Machine-based registration error at random angles against the true (bent) geometry."""

    json: bool = False
    seed: int = 0
    samples: int = 50
    """Number of random C-arm angles to test."""


@dataclass
class TrackingStudy:
    """Live motion compensation over simulated fluoroscopy runs (still, drift, sudden moves)."""

    out: Path = Path("validation-tracking")
    """Output folder (results.json, plots, report.md/html; each run's outcome in cases/: a rerun resumes)."""
    quick: bool = False
    """One 20 s run at 128 px (minutes the first time, then the run is cached)."""
    json: bool = False
    """Print the summary as one JSON object."""
    seed: int = 0
    """Seed of the patient's script, the frames' noise and the captures."""
    every_frame: bool = False
    """Process every frame (a deterministic replay) instead of skipping frames that arrive while busy."""


@dataclass
class RotationalRunStudy:
    """The paper's retrospective validation: random frames of a rotational run registered to its own 3DRA."""

    volume: str | None = None
    """3DRA reconstructed from the run: DICOM folder/file (with --pacs: its series UID, default the study's CT)."""
    run: str | None = None
    """The rotational run: a multi-frame XA/RF file (with --pacs: its Series Instance UID, default the longest run)."""
    pacs: str | None = None
    """DICOMweb base URL of a PACS (credentials: ROADMAP3D_PACS_USERNAME/_PASSWORD or the config file)."""
    study: str | None = None
    """Study Instance UID on the PACS holding the 3DRA and its run."""
    ca_bundle: Path | None = None
    """CA certificates (PEM) to verify an https:// PACS against."""
    calibration: Path | None = None
    """C-arm calibration table JSON (per-angle deviations) that refines each frame's geometry."""
    sid_mm: float | None = None
    """Source-detector distance for runs without DistanceSourceToDetector (0018,1110)."""
    sod_mm: float | None = None
    """Source-iso-center distance for runs without DistanceSourceToPatient (0018,1111)."""
    cases: int = 20
    """Number of random registrations."""
    contrast: bool | None = None
    """Whether the run shows iodine contrast in the vessels (the report's grouping; default unknown)."""
    out: Path = Path("validation-rotational-run")
    """Output folder (results.jsonl, report.md/html, histograms)."""
    json: bool = False
    """Print the summary as one JSON object."""
    seed: int = 0


@dataclass
class VolumeStudy:
    """How well registration holds on your own CT or 3DRA: random views and offsets, images formed
    from the volume (a best case: the images come from the same volume)."""

    volume: Path
    """The CT or 3DRA: DICOM series folder, enhanced multi-frame file, NIfTI, NRRD, MetaImage or the
    project's .npz (--pacs: a series UID)."""
    pacs: str | None = None
    """DICOMweb base URL of a PACS (credentials: ROADMAP3D_PACS_USERNAME/_PASSWORD or the config file)."""
    study: str | None = None
    """Study Instance UID on the PACS holding the --volume series."""
    ca_bundle: Path | None = None
    """CA certificates (PEM) to verify an https:// PACS against."""
    isocenter: str | None = None
    """Iso-center "x,y,z" in mm, "head" (the middle of the head) or "volume-center" (default: IsocenterPosition
    from the files, else the origin)."""
    cases: int = 20
    """Number of random registrations."""
    max_mm: float = 25.0
    """Largest translation of the random offsets (length, random 3-D direction), mm."""
    max_deg: float = 10.0
    """Largest rotation of the random offsets (about a random axis through the iso-center), degrees."""
    biplane: bool = False
    """Register two views of the same moment (plane B lateral to plane A), six parameters."""
    json: bool = False
    """Print the summary as one JSON object."""
    out: Path | None = None
    """Output folder (results.jsonl, summary.json, report.md)."""
    seed: int = 0
    """Seed of the views, offsets, noise and annealing."""
    realism: str = "clean"
    """Images: clean (line integrals, noise, blur, catheter), clinical (every effect), each (every effect alone), or
    effects joined by + (blades, text, overlay, display, contrast, scatter, heel, table, neck); comma-separated arms."""
    strengths: str = "1"
    """Strengths of the effects, comma-separated (0 none, 1 typical, 2 severe): each arm runs at each (a sweep)."""
    roi: Literal["cranium", "none"] = "cranium"
    """The part of the patient the registration follows, as register --roi: "cranium" leaves the image's pixels that
    see mostly the neck below the skull base out of the measure; "none" every pixel of the field."""
    quick: bool = False
    """A few minutes: 8 cases per arm (unless --cases is given)."""
