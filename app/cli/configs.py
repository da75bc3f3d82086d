"""The options of every ``roadmap3d`` command but ``validate`` (whose studies are in
:mod:`app.cli.options`): one frozen dataclass per command, from which tyro builds the parser
(each field's docstring is its help) and which the command's runner takes whole. Light:
importing it loads no engine module.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro

#: A flag given once per value, in order (``--image A.dcm --image B.dcm``).
Repeated = tyro.conf.UseAppendAction


@dataclass(frozen=True)
class Bench:
    """Measure DRR, similarity, registration and reconstruction speed (ratios vs references)."""

    json: bool = False
    """Print one JSON object on stdout."""
    quick: bool = False
    """Fewer repetitions and no 256^3 case (for smoke tests)."""
    seed: int = 0
    """Seed of the phantom and the annealing."""


@dataclass(frozen=True)
class Register:
    """Register a 3DRA/CT volume to an XA/RF image and print a summary."""

    volume: Path
    """DICOM series folder, enhanced multi-frame file, NIfTI (.nii, .nii.gz), NRRD, MetaImage (.mha, .mhd) or the
    project's .npz (with --pacs: a series UID)."""
    image: Annotated[tuple[Path, ...], Repeated]
    """XA/RF DICOM file, single or multi-frame, or a TIFF/PNG with its geometry (--geometry; with --pacs: a series
    UID). Give it twice (--image A.dcm --image B.dcm) for a biplane pair of one moment: six parameters in plane A's
    frame."""
    frame: int | None = None
    """Frame of a multi-frame image (0-based)."""
    initial_motion: Path | None = None
    """JSON with "patient_motion" (4x4), or a DICOM Spatial Registration, to start from."""
    truth: Path | None = None
    """JSON with the true "patient_motion", or a DICOM Spatial Registration: adds residuals and success."""
    out: Path | None = None
    """Write the result JSON here."""
    out_dicom: Path | None = None
    """Write the result as a DICOM Spatial Registration object (REG) here."""
    out_transform: Path | None = None
    """Write the result as an ITK transform (.tfm or .h5; SimpleITK, 3D Slicer): the inverse of the patient motion,
    in LPS (fixed = the patient as imaged, moving = the volume)."""
    geometry: Annotated[tuple[Path, ...], Repeated] = ()
    """The geometry side file (JSON) of a TIFF/PNG --image, one per image in order (default: the image's name with
    .json). Keys: docs/formats.md."""
    isocenter: str | None = None
    """Iso-center "x,y,z" mm, "head" (the middle of the head) or "volume-center" (default: IsocenterPosition of
    the volume, else the origin)."""
    seed: int = 0
    """Seed of the annealing."""
    sid_mm: float | None = None
    """Source-detector distance for images without DistanceSourceToDetector (0018,1110)."""
    sod_mm: float | None = None
    """Source-iso-center distance for images without DistanceSourceToPatient (0018,1111)."""
    pixel_mm: float | None = None
    """Pixel spacing at the detector (mm, square pixels) for images without ImagerPixelSpacing (0018,1164)."""
    pacs: str | None = None
    """DICOMweb URL of a PACS to load --volume/--image from (credentials: ROADMAP3D_PACS_USERNAME and
    ROADMAP3D_PACS_PASSWORD, or the config file; never on the command line)."""
    study: str | None = None
    """Study Instance UID on the PACS."""
    ca_bundle: Path | None = None
    """CA certificates (PEM) to verify an https:// PACS against."""
    store: bool = False
    """Store the result into the study on the PACS: the Spatial Registration object and the overlay (Secondary
    Capture)."""
    verbose: bool = False
    """Print where the time went (start-up, reading, preparing the volume, registration) on stderr."""
    confidence: bool = False
    """Also assess the estimate (CONVENTIONS §7): its confidence and whether a roadmap would apply or withhold it,
    and why (the studies' rule, on the registration's prepared levels; a few seconds more on a CT; written to --out
    too)."""
    no_cache: bool = False
    """Decode and prepare the volume from scratch and keep nothing on disk (default: a DICOM series' decoded volume,
    by the state of its files, and the view-independent part of the preparation, by the volume's content, are kept
    in the cache folder, ROADMAP3D_CACHE; ROADMAP3D_NO_CACHE=1 does the same as this flag)."""
    explain: bool = False
    """Print the plan of stages the registration runs (annealing levels, polishes, depth correction, rotation
    check, with their budgets) before running it."""
    report: Path | None = None
    """Write a report folder here (new or empty): report.html with the images, overlays, evidence plots, numbers
    and inputs (docs/report.md); assesses the confidence."""
    report_identify: bool = False
    """Name the patient (name, ID) and the file paths in the report (left out by default)."""
    image_mask: Annotated[tuple[Path, ...], Repeated] = ()
    """Your own field mask for --image: a PNG or TIFF of the image's stored size, nonzero = usable (one per --image,
    in order); it narrows the field found from the file (docs/field-of-view.md)."""
    landmarks: Path | None = None
    """JSON of picked point pairs to start from instead of the machine-based pose, for a patient far from it:
    {"landmarks": [{"image_px": [col, row], "volume_mm": [x, y, z], "plane": "A"}, ...]}, at least 4 on one image
    (docs/landmarks.md)."""
    roi: Literal["cranium", "none"] = "cranium"
    """The part of the patient the registration follows: "cranium" (default) the head above the skull base (found in
    the volume): the image's pixels that see mostly the neck below it, which follows a head's motion only partly, are
    left out of the measure (the whole image when the volume has no neck); "none" every pixel of the field
    (docs/clinical-images.md)."""
    roi_mask: Path | None = None
    """A label mask on the volume's grid (.npz with an array "mask", NIfTI, or a DICOM SEG) instead of the cranium:
    the registration follows the labelled voxels only (outside them bone is rendered as soft tissue)."""
    estimate_geometry: bool = False
    """With two planes, estimate each plane's source-image distance together with the pose, for a C-arm nobody
    calibrated or a file whose distances are nominal (docs/landmarks.md)."""


