"""The ``roadmap3d`` command line.

This module only declares the commands and their options and turns errors into messages;
each command's work lives in the module that owns it (imported lazily so ``--help`` is fast).
Errors meant for users (bad files, bad values) become ``error: ...`` on stderr and exit code 2;
set ``ROADMAP3D_DEBUG=1`` to see the traceback instead.
"""

from __future__ import annotations

import importlib
import os
import sys
from pathlib import Path
from typing import Annotated, Literal, NoReturn

import tyro

from app.cli._perf import exit_code, exit_without_teardown, small_pages
from app.cli.options import (
    BiplaneStudy,
    CalibrationStudy,
    CaptureStudy,
    ClinicalStudy,
    PhantomStudy,
    RotationalRunStudy,
    Table1,
    TrackingStudy,
    VolumeStudy,
)

ImageKind = Literal["fluoro", "exposure"]


class UserError(Exception):
    """A problem with the user's input that deserves a message, not a traceback."""


# --------------------------------------------------------------------------------------
# validate
# --------------------------------------------------------------------------------------
Study = (
    Annotated[Table1, tyro.conf.subcommand("table1")]
    | Annotated[PhantomStudy, tyro.conf.subcommand("phantom")]
    | Annotated[ClinicalStudy, tyro.conf.subcommand("clinical")]
    | Annotated[CalibrationStudy, tyro.conf.subcommand("calibration")]
    | Annotated[TrackingStudy, tyro.conf.subcommand("tracking")]
    | Annotated[RotationalRunStudy, tyro.conf.subcommand("rotational-run")]
    | Annotated[BiplaneStudy, tyro.conf.subcommand("biplane")]
    | Annotated[VolumeStudy, tyro.conf.subcommand("volume")]
    | Annotated[CaptureStudy, tyro.conf.subcommand("capture")]
)


#: Each study's runner, ``(module, function)``, imported when the study runs (``--help`` stays light).
STUDY_RUNNERS: dict[type, tuple[str, str]] = {
    Table1: ("app.cli.study_commands", "run_table1"),
    PhantomStudy: ("app.cli.study_commands", "run_phantom_study"),
    ClinicalStudy: ("app.cli.study_commands", "run_clinical_study"),
    CalibrationStudy: ("app.cli.study_commands", "run_calibration_study"),
    TrackingStudy: ("app.cli.study_commands", "run_tracking_study"),
    RotationalRunStudy: ("app.cli.rotational_commands", "run_rotational_validation"),
    BiplaneStudy: ("app.cli.study_commands", "run_biplane_study"),
    VolumeStudy: ("app.cli.study_commands", "run_volume_validation"),
    CaptureStudy: ("app.cli.capture_commands", "run_capture_study"),
}


def validate(study: Study) -> int:
    """Run one of the paper's validation studies."""
    module, function = STUDY_RUNNERS[type(study)]
    return getattr(importlib.import_module(module), function)(study)


# --------------------------------------------------------------------------------------
# bench
# --------------------------------------------------------------------------------------
def bench(json: bool = False, quick: bool = False, seed: int = 0) -> int:
    """Measure DRR, similarity, registration and reconstruction speed (ratios vs references).

    Args:
        json: Print one JSON object on stdout.
        quick: Fewer repetitions and no 256^3 case (for smoke tests).
        seed: Seed of the phantom and the annealing.
    """
    from app.cli.study_commands import run_bench

    return run_bench(json=json, quick=quick, seed=seed)


