"""The hospital-network commands: ``listen`` (a DICOM node) and the PACS side of ``register``.

Prints; the work is in :mod:`registration.io.node` and :mod:`registration.io.pacs`. Bad input
raises ``ValueError`` (``NodeError``, ``PacsError``, ``DicomError``), which ``cli.main`` turns
into ``error: ...`` and exit code 2.
"""

from __future__ import annotations

import signal
import sys
import threading
import warnings
from collections import deque
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from app.cli.configs import Listen, Register, Track
from registration.io import audit, dicom
from registration.io.node import DicomNode, Received
from registration.io.overlay import overlay_rgb

#: After SIGTERM/Ctrl-C ``listen`` ends within this many seconds, whatever peers or registrations do.
EXIT_GRACE_S = 4.5


def _exit_soon(code: int, grace_s: float = EXIT_GRACE_S) -> None:
    """End the process ``grace_s`` seconds from now if it is still alive."""
    import os
    import time

    def watchdog() -> None:
        time.sleep(grace_s)
        _say("stopped (forced: something did not end in time)")
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)

    threading.Thread(target=watchdog, name="exit-watchdog", daemon=True).start()


#: One line at a time: the node's threads (receiving, registering) print side by side.
_PRINTING = threading.Lock()


def _say(text: str = "") -> None:
    with _PRINTING:
        print(text, flush=True)


def _err(text: str) -> None:
    with _PRINTING:
        print(text, file=sys.stderr, flush=True)


def default_received_folder() -> Path:
    from platformdirs import user_data_dir

    return Path(user_data_dir("roadmap3d")) / "received"


