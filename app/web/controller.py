"""The controller: what the user's clicks and slider moves do.

Each callback changes only the :class:`~app.web.session.Session` (which validates and refuses
while a registration runs) and then wakes the presenter; it never draws. The controller also
shows the session's state back in the controls (:meth:`Controller.sync_controls`, without
re-triggering their callbacks), enables and disables them around a run, and runs
Auto-correct: a registration a moment after the patient last moved.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from collections.abc import Callable
from functools import wraps
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from app.web import status
from app.web.layout import OFFSET_LABELS, TZ_CORRECTED_LABEL, Layout, format_cm, format_option, offset_limit
from app.web.session import Session
from app.web.session_state import RunState
from app.web.upload import limit_uploads
from registration.core.geometry import clinically_relevant
from registration.io import audit

if TYPE_CHECKING:
    import viser

    from app.web.data import DataSource
    from app.web.panels import Panel

log = logging.getLogger(__name__)

#: Auto-correct waits this long after the last patient movement before re-registering.
AUTOCORRECT_DELAY_S = 0.6
#: What the status line says when the C-arm leaves the paper's clinically relevant subset.
OUTSIDE_RELEVANT = (
    "Outside the paper's clinically relevant subset (image format 15/19 cm, or a volume "
    "smaller than the image): the product keeps the machine-based registration here."
)


class Controller:
    """Binds the layout's widgets to the session."""

    def __init__(
        self,
        server: viser.ViserServer,
        session: Session,
        layout: Layout,
        *,
        phantom: DataSource,
        max_upload_bytes: int,
        wake: Callable[[], None],
        force_refresh: Callable[[], None],
    ) -> None:
        self.server = server
        self.session = session
        self.layout = layout
        self.phantom = phantom
        self.max_upload_bytes = max_upload_bytes
        self.wake = wake
        self.force_refresh = force_refresh
        self.panels: list[Panel] = []
        self.ui_running = False
        self.autocorrect_due: float | None = None
        self._sync_depth = 0
        self._sync_lock = threading.RLock()
        #: The run whose outcome the status line told last (each run's is told once, when drawn).
        self._announced: RunState | None = None
        #: A later preparation (another volume format) is showing its progress in the status line.
        self._preparing = False

    # ----- binding ----------------------------------------------------------------------
    def guarded(self, fn: Callable[..., None]) -> Callable[..., None]:
        """Turn any failure of a callback into a message in the page (never a stack trace)."""

        @wraps(fn)
        def wrapper(*args: Any) -> None:
            try:
                fn(*args)
            except ValueError as exc:
                self.message(str(exc), error=True)
                self.sync_controls()
            except Exception as exc:
                log.exception("callback failed")
                self.message(f"Something went wrong: {exc}", error=True)
                self.sync_controls()
            self.wake()

        return wrapper

    def bind(self) -> None:
        ui, s, on = self.layout, self.session, self.guarded
        for slider in ui.offset_sliders:
            slider.on_update(on(self._on_offsets))
        for name, button in ui.table_buttons.items():
            button.on_click(
                on(lambda _e, name=name: self._moved(lambda: s.apply_table_offset(name), f"{name} (Table I)"))
            )
        ui.random_button.on_click(on(lambda _e: self._moved(s.random_offset, "Random")))
        ui.reset_button.on_click(on(lambda _e: self._moved(s.reset, "Reset")))
        for control in ui.carm_controls:
            control.on_update(on(self._on_carm))
        ui.register_button.on_click(on(lambda e: self.start_registration(client=self.address(e))))
        ui.stop_button.on_click(on(lambda e: self.stop_registration(client=self.address(e))))
        ui.field_mask_upload.on_upload(on(self._on_field_mask))
        ui.region_upload.on_upload(on(self._on_region))
        for box in (ui.show_ghost, ui.show_skull, ui.show_gradients, ui.show_field):
            box.on_update(on(lambda _e: self.force_refresh()))
        ui.autocorrect.on_update(on(lambda _e: self._on_autocorrect()))
        ui.upload.on_upload(on(self._on_upload))
        ui.phantom_button.on_click(on(lambda _e: self.use_data(self.phantom)))
        ui.isocenter_button.on_click(on(lambda _e: self.set_isocenter(str(ui.isocenter_field.value))))
        ui.volume_center_button.on_click(on(lambda _e: self.set_isocenter("volume center")))
        ui.head_center_button.on_click(on(lambda _e: self.set_isocenter("head")))
        self.show_source()

        def refused(_client_id: Any, text: str) -> None:
            self.message(text, error=True)

        limit_uploads(self.server, self.max_upload_bytes, refused)

    # ----- patient and C-arm ------------------------------------------------------------
    def syncing(self) -> bool:
        return self._sync_depth > 0

    def _on_offsets(self, _event: Any) -> None:
        if self.syncing():
            return
        self.session.set_offsets([s.value for s in self.layout.offset_sliders])
        self.patient_moved()
        self._tell_moved("Patient motion" if self.session.has_truth else "Roadmap offset", restarted=False)

    def _moved(self, action: Callable[[], object], what: str) -> None:
        action()
        self.sync_controls()
        self.patient_moved()
        self._tell_moved(what, restarted=True)

    def _tell_moved(self, what: str, *, restarted: bool) -> None:
        """The status line after the motion controls: what moved, by how much, what comes next."""
        s = self.session
        self.message(
            status.moved_text(
                what, s.offsets(), has_truth=s.has_truth, autocorrect=bool(self.layout.autocorrect.value),
                restarted=restarted,
            )
        )  # fmt: skip

    def patient_moved(self) -> None:
        """Schedule Auto-correct (if on)."""
        if self.layout.autocorrect.value:
            self.autocorrect_due = time.monotonic() + AUTOCORRECT_DELAY_S

    def _on_autocorrect(self) -> None:
        if self.layout.autocorrect.value and not self.session.running:
            self.autocorrect_due = time.monotonic()

    def _on_carm(self, _event: Any) -> None:
        if self.syncing():
            return
        ui = self.layout
        self.session.update_settings(
            primary_deg=float(ui.primary.value),
            secondary_deg=float(ui.secondary.value),
            sid_mm=float(ui.sid.value),
            image_format_cm=format_cm(ui.image_format.value),
            volume_format_cm=format_cm(ui.volume_format.value),
            kind=str(ui.kind.value),
            contrast=bool(ui.contrast.value),
            catheter=bool(ui.catheter.value),
            biplane=bool(ui.biplane.value),
            primary_b_deg=float(ui.primary_b.value),
            secondary_b_deg=float(ui.secondary_b.value),
        )
        # The patient stays put in the room: its offsets in the new view frame change.
        self.sync_controls()
        self._tell_panels()
        st = self.session.settings
        if not clinically_relevant(st.volume_format_cm, st.image_format_cm):
            self.message(OUTSIDE_RELEVANT)
        elif ui.status.content.startswith("Outside"):
            self.message("Ready.")

    def _tell_panels(self) -> None:
        for panel in self.panels:
            panel.settings_changed()

    def sync_controls(self) -> None:
        """Show the session's state in the controls without re-triggering their callbacks."""
        ui, s = self.layout, self.session
        with self._sync_lock:
            self._sync_depth += 1
            try:
                with s.lock:
                    offsets = s.offsets()
                    st = s.settings
                for i, (slider, value) in enumerate(zip(ui.offset_sliders, offsets, strict=True)):
                    value = float(np.clip(round(float(value), 2), -offset_limit(i), offset_limit(i)))
                    if abs(slider.value - value) > 1e-9:
                        slider.value = value
                for control, value in (
                    (ui.primary, st.primary_deg),
                    (ui.secondary, st.secondary_deg),
                    (ui.sid, st.sid_mm),
                    (ui.image_format, format_option(st.image_format_cm)),
                    (ui.volume_format, format_option(st.volume_format_cm)),
                    (ui.kind, st.kind),
                    (ui.contrast, st.contrast),
                    (ui.catheter, st.catheter),
                    (ui.biplane, st.biplane),
                    (ui.primary_b, st.primary_b_deg),
                    (ui.secondary_b, st.secondary_b_deg),
                ):
                    if control.value != value:
                        control.value = value
                biplane = self.session.biplane
                ui.plane_b_folder.visible = biplane
                tz_label = TZ_CORRECTED_LABEL if biplane else OFFSET_LABELS["tz"]
                if ui.offset_sliders[2].label != tz_label:
                    ui.offset_sliders[2].label = tz_label
            finally:
                self._sync_depth -= 1

    # ----- the user's data ----------------------------------------------------------------
    def address(self, event: Any) -> str:
        """The network address of the client behind a GUI event (for the audit log)."""
        from app.web.signin import client_address

        return client_address(self.server, getattr(event, "client", None))

    def _data_uids(self) -> dict[str, Any]:
        """The study and series UIDs of the data shown (none for the phantom): the audit log's."""
        data = self.session.data
        metas = []
        try:
            if getattr(data, "fixed_xray", None) is not None:
                metas.append(data.fixed_xray.meta)
                metas.append(data.volume(self.session.settings.volume_format_cm).meta)
        except Exception:  # the audit line never stops the action
            return {}
        study = next((m.get("study_uid") for m in metas if m.get("study_uid")), None)
        return {"study_uid": study, "series_uids": [m.get("series_uid") for m in metas if m.get("series_uid")]}

    def stop_registration(self, *, client: str = "") -> None:
        running = self.session.running
        self.session.stop_registration()
        audit.record("stop", client=client, result="stopped a registration" if running else "nothing running",
                     **self._data_uids())  # fmt: skip

    def _on_upload(self, event: Any) -> None:
        uploaded = self.layout.upload.value
        self.load_upload(uploaded.name, uploaded.content, client=self.address(event))

    def load_upload(self, name: str, content: bytes, *, client: str = "") -> bool:
        """Read an uploaded zip and show it; a refusal becomes a message in the page."""
        from app.web.upload import distance_mm, read_upload

        ui = self.layout
        self.message(f"Reading {name} ({len(content) / 1e6:.1f} MB)…")
        try:
            sid_mm = distance_mm(str(ui.upload_sid.value), "SID")
            sod_mm = distance_mm(str(ui.upload_sod.value), "SOD")
            data = read_upload(
                name, content, max_bytes=self.max_upload_bytes, config=self.session.config, sid_mm=sid_mm, sod_mm=sod_mm
            )
        except ValueError as exc:  # UploadError, DicomError: say why, keep what is shown
            hint = ""
            if "sid_mm" in str(exc) or "sod_mm" in str(exc):
                hint = " · Enter the distance under Data (SID/SOD) and upload again."
            self.message(f"Upload refused: {exc}{hint}", error=True)
            audit.record("upload", client=client, result=f"refused: {str(exc)[:200]}")
            return False
        self.use_data(data)
        audit.record("upload", client=client, result=f"loaded, {len(content)} bytes", **self._data_uids())
        nominal = " (C-arm geometry nominal: the file's tags, no calibration)" if data.fixed_xray is not None else ""
        self.message(f"Loaded {name}: {data.label}{nominal}. Press **Register**.")
        return True

    def _on_field_mask(self, event: Any) -> None:
        uploaded = self.layout.field_mask_upload.value
        self.load_field_mask(uploaded.name, uploaded.content, client=self.address(event))

    def load_field_mask(self, name: str, content: bytes, *, client: str = "") -> None:
        """The user's field mask for their image (a PNG/TIFF upload): the field narrowed, shown
        shaded (Display: Usable field) and used by the next Register. A refusal is said in the page."""
        import tempfile

        suffix = Path(name).suffix.lower()
        if suffix not in (".png", ".tif", ".tiff"):
            raise ValueError(f"{name}: a field mask is a PNG or TIFF image")
        if len(content) > 64 * 2**20:
            raise ValueError(f"{name}: {len(content) / 2**20:.0f} MB is too large for a field mask")
        with tempfile.TemporaryDirectory(prefix="roadmap3d-mask-") as folder:
            path = Path(folder) / f"mask{suffix}"
            path.write_bytes(content)
            self.session.set_image_mask(path)
        self.layout.show_field.value = True
        self.show_source()
        audit.record("upload", client=client, result=f"field mask {len(content)} bytes", **self._data_uids())
        usable = self.session.data.fixed_xray.mask.mean() if self.session.data.fixed_xray is not None else 0.0
        self.message(f"Field mask {name}: {100 * usable:.0f} % of the image is used. Press **Register**.")

    def _on_region(self, event: Any) -> None:
        uploaded = self.layout.region_upload.value
        self.load_region(uploaded.name, uploaded.content, client=self.address(event))

    def load_region(self, name: str, content: bytes, *, client: str = "") -> None:
        """The user's region of interest for their volume (a label mask upload): the next Register
        follows only its voxels. A refusal is said in the page."""
        import tempfile

        lower = name.lower()
        suffix = next((x for x in (".nii.gz", ".nii", ".npz", ".dcm") if lower.endswith(x)), None)
        if suffix is None:
            raise ValueError(f"{name}: a region mask is .npz, NIfTI (.nii, .nii.gz) or a DICOM SEG (.dcm)")
        if len(content) > self.max_upload_bytes:
            raise ValueError(f"{name}: {len(content) / 1e6:.0f} MB is over the upload limit")
        with tempfile.TemporaryDirectory(prefix="roadmap3d-region-") as folder:
            path = Path(folder) / f"region{suffix}"
            path.write_bytes(content)
            self.session.set_region(path, name)
        self.show_source()
        audit.record("upload", client=client, result=f"region mask {len(content)} bytes", **self._data_uids())
        region = self.session.data.region
        self.message(f"Region {name}: the registration follows {int(region.mask.sum()):,} voxels. Press **Register**.")

    def use_data(self, data: DataSource) -> None:
        self.session.use_data(data)
        self.layout.autocorrect.value = False
        self.sync_controls()
        self.set_running_ui(self.session.running)
        self.show_source()
        self._tell_panels()

    def show_source(self) -> None:
        """The Data tab's source line and the registration volume's description."""
        ui, data = self.layout, self.session.data
        fmt_cm = self.session.settings.volume_format_cm
        volume = data.volume(fmt_cm)
        ui.source.content = f"**Showing:** {data.source}  \n<small>{volume.label}</small>"
        fmt = "" if data.fixed_xray is not None else f"{fmt_cm:g} cm, "
        ui.volume_info.content = (
            f"<small>Registration volume: {volume.label} ({fmt}{'x'.join(str(n) for n in volume.shape)} voxels of "
            f"{float(np.mean(volume.spacing_mm)):.2f} mm)</small>"
        )
        field = data.fixed_xray.meta.get("field") if data.fixed_xray is not None else None
        if field:  # how the X-ray image's usable field was found (docs/field-of-view.md)
            ui.volume_info.content += (
                f"  \n<small>Image field: {field.get('found_by', '')}; {field.get('usable_pixels', 0):,} pixels "
                f"usable ({100.0 * field.get('usable_fraction', 0.0):.0f} % of the image)</small>"
            )
        if data.fixed_xray is not None:
            g = data.fixed_xray.geometry
            ui.volume_info.content += (
                f"  \n<small>C-arm geometry: nominal (the file's angles {g.primary_deg:+.1f}°, "
                f"{g.secondary_deg:+.1f}°, SID {g.sid_mm:.0f} mm, SOD {g.sod_mm:.0f} mm; "
                "no C-arm calibration applied)</small>"
            )
        region = getattr(data, "region", None)
        if region is not None:  # what the registration follows (docs/clinical-images.md)
            ui.volume_info.content += f"  \n<small>Region: {region.describe()}" + (
                "; the image's pixels that see mostly the neck below it are left out</small>"
                if region.skull_base_z_mm is not None else "</small>"
            )  # fmt: skip
        ui.phantom_button.visible = data is not self.phantom
        ui.show_ghost.disabled = not self.session.has_truth
        self.show_isocenter()

    # ----- the iso-center -------------------------------------------------------------------
    def show_isocenter(self) -> None:
        """The Data tab's iso-center: where it is, where it came from, the field showing it."""
        ui, data = self.layout, self.session.data
        from app.web.data import FileData

        if isinstance(data, FileData):
            iso = data.isocenter_mm
            ui.isocenter_info.content = f"**Iso-center:** {data.isocenter_text}"
            ui.isocenter_field.value = f"{iso[0]:.2f}, {iso[1]:.2f}, {iso[2]:.2f}"
        else:
            ui.isocenter_info.content = (
                "**Iso-center:** (0.00, 0.00, 0.00) mm, the world origin: the phantom is imaged about it "
                "<small>(the field below is for your data)</small>"
            )
            ui.isocenter_field.value = "0.00, 0.00, 0.00"
        self._enable_isocenter(self.session.running)

    def _enable_isocenter(self, running: bool) -> None:
        from app.web.data import FileData

        fixed = not isinstance(self.session.data, FileData)
        ui = self.layout
        for control in (*ui.isocenter_controls, ui.field_mask_upload, ui.region_upload):  # for the user's data
            control.disabled = running or fixed

    def set_isocenter(self, text: str) -> None:
        """The iso-center typed into the Data tab (or "head", "volume center"): checked against the volume
        (:func:`app.web.upload.isocenter_field`), then the user's image is placed about it, the scene's
        marker moves there and the next Register uses it. A bad value changes nothing: it is said
        in the page (the guard turns the ValueError into a red status line and a notification)."""
        from app.web.upload import isocenter_field

        s = self.session
        iso, source = isocenter_field(text, s.data.volume(s.settings.volume_format_cm))
        s.set_isocenter(iso, source)
        self.sync_controls()
        self.show_isocenter()
        self._tell_panels()
        self.message(
            f"Iso-center set to ({iso[0]:.2f}, {iso[1]:.2f}, {iso[2]:.2f}) mm, from {source}: the image is placed "
            "about it and the roadmap restarts from the sensor pose. Press **Register**."
        )

    # ----- registration -----------------------------------------------------------------
    def start_registration(self, *, trigger: str = "Register", client: str = "") -> bool:
        """Start a registration (``trigger``: "Register" or "Auto-correct", told in the status line)."""
        self.autocorrect_due = None
        started = self.session.start_registration(on_done=self.wake, trigger=trigger)
        self._registration_client = client
        audit.record("registration", client=client, result=f"started ({trigger})" if started else "not started",
                     **self._data_uids())  # fmt: skip
        if started:
            self.set_running_ui(True)
            auto = trigger == "Auto-correct"
            self.message("Auto-correct: the patient moved; registering…" if auto else "Registering…")
        return started

    def set_running_ui(self, running: bool) -> None:
        ui = self.layout
        self.ui_running = running
        fixed_geometry = self.session.data.fixed_xray is not None  # the user's image sets the C-arm
        for control in ui.carm_controls:
            control.disabled = running or fixed_geometry
        for control in ui.motion_controls:
            control.disabled = running
        self._enable_isocenter(running)
        ui.register_button.disabled = running
        ui.stop_button.disabled = not running

    def tick(self, now: float, drawn: bool = True) -> None:
        """Called by the presenter after each frame (``drawn``: the session's current state is on
        screen): the controls follow a run that ended, the status line tells its outcome once,
        with the frame that shows it, and a due Auto-correct starts."""
        if not self.session.running and self.ui_running:
            self.set_running_ui(False)
        if drawn:
            self._announce_outcome()
            if self._preparing:
                self._preparing = False
                fmt = self.session.settings.volume_format_cm
                what = "your volume" if self.session.data.fixed_xray is not None else f"the {fmt:g} cm volume"
                self.message(f"Ready: {what} and its surfaces are loaded.")
        due = self.autocorrect_due
        if due is not None and now >= due and self.layout.autocorrect.value and not self.session.running:
            self.autocorrect_due = None
            self.start_registration(trigger="Auto-correct")

    def _announce_outcome(self) -> None:
        """Tell a registration's outcome (applied, withheld, stopped, failed) in the status line,
        once per run, in the words of the badge (:func:`app.web.status.run_outcome`)."""
        s = self.session
        with s.lock:
            run = s.run
            if run is self._announced or run.running:
                return
            self._announced = run
            if run.result is None and run.error is None and not run.abandoned:
                return  # a fresh state (the patient moved, new data): nothing ran
            residual = s.residual() if s.has_truth else None
            text, error = status.run_outcome(run, residual, biplane=s.graded_biplane)
            if getattr(run, "skull_spine", None) is not None:
                text += f" · {run.skull_spine.message()}"
        self.message(text, error=error)
        assessment = getattr(run, "assessment", None)
        if run.abandoned or (run.result is not None and getattr(run.result, "stopped", False)):
            outcome = "stopped"
        elif run.error is not None or run.result is None:
            outcome = "failed"
        elif assessment is not None:
            outcome = "applied" if assessment["applied"] else "withheld"
        else:
            outcome = "applied"  # without an assessment the roadmap takes the estimate
        audit.record("correction", client=getattr(self, "_registration_client", ""),
                     result=f"{outcome}: {re.sub(r'[*_`]', '', text)[:200]}", **self._data_uids())  # fmt: skip

    def preparing(self, text: str) -> None:
        """A later preparation (another volume format) reports here; once its frame is drawn the
        status line says it is ready."""
        self._preparing = True
        self.message(f"{text}…")

    def message(self, text: str, *, error: bool = False) -> None:
        self.layout.status.content = f"<span style='color:#ff6b6b'>⚠ {text}</span>" if error else text
        if error:
            for client in list(self.server.get_clients().values()):
                try:
                    client.add_notification("Cannot do that", text, color="red", auto_close_seconds=6.0)
                except Exception:  # a tab closing right now
                    pass