# --------------------------------------------------------------------------------------
# data in and out
# --------------------------------------------------------------------------------------
def register(
    volume: Path,
    image: Annotated[list[Path], tyro.conf.UseAppendAction],
    frame: int | None = None,
    initial_motion: Path | None = None,
    truth: Path | None = None,
    out: Path | None = None,
    out_dicom: Path | None = None,
    out_transform: Path | None = None,
    geometry: Annotated[list[Path], tyro.conf.UseAppendAction] = [],  # noqa: B006 (tyro: an append flag)
    isocenter: str | None = None,
    seed: int = 0,
    sid_mm: float | None = None,
    sod_mm: float | None = None,
    pixel_mm: float | None = None,
    pacs: str | None = None,
    study: str | None = None,
    ca_bundle: Path | None = None,
    store: bool = False,
    verbose: bool = False,
    confidence: bool = False,
    no_cache: bool = False,
    explain: bool = False,
    report: Path | None = None,
    report_identify: bool = False,
    image_mask: Annotated[list[Path], tyro.conf.UseAppendAction] = [],  # noqa: B006 (tyro: an append flag)
    landmarks: Path | None = None,
    roi: Literal["none", "cranium"] = "none",
    roi_mask: Path | None = None,
    estimate_geometry: bool = False,
) -> int:
    """Register a 3DRA/CT volume to an XA/RF image and print a summary.

    Args:
        volume: DICOM series folder, enhanced multi-frame file, NIfTI (.nii, .nii.gz), NRRD, MetaImage (.mha, .mhd)
            or the project's .npz (with --pacs: a series UID).
        image: XA/RF DICOM file, single or multi-frame, or a TIFF/PNG with its geometry (--geometry; with --pacs: a
            series UID). Give it twice (--image A.dcm --image B.dcm) for a biplane pair of one moment: six
            parameters in plane A's frame.
        frame: Frame of a multi-frame image (0-based).
        initial_motion: JSON with "patient_motion" (4x4), or a DICOM Spatial Registration, to start from.
        truth: JSON with the true "patient_motion", or a DICOM Spatial Registration: adds residuals and success.
        out: Write the result JSON here.
        out_dicom: Write the result as a DICOM Spatial Registration object (REG) here.
        out_transform: Write the result as an ITK transform (.tfm or .h5; SimpleITK, 3D Slicer): the inverse of
            the patient motion, in LPS (fixed = the patient as imaged, moving = the volume).
        geometry: The geometry side file (JSON) of a TIFF/PNG --image, one per image in order (default: the
            image's name with .json). Keys: docs/formats.md.
        isocenter: Iso-center "x,y,z" mm or "volume-center" (default: IsocenterPosition of the volume, else the origin).
        seed: Seed of the annealing.
        sid_mm: Source-detector distance for images without DistanceSourceToDetector (0018,1110).
        sod_mm: Source-iso-center distance for images without DistanceSourceToPatient (0018,1111).
        pixel_mm: Pixel spacing at the detector (mm, square pixels) for images without ImagerPixelSpacing (0018,1164).
        pacs: DICOMweb URL of a PACS to load --volume/--image from (credentials: ROADMAP3D_PACS_USERNAME and
            ROADMAP3D_PACS_PASSWORD, or the config file; never on the command line).
        study: Study Instance UID on the PACS.
        ca_bundle: CA certificates (PEM) to verify an https:// PACS against.
        store: Store the result into the study on the PACS: the Spatial Registration object and the overlay
            (Secondary Capture).
        verbose: Print where the time went (start-up, reading, preparing the volume, registration) on stderr.
        confidence: Also assess the estimate (CONVENTIONS §7): its confidence and whether a roadmap would apply or
            withhold it, and why (the studies' rule, on the registration's prepared levels; a few seconds more on a
            CT; written to --out too).
        no_cache: Prepare the volume from scratch and keep nothing on disk (default: the view-independent part
            of the preparation is kept in the cache folder, ROADMAP3D_CACHE, by the volume's content;
            ROADMAP3D_NO_CACHE=1 does the same as this flag).
        explain: Print the plan of stages the registration runs (annealing levels, polishes, depth correction,
            rotation check, with their budgets) before running it.
        report: Write a report folder here (new or empty): report.html with the images, overlays, evidence
            plots, numbers and inputs (docs/report.md); assesses the confidence.
        report_identify: Name the patient (name, ID) and the file paths in the report (left out by default).
        image_mask: Your own field mask for --image: a PNG or TIFF of the image's stored size, nonzero = usable
            (one per --image, in order); it narrows the field found from the file (docs/field-of-view.md).
        landmarks: JSON of picked point pairs to start from instead of the machine-based pose, for a patient
            far from it: {"landmarks": [{"image_px": [col, row], "volume_mm": [x, y, z], "plane": "A"}, ...]},
            at least 4 on one image (docs/landmarks.md).
        roi: The part of the volume the registration follows: "cranium" leaves out the cervical spine below the
            skull base (found in the volume), which follows a head's motion only partly; "none" the whole volume.
        roi_mask: A label mask on the volume's grid (.npz with an array "mask", NIfTI, or a DICOM SEG): the
            registration follows the labelled voxels only (outside them, bone is rendered as soft tissue).
        estimate_geometry: With two planes, estimate each plane's source-image distance together with the pose,
            for a C-arm nobody calibrated or a file whose distances are nominal (docs/landmarks.md).
    """
    small_pages()
    if pacs is not None or os.environ.get("ROADMAP3D_PACS_URL") and (study or store):
        if confidence or report is not None:
            raise UserError("--confidence and --report work on files only (not with --pacs) for now")
        from app.cli.net_commands import run_register_pacs

        return run_register_pacs(
            pacs=pacs,
            study=study,
            volume_series=str(volume),
            image_series=str(_one_image(image, "--pacs")),
            ca_bundle=ca_bundle,
            store=store,
            out_dicom=out_dicom,
            frame=frame,
            initial_motion=initial_motion,
            truth=truth,
            out=out,
            isocenter=isocenter,
            seed=seed,
            sid_mm=sid_mm,
            sod_mm=sod_mm,
        )
    if study or store or ca_bundle:
        raise UserError("--study, --store and --ca-bundle need --pacs URL")
    if len(image) not in (1, 2):
        raise UserError(f"--image takes one X-ray file, or two (plane A and plane B of one moment); got {len(image)}")
    from app.cli._perf import read_ahead_for_register

    read_ahead_for_register(volume, image)  # the OS reads the files in while the engine is imported
    from app.cli.commands import run_register

    return run_register(
        volume=volume,
        image=image,
        frame=frame,
        initial_motion=initial_motion,
        truth=truth,
        out=out,
        out_dicom=out_dicom,
        out_transform=out_transform,
        geometry=geometry,
        isocenter=isocenter,
        seed=seed,
        sid_mm=sid_mm,
        sod_mm=sod_mm,
        pixel_mm=pixel_mm,
        verbose=verbose,
        confidence=confidence,
        cache=not no_cache,
        explain=explain,
        report=report,
        report_identify=report_identify,
        image_mask=image_mask,
        landmarks=landmarks,
        roi=roi,
        roi_mask=roi_mask,
        estimate_geometry=estimate_geometry,
    )


