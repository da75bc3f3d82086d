"""The data commands: ``register``, ``info``, ``phantom`` and ``mesh``.

The only module of ``registration/`` that prints. Bad input raises ``ValueError`` (often a
:class:`~registration.io.dicom.DicomError` naming the file and the tag), which ``cli.main``
turns into ``error: ...`` and exit code 2. Output files are written through temporary
files and renamed, so a failed command leaves no partial output.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import threading
import time
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from app.cli.configs import Info, Mesh, Phantom
from registration.core.geometry import OFFSET_NAMES, TABLE_I, CArm, check_rigid, matrix_to_offsets, offsets_to_matrix
from registration.io import dicom
from registration.io.isocenter import resolve_isocenter
from registration.sim.threedra import VOLUME_SOURCES, VolumeRecipe

if TYPE_CHECKING:
    from registration.core.drr import DRRRenderer
    from registration.core.images import XRayImage
    from registration.core.prepare import PreparedVolume
    from registration.core.volume import Volume
    from registration.io.cache import PreparationCache

#: Files written by ``roadmap3d phantom`` inside its output folder.
PHANTOM_VOLUME_DIR = "volume"
PHANTOM_FLUORO = "xa_fluoro.dcm"
PHANTOM_EXPOSURE = "xa_exposure.dcm"
PHANTOM_FLUORO_B = "xa_fluoro_plane_b.dcm"
#: Seconds between the phantom's fluoro frame and its exposure (two acquisitions, not one moment).
EXPOSURE_AFTER_FLUORO_S = 4.0
PHANTOM_TRUTH = "truth.json"
#: Long work (building the FDK 3DRA the first time) is announced on stderr once it has taken
#: this long (seconds); a cached volume loads well within it ...
PROGRESS_AFTER_S = 3.0
#: ... and its elapsed time is repeated this often (seconds).
PROGRESS_EVERY_S = 30.0


def _say(text: str = "", *, stream: TextIO | None = None) -> None:
    print(text, file=stream or sys.stdout)


def _process_age_s() -> float | None:
    """Seconds since this process started (Linux: /proc), None where that is not known."""
    try:
        ticks = os.sysconf("SC_CLK_TCK")
        start = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19]) / ticks
        return float(Path("/proc/uptime").read_text().split()[0]) - start
    except (OSError, ValueError, IndexError):
        return None


class _Stopwatch:
    """Where a command's time went: the start-up before it (interpreter, imports) and its laps."""

    def __init__(self) -> None:
        self.startup_s = _process_age_s()
        self.laps: list[tuple[str, float]] = []
        self._last = time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.laps.append((name, now - self._last))
        self._last = now

    def report(self) -> str:
        parts = ([] if self.startup_s is None else [("start-up (interpreter, imports)", self.startup_s)]) + self.laps
        total = sum(s for _, s in parts)
        return "time: " + ", ".join(f"{name} {s:.2f} s" for name, s in parts) + f"; total {total:.2f} s"


def _show_warnings(caught: list[warnings.WarningMessage]) -> None:
    for message in dict.fromkeys(str(w.message) for w in caught):
        _say(f"warning: {message}", stream=sys.stderr)


@contextmanager
def _progress(message: str, *, after_s: float | None = None, every_s: float | None = None) -> Iterator[None]:
    """Say ``message`` on stderr if the block runs longer than ``after_s``, then the elapsed time
    every ``every_s`` and the total at the end (defaults: ``PROGRESS_AFTER_S``, ``PROGRESS_EVERY_S``)."""
    after = PROGRESS_AFTER_S if after_s is None else after_s
    every = PROGRESS_EVERY_S if every_s is None else every_s
    start = time.perf_counter()
    done = threading.Event()
    said = threading.Event()

    def watch() -> None:
        if done.wait(after):
            return
        _say(f"{message} ...", stream=sys.stderr)
        said.set()
        while not done.wait(every):
            _say(f"  ... {time.perf_counter() - start:.0f} s", stream=sys.stderr)

    watcher = threading.Thread(target=watch, name="roadmap3d-progress", daemon=True)
    watcher.start()
    try:
        yield
    finally:
        done.set()
        watcher.join()
    if said.is_set():
        _say(f"  done in {time.perf_counter() - start:.0f} s", stream=sys.stderr)