@dataclass(frozen=True)
class Info:
    """Show what roadmap3d reads from a file or folder (kind, geometry, shape, spacing, values, decoder; for an
    X-ray image how its usable field was found and which intensity relationship was assumed)."""

    path: tyro.conf.Positional[Path]
    """DICOM file or series folder, a volume (NIfTI, NRRD, MetaImage, the project's .npz) or an X-ray (TIFF, PNG)."""
    json: bool = False
    """Print the report as one JSON object."""
    sid_mm: float | None = None
    """Source-detector distance for images without DistanceSourceToDetector (0018,1110)."""
    sod_mm: float | None = None
    """Source-iso-center distance for images without DistanceSourceToPatient (0018,1111)."""
    pixel_mm: float | None = None
    """Pixel spacing at the detector (mm, square pixels) for images without ImagerPixelSpacing (0018,1164)."""
    image_mask: Path | None = None
    """Your own field mask for an X-ray image (PNG or TIFF of its stored size, nonzero = usable)."""


@dataclass(frozen=True)
class Phantom:
    """Export the built-in phantom: a DICOM 3DRA series, XA images with known motion, truth JSON."""

    out: Path
    """Output folder (created; must be empty or absent)."""
    volume_format: float = 27.0
    """3DRA volume format in cm."""
    image_format: float = 27.0
    """X-ray image format in cm."""
    primary_deg: float = 0.0
    """LAO(+)/RAO(-) angle of the XA views."""
    secondary_deg: float = 0.0
    """CRAN(+)/CAUD(-) angle of the XA views."""
    offset: str = "T4"
    """Patient motion: T1..T4 (Table I) or "tx,ty,tz,rx,ry,rz"."""
    contrast: bool = True
    """Iodine contrast in the vessels."""
    seed: int = 0
    """Phantom variant and noise seed."""
    voxels: int = 256
    """3DRA grid size along each axis."""
    pixels: int = 512
    """X-ray image size (square)."""
    volume_source: Literal["fdk", "resampled"] = "fdk"
    """3DRA series: FDK of a simulated rotational run (minutes once, then cached) or resampled phantom."""


@dataclass(frozen=True)
class Mesh:
    """Write the vessel and bone surfaces of a volume (STL, PLY or GLB by the file extension)."""

    volume: Path
    """DICOM series folder, enhanced multi-frame file, NIfTI, NRRD, MetaImage or the project's .npz."""
    out: Path
    """Output mesh file (.stl, .ply or .glb)."""
    vessel_hu: float | None = None
    """Vessel threshold in HU (default 250: iodinated contrast, away from bone)."""
    bone_hu: float | None = None
    """Bone threshold in HU (default 700)."""
    step: int = 1
    """Marching-cubes step in voxels (2 or more: fewer faces, faster)."""