def _one_image(images: list[Path], flag: str) -> Path:
    if len(images) != 1:
        raise UserError(f"{flag} registers one image series; got {len(images)} --image values")
    return images[0]


def info(
    path: Path,
    /,
    json: bool = False,
    sid_mm: float | None = None,
    sod_mm: float | None = None,
    pixel_mm: float | None = None,
    image_mask: Path | None = None,
) -> int:
    """Show what roadmap3d reads from a file or folder (kind, geometry, shape, spacing, values, decoder; for an
    X-ray image how its usable field was found and which intensity relationship was assumed).

    Args:
        path: DICOM file, DICOM series folder or .npz volume.
        json: Print the report as one JSON object.
        sid_mm: Source-detector distance for images without DistanceSourceToDetector (0018,1110).
        sod_mm: Source-iso-center distance for images without DistanceSourceToPatient (0018,1111).
        pixel_mm: Pixel spacing at the detector (mm, square pixels) for images without ImagerPixelSpacing (0018,1164).
        image_mask: Your own field mask for an X-ray image (PNG or TIFF of its stored size, nonzero = usable).
    """
    from app.cli.commands import run_info

    return run_info(path, as_json=json, sid_mm=sid_mm, sod_mm=sod_mm, image_mask=image_mask, pixel_mm=pixel_mm)