def parse_isocenter(text: str | None, volume: Volume | None = None) -> tuple[float, float, float]:
    """``"x,y,z"`` in mm, ``"volume-center"`` (needs ``volume``), or the default of
    :func:`resolve_isocenter` (the volume's IsocenterPosition, else the world origin, CONVENTIONS §1)."""
    return resolve_isocenter(text, volume)[0]


def parse_offset(text: str) -> tuple[str, np.ndarray]:
    """A Table I name (T1..T4) or ``"tx,ty,tz,rx,ry,rz"`` (mm, degrees, view frame)."""
    key = text.strip().upper()
    if key in TABLE_I:
        return key, np.asarray(TABLE_I[key], dtype=np.float64)
    try:
        values = np.array([float(v) for v in text.split(",")], dtype=np.float64)
    except ValueError:
        values = np.array([])
    if values.shape != (6,) or not np.all(np.isfinite(values)):
        raise ValueError(
            f"--offset must be one of {', '.join(TABLE_I)} or six numbers 'tx,ty,tz,rx,ry,rz' (mm, deg), got {text!r}"
        )
    return "custom", values


def read_motion_json(path: Path, *, what: str) -> tuple[np.ndarray, dict[str, Any]]:
    """The 4x4 ``patient_motion`` of a result/truth JSON file, and the whole document."""
    try:
        document = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise ValueError(f"{path}: no such file ({what})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read the {what} file ({exc})") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None
    except RecursionError:
        raise ValueError(f"{path}: the {what} file nests its JSON too deeply to be a motion file") from None
    if not isinstance(document, dict) or "patient_motion" not in document:
        raise ValueError(f"{path}: the {what} file must be a JSON object with a 'patient_motion' 4x4 matrix")
    try:
        matrix = np.asarray(document["patient_motion"], dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: 'patient_motion' must be a 4x4 list of numbers") from None
    try:
        motion = check_rigid(matrix, name=f"{path}: patient_motion")
    except ValueError as exc:
        raise ValueError(str(exc)) from None
    shift_mm = float(np.linalg.norm(motion[:3, 3]))
    if shift_mm > MAX_MOTION_MM:
        raise ValueError(
            f"{path}: the {what}'s translation is {shift_mm:.4g} mm; a patient motion is at most {MAX_MOTION_MM:g} mm"
        )
    return motion, document


#: Largest translation (mm) a motion file may hold: far beyond any patient motion on the table.
MAX_MOTION_MM = 1000.0


def check_writable(target: Path | None, flag: str) -> None:
    """Refuse an output the command could not write, before any work: found only after a
    registration ran, the message named the ``.tmp`` file."""
    if target is None:
        return
    target = Path(target)
    if target.is_dir():
        raise ValueError(f"{target}: is a folder; {flag} takes a file name")
    parent = target.parent if str(target.parent) else Path(".")
    if not parent.is_dir():
        raise ValueError(f"{target}: its folder {parent} does not exist ({flag})")
    if target.exists() and not os.access(target, os.W_OK):
        raise ValueError(f"{target}: not writable ({flag})")
    try:
        probe = tempfile.NamedTemporaryFile(dir=parent, prefix=f".{target.name}.", suffix=".probe", delete=True)
    except OSError as exc:
        raise ValueError(f"{target}: cannot write into {parent} ({flag}: {exc.strerror or exc})") from None
    probe.close()


def read_motion(path: Path, *, what: str, volume_frame_of_reference: str | None = None) -> tuple[np.ndarray, dict]:
    """The patient motion of a result/truth file: the project's JSON or a DICOM Spatial Registration.

    For a DICOM object the motion is the one from the volume's Frame of Reference (when the
    object names it) into the other frame it relates; see :mod:`registration.io.dicom.spatial`.
    """
    path = Path(path)
    if path.is_file() and path.read_bytes()[:1] != b"{":
        try:
            dicom.read_dataset(path, stop_before_pixels=True)
        except dicom.DicomError:
            pass  # not DICOM: the JSON reader says what is wrong with it
        else:
            reg = dicom.read_registration(path)  # names the SOP class of any other DICOM object
            return reg.volume_motion(volume_frame_of_reference), {"dicom_registration": reg.sop_instance_uid}
    return read_motion_json(path, what=what)


def _format_offsets(motion: np.ndarray, geometry: CArm) -> str:
    o = matrix_to_offsets(motion, geometry)
    o = np.where(np.abs(o) < 5e-3, 0.0, o)  # no "-0.00"
    return (
        f"t = ({o[0]:+.2f}, {o[1]:+.2f}, {o[2]:+.2f}) mm, r = ({o[3]:+.2f}, {o[4]:+.2f}, {o[5]:+.2f}) deg "
        "in the view frame"
    )


# --------------------------------------------------------------------------------------
# register
# --------------------------------------------------------------------------------------
#: Kernels every registration runs (numba: compiled on the first run, then loaded from the
#: on-disk cache beside the modules, ``__pycache__``), by module.
REGISTRATION_KERNELS = (
    ("registration.core.drr", ("_ray_setup", "_render_joseph", "_render_joseph_serial")),
    ("registration.core.similarity", ("_gd_prepared",)),
)


def kernels_to_compile() -> list[str]:
    """The registration kernels with no compiled copy on disk newer than their source: the first run
    after an install or an update compiles them (all of them: 20-50 s on 2 cores). Read from the
    file names numba's on-disk cache uses beside each module (``__pycache__/<module>.<function>-*.nbi``);
    a hint only."""
    import importlib

    missing = []
    for module, names in REGISTRATION_KERNELS:
        source = Path(importlib.import_module(module).__file__ or "")
        stem = source.stem
        for name in names:
            qualname = getattr(
                getattr(getattr(importlib.import_module(module), name, None), "py_func", None), "__qualname__", name
            )
            indexes = list((source.parent / "__pycache__").glob(f"{stem}.{qualname}-*.nbi"))
            try:
                if not any(index.stat().st_mtime >= source.stat().st_mtime for index in indexes):
                    missing.append(name)
            except OSError:
                continue
    return missing


def prepare_for_registration(
    volume: Volume,
    views: Sequence[XRayImage],
    initial_motion: np.ndarray | None = None,
    *,
    cache: bool = True,
    background: bool = True,
) -> tuple[PreparedVolume, PreparationCache | None]:
    """The volume as ``register`` (and ``track`` and the app's file data) renders it: cropped to
    what the views' fields reach over the default search from ``initial_motion``, its pyramid
    levels resampled to isotropic grids in mm (:func:`registration.core.register.prepared_volume`,
    :mod:`registration.core.prepare`), prepared once per volume and views (kept in memory) and,
    with ``cache``, its view-independent part kept on disk
    (:class:`registration.io.cache.PreparationCache`). Returns the preparation and the store;
    with ``background`` the store writes from threads of its own: ``store.flush()`` before the
    process exits (a long-running process such as the app need not wait)."""
    from registration.core.register import RegistrationOptions, prepared_volume
    from registration.io.cache import PreparationCache

    store = PreparationCache(background=background) if cache else None
    start = np.eye(4) if initial_motion is None else np.asarray(initial_motion, dtype=np.float64)
    prepared = prepared_volume(volume, tuple(views), start, RegistrationOptions(), store=store)
    return prepared, store


def confidence_renderer(prepared: PreparedVolume, *, planes: int = 1) -> DRRRenderer:
    """The renderer ``register --confidence`` assesses with
    (:func:`registration.core.preparation.probe_renderer`)."""
    from registration.core.preparation import probe_renderer

    return probe_renderer(prepared, planes=planes)


# --------------------------------------------------------------------------------------
# info
# --------------------------------------------------------------------------------------
def _print_info(report: dict[str, Any]) -> None:
    order = ("path", "accepted", "kind", "format", "sop_class", "modality", "label", "image_kind")
    for key in order:
        if key in report and report[key] not in ("", None):
            _say(f"{key:>18}: {report[key]}")
    for key, value in report.items():
        if key in order or key in ("warnings", "problem"):
            continue
        if key == "geometry" and isinstance(value, dict):
            g = value
            _say(
                f"{'geometry':>18}: primary {g['primary_deg']:+.2f} deg, secondary {g['secondary_deg']:+.2f} deg, "
                f"SID {g['sid_mm']:.1f} mm, SOD {g['sod_mm']:.1f} mm, {g['cols']}x{g['rows']} px of "
                f"{g['pixel_mm'][1]:.4g}x{g['pixel_mm'][0]:.4g} mm, iso-center {g['isocenter_mm']}"
            )
        elif key == "header" and isinstance(value, dict):
            _say(f"{'header':>18}:")
            for tag, text in value.items():
                _say(f"{tag:>32}  {text[:80]}")
        elif key == "index_to_world":
            rows = ["[" + ", ".join(f"{v:9.4f}" for v in row) + "]" for row in value]
            _say(f"{'index_to_world':>18}: {rows[0]}")
            for row in rows[1:]:
                _say(f"{'':>18}  {row}")
        else:
            _say(f"{key:>18}: {value}")
    for message in report.get("warnings", []):
        _say(f"{'warning':>18}: {message}")


def run_info(options: Info) -> int:
    """Print what the project reads from ``path``; exit code 2 when it is not accepted."""
    path, as_json, sid_mm, sod_mm = options.path, options.json, options.sid_mm, options.sod_mm
    pixel_mm, image_mask = options.pixel_mm, options.image_mask
    report = dicom.inspect(path, sid_mm=sid_mm, sod_mm=sod_mm, image_mask=image_mask, pixel_mm=pixel_mm)
    if as_json:
        _say(json.dumps(report, indent=2))
    else:
        _print_info(report)
    if not report.get("accepted"):
        _say(f"error: {report.get('problem')}", stream=sys.stderr)
        return 2
    return 0


# --------------------------------------------------------------------------------------
# phantom
# --------------------------------------------------------------------------------------
def _phantom_3dra(
    *,
    source: str,
    seed: int,
    contrast: bool,
    volume_format: float,
    voxels: int,
) -> tuple[Volume, str, dict[str, Any]]:
    """The 3DRA to export, its SeriesDescription (<= 64 characters) and how it was made (for the truth).

    The same phantom (seed, contrast) as the XA images; the run's own noise seed and protocol
    are the recipe's defaults, so the cache entry is shared with the validation and the app.
    """
    recipe = VolumeRecipe(
        phantom_seed=seed, volume_format_cm=volume_format, source=source, voxels=voxels, contrast=contrast,
        noise_seed=seed,
    )  # fmt: skip
    if not recipe.reconstructed:
        volume = recipe.build()
        return volume, "3DRA stand-in: phantom resampled to the 3DRA grid", {"volume_source": source}
    message = (
        f"3DRA: simulating the rotational run and reconstructing it (FDK, {voxels}^3 voxels, "
        f"{volume_format:g} cm format); this takes minutes the first time and is cached afterwards"
    )
    with _progress(message):
        volume = recipe.build()
    run = {k: volume.meta[k] for k in ("projections", "arc_deg", "pixels", "kind", "seed") if k in volume.meta}
    label = f"3DRA: {volume.label}, head phantom seed {seed} {'with' if contrast else 'without'} contrast"
    description = f"3DRA: FDK reconstruction, {run.get('projections', '?')} projections"
    return volume.with_data(volume.data, label=label), description, {"volume_source": source, "rotational_run": run}


def run_phantom_export(options: Phantom) -> int:
    """Export the phantom: DICOM 3DRA series, XA fluoro and exposure with known motion, truth JSON.

    The 3DRA series is ``volume_source`` (one of :data:`registration.sim.threedra.VOLUME_SOURCES`).
    The XA images are the analytic phantom moved by the known motion and projected with the nominal geometry that
    their positioner tags state; the FDK volume is reconstructed in the same world frame (from
    the calibrated geometry of its run), so the truth holds for either source.
    """
    out, volume_format, image_format = options.out, options.volume_format, options.image_format
    primary_deg, secondary_deg, offset = options.primary_deg, options.secondary_deg, options.offset
    contrast, seed, voxels, pixels = options.contrast, options.seed, options.voxels, options.pixels
    volume_source = options.volume_source
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ValueError(f"{out}: exists and is not an empty folder; refusing to overwrite")
    if voxels < 8 or pixels < 16:
        raise ValueError(f"voxels must be >= 8 and pixels >= 16, got {voxels} and {pixels}")
    if volume_source not in VOLUME_SOURCES:
        raise ValueError(f"--volume-source must be one of {', '.join(VOLUME_SOURCES)}, got {volume_source!r}")
    offset_name, offsets = parse_offset(offset)

    from registration.sim.phantom import make_head_phantom
    from registration.sim.xray import simulate_xray

    start = time.perf_counter()
    geometry = CArm.for_format(image_format, pixels=pixels, primary_deg=primary_deg, secondary_deg=secondary_deg)
    motion = offsets_to_matrix(offsets, geometry)
    phantom = make_head_phantom(seed=seed, contrast=contrast)
    volume, description, made = _phantom_3dra(
        source=volume_source, seed=seed, contrast=contrast, volume_format=volume_format, voxels=voxels
    )
    fluoro = simulate_xray(phantom, geometry, motion=motion, kind="fluoro", seed=seed)
    exposure = simulate_xray(phantom, geometry, motion=motion, kind="exposure", seed=seed + 1)
    # Plane B of the biplane system (CONVENTIONS §6): lateral, its own distances and detector,
    # the same moment as the plane A fluoro frame (same motion, own noise).
    from registration.sim.biplane import plane_b_spec

    geometry_b = plane_b_spec().nominal(90.0 + primary_deg, secondary_deg, pixels=max(16, 2 * round(0.375 * pixels)))
    fluoro_b = simulate_xray(phantom, geometry_b, motion=motion, kind="fluoro", seed=seed + 2)
    moment = datetime.now(UTC)
    uid_seed = f"roadmap3d phantom {seed} {volume_format} {image_format} {voxels} {pixels} {contrast} {volume_source}"
    study_uid = str(dicom.make_uid(uid_seed, "study"))
    vessels = phantom.vessel_centerline_mm()
    truth = {
        "patient_motion": motion.tolist(),
        "offset": {"name": offset_name, **dict(zip(OFFSET_NAMES, offsets.tolist(), strict=True))},
        "geometry": geometry.to_dict(),
        "geometry_plane_b": geometry_b.to_dict(),
        "volume_format_cm": volume_format,
        "image_format_cm": image_format,
        "phantom": {"seed": seed, "contrast": contrast},
        "volume_label": volume.label,
        **made,
        "images": "the analytic phantom moved by patient_motion, projected with the nominal geometry of the "
        "XA positioner tags",
        "files": {
            "volume": PHANTOM_VOLUME_DIR,
            "fluoro": PHANTOM_FLUORO,
            "exposure": PHANTOM_EXPOSURE,
            "fluoro_plane_b": PHANTOM_FLUORO_B,
        },
        "vessel_points_mm": np.round(vessels[:: max(1, len(vessels) // 200)], 3).tolist(),
        "conventions": "shared/CONVENTIONS.md §4: anatomy the volume shows at X is at M @ X in the images",
    }
    with dicom.atomic_folder(out) as tmp:
        dicom.write_series(
            volume, tmp / PHANTOM_VOLUME_DIR, description=description, study_uid=study_uid, uid_seed=uid_seed
        )
        dicom.write_xray(fluoro, tmp / PHANTOM_FLUORO, study_uid=study_uid, uid_seed=uid_seed, plane="PLANE A",
                         acquired_at=moment)  # fmt: skip
        dicom.write_xray(fluoro_b, tmp / PHANTOM_FLUORO_B, study_uid=study_uid, uid_seed=f"{uid_seed} plane B",
                         plane="PLANE B", acquired_at=moment, description="roadmap3d fluoro, plane B")  # fmt: skip
        # The exposure is its own acquisition, a few seconds after the fluoro frame: never one moment
        # with it, however fast this machine writes the files (biplane pairing refuses it).
        dicom.write_xray(exposure, tmp / PHANTOM_EXPOSURE, study_uid=study_uid, uid_seed=uid_seed,
                         acquired_at=moment + timedelta(seconds=EXPOSURE_AFTER_FLUORO_S))  # fmt: skip
        if volume_source == "fdk":  # the run the 3DRA was reconstructed from (validate rotational-run)
            from app.cli.rotational_commands import export_phantom_run

            truth["files"].update(
                export_phantom_run(
                    tmp, volume, seed=seed, contrast=contrast, volume_format=volume_format, study_uid=study_uid,
                    uid_seed=uid_seed,
                )
            )  # fmt: skip
        dicom.write_text_atomic(tmp / PHANTOM_TRUTH, dicom.json_dumps(truth))
    _say(f"wrote {out}/ in {time.perf_counter() - start:.1f} s:")
    _say(
        f"  {PHANTOM_VOLUME_DIR}/       {volume.shape[0]} CT slices of {volume.shape[2]}x{volume.shape[1]} "
        f"({volume.label})"
    )
    _say(f"  {PHANTOM_FLUORO}    XA fluoroscopy, {pixels}x{pixels} px, {image_format:g} cm format")
    _say(f"  {PHANTOM_EXPOSURE}  XA exposure")
    _say(
        f"  {PHANTOM_FLUORO_B}  XA fluoroscopy of plane B (lateral, same moment as {PHANTOM_FLUORO}), "
        f"{geometry_b.cols}x{geometry_b.rows} px"
    )
    if "rotational_run_file" in truth["files"]:
        _say("  rotational_run.dcm  the 3DRA's rotational run (multi-frame XA, per-frame angles) + its calibration")
    _say(f"  {PHANTOM_TRUTH}      patient motion {offset_name}: {_format_offsets(motion, geometry)}")
    _say(
        f"try: roadmap3d register --volume {out / PHANTOM_VOLUME_DIR} --image {out / PHANTOM_FLUORO} "
        f"--truth {out / PHANTOM_TRUTH}"
    )
    _say(f"biplane: add --image {out / PHANTOM_FLUORO_B}")
    return 0


# --------------------------------------------------------------------------------------
# mesh
# --------------------------------------------------------------------------------------
def run_mesh(options: Mesh) -> int:
    """Write the vessel and bone surfaces of a volume file to STL, PLY or GLB."""
    volume, out, vessel_hu, bone_hu = options.volume, options.out, options.vessel_hu, options.bone_hu
    step = options.step
    from registration.io.meshes import (
        BONE_HU,
        MESH_SUFFIXES,
        NO_VESSELS_NOTE,
        VESSEL_HU,
        surface_meshes,
        write_meshes,
    )

    out = Path(out)
    if out.suffix.lower() not in MESH_SUFFIXES:
        raise ValueError(f"{out}: the output must end in {', '.join(MESH_SUFFIXES)}")
    check_writable(out, "--out")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        vol = dicom.read_volume(volume)
    _show_warnings(caught)
    meshes = surface_meshes(
        vol,
        vessel_hu=VESSEL_HU if vessel_hu is None else vessel_hu,
        bone_hu=BONE_HU if bone_hu is None else bone_hu,
        step=step,
    )
    if not meshes:
        raise ValueError(
            f"{volume}: no vessel or bone surface found (values {vol.data.min():.0f}..{vol.data.max():.0f})"
        )
    write_meshes(meshes, out)
    parts = ", ".join(f"{name}: {len(m.vertices)} vertices, {len(m.faces)} faces" for name, m in meshes.items())
    if "vessels" not in meshes:
        _say(f"note: {NO_VESSELS_NOTE}")
    _say(f"wrote {out} ({parts})")
    return 0