@dataclass(frozen=True)
class Listen:
    """Receive images from the C-arm: a DICOM node (C-ECHO, C-STORE SCP) until Ctrl-C."""

    allow: tuple[str, ...] = ()
    """Calling AE titles accepted (the C-arm's, the PACS's); everyone else is refused."""
    ae_title: str = "ROADMAP3D"
    """This node's AE title (callers must call it by this name)."""
    port: int = 11112
    """Port to listen on (0: any free port, printed)."""
    host: str = "127.0.0.1"
    """Interface to bind; 127.0.0.1 keeps the node on this machine."""
    folder: Path | None = None
    """Private folder (0700) for received files (default: the user data dir's roadmap3d/received)."""
    volume: Path | None = None
    """Register every received XA/RF image to this 3DRA/CT, and track every received run (CONVENTIONS §7)."""
    sid_mm: float | None = None
    """Source-detector distance for images without DistanceSourceToDetector (0018,1110)."""
    sod_mm: float | None = None
    """Source-iso-center distance for images without DistanceSourceToPatient (0018,1111)."""


@dataclass(frozen=True)
class Serve:
    """Keep the engine warm for this user's `roadmap3d register`: kernels loaded, volumes read and prepared kept,
    answering on a private local socket until Ctrl-C."""

    socket: Path | None = None
    """The socket to listen on (default: $XDG_RUNTIME_DIR/roadmap3d/worker.sock, else /tmp/roadmap3d-UID/worker.sock;
    clients find another one by ROADMAP3D_WORKER_SOCKET)."""
    keep: int = 2
    """Volumes kept in memory with their preparations (the least recently used is let go first)."""
    verbose: bool = False
    """Print a line per command served."""


@dataclass(frozen=True)
class Audit:
    """Print the audit trail: registrations, corrections, Stop, uploads, PACS loads and stores, DICOM associations
    and sign-ins, one line each (time, client, action, result, UIDs)."""

    last: int = 50
    """Print the last N lines."""
    all_lines: bool = False
    """Print every line (the rotated files too)."""
    as_json: bool = False
    """Print the JSON lines as stored."""
    folder: Path | None = None
    """Audit folder (default: ROADMAP3D_AUDIT_DIR, else the user data dir's roadmap3d/audit)."""


@dataclass(frozen=True)
class Serving:
    """How the web app is served: address, sign-in, TLS, origins, logging."""

    host: str = "127.0.0.1"
    """Interface to bind; 127.0.0.1 keeps the app on this machine."""
    port: int = 8080
    """Port to listen on (the next free one is taken if busy)."""
    open_browser: bool = False
    """Open the page in the default browser."""
    token: str | None = None
    """Sign-in token (default: ROADMAP3D_TOKEN, else a random one); the address printed carries it once."""
    no_sign_in: bool = False
    """Serve without sign-in (127.0.0.1 only)."""
    certfile: Path | None = None
    """TLS certificate (PEM, with its chain): serve https:// and wss://."""
    keyfile: Path | None = None
    """TLS private key (PEM) of --certfile (when not inside it)."""
    allow_origin: tuple[str, ...] = ()
    """Other web origins (scheme://host:port) whose pages may connect, e.g. behind a proxy."""
    password_file: Path | None = None
    """Sign in by a password instead of a token: the file `roadmap3d password FILE` made."""
    verbose: bool = False
    """Log each registration's plan (as register --explain prints it) on stderr."""


@dataclass(frozen=True)
class Demo(Serving):
    """Start the web app on the built-in phantom."""


@dataclass(frozen=True)
class App(Serving):
    """Start the web app, optionally on your own DICOM data."""

    volume: Path | None = None
    """3DRA/CT volume (DICOM folder, multi-frame file or .npz)."""
    image: Path | None = None
    """XA/RF DICOM image."""
    frame: int | None = None
    """Frame of a multi-frame image."""
    allow_share: bool = False
    """Let viser's share button open a public tunnel (off: refused)."""
    max_upload_mb: float = 512.0
    """Largest upload accepted from the browser."""
    pacs: str | None = None
    """DICOMweb URL of a PACS for the PACS tab (credentials: ROADMAP3D_PACS_USERNAME/_PASSWORD or the config
    file)."""
    listen_port: int | None = None
    """Also receive images from the C-arm: a DICOM node (AE title ROADMAP3D) on 127.0.0.1 at this port."""
    allow: tuple[str, ...] = ()
    """Calling AE titles the app's DICOM node accepts (needed with --listen-port)."""
    sid_mm: float | None = None
    """Source-detector distance for an --image without DistanceSourceToDetector (0018,1110)."""
    sod_mm: float | None = None
    """Source-iso-center distance for an --image without DistanceSourceToPatient (0018,1111)."""
    isocenter: str | None = None
    """Iso-center of --volume/--image, "x,y,z" mm, "head" or "volume-center" (default: IsocenterPosition of the volume,
    else the origin), as for register."""