# --------------------------------------------------------------------------------------
# listen
# --------------------------------------------------------------------------------------
class _Registrar:
    """Registers received X-ray images (tracks received runs) against one volume on a worker
    thread, in arrival order."""

    def __init__(self, volume_path: Path, results: Path, *, sid_mm: float | None = None,
                 sod_mm: float | None = None) -> None:  # fmt: skip
        #: The distances of received images that lack them (``--sid-mm``/``--sod-mm``).
        self.distances_mm = {"sid_mm": sid_mm, "sod_mm": sod_mm}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self.volume = dicom.read_volume(volume_path)
        self.results = results
        #: Received images not yet taken up, in arrival order.
        self.pending: deque[Received] = deque()
        self.counts = {"registered": 0, "tracked": 0, "skipped": 0, "failed": 0, "not registered": 0}
        self._busy: Received | None = None
        self._closing = False
        self._cond = threading.Condition()
        self.thread = threading.Thread(target=self._work, name="roadmap3d-listen-register", daemon=True)
        self.thread.start()

    def put(self, item: Received) -> None:
        """Queue a received image (said when others wait for the one being registered)."""
        with self._cond:
            self.pending.append(item)
            waiting = len(self.pending)
            self._cond.notify()
        if waiting > 1 or self._busy is not None:
            _say(f"queued {item.path.name}: {waiting} waiting")

    def _next(self) -> Received | None:
        """The next image to work on: a run in its turn, else the newest single image (the older
        single images waiting are skipped: the newest shows where the patient is now)."""
        with self._cond:
            while not self.pending and not self._closing:
                self._cond.wait()
            if self._closing:
                return None
            runs = [i for i in self.pending if i.frames > 1]
            if runs:
                item = runs[0]
                self.pending.remove(item)
                self._busy = item
                return item
            item = self.pending.pop()
            skipped = list(self.pending)
            self.pending.clear()
            self._busy = item
        for old in skipped:
            self.counts["skipped"] += 1
            _say(f"skipped {old.path.name}: a newer image ({item.path.name}) arrived while registering")
            audit.record("registration", client=old.peer, study_uid=old.study_uid, series_uids=[old.series_uid],
                         instance_uid=old.instance_uid, result="skipped: a newer image arrived")  # fmt: skip
        return item

    def _work(self) -> None:
        while (item := self._next()) is not None:
            try:
                if item.frames > 1:
                    self._track(item)
                    self.counts["tracked"] += 1
                else:
                    self._register(item)
                    self.counts["registered"] += 1
            except Exception as exc:  # a message for the user, and the next image still registered
                self.counts["failed"] += 1
                _err(f"error: cannot register {item.path}: {exc}")
                audit.record("registration", client=item.peer, study_uid=item.study_uid,
                             series_uids=[item.series_uid], instance_uid=item.instance_uid,
                             result=f"failed: {str(exc)[:200]}")  # fmt: skip
            finally:
                with self._cond:
                    self._busy = None

    def _write(self, item: Received, document: dict) -> Path:
        self.results.mkdir(mode=0o700, exist_ok=True)
        out = self.results / f"{item.path.stem}.json"
        dicom.write_text_atomic(out, dicom.json_dumps(document))
        return out

    def _open_run(self, item: Received) -> dicom.XRayRun:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return dicom.read_xray_run(item.path, **self.distances_mm)

    def read(self, item: Received) -> list[Any]:
        """The received image (a run: all its frames), with ``--sid-mm``/``--sod-mm`` where the file lacks them."""
        if item.frames > 1:
            return self._open_run(item).frames()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return [dicom.read_xray(item.path, **self.distances_mm)]

    def _register(self, item: Received) -> None:
        from app.cli.commands import prepare_for_registration
        from registration.core.register import register

        (xray,) = self.read(item)
        # prepared as ``roadmap3d register`` prepares it (cropped, levels in mm, kept on disk)
        prepared, _store = prepare_for_registration(self.volume, [xray])
        result = register(self.volume, xray, renderer=prepared.renderer)
        m = result.patient_motion
        document = result.to_dict()
        document["image"] = {"path": str(item.path), "frame": xray.meta.get("frame", 0)}
        document["volume"] = {"label": self.volume.label}
        out = self._write(item, document)
        audit.record(
            "registration",
            client=item.peer,
            study_uid=item.study_uid,
            series_uids=[item.series_uid],
            instance_uid=item.instance_uid,
            result=f"registered: similarity {result.similarity:.4f}",
        )
        _say(
            f"registered {item.path.name}: translation ({m[0, 3]:+.2f}, {m[1, 3]:+.2f}, {m[2, 3]:+.2f}) mm, "
            f"similarity {result.similarity:.4f}, {result.seconds:.1f} s -> {out}"
        )

    def _track(self, item: Received) -> None:
        """A received run: tracked frame by frame (CONVENTIONS §7), every frame (a replay)."""
        from app.cli.commands import prepare_for_registration
        from registration.core.tracking import track_run

        run = self._open_run(item)
        frames = run.frames()
        # the run's field, as ``roadmap3d track`` prepares it (not a pyramid of the whole volume)
        prepared, _store = prepare_for_registration(self.volume, [frames[0]])
        result = track_run(self.volume, [frames], run.times_s, realtime=False, renderer=prepared.renderer)
        document = result.to_dict()
        document["run"] = {"path": str(item.path), "frames": len(frames)}
        document["volume"] = {"label": self.volume.label}
        out = self._write(item, document)
        counts: dict[str, int] = {}
        for f in result.frames:
            counts[f.status] = counts.get(f.status, 0) + 1
        statuses = ", ".join(f"{n} {status}" for status, n in sorted(counts.items()))
        audit.record("tracking", client=item.peer, study_uid=item.study_uid, series_uids=[item.series_uid],
                     instance_uid=item.instance_uid, count=len(frames), result=f"tracked: {statuses}")  # fmt: skip
        _say(f"tracked {item.path.name}: {len(frames)} frames ({statuses}) -> {out}")

    def close(self, wait_s: float = 2.0) -> None:
        """Stop: what waits is said not registered, as is a registration still running after ``wait_s``."""
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        self.thread.join(timeout=wait_s)
        with self._cond:
            left = ([self._busy] if self._busy is not None else []) + list(self.pending)
            self.pending.clear()
        for item in left:
            self.counts["not registered"] += 1
            _say(f"not registered {item.path.name}: stopped before it was done")
            audit.record("registration", client=item.peer, study_uid=item.study_uid, series_uids=[item.series_uid],
                         instance_uid=item.instance_uid, result="not registered: stopped")  # fmt: skip
        _say("registrations: " + ", ".join(f"{n} {what}" for what, n in self.counts.items()))


