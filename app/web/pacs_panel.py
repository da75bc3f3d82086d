"""The app's PACS browser: patients -> studies -> series over DICOMweb, load, store the result.

A control tab "PACS" beside Data (:mod:`app.web.panels`). The PACS is ``roadmap3d app --pacs URL``
(or ``ROADMAP3D_PACS_URL``); credentials come from the environment or the config file
(:mod:`registration.io.pacs`), never from the page. Listing and loading run on a worker thread;
the retrieved series stay in a private temporary folder until the next load or the app closes.
"Store result" writes the current estimate as a Spatial Registration object and the overlay as
a Secondary Capture into the study the image came from.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
import threading
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import viser

from app.web.panels import BasePanel, PanelContext

if TYPE_CHECKING:
    from registration.io.pacs import Pacs, PacsSettings, SeriesEntry, StudyEntry

log = logging.getLogger(__name__)

NONE = "(none)"


class PacsPanel(BasePanel):
    """Browse a DICOMweb PACS and load a 3DRA/CT and an XA/RF image (or a run's frame) from it."""

    def __init__(self, ctx: PanelContext, *, settings: PacsSettings | None = None) -> None:
        self.ctx = ctx
        self._settings = settings
        self._pacs: Pacs | None = None
        self._studies: dict[str, StudyEntry] = {}
        self._series: dict[str, SeriesEntry] = {}
        self._frames: dict[str, int] = {}
        self._work: Path | None = None
        self._loaded: dict[str, Any] | None = None
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        gui = ctx.server.gui
        with ctx.layout.control_tab("PACS", viser.Icon.SERVER):
            self.info = gui.add_markdown(self._server_line())
            # without a PACS there is nothing to list: the button waits for one
            self.refresh_button = gui.add_button("List studies", icon=viser.Icon.REFRESH,
                                                 disabled=not self._configured())  # fmt: skip
            self.patient = gui.add_dropdown("Patient", (NONE,))
            self.study = gui.add_dropdown("Study", (NONE,))
            self.volume_series = gui.add_dropdown("3DRA / CT", (NONE,))
            self.image_series = gui.add_dropdown("XA / RF", (NONE,))
            self.frame = gui.add_number("Frame of a run", 0, min=0, step=1)
            self.load_button = gui.add_button("Load from PACS", icon=viser.Icon.DOWNLOAD, disabled=True)
            self.store_button = gui.add_button("Store result to PACS", icon=viser.Icon.UPLOAD, disabled=True)
            self.status = gui.add_markdown("")
            self.node_info = gui.add_markdown(
                "<small>DICOM node: off (`roadmap3d app --listen-port P --allow AE`)</small>"
            )
            self.use_received = gui.add_button("Show the received image", icon=viser.Icon.PHOTO, disabled=True)
        self.refresh_button.on_click(ctx.guarded(lambda _e: self._in_background(self.list_studies)))
        self.patient.on_update(ctx.guarded(lambda _e: self._show_studies()))
        self.study.on_update(ctx.guarded(lambda _e: self._in_background(self._list_series)))
        self.load_button.on_click(ctx.guarded(lambda e: self._in_background(self._audited("pacs-load", e))))
        self.store_button.on_click(ctx.guarded(lambda e: self._in_background(self._audited("pacs-store", e))))
        self.use_received.on_click(ctx.guarded(lambda _e: self.show_received()))
        self._node: Any = None
        self._node_folder: Path | None = None
        self.received: Any = None
        #: Called with (path, name) when the node receives a multi-frame run (the app wires the
        #: Play run panel's :meth:`~app.web.playback.PlaybackPanel.load_run_file` here).
        self.run_receivers: list[Callable[[Path, str], bool]] = []
        node = node_settings_from_env()
        if node is not None:
            self.start_node(**node)

    # ----- helpers -----------------------------------------------------------------------
    def _configured(self) -> bool:
        """A PACS was given: the app's settings, ``ROADMAP3D_PACS_URL`` or the server's PACS config file."""
        import os

        from registration.io.pacs_settings import default_config_path

        return bool(self._settings or os.environ.get("ROADMAP3D_PACS_URL") or default_config_path().is_file())

    def _server_line(self) -> str:
        import os

        url = self._settings.display_url if self._settings else os.environ.get("ROADMAP3D_PACS_URL")
        if not url:
            if self._configured():
                return "<small>PACS: as set in the server's PACS config file.</small>"
            return "<small>No PACS configured: start with `roadmap3d app --pacs URL` (DICOMweb).</small>"
        return f"<small>PACS: {url.split('@')[-1]}</small>"

    def _client(self) -> Pacs:
        from registration.io.pacs import Pacs, PacsSettings

        if self._pacs is None:
            self._pacs = Pacs(self._settings or PacsSettings.resolve(None))
        return self._pacs

    def _say(self, text: str, *, error: bool = False) -> None:
        self.status.content = f"<small>{text}</small>"
        self.ctx.message(text, error=error)

    def _in_background(self, work: Any) -> None:
        if threading.current_thread() is self._thread:  # a widget changed by the worker itself
            work()
            return
        if self._thread is not None and self._thread.is_alive():
            self._say("The PACS is still busy with the last request.")
            return

        def run() -> None:
            try:
                work()
            except ValueError as exc:  # PacsError, DicomError: say why
                self._say(str(exc), error=True)
            except Exception:  # noqa: BLE001 - a worker must not die silently
                log.exception("PACS request failed")
                self._say("The PACS request failed (see the log).", error=True)

        self._thread = threading.Thread(target=run, name="roadmap3d-pacs", daemon=True)
        self._thread.start()

    def wait(self, timeout_s: float = 60.0) -> bool:
        """Wait for the worker (tests, scripts); True when idle."""
        thread = self._thread
        if thread is not None:
            thread.join(timeout_s)
        return thread is None or not thread.is_alive()

    # ----- listing -----------------------------------------------------------------------
    def list_studies(self) -> None:
        """Patients and studies (QIDO-RS)."""
        pacs = self._client()
        studies = pacs.studies()
        self._studies = {s.study_uid: s for s in studies}
        patients = sorted({f"{s.patient_name or '?'} ({s.patient_id})" for s in studies})
        self.patient.options = tuple(patients) or (NONE,)
        self._show_studies()
        noun = "study" if len(studies) == 1 else "studies"
        self._say(f"{len(studies)} {noun} of {len(patients)} patient(s) on {pacs.name}")

    def _study_label(self, s: StudyEntry) -> str:
        what = s.description or "study"
        return f"{s.date or '-'} {what} [{'/'.join(s.modalities)}] …{s.study_uid[-8:]}"

    def _show_studies(self) -> None:
        patient = self.patient.value
        labels = {
            self._study_label(s): uid
            for uid, s in self._studies.items()
            if f"{s.patient_name or '?'} ({s.patient_id})" == patient
        }
        self._study_uid_of = labels
        self.study.options = tuple(labels) or (NONE,)
        self._list_series()

    def _list_series(self) -> None:
        uid = getattr(self, "_study_uid_of", {}).get(self.study.value)
        if uid is None:
            self.volume_series.options = self.image_series.options = (NONE,)
            self.load_button.disabled = True
            return
        pacs = self._client()
        series = pacs.series(uid)
        self._series = {}
        volumes, images = [], []
        for s in series:
            if s.role == "volume":
                label = s.label()
                volumes.append(label)
            elif s.role == "xray":
                frames = pacs.frames(uid, s.series_uid)
                self._frames[s.series_uid] = frames
                label = s.label() + (f", run of {frames} frames" if frames > 1 else "")
                images.append(label)
            else:
                continue
            self._series[label] = s
        self.volume_series.options = tuple(volumes) or (NONE,)
        self.image_series.options = tuple(images) or (NONE,)
        self.load_button.disabled = not (volumes and images)

    # ----- loading -----------------------------------------------------------------------
    def _audited(self, action: str, event: Any) -> Any:
        """The work of a PACS button, recorded in the audit log with its outcome and the UIDs."""
        from app.web.signin import client_address
        from registration.io import audit

        client = client_address(self.ctx.server, getattr(event, "client", None))
        work = self.load_selected if action == "pacs-load" else self.store_result

        def run() -> None:
            self._audit_uids: dict[str, Any] = {}
            try:
                work()
            except BaseException as exc:
                audit.record(action, client=client, result=f"failed: {str(exc)[:200]}", **self._audit_uids)
                raise
            audit.record(action, client=client, result="ok", **self._audit_uids)

        return run

    def load_selected(self) -> None:
        """Retrieve the chosen series (WADO-RS) and show them as the app's data."""
        from app.web.data import FileData
        from registration.io import dicom
        from registration.io.isocenter import resolve_isocenter

        vol_s = self._series.get(self.volume_series.value)
        img_s = self._series.get(self.image_series.value)
        if vol_s is None or img_s is None:
            raise ValueError("Choose a 3DRA/CT series and an XA/RF series first.")
        pacs = self._client()
        self._audit_uids = {"study_uid": img_s.study_uid, "series_uids": [vol_s.series_uid, img_s.series_uid]}
        self._say(f"Retrieving {vol_s.label()} and {img_s.label()}…")
        work = Path(tempfile.mkdtemp(prefix="roadmap3d-app-pacs-"))
        try:
            volume_folder = pacs.retrieve_series(vol_s.study_uid, vol_s.series_uid, work / "volume")
            images = sorted(pacs.retrieve_series(img_s.study_uid, img_s.series_uid, work / "image").iterdir())
            frames = self._frames.get(img_s.series_uid, 1)
            frame = int(self.frame.value) if frames > 1 else None
            if frame is not None and not 0 <= frame < frames:
                raise ValueError(f"Frame {frame} is not in the run (0..{frames - 1}).")
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                volume = dicom.read_volume(volume_folder)
                iso, iso_from = resolve_isocenter(None, volume)  # its IsocenterPosition, else the origin (as register)
                xray = dicom.read_xray(images[0], frame=frame, isocenter_mm=iso)
        except BaseException:
            shutil.rmtree(work, ignore_errors=True)
            raise
        source = f"PACS {pacs.name}: {vol_s.label()} + {img_s.label()}" + (f" frame {frame}" if frame else "")
        data = FileData(volume, xray, source=source, config=self.ctx.session.config, isocenter_from=iso_from)
        self.ctx.session.use_data(data)
        with self._lock:
            old, self._work = self._work, work
            self._loaded = {"data": data, "study_uid": img_s.study_uid}
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        self.ctx.layout.source.content = f"**Showing:** {source}  \n<small>{volume.label}</small>"
        self.ctx.layout.phantom_button.visible = True
        self.store_button.disabled = False
        self.ctx.refresh()
        self._say(f"Loaded from the PACS: {data.label}. Press **Register**, then **Store result to PACS**.")

    # ----- storing -----------------------------------------------------------------------
    def store_result(self) -> None:
        """The current estimate as a REG object + the overlay capture, into the image's study (STOW-RS)."""
        from registration.io import dicom
        from registration.io.dicom.capture import write_overlay_capture
        from registration.io.overlay import overlay_rgb

        with self._lock:
            loaded = self._loaded
        session = self.ctx.session
        if loaded is None or session.data is not loaded["data"]:
            raise ValueError("Load a volume and an image from the PACS first: the result goes back to their study.")
        if session.running:
            raise ValueError("A registration is running: store its result when it has finished.")
        with session.lock:
            motion = np.array(session.estimate, dtype=np.float64)
        data = loaded["data"]
        volume, xray = data.volume(), data.fixed_xray
        work = Path(tempfile.mkdtemp(prefix="roadmap3d-app-store-"))
        try:
            reg = dicom.write_registration(
                work / "registration.dcm", motion, volume=volume, xray=xray, description="roadmap3d app"
            )
            capture = write_overlay_capture(
                work / "overlay.dcm",
                overlay_rgb(volume, xray, motion),
                xray=xray,
                description="roadmap3d overlay (registered 3DRA vessels)",
            )
            pacs = self._client()
            reg_uid = dicom.read_registration(reg).sop_instance_uid
            self._audit_uids = {"study_uid": loaded["study_uid"], "instance_uid": reg_uid}
            pacs.store([reg, capture])
        finally:
            shutil.rmtree(work, ignore_errors=True)
        self._say(f"Stored the registration (REG) and the overlay (Secondary Capture) on {pacs.name}.")

    # ----- the DICOM node (images from the C-arm) -----------------------------------------
    def start_node(self, *, allowed: tuple[str, ...], port: int = 11112, ae_title: str = "ROADMAP3D") -> int:
        """Receive images over DICOM (C-STORE) on 127.0.0.1; the port it listens on."""
        from registration.io import audit
        from registration.io.node import DicomNode

        if self._node is not None:
            raise ValueError("The DICOM node already runs.")
        folder = Path(tempfile.mkdtemp(prefix="roadmap3d-app-node-"))
        try:
            node = DicomNode(folder / "received", allowed=allowed, ae_title=ae_title, port=port,
                             on_received=self._on_received, audit=audit.record).start()  # fmt: skip
        except BaseException:
            shutil.rmtree(folder, ignore_errors=True)
            raise
        self._node, self._node_folder = node, folder
        self.node_info.content = (
            f"<small>DICOM node: {node.ae_title} on 127.0.0.1:{node.port}, accepting {', '.join(node.allowed)}</small>"
        )
        return node.port

    def _on_received(self, item: Any) -> None:
        """Called by the node before it answers the C-STORE: the page knows when the sender does."""
        if item.role != "xray":
            self.node_info.content = (
                f"<small>Received {item.modality} from {item.calling_ae} (not an X-ray image)</small>"
            )
            return
        self.received = item
        self.use_received.disabled = False
        frames = f", {item.frames} frames (the last is shown)" if item.frames > 1 else ""
        self.node_info.content = f"<small>Received {item.modality} from {item.calling_ae}{frames}</small>"
        if item.frames > 1 and self.run_receivers:
            self._feed_run(item)
            return
        self.ctx.message(f"Received an X-ray image from {item.calling_ae}: **Show the received image** (PACS tab).")

    def _feed_run(self, item: Any) -> None:
        """A received run becomes the Play run panel's run (unless one is playing: then a message)."""
        name = f"{item.modality} run from {item.calling_ae}"
        try:
            loaded = all([receiver(item.path, name) for receiver in self.run_receivers])
        except ValueError as exc:
            self.ctx.message(f"Received a run from {item.calling_ae}, not loaded into Play run: {exc}.", error=True)
            return
        if loaded:
            self.ctx.message(f"Received a run from {item.calling_ae} ({item.frames} frames): **Play** it (Play run).")
        else:
            self.ctx.message(f"Received a run from {item.calling_ae} that Play run cannot play (see its tab).",
                             error=True)  # fmt: skip

    def show_received(self) -> None:
        """The received image (a run: its last frame) with the volume now shown."""
        from app.web.data import FileData
        from registration.io import dicom
        from registration.io.isocenter import resolve_isocenter

        item = self.received
        if item is None:
            raise ValueError("No image received yet.")
        session = self.ctx.session
        volume = session.data.volume(session.settings.volume_format_cm)
        if isinstance(session.data, FileData):  # the iso-center the user's volume is shown about now
            iso, iso_from = session.data.isocenter_mm, session.data.isocenter_from
        else:
            iso, iso_from = resolve_isocenter(None, volume)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            xray = dicom.read_xray(item.path, frame=item.frames - 1 if item.frames > 1 else None, isocenter_mm=iso)
        source = f"C-arm {item.calling_ae} (DICOM node) + {volume.label}"
        session.use_data(FileData(volume, xray, source=source, config=session.config, isocenter_from=iso_from))
        self.ctx.layout.source.content = f"**Showing:** {source}"
        self.ctx.layout.phantom_button.visible = True
        self.ctx.refresh()
        self._say("Showing the received image. Press **Register**.")

    def close(self) -> None:
        with self._lock:
            work, self._work = self._work, None
        if work is not None:
            shutil.rmtree(work, ignore_errors=True)
        if self._node is not None:
            self._node.stop()
            self._node = None
        if self._node_folder is not None:
            shutil.rmtree(self._node_folder, ignore_errors=True)
            self._node_folder = None


def node_settings_from_env() -> dict[str, Any] | None:
    """The DICOM node ``roadmap3d app --listen-port P --allow AE ...`` asked for, or None."""
    import os

    from registration.io.node import ENV_APP_NODE_AE, ENV_APP_NODE_ALLOW, ENV_APP_NODE_PORT

    port = os.environ.get(ENV_APP_NODE_PORT)
    if not port:
        return None
    allowed = tuple(a for a in os.environ.get(ENV_APP_NODE_ALLOW, "").split("\\") if a)
    return {"port": int(port), "allowed": allowed, "ae_title": os.environ.get(ENV_APP_NODE_AE) or "ROADMAP3D"}