def phantom(
    out: Path,
    volume_format: float = 27.0,
    image_format: float = 27.0,
    primary_deg: float = 0.0,
    secondary_deg: float = 0.0,
    offset: str = "T4",
    contrast: bool = True,
    seed: int = 0,
    voxels: int = 256,
    pixels: int = 512,
    volume_source: Literal["fdk", "resampled"] = "fdk",
) -> int:
    """Export the built-in phantom: a DICOM 3DRA series, XA images with known motion, truth JSON.

    Args:
        out: Output folder (created; must be empty or absent).
        volume_format: 3DRA volume format in cm.
        image_format: X-ray image format in cm.
        primary_deg: LAO(+)/RAO(-) angle of the XA views.
        secondary_deg: CRAN(+)/CAUD(-) angle of the XA views.
        offset: Patient motion: T1..T4 (Table I) or "tx,ty,tz,rx,ry,rz".
        contrast: Iodine contrast in the vessels.
        seed: Phantom variant and noise seed.
        voxels: 3DRA grid size along each axis.
        pixels: X-ray image size (square).
        volume_source: 3DRA series: FDK of a simulated rotational run (minutes once, then cached) or resampled phantom.
    """
    from app.cli.commands import run_phantom_export

    return run_phantom_export(
        out=out,
        volume_format=volume_format,
        image_format=image_format,
        primary_deg=primary_deg,
        secondary_deg=secondary_deg,
        offset=offset,
        contrast=contrast,
        seed=seed,
        voxels=voxels,
        pixels=pixels,
        volume_source=volume_source,
    )


def mesh(volume: Path, out: Path, vessel_hu: float | None = None, bone_hu: float | None = None, step: int = 1) -> int:
    """Write the vessel and bone surfaces of a volume (STL, PLY or GLB by the file extension).

    Args:
        volume: DICOM series folder, enhanced multi-frame file, or the project's .npz.
        out: Output mesh file (.stl, .ply or .glb).
        vessel_hu: Vessel threshold in HU (default 250: iodinated contrast, away from bone).
        bone_hu: Bone threshold in HU (default 700).
        step: Marching-cubes step in voxels (2 or more: fewer faces, faster).
    """
    from app.cli.commands import run_mesh

    return run_mesh(volume=volume, out=out, vessel_hu=vessel_hu, bone_hu=bone_hu, step=step)


# --------------------------------------------------------------------------------------
# the hospital network
# --------------------------------------------------------------------------------------
def listen(
    allow: tuple[str, ...] = (),
    ae_title: str = "ROADMAP3D",
    port: int = 11112,
    host: str = "127.0.0.1",
    folder: Path | None = None,
    volume: Path | None = None,
    sid_mm: float | None = None,
    sod_mm: float | None = None,
) -> int:
    """Receive images from the C-arm: a DICOM node (C-ECHO, C-STORE SCP) until Ctrl-C.

    Args:
        allow: Calling AE titles accepted (the C-arm's, the PACS's); everyone else is refused.
        ae_title: This node's AE title (callers must call it by this name).
        port: Port to listen on (0: any free port, printed).
        host: Interface to bind; 127.0.0.1 keeps the node on this machine.
        folder: Private folder (0700) for received files (default: the user data dir's roadmap3d/received).
        volume: Register every received XA/RF image to this 3DRA/CT, and track every received run (CONVENTIONS §7).
        sid_mm: Source-detector distance for images without DistanceSourceToDetector (0018,1110).
        sod_mm: Source-iso-center distance for images without DistanceSourceToPatient (0018,1111).
    """
    from app.cli.net_commands import run_listen

    return run_listen(ae_title=ae_title, port=port, host=host, allow=allow, folder=folder, volume=volume,
                      sid_mm=sid_mm, sod_mm=sod_mm)  # fmt: skip