def run_listen(options: Listen) -> int:
    """Run the DICOM node until interrupted; print each received instance (and its registration)."""
    ae_title, port, host, allow, folder = options.ae_title, options.port, options.host, options.allow, options.folder
    volume, sid_mm, sod_mm = options.volume, options.sid_mm, options.sod_mm
    if volume is None and (sid_mm is not None or sod_mm is not None):
        raise ValueError("--sid-mm/--sod-mm apply to the images registered with --volume")
    folder = Path(folder) if folder is not None else default_received_folder()
    registrar = _Registrar(volume, folder / "results", sid_mm=sid_mm, sod_mm=sod_mm) if volume is not None else None

    def received(item: Received) -> None:
        _say(
            f"received {item.modality or '?'} from {item.calling_ae}: {item.path} "
            f"({item.frames} frame{'s' * (item.frames != 1)})"
        )
        if registrar is not None and item.role == "xray":
            registrar.put(item)

    node = DicomNode(folder, allowed=allow, ae_title=ae_title, host=host, port=port, on_received=received,
                     audit=audit.record)  # fmt: skip
    stop = threading.Event()

    def on_signal(signum: int, frame: Any) -> None:
        stop.set()

    previous = signal.signal(signal.SIGTERM, on_signal)
    node.start()
    try:
        if host not in ("127.0.0.1", "localhost", "::1"):
            _err(f"warning: listening on {host}: reachable from other machines (only {', '.join(allow)} accepted)")
        _say(
            f"listening on {host}:{node.port} as {node.ae_title}; accepting calling AE titles "
            f"{', '.join(node.allowed)}; received files go to {node.folder}"
        )
        if registrar is not None:
            _say(f"registering received X-ray images to {registrar.volume.label}")
        while not stop.wait(0.2):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        _exit_soon(0)  # whatever a peer or a registration does, the process ends within EXIT_GRACE_S
        node.stop()
        signal.signal(signal.SIGTERM, previous)
        if registrar is not None:
            registrar.close()
        _say(f"stopped; {len(node.received)} instance(s) received")
    return 0


# --------------------------------------------------------------------------------------
# register --pacs
# --------------------------------------------------------------------------------------
def _study_series(client: Any, study: str | None, wanted: tuple[tuple[str, str], ...]) -> dict[str, Any]:
    """The study's series by UID, after checking that each wanted (series UID, flag) is there."""
    if not study:
        flags = "/".join(flag for _, flag in wanted)
        raise ValueError(f"--pacs needs --study UID (and {flags} as Series Instance UIDs of that study)")
    known = {s.series_uid: s for s in client.series(study)}
    if not known:
        raise ValueError(f"PACS {client.name}: study {study} not found or empty")
    for uid, flag in wanted:
        if uid not in known:
            raise ValueError(f"PACS {client.name}: study {study} has no series {uid} ({flag})")
    return known


def retrieve_volume(client: Any, study: str | None, volume_series: str, work: Path) -> Path:
    """Retrieve a study's volume series (WADO-RS) into ``work``; the folder. Errors as :func:`retrieve_pair`."""
    known = _study_series(client, study, ((volume_series, "--volume"),))
    _err(f"retrieving {known[volume_series].label()} from {client.name}")
    return client.retrieve_series(study, volume_series, work / "volume")


def retrieve_pair(
    client: Any, study: str | None, volume_series: str, image_series: str, work: Path, *, image_flag: str
) -> tuple[Path, Path]:
    """Retrieve a study's volume series and its one-instance X-ray series (image or run) into
    ``work``; (volume folder, image file). Errors name the PACS, the study and the series."""
    known = _study_series(client, study, ((volume_series, "--volume"), (image_series, image_flag)))
    _err(f"retrieving {known[volume_series].label()} and {known[image_series].label()} from {client.name}")
    volume_folder = client.retrieve_series(study, volume_series, work / "volume")
    return volume_folder, _retrieve_instance(client, study, image_series, work / "image")


def _retrieve_instance(client: Any, study: str | None, series: str, folder: Path) -> Path:
    """The one instance of an X-ray series (an image or a run), retrieved into ``folder``."""
    files = sorted(client.retrieve_series(study, series, folder).iterdir())
    if len(files) != 1:
        raise ValueError(
            f"PACS {client.name}: series {series} holds {len(files)} instances; expected one XA/RF "
            "image or run (a series of single images: pick one, or store them as one run)"
        )
    return files[0]


