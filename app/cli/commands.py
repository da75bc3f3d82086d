"""The data commands ``info`` and ``mesh``, and the helpers every command shares.

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
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from app.cli.configs import Info, Mesh
from app.launch import process_age_s
from registration.core.geometry import TABLE_I, CArm, check_rigid, matrix_to_offsets
from registration.io import dicom
from registration.io.isocenter import resolve_isocenter

if TYPE_CHECKING:
    from registration.core.drr import DRRRenderer
    from registration.core.images import XRayImage
    from registration.core.prepare import PreparedVolume
    from registration.core.volume import Volume
    from registration.io.cache import PreparationCache

#: Long work (building the FDK 3DRA the first time) is announced on stderr once it has taken
#: this long (seconds); a cached volume loads well within it ...
PROGRESS_AFTER_S = 3.0
#: ... and its elapsed time is repeated this often (seconds).
PROGRESS_EVERY_S = 30.0


def _say(text: str = "", *, stream: TextIO | None = None) -> None:
    print(text, file=stream or sys.stdout)


#: The client's start-up (seconds) while a worker runs its command (:mod:`app.cli.worker`).
_client_startup: list[float | None] = []


def client_startup(seconds: float | None) -> None:
    """While a worker runs a client's command: the client's start-up, which the command's
    stopwatch reports instead of the worker's age (None: back to this process's own)."""
    _client_startup[:] = [] if seconds is None else [seconds]


class _Stopwatch:
    """Where a command's time went: the start-up before it (interpreter, imports) and its laps."""

    def __init__(self) -> None:
        self.startup_s = _client_startup[0] if _client_startup else process_age_s()
        warm = "start-up (client; the worker's engine was warm)"
        self.startup_name = warm if _client_startup else "start-up (interpreter, imports)"
        self.laps: list[tuple[str, float]] = []
        self._last = time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.laps.append((name, now - self._last))
        self._last = now

    def report(self) -> str:
        parts = ([] if self.startup_s is None else [(self.startup_name, self.startup_s)]) + self.laps
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
    """``"x,y,z"`` in mm, ``"head"`` or ``"volume-center"`` (both need ``volume``), or the default of
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
    ("registration.core.drr_kernels", ("_ray_setup", "_render_joseph", "_render_joseph_serial")),
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