def audit(last: int = 50, all_lines: bool = False, as_json: bool = False, folder: Path | None = None) -> int:
    """Print the audit trail: registrations, corrections, Stop, uploads, PACS loads and stores,
    DICOM associations and sign-ins, one line each (time, client, action, result, UIDs).

    Args:
        last: Print the last N lines.
        all_lines: Print every line (the rotated files too).
        as_json: Print the JSON lines as stored.
        folder: Audit folder (default: ROADMAP3D_AUDIT_DIR, else the user data dir's roadmap3d/audit).
    """
    import json as json_module

    from registration.io.audit import AuditLog

    log = AuditLog(folder)
    lines = list(log.lines())
    if not lines:
        print(f"no audit lines in {log.folder}", file=sys.stderr)
        return 0
    for line in lines if all_lines else lines[-max(0, last) :]:
        if as_json:
            print(json_module.dumps(line))
            continue
        uids = []
        if "study_uid" in line:
            uids.append(f"study {line['study_uid']}")
        if line.get("series_uids"):
            uids.append("series " + ",".join(line["series_uids"]))
        if "instance_uid" in line:
            uids.append(f"instance {line['instance_uid']}")
        if "ae_title" in line:
            uids.append(f"AE {line['ae_title']}")
        extra = f"  [{'; '.join(uids)}]" if uids else ""
        print(f"{line.get('time', '?')}  {line.get('client') or '-':<15}  {line.get('action', '?'):<24}  "
              f"{line.get('result', '')}{extra}")  # fmt: skip
    return 0


# --------------------------------------------------------------------------------------
# the web app
# --------------------------------------------------------------------------------------
def demo(
    port: int = 8080,
    host: str = "127.0.0.1",
    open_browser: bool = False,
    token: str | None = None,
    no_sign_in: bool = False,
    certfile: Path | None = None,
    keyfile: Path | None = None,
    allow_origin: tuple[str, ...] = (),
    password_file: Path | None = None,
    verbose: bool = False,
) -> int:
    """Start the web app on the built-in phantom.

    Args:
        port: Port to listen on (the next free one is taken if busy).
        host: Interface to bind; 127.0.0.1 keeps the app on this machine.
        open_browser: Open the page in the default browser.
        token: Sign-in token (default: ROADMAP3D_TOKEN, else a random one); the address printed carries it once.
        no_sign_in: Serve without sign-in (127.0.0.1 only).
        certfile: TLS certificate (PEM, with its chain): serve https:// and wss://.
        keyfile: TLS private key (PEM) of --certfile (when not inside it).
        allow_origin: Other web origins (scheme://host:port) whose pages may connect, e.g. behind a proxy.
        password_file: Sign in by a password instead of a token: the file `roadmap3d password FILE` made.
        verbose: Log each registration's plan (as register --explain prints it) on stderr.
    """
    from app.web.main import run_app

    return run_app(host=host, port=port, volume=None, image=None, open_browser=open_browser,
                   token=token, no_sign_in=no_sign_in, certfile=certfile, keyfile=keyfile,
                   allow_origin=allow_origin, password_file=password_file, verbose=verbose)  # fmt: skip


