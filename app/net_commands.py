"""The hospital-network commands: ``listen`` (a DICOM node) and the PACS side of ``register``.

Prints; the work is in :mod:`registration.io.node` and :mod:`registration.io.pacs`. Bad input
raises ``ValueError`` (``NodeError``, ``PacsError``, ``DicomError``), which ``cli.main`` turns
into ``error: ...`` and exit code 2.
"""

from __future__ import annotations

import queue
import signal
import sys
import threading
import warnings
from pathlib import Path
from typing import Any

from registration.io import dicom
from registration.io.node import DicomNode, Received


def _say(text: str = "") -> None:
    print(text, flush=True)


def _err(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def default_received_folder() -> Path:
    from platformdirs import user_data_dir

    return Path(user_data_dir("roadmap3d")) / "received"


# --------------------------------------------------------------------------------------
# listen
# --------------------------------------------------------------------------------------
class _Registrar:
    """Registers received X-ray images to one volume on a worker thread, in arrival order."""

    def __init__(self, volume_path: Path, results: Path) -> None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self.volume = dicom.read_volume(volume_path)
        self.results = results
        self.queue: queue.Queue[Received | None] = queue.Queue()
        self.thread = threading.Thread(target=self._work, name="roadmap3d-listen-register", daemon=True)
        self.thread.start()

    def _work(self) -> None:
        from registration.core.register import register

        while (item := self.queue.get()) is not None:
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    frame = item.frames - 1 if item.frames > 1 else None  # a run: its newest frame
                    xray = dicom.read_xray(item.path, frame=frame)
                result = register(self.volume, xray)
                m = result.patient_motion
                document = result.to_dict()
                document["image"] = {"path": str(item.path), "frame": xray.meta.get("frame", 0)}
                document["volume"] = {"label": self.volume.label}
                self.results.mkdir(mode=0o700, exist_ok=True)
                out = self.results / f"{item.path.stem}.json"
                dicom.write_text_atomic(out, dicom.json_dumps(document))
                _say(
                    f"registered {item.path.name}: translation ({m[0, 3]:+.2f}, {m[1, 3]:+.2f}, {m[2, 3]:+.2f}) mm, "
                    f"similarity {result.similarity:.4f}, {result.seconds:.1f} s -> {out}"
                )
            except ValueError as exc:
                _err(f"error: cannot register {item.path}: {exc}")

    def close(self) -> None:
        self.queue.put(None)
        self.thread.join(timeout=60)


def run_listen(
    *,
    ae_title: str,
    port: int,
    host: str,
    allow: tuple[str, ...],
    folder: Path | None,
    volume: Path | None,
) -> int:
    """Run the DICOM node until interrupted; print each received instance (and its registration)."""
    folder = Path(folder) if folder is not None else default_received_folder()
    registrar = _Registrar(volume, folder / "results") if volume is not None else None

    def received(item: Received) -> None:
        _say(
            f"received {item.modality or '?'} from {item.calling_ae}: {item.path} "
            f"({item.frames} frame{'s' * (item.frames != 1)})"
        )
        if registrar is not None and item.role == "xray":
            registrar.queue.put(item)

    node = DicomNode(folder, allowed=allow, ae_title=ae_title, host=host, port=port, on_received=received)
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
        node.stop()
        signal.signal(signal.SIGTERM, previous)
        if registrar is not None:
            registrar.close()
        _say(f"stopped; {len(node.received)} instance(s) received")
    return 0