@dataclass(frozen=True)
class Password:
    """Make a password file for `roadmap3d app/demo --password-file FILE`: asks for the password twice (or reads
    one line from standard input when it is not a terminal) and writes only its salted scrypt hash, readable by you
    alone."""

    file: tyro.conf.Positional[Path]
    """The password file to write."""
    force: bool = False
    """Replace an existing file."""


@dataclass(frozen=True)
class Track:
    """Follow patient motion over a fluoroscopy run at its frame times (CONVENTIONS §7)."""

    volume: Path
    """DICOM series folder, enhanced multi-frame file, NIfTI, NRRD, MetaImage or the project's .npz."""
    run: Path
    """Multi-frame XA/RF run with its frame times (plane A for a biplane pair)."""
    run_b: Path | None = None
    """Plane B's run of a biplane pair (same frame times; with --pacs: a series UID of --study)."""
    out: Path | None = None
    """Write the per-frame list (frame, t_s, patient_motion, status, latency_ms, confidence) here."""
    truth: Path | None = None
    """run_truth.json with each frame's true patient_motion (adds errors, precision, recall)."""
    isocenter: str | None = None
    """Iso-center "x,y,z" mm, "head" (the middle of the head) or "volume-center" (default: IsocenterPosition of
    the volume, else the origin)."""
    seed: int = 0
    """Seed of the full captures."""
    every_frame: bool = False
    """Process every frame (a replay) instead of skipping the frames that arrive while busy."""
    pacs: str | None = None
    """DICOMweb URL of a PACS: --volume, --run (and --run-b) are then Series Instance UIDs of --study."""
    study: str | None = None
    """Study Instance UID on the PACS."""
    ca_bundle: Path | None = None
    """CA certificates (PEM) to verify an https:// PACS against."""
    sid_mm: float | None = None
    """Source-detector distance for runs without DistanceSourceToDetector (0018,1110)."""
    sod_mm: float | None = None
    """Source-iso-center distance for runs without DistanceSourceToPatient (0018,1111)."""
    frame_time_ms: float | None = None
    """Frame spacing for runs without FrameTimeVector, FrameTime or CineRate."""
    report: Path | None = None
    """Write a report folder here (new or empty): strip charts, per-frame decisions, the last frame compared in
    place (docs/report.md)."""
    report_identify: bool = False
    """Name the patient (name, ID) and the file paths in the report (left out by default)."""
    pixel_mm: float | None = None
    """Pixel spacing at the detector (mm, square pixels) for runs without ImagerPixelSpacing (0018,1164)."""


@dataclass(frozen=True)
class PhantomRun:
    """Export a simulated fluoroscopy run of the phantom (15 frames/s) with per-frame truth and its 3DRA."""

    out: Path
    """Output folder (created; must be empty or absent)."""
    seconds: float = 20.0
    """Length of the run."""
    pixels: int = 128
    """Frame size (square); 128 px frames take ~0.2 s each to simulate."""
    image_format: float = 27.0
    """Image format in cm (also the 3DRA's volume format)."""
    primary_deg: float = 0.0
    """LAO(+)/RAO(-) angle of plane A."""
    secondary_deg: float = 0.0
    """CRAN(+)/CAUD(-) angle of plane A."""
    biplane: bool = False
    """Also write plane B (lateral, primary + 90 deg) at the same moments."""
    sudden_moves: int = 2
    """Sudden moves (up to 25 mm / 10 deg within 0.5 s) besides drift and breathing."""
    seed: int = 0
    """Seed of the patient's script and the frames' noise."""
    voxels: int = 128
    """3DRA grid size along each axis."""
    volume_source: Literal["fdk", "resampled"] = "fdk"
    """3DRA series: FDK of a simulated rotational run, or the resampled phantom."""