def app(
    host: str = "127.0.0.1",
    port: int = 8080,
    volume: Path | None = None,
    image: Path | None = None,
    frame: int | None = None,
    allow_share: bool = False,
    max_upload_mb: float = 512.0,
    open_browser: bool = False,
    pacs: str | None = None,
    listen_port: int | None = None,
    allow: tuple[str, ...] = (),
    sid_mm: float | None = None,
    sod_mm: float | None = None,
    isocenter: str | None = None,
    token: str | None = None,
    no_sign_in: bool = False,
    certfile: Path | None = None,
    keyfile: Path | None = None,
    allow_origin: tuple[str, ...] = (),
    password_file: Path | None = None,
    verbose: bool = False,
) -> int:
    """Start the web app, optionally on your own DICOM data.

    Args:
        host: Interface to bind; 127.0.0.1 keeps the app on this machine.
        port: Port to listen on (the next free one is taken if busy).
        volume: 3DRA/CT volume (DICOM folder, multi-frame file or .npz).
        image: XA/RF DICOM image.
        frame: Frame of a multi-frame image.
        allow_share: Let viser's share button open a public tunnel (off: refused).
        max_upload_mb: Largest upload accepted from the browser.
        open_browser: Open the page in the default browser.
        pacs: DICOMweb URL of a PACS for the PACS tab (credentials: ROADMAP3D_PACS_USERNAME/_PASSWORD or the
            config file).
        listen_port: Also receive images from the C-arm: a DICOM node (AE title ROADMAP3D) on 127.0.0.1 at this port.
        allow: Calling AE titles the app's DICOM node accepts (needed with --listen-port).
        sid_mm: Source-detector distance for an --image without DistanceSourceToDetector (0018,1110).
        sod_mm: Source-iso-center distance for an --image without DistanceSourceToPatient (0018,1111).
        isocenter: Iso-center of --volume/--image, "x,y,z" mm or "volume-center" (default: IsocenterPosition of the
            volume, else the origin), as for register.
        token: Sign-in token (default: ROADMAP3D_TOKEN, else a random one); the address printed carries it once.
        no_sign_in: Serve without sign-in (127.0.0.1 only).
        certfile: TLS certificate (PEM, with its chain): serve https:// and wss://.
        keyfile: TLS private key (PEM) of --certfile (when not inside it).
        allow_origin: Other web origins (scheme://host:port) whose pages may connect, e.g. behind a proxy.
        password_file: Sign in by a password instead of a token: the file `roadmap3d password FILE` made.
        verbose: Log each registration's plan (as register --explain prints it) on stderr.
    """
    if listen_port is not None:
        from registration.io.node import ENV_APP_NODE_ALLOW, ENV_APP_NODE_PORT, check_ae_title

        if not allow:
            raise UserError("--listen-port needs --allow AE (the C-arm's AE title)")
        titles = [check_ae_title(a, "--allow") for a in allow]
        os.environ[ENV_APP_NODE_PORT] = str(listen_port)
        os.environ[ENV_APP_NODE_ALLOW] = "\\".join(titles)
    elif allow:
        raise UserError("--allow needs --listen-port")
    from app.web.main import run_app

    if pacs is not None:
        from registration.io.pacs import ENV_URL, PacsSettings

        PacsSettings.resolve(pacs)  # a bad URL or config is an error now, not in the page
        os.environ[ENV_URL] = pacs  # the PACS tab (app/web/pacs_panel.py) reads it
    return run_app(
        host=host,
        port=port,
        volume=volume,
        image=image,
        frame=frame,
        allow_share=allow_share,
        max_upload_mb=max_upload_mb,
        open_browser=open_browser,
        sid_mm=sid_mm,
        sod_mm=sod_mm,
        isocenter=isocenter,
        token=token,
        no_sign_in=no_sign_in,
        certfile=certfile,
        keyfile=keyfile,
        allow_origin=allow_origin,
        password_file=password_file,
        verbose=verbose,
    )