def run_track_pacs(options: Track, track_files: Callable[[Track], int]) -> int:
    """``track --pacs``: retrieve the volume and the run (WADO-RS) into a private folder, track
    them with ``track_files`` (as files).
    ``--run-b``: plane B's run of a biplane pair, a series of the same study (both planes
    tracked together, as ``track --run A --run-b B`` does with files)."""
    import shutil
    import tempfile

    from registration.io.pacs import Pacs, PacsSettings

    study, volume_series, run_series = options.study, str(options.volume), str(options.run)
    run_b_series = None if options.run_b is None else str(options.run_b)
    if run_b_series is not None and str(run_b_series) == str(run_series):
        raise ValueError(f"--run and --run-b are the same series {run_series}: a biplane pair needs both planes' runs")
    client = Pacs(PacsSettings.resolve(options.pacs, ca_bundle=options.ca_bundle))
    work = Path(tempfile.mkdtemp(prefix="roadmap3d-track-"))
    local = replace(options, pacs=None, study=None, ca_bundle=None)
    try:
        if run_b_series is None:
            volume_folder, run_file = retrieve_pair(client, study, volume_series, run_series, work, image_flag="--run")
            return track_files(replace(local, volume=volume_folder, run=run_file))
        wanted = ((volume_series, "--volume"), (run_series, "--run"), (str(run_b_series), "--run-b"))
        known = _study_series(client, study, wanted)
        _err(f"retrieving {', '.join(known[uid].label() for uid, _ in wanted)} from {client.name}")
        volume_folder = client.retrieve_series(study, volume_series, work / "volume")
        run_file = _retrieve_instance(client, study, run_series, work / "run")
        run_b_file = _retrieve_instance(client, study, str(run_b_series), work / "run_b")
        return track_files(replace(local, volume=volume_folder, run=run_file, run_b=run_b_file))
    finally:
        shutil.rmtree(work, ignore_errors=True)


def run_register_pacs(options: Register, register_files: Callable[[Register], int]) -> int:
    """``register --pacs``: retrieve the two series, register them with ``register_files`` (as
    files), optionally store the REG object and the overlay capture back into the study (STOW-RS)."""
    import shutil
    import tempfile

    from registration.io.dicom.capture import write_overlay_capture
    from registration.io.pacs import Pacs, PacsSettings

    study, out_dicom = options.study, options.out_dicom
    client = Pacs(PacsSettings.resolve(options.pacs, ca_bundle=options.ca_bundle))
    work = Path(tempfile.mkdtemp(prefix="roadmap3d-register-"))
    try:
        volume_folder, image_file = retrieve_pair(
            client, study, str(options.volume), str(options.image[0]), work, image_flag="--image"
        )
        image_files = [image_file]
        registration = work / "registration.dcm"
        local = replace(options, volume=volume_folder, image=(image_file,), out_dicom=registration, pacs=None,
                        study=None, ca_bundle=None, store=False)  # fmt: skip
        code = register_files(local)
        if code != 0:
            return code
        if out_dicom is not None:
            shutil.copyfile(registration, out_dicom)
            _say(f"wrote {out_dicom}")
        if options.store:
            reg = dicom.read_registration(registration)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                volume = dicom.read_volume(volume_folder)
                xray = dicom.read_xray(image_files[0], frame=options.frame)
            motion = reg.volume_motion(str(volume.meta.get("frame_of_reference_uid") or "") or None)
            capture = write_overlay_capture(
                work / "overlay.dcm",
                overlay_rgb(volume, xray, motion),
                xray=xray,
                description="roadmap3d overlay (registered 3DRA vessels)",
                comment=f"registered with roadmap3d; Spatial Registration {reg.sop_instance_uid}",
            )
            client.store([registration, capture])
            _say(
                f"stored on {client.name}, study {study}: the Spatial Registration object "
                f"(SOP instance {reg.sop_instance_uid}) and the overlay as a Secondary Capture"
            )
        return 0
    finally:
        shutil.rmtree(work, ignore_errors=True)