def password(file: tyro.conf.Positional[Path], force: bool = False) -> int:
    """Make a password file for `roadmap3d app/demo --password-file FILE`: asks for the password
    twice (or reads one line from standard input when it is not a terminal) and writes only its
    salted scrypt hash, readable by you alone.

    Args:
        file: The password file to write.
        force: Replace an existing file.
    """
    import getpass

    from registration.io.dicom import write_text_atomic
    from registration.io.passwords import PasswordHash

    if file.is_dir():
        raise UserError(f"{file}: is a folder; give the password file's name")
    if file.exists() and not force:
        raise UserError(f"{file}: exists; give --force to replace it")
    if sys.stdin.isatty():
        first = getpass.getpass("Password: ")
        if getpass.getpass("Again: ") != first:
            raise UserError("the two passwords differ; nothing written")
    else:
        first = sys.stdin.readline().rstrip("\r\n")
    try:
        line = PasswordHash.of(first).text()
    except ValueError as exc:
        raise UserError(f"{exc}; nothing written") from None
    write_text_atomic(file, line + "\n", mode=0o600)  # readable by you alone, from its first byte
    print(f"wrote {file} (the password's hash; start the app with --password-file {file})")
    return 0


# --------------------------------------------------------------------------------------
# fluoroscopy runs
# --------------------------------------------------------------------------------------
def track(
    volume: Path,
    run: Path,
    run_b: Path | None = None,
    out: Path | None = None,
    truth: Path | None = None,
    isocenter: str | None = None,
    seed: int = 0,
    every_frame: bool = False,
    pacs: str | None = None,
    study: str | None = None,
    ca_bundle: Path | None = None,
    sid_mm: float | None = None,
    sod_mm: float | None = None,
    frame_time_ms: float | None = None,
    report: Path | None = None,
    report_identify: bool = False,
    pixel_mm: float | None = None,
) -> int:
    """Follow patient motion over a fluoroscopy run at its frame times (CONVENTIONS §7).

    Args:
        volume: DICOM series folder, enhanced multi-frame file, or the project's .npz.
        run: Multi-frame XA/RF run with its frame times (plane A for a biplane pair).
        run_b: Plane B's run of a biplane pair (same frame times; with --pacs: a series UID of --study).
        out: Write the per-frame list (frame, t_s, patient_motion, status, latency_ms, confidence) here.
        truth: run_truth.json with each frame's true patient_motion (adds errors, precision, recall).
        isocenter: Iso-center "x,y,z" mm or "volume-center" (default: IsocenterPosition of the volume, else the origin).
        seed: Seed of the full captures.
        every_frame: Process every frame (a replay) instead of skipping the frames that arrive while busy.
        pacs: DICOMweb URL of a PACS: --volume, --run (and --run-b) are then Series Instance UIDs of --study.
        study: Study Instance UID on the PACS.
        ca_bundle: CA certificates (PEM) to verify an https:// PACS against.
        sid_mm: Source-detector distance for runs without DistanceSourceToDetector (0018,1110).
        sod_mm: Source-iso-center distance for runs without DistanceSourceToPatient (0018,1111).
        frame_time_ms: Frame spacing for runs without FrameTimeVector, FrameTime or CineRate.
        report: Write a report folder here (new or empty): strip charts, per-frame decisions, the last frame
            compared in place (docs/report.md).
        report_identify: Name the patient (name, ID) and the file paths in the report (left out by default).
        pixel_mm: Pixel spacing at the detector (mm, square pixels) for runs without ImagerPixelSpacing (0018,1164).
    """
    if pacs is not None:
        if report is not None:
            raise UserError("--report works on files only (not with --pacs) for now")
        if pixel_mm is not None:
            raise UserError("--pixel-mm works on files only (not with --pacs) for now")
        from app.cli.net_commands import run_track_pacs

        return run_track_pacs(
            pacs=pacs, study=study, volume_series=str(volume), run_series=str(run), ca_bundle=ca_bundle,
            run_b_series=None if run_b is None else str(run_b), out=out, truth=truth, isocenter=isocenter,
            seed=seed, every_frame=every_frame, sid_mm=sid_mm, sod_mm=sod_mm, frame_time_ms=frame_time_ms,
        )  # fmt: skip
    if study or ca_bundle:
        raise UserError("--study and --ca-bundle need --pacs URL")
    from app.cli.track_commands import run_track

    return run_track(
        volume=volume, run=run, run_b=run_b, out=out, truth=truth, isocenter=isocenter, seed=seed,
        every_frame=every_frame, sid_mm=sid_mm, sod_mm=sod_mm, frame_time_ms=frame_time_ms, report=report,
        report_identify=report_identify, pixel_mm=pixel_mm,
    )  # fmt: skip


def phantom_run(
    out: Path,
    seconds: float = 20.0,
    pixels: int = 128,
    image_format: float = 27.0,
    primary_deg: float = 0.0,
    secondary_deg: float = 0.0,
    biplane: bool = False,
    sudden_moves: int = 2,
    seed: int = 0,
    voxels: int = 128,
    volume_source: Literal["fdk", "resampled"] = "fdk",
) -> int:
    """Export a simulated fluoroscopy run of the phantom (15 frames/s) with per-frame truth and its 3DRA.

    Args:
        out: Output folder (created; must be empty or absent).
        seconds: Length of the run.
        pixels: Frame size (square); 128 px frames take ~0.2 s each to simulate.
        image_format: Image format in cm (also the 3DRA's volume format).
        primary_deg: LAO(+)/RAO(-) angle of plane A.
        secondary_deg: CRAN(+)/CAUD(-) angle of plane A.
        biplane: Also write plane B (lateral, primary + 90 deg) at the same moments.
        sudden_moves: Sudden moves (up to 25 mm / 10 deg within 0.5 s) besides drift and breathing.
        seed: Seed of the patient's script and the frames' noise.
        voxels: 3DRA grid size along each axis.
        volume_source: 3DRA series: FDK of a simulated rotational run, or the resampled phantom.
    """
    from app.cli.track_commands import run_phantom_run_export

    return run_phantom_run_export(
        out=out, seconds=seconds, pixels=pixels, image_format=image_format, primary_deg=primary_deg,
        secondary_deg=secondary_deg, biplane=biplane, sudden_moves=sudden_moves, seed=seed, voxels=voxels,
        volume_source=volume_source,
    )  # fmt: skip


COMMANDS = {
    "demo": demo,
    "app": app,
    "validate": validate,
    "bench": bench,
    "register": register,
    "info": info,
    "phantom": phantom,
    "mesh": mesh,
    "listen": listen,
    "audit": audit,
    "password": password,
    "track": track,
    "phantom-run": phantom_run,
}


def main(argv: list[str] | None = None) -> None:
    """Entry point of the ``roadmap3d`` console script."""
    debug = os.environ.get("ROADMAP3D_DEBUG") == "1"
    if argv is None:  # the console script: the process ends after its exit handlers, without teardown
        exit_without_teardown()

    def finish(code: int) -> NoReturn:
        sys.exit(exit_code(code) if argv is None else code)

    try:
        code = tyro.extras.subcommand_cli_from_dict(
            COMMANDS, args=argv, config=(tyro.conf.OmitArgPrefixes,), prog="roadmap3d"
        )
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)
    except (UserError, ValueError, OSError) as exc:
        if debug:
            raise
        print(f"error: {exc}", file=sys.stderr)
        finish(2)
    except (ArithmeticError, RecursionError, MemoryError, LookupError, TypeError) as exc:
        # Reachable only from a value no check caught (a file or an option): still a message, exit 2.
        if debug:
            raise
        what = str(exc).strip()[:200] or "no details"
        given = " ".join(sys.argv[1:] if argv is None else argv)
        given = given if len(given) <= 300 else given[:297] + "..."
        print(f"error: {type(exc).__name__} ({what}) on the input of: roadmap3d {given}; rerun with "
              "ROADMAP3D_DEBUG=1 to see where", file=sys.stderr)  # fmt: skip
        finish(2)
    finish(int(code or 0))


if __name__ == "__main__":
    main()
