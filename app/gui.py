"""The viser adapter: panels, controls and the presenter that keeps every tab up to date.

The session is **shared**: every browser tab shows and controls the same patient, C-arm and
registration (server-level GUI and scene). Callbacks only change the :class:`Session`; a single
presenter thread turns its state into pictures, scene poses and text at up to 10 Hz, so slow
work (re-forming an X-ray image) never blocks a callback and a fast-moving slider only costs
the latest frame.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from functools import wraps
from typing import Any

import numpy as np
import viser

from app import views
from app.calibration import CalibrationView
from app.data import PhantomData
from app.scene import Scene
from app.session import ROTATION_RANGE_DEG, TRANSLATION_RANGE_MM, Session
from app.upload import limit_uploads
from registration.core.geometry import (
    IMAGE_FORMATS_CM,
    OFFSET_NAMES,
    TABLE_I,
    CArm,
    clinically_relevant,
    matrix_to_offsets,
)

log = logging.getLogger(__name__)

#: Live updates during a run (the issue asks for at least 5 per second).
LIVE_HZ = 10.0
#: Auto-correct waits this long after the last patient movement before re-registering.
AUTOCORRECT_DELAY_S = 0.6

FORMAT_OPTIONS = tuple(f"{f:g} cm" for f in IMAGE_FORMATS_CM)
OFFSET_LABELS = {
    "tx": "tx (mm)",
    "ty": "ty (mm)",
    "tz": "tz (mm)",
    "rx": "rx (°)",
    "ry": "ry (°)",
    "rz": "rz (°)",
}


def _format_cm(option: str) -> float:
    return float(option.split()[0])


def _badge(text: str, color: str) -> str:
    return (
        f'<div style="display:flex;justify-content:flex-start;padding:2px 0 4px 0">'
        f'<span style="background:{color};color:#fff;font-weight:600;letter-spacing:0.04em;'
        f'padding:3px 10px;border-radius:4px;font-size:0.82em">{text}</span></div>'
    )


class RoadmapApp:
    """Builds the GUI on ``server`` for ``session`` and runs the presenter thread."""

    def __init__(
        self,
        server: viser.ViserServer,
        session: Session,
        *,
        phantom: PhantomData | None = None,
        max_upload_mb: float = 512.0,
    ) -> None:
        self.server = server
        self.session = session
        self.max_upload_bytes = int(max_upload_mb * 1e6)
        self._phantom_data = phantom if phantom is not None else session.data
        self.gui = server.gui
        self._sync_depth = 0
        self._sync_lock = threading.RLock()
        self._quit = threading.Event()
        self._wake = threading.Event()
        self._shown_version = -1
        self._shown_progress: object = None
        self._last_live = 0.0
        self._ui_running = False
        self._autocorrect_due: float | None = None
        self._mesh_key: tuple | None = None
        self._shown_geometry: CArm | None = None
        self._shown_carm: tuple | None = None
        self._tiles_of: object = None
        self._tiles: dict[str, np.ndarray] = {}
        self._preview_version = -1
        self.frames_shown = 0
        self._plotted = False
        self.live_updates: deque[float] = deque(maxlen=10_000)  # times of live frames (tests, measurements)

        self.scene = Scene(server)
        self._build_panels()
        self._thread = threading.Thread(target=self._present_loop, name="presenter", daemon=True)

    # ----- layout -----------------------------------------------------------------------
    def _build_panels(self) -> None:
        gui = self.gui
        gui.main_panel.dock_right()
        gui.main_panel.set_width(380)

        # Left: what the clinician looks at.
        self.view_panel = gui.add_panel()
        with self.view_panel.add_tab("Roadmap", viser.Icon.PHOTO):
            self.images = gui.add_image(np.zeros((384, 772, 3), np.uint8), label=None, format="jpeg", jpeg_quality=88)
            self.badge = gui.add_html(_badge("PREPARING", "#495057"))
            self.readout = gui.add_markdown("Residual: –")
            self.details = gui.add_markdown("")
            self.plot = gui.add_uplot(
                data=(np.zeros(1), np.full(1, np.nan), np.full(1, np.nan)),
                series=(
                    {"label": "iteration"},
                    {"label": "similarity", "stroke": "#4dabf7", "width": 2, "scale": "sim"},
                    {"label": "log10 temperature", "stroke": "#ffa94d", "width": 1.5, "scale": "temp"},
                ),
                scales={"x": {"time": False}, "sim": {"auto": True}, "temp": {"auto": True}},
                axes=(
                    {"stroke": "#adb5bd", "grid": {"stroke": "#2c2e33"}},
                    {"scale": "sim", "stroke": "#4dabf7", "grid": {"stroke": "#2c2e33"}},
                    {"scale": "temp", "side": 1, "stroke": "#ffa94d", "grid": {"show": False}},
                ),
                title="Convergence: gradient difference (best) and temperature",
                height=190,
            )
        with self.view_panel.add_tab("Calibration", viser.Icon.GRID_DOTS):
            self.calibration = CalibrationView(
                self.server,
                self._phantom_data,
                angles=self._calibration_angles,
                message=self.message,
                on_toggle=self._calibration_toggled,
            )
        self.view_panel.dock_left()
        self.view_panel.set_width(600)

        # Right: the controls.
        gui.add_markdown("**3D roadmap** · automatic patient-motion correction")
        self.volume_info = gui.add_markdown("")
        self.register_button = gui.add_button("Register", color="green", icon=viser.Icon.TARGET)
        self.stop_button = gui.add_button("Stop", color="red", icon=viser.Icon.PLAYER_STOP, disabled=True)
        self.autocorrect = gui.add_checkbox(
            "Auto-correct", False, hint="Re-register whenever the patient moves, as the product does"
        )
        self.status = gui.add_markdown("")
        tabs = gui.add_tab_group()
        with tabs.add_tab("Patient motion", viser.Icon.USER):
            self.offset_sliders = []
            for i, name in enumerate(OFFSET_NAMES):
                limit = TRANSLATION_RANGE_MM if i < 3 else ROTATION_RANGE_DEG
                self.offset_sliders.append(
                    gui.add_slider(
                        OFFSET_LABELS[name],
                        -limit,
                        limit,
                        0.1,
                        0.0,
                        hint="Patient motion in the view frame (x = image columns, y = rows, z = toward the source)",
                    )  # fmt: skip
                )
            gui.add_markdown("Table I of the paper (initial offsets):")
            self.table_buttons = {
                name: gui.add_button(name, hint=f"Table I offset {TABLE_I[name]}") for name in TABLE_I
            }
            self.random_button = gui.add_button("Random", hint="A random motion within 25 mm and 10°")
            self.reset_button = gui.add_button("Reset", hint="No patient motion; roadmap from the C-arm sensors")
        with tabs.add_tab("C-arm", viser.Icon.RADAR):
            self.primary = gui.add_slider(
                "LAO/RAO (°)", -120.0, 120.0, 1.0, 0.0, hint="Primary angle: LAO positive, RAO negative"
            )
            self.secondary = gui.add_slider(
                "CRAN/CAUD (°)", -50.0, 50.0, 1.0, 0.0, hint="Secondary angle: CRAN positive, CAUD negative"
            )
            self.sid = gui.add_slider("SID (mm)", 900.0, 1300.0, 10.0, 1200.0)
            self.image_format = gui.add_dropdown("Image format", FORMAT_OPTIONS, initial_value="27 cm")
            self.volume_format = gui.add_dropdown("Volume format", FORMAT_OPTIONS, initial_value="27 cm")
            self.kind = gui.add_dropdown("Image type", ("fluoro", "exposure"), initial_value="fluoro")
            self.contrast = gui.add_checkbox("Contrast in vessels", True)
            self.catheter = gui.add_checkbox("Catheter", False)
        with tabs.add_tab("Data", viser.Icon.DATABASE):
            self.source = gui.add_markdown("")
            self.upload = gui.add_upload_button(
                "Upload your DICOM (.zip)",
                icon=viser.Icon.UPLOAD,
                mime_type="application/zip",
                hint="A zip with a 3DRA/CT volume (series, multi-frame or .npz) and one XA/RF image",
            )
            gui.add_markdown(
                f"<small>Limit {self.max_upload_bytes / 1e6:g} MB. Unpacked into a private temporary folder, read, "
                "then deleted. Your data has no ground truth: the motion controls move the roadmap.</small>"
            )
            self.phantom_button = gui.add_button("Back to the phantom", visible=False)
        with tabs.add_tab("Display", viser.Icon.EYE):
            self.show_ghost = gui.add_checkbox("True position (ghost)", False)
            self.show_skull = gui.add_checkbox("Skull", True)
            self.show_gradients = gui.add_checkbox("Gradient images", False)

        self.carm_controls: list[Any] = [
            self.primary, self.secondary, self.sid, self.image_format, self.volume_format,
            self.kind, self.contrast, self.catheter,
        ]  # fmt: skip
        self.motion_controls: list[Any] = [
            *self.offset_sliders,
            *self.table_buttons.values(),
            self.random_button,
            self.reset_button,
        ]
        self._bind()

    # ----- callbacks --------------------------------------------------------------------
    def _guarded(self, fn: Callable[..., None]) -> Callable[..., None]:
        """Turn any failure of a callback into a message in the page (never a stack trace)."""

        @wraps(fn)
        def wrapper(*args: Any) -> None:
            try:
                fn(*args)
            except ValueError as exc:
                self.message(str(exc), error=True)
                self._sync_controls()
            except Exception as exc:
                log.exception("callback failed")
                self.message(f"Something went wrong: {exc}", error=True)
                self._sync_controls()
            self._wake.set()

        return wrapper

    def _syncing(self) -> bool:
        return self._sync_depth > 0

    def _bind(self) -> None:
        on = self._guarded

        for slider in self.offset_sliders:
            slider.on_update(on(self._on_offsets))
        for name, button in self.table_buttons.items():
            button.on_click(on(lambda _e, name=name: self._moved(lambda: self.session.apply_table_offset(name))))
        self.random_button.on_click(on(lambda _e: self._moved(self.session.random_offset)))
        self.reset_button.on_click(on(lambda _e: self._moved(self.session.reset)))
        for control in self.carm_controls:
            control.on_update(on(self._on_carm))
        self.register_button.on_click(on(lambda _e: self.start_registration()))
        self.stop_button.on_click(on(lambda _e: self.session.stop_registration()))
        for box in (self.show_ghost, self.show_skull, self.show_gradients):
            box.on_update(on(lambda _e: self._force_refresh()))
        self.autocorrect.on_update(on(lambda _e: self._on_autocorrect()))
        self.upload.on_upload(on(self._on_upload))
        self.phantom_button.on_click(on(lambda _e: self._use_data(self._phantom_data)))
        self._show_source()

        def refused(client_id: Any, text: str) -> None:
            self.message(text, error=True)

        limit_uploads(self.server, self.max_upload_bytes, refused)

    def _on_offsets(self, _event: Any) -> None:
        if self._syncing():
            return
        self.session.set_offsets([s.value for s in self.offset_sliders])
        self._patient_moved()

    def _moved(self, action: Callable[[], object]) -> None:
        action()
        self._sync_controls()
        self._patient_moved()

    def _patient_moved(self) -> None:
        if self.autocorrect.value:
            self._autocorrect_due = time.monotonic() + AUTOCORRECT_DELAY_S

    def _on_autocorrect(self) -> None:
        if self.autocorrect.value and not self.session.running:
            self._autocorrect_due = time.monotonic()

    def _on_carm(self, _event: Any) -> None:
        if self._syncing():
            return
        self.session.update_settings(
            primary_deg=float(self.primary.value),
            secondary_deg=float(self.secondary.value),
            sid_mm=float(self.sid.value),
            image_format_cm=_format_cm(self.image_format.value),
            volume_format_cm=_format_cm(self.volume_format.value),
            kind=str(self.kind.value),
            contrast=bool(self.contrast.value),
            catheter=bool(self.catheter.value),
        )
        # The patient stays put in the room: its offsets in the new view frame change.
        self._sync_controls()
        self.calibration.refresh()
        st = self.session.settings
        if not clinically_relevant(st.volume_format_cm, st.image_format_cm):
            self.message(
                "Outside the paper's clinically relevant subset (image format 15/19 cm, or a volume "
                "smaller than the image): the product keeps the machine-based registration here."
            )
        elif self.status.content.startswith("Outside"):
            self.message("Ready.")

    def _calibration_angles(self) -> tuple[float, float, float]:
        with self.session.lock:
            st = self.session.settings
        return st.primary_deg, st.secondary_deg, st.volume_format_cm

    def _calibration_toggled(self) -> None:
        self._force_refresh()
        self._wake.set()

    def _force_refresh(self) -> None:
        self._shown_version = -1

    def _sync_controls(self) -> None:
        """Show the session's state in the controls without re-triggering their callbacks."""
        s = self.session
        with self._sync_lock:
            self._sync_depth += 1
            try:
                with s.lock:
                    offsets = s.offsets()
                    st = s.settings
                for slider, value, i in zip(self.offset_sliders, offsets, range(6), strict=True):
                    limit = TRANSLATION_RANGE_MM if i < 3 else ROTATION_RANGE_DEG
                    value = float(np.clip(round(float(value), 2), -limit, limit))
                    if abs(slider.value - value) > 1e-9:
                        slider.value = value
                for control, value in (
                    (self.primary, st.primary_deg),
                    (self.secondary, st.secondary_deg),
                    (self.sid, st.sid_mm),
                    (self.image_format, f"{st.image_format_cm:g} cm"),
                    (self.volume_format, f"{st.volume_format_cm:g} cm"),
                    (self.kind, st.kind),
                    (self.contrast, st.contrast),
                    (self.catheter, st.catheter),
                ):
                    if control.value != value:
                        control.value = value
            finally:
                self._sync_depth -= 1

    # ----- the user's data ----------------------------------------------------------------
    def _on_upload(self, _event: Any) -> None:
        uploaded = self.upload.value
        self.load_upload(uploaded.name, uploaded.content)

    def load_upload(self, name: str, content: bytes) -> bool:
        """Read an uploaded zip and show it; a refusal becomes a message in the page."""
        from app.upload import read_upload

        self.message(f"Reading {name} ({len(content) / 1e6:.1f} MB)…")
        try:
            data = read_upload(name, content, max_bytes=self.max_upload_bytes, config=self.session.config)
        except ValueError as exc:  # UploadError, DicomError: say why, keep what is shown
            self.message(f"Upload refused: {exc}", error=True)
            return False
        self._use_data(data)
        self.message(f"Loaded {name}: {data.label}. Press **Register**.")
        return True

    def _use_data(self, data: Any) -> None:
        self.session.use_data(data)
        self.autocorrect.value = False
        self._sync_controls()
        self._set_running_ui(self.session.running)
        self._show_source()

    def _show_source(self) -> None:
        data = self.session.data
        label = data.volume(self.session.settings.volume_format_cm).label
        self.source.content = f"**Showing:** {data.source}  \n<small>{label}</small>"
        volume = data.volume(self.session.settings.volume_format_cm)
        fmt = "" if data.fixed_xray is not None else f"{self.session.settings.volume_format_cm:g} cm, "
        self.volume_info.content = (
            f"<small>Registration volume: {label} ({fmt}{'x'.join(str(n) for n in volume.shape)} voxels of "
            f"{float(np.mean(volume.spacing_mm)):.2f} mm)</small>"
        )
        self.phantom_button.visible = data is not self._phantom_data
        self.show_ghost.disabled = not self.session.has_truth

    # ----- registration -----------------------------------------------------------------
    def start_registration(self) -> bool:
        self._autocorrect_due = None
        started = self.session.start_registration(on_done=self._wake.set)
        if started:
            self._set_running_ui(True)
            self.message("Registering…")
        return started

    def _set_running_ui(self, running: bool) -> None:
        self._ui_running = running
        fixed_geometry = self.session.data.fixed_xray is not None  # the user's image sets the C-arm
        for control in self.carm_controls:
            control.disabled = running or fixed_geometry
        for control in self.motion_controls:
            control.disabled = running
        self.register_button.disabled = running
        self.stop_button.disabled = not running

    def message(self, text: str, *, error: bool = False) -> None:
        self.status.content = f"<span style='color:#ff6b6b'>⚠ {text}</span>" if error else text
        if error:
            for client in list(self.server.get_clients().values()):
                try:
                    client.add_notification("Cannot do that", text, color="red", auto_close_seconds=6.0)
                except Exception:  # a tab closing right now
                    pass

    # ----- the presenter ----------------------------------------------------------------
    def start(self) -> None:
        self._present()  # first frame before the loop starts (and before the URL is used)
        self._thread.start()

    def close(self) -> None:
        self.calibration.close()
        self._quit.set()
        self._wake.set()
        self.session.stop_registration(wait=True, timeout=3.0)
        if self._thread.is_alive():
            self._thread.join(timeout=3.0)

    def _present_loop(self) -> None:
        next_tick = time.monotonic()
        while not self._quit.is_set():
            next_tick = max(next_tick + 1.0 / LIVE_HZ, time.monotonic() - 1.0 / LIVE_HZ)
            self._wake.wait(max(0.0, next_tick - time.monotonic()))
            self._wake.clear()
            if self._quit.is_set():
                break
            try:
                self._present()
            except Exception as exc:
                log.exception("presenter failed")
                self.message(f"Cannot show this: {exc}", error=True)
                with self.session.lock:
                    self._shown_version = self.session.version  # don't retry the same failure forever

    def _present(self) -> None:
        s = self.session
        with s.lock:
            version = s.version
            run = s.run
            progress = run.progress
            running = run.running
            settings = s.settings
        now = time.monotonic()
        live = running and progress is not None and progress is not self._shown_progress
        if version == self._shown_version and not (live and now - self._last_live >= 0.8 / LIVE_HZ):  # timer jitter
            if not running and self._ui_running:
                self._set_running_ui(False)
            self._maybe_autocorrect(now)
            return
        mesh_key = (id(s.data), settings.volume_format_cm)
        if mesh_key != self._mesh_key:
            self.message("Loading the volume and its surfaces…")
            self.scene.set_anatomy(s.data.meshes(settings.volume_format_cm))
            self._mesh_key = mesh_key
            self._show_source()
        is_preview = not s.xray_ready() and self._preview_version != version
        if is_preview:
            # Forming the full image takes a moment: show a quick one first, then come back.
            xray = s.xray_preview()
            self._preview_version = version
            self._wake.set()
        else:
            xray = s.xray()
        with s.lock:
            estimate = s.estimate.copy()
            truth = s.true_motion.copy() if s.has_truth else None
            run = s.run
            progress = run.progress
            running = run.running
        shown = progress.best_motion if running and progress is not None else estimate
        self._show(xray, np.asarray(shown, np.float64), truth, settings.volume_format_cm, live=running)
        if not is_preview:
            self._shown_version = version  # only now: tests and the loop read it as "on screen"
        self._shown_progress = progress
        if live:
            self._last_live = now
            self.live_updates.append(now)
        if not running and self._ui_running:
            self._set_running_ui(False)
        self._maybe_autocorrect(now)

    def _maybe_autocorrect(self, now: float) -> None:
        due = self._autocorrect_due
        if due is not None and now >= due and self.autocorrect.value and not self.session.running:
            self._autocorrect_due = None
            self.start_registration()

    def _image_tiles(self, xray: Any) -> dict[str, np.ndarray]:
        """What depends on the X-ray image only, computed once per image."""
        if self._tiles_of is not xray:
            size = self.session.config.display_px
            mask_u8 = xray.mask.astype(np.uint8)
            self._tiles = {
                "fluoro": views.resize(views.to_gray(xray.image, xray.mask), size),
                "mask": views.resize(mask_u8, size).astype(bool),
                "mask_half": views.resize(mask_u8, size // 2).astype(bool),
                "mask_third": views.resize(mask_u8, size // 3).astype(bool),
                "gradient": views.resize(views.gradient_image(xray.image, xray.mask), size),
            }
            self._tiles_of = xray
        return self._tiles

    def _show(
        self, xray: Any, motion: np.ndarray, truth: np.ndarray | None, volume_format: float, *, live: bool
    ) -> None:
        s = self.session
        size = s.config.display_px
        geometry: CArm = xray.geometry
        tiles = self._image_tiles(xray)

        fluoro = views.gray_rgb(tiles["fluoro"])
        meshes = s.data.meshes(volume_format)
        vessels = meshes.get("vessels")
        if vessels is not None:
            spacing = s.data.mesh_spacing_mm(volume_format)
            silhouette = views.vessel_silhouette(
                np.asarray(vessels.vertices), motion, geometry.resized(size, size), spacing
            )
            views.draw_outline(fluoro, silhouette, thickness=1 if size <= 400 else 2)
        views.label(fluoro, f"{xray.kind.upper()}  {views.angles_text(geometry)}")
        views.label(fluoro, "red: roadmap at the estimate", corner="bottom-left")

        # The DRR thumbnail: coarser while the optimizer runs (it competes for the same cores).
        drr_px = size // 3 if live else size // 2
        drr_mask = tiles["mask_third"] if live else tiles["mask_half"]
        drr = s.data.renderer(volume_format).render(geometry.resized(drr_px, drr_px), motion, level=2 if live else 1)
        drr_gray = views.resize(views.to_gray(drr, drr_mask), size)
        drr_gray[~tiles["mask"]] = 0
        drr_tile = views.label(views.gray_rgb(drr_gray), "DRR at the estimate")
        composite = views.side_by_side(fluoro, drr_tile)
        if self.show_gradients.value:
            g1 = views.label(views.gray_rgb(tiles["gradient"]), "gradient: image")
            g2 = views.label(views.gray_rgb(views.resize(views.gradient_image(drr, drr_mask), size)), "gradient: DRR")
            composite = views.stacked(composite, views.side_by_side(g1, g2))
        carm_key = (geometry.primary_deg, geometry.secondary_deg, geometry.sid_mm, round(geometry.field_diameter_mm, 3))
        detector_image = views.resize(fluoro, 256)

        readout, badge, details = self._texts(motion, truth)
        with s.lock:
            run = s.run
            it = list(run.iterations or [])
            sim = list(run.similarity or [])
            temp = list(run.temperature or [])
        with self.server.atomic():
            if self._shown_carm != carm_key:
                self.scene.set_carm(geometry, detector_image)
                self._shown_carm = carm_key
                self._shown_geometry = geometry
            else:
                self.scene.set_detector_image(detector_image)
            calibrating = bool(self.calibration.enabled.value)  # the dodecahedron is imaged on its own
            self.scene.place(motion, truth, show_ghost=bool(self.show_ghost.value) and not calibrating)
            for handle in self.scene.patient:
                handle.visible = not calibrating and ("vessel" in handle.name or bool(self.show_skull.value))
            self.images.image = composite
            self.readout.content = readout
            self.badge.content = badge
            self.details.content = details
            if it or self._plotted:
                n = min(len(it), len(sim), len(temp))
                sim_arr = np.asarray(sim[:n], np.float64)
                sim_arr[~np.isfinite(sim_arr)] = np.nan
                temp_arr = np.asarray(temp[:n], np.float64)
                log_temp = np.full(n, np.nan)  # the final polish has no temperature: a gap, not a cliff
                log_temp[temp_arr > 0] = np.log10(temp_arr[temp_arr > 0])
                if n == 0:  # a new patient position: clear the last run's curves
                    self.plot.data = (np.zeros(1), np.full(1, np.nan), np.full(1, np.nan))
                else:
                    self.plot.data = (np.asarray(it[:n], np.float64), sim_arr, log_temp)
                self._plotted = n > 0
        self.frames_shown += 1

    def _texts(self, motion: np.ndarray, truth: np.ndarray | None) -> tuple[str, str, str]:
        s = self.session
        residual = s.residual(motion)
        with s.lock:
            run = s.run
            progress, result, running, error = run.progress, run.result, run.running, run.error
        if residual is None:
            o = matrix_to_offsets(motion, s.geometry())
            readout = (
                f"**Roadmap offset: {o[0]:+.2f}, {o[1]:+.2f}, {o[2]:+.2f} mm; "
                f"{o[3]:+.2f}, {o[4]:+.2f}, {o[5]:+.2f}°** (no ground truth for your data)"
            )
        else:
            readout = f"**{residual.readout()}**"
        if running:
            badge = _badge("REGISTERING…", "#1c7ed6")
        elif residual is None:
            badge = _badge("REGISTERED" if result is not None else "SENSOR ALIGNMENT ONLY", "#495057")
        elif residual.success:
            badge = _badge("✓ REGISTERED  (< 1 mm, < 3°)", "#2b8a3e")
        else:
            badge = _badge("✗ MISALIGNED  (≥ 1 mm or ≥ 3°)", "#c92a2a")
        lines = []
        if running and progress is not None:
            lines.append(
                f"Time {progress.elapsed_s:.1f} s · {progress.drr_count} DRRs · "
                f"level {progress.level} · T = {progress.temperature:.3g}"
            )
        elif result is not None:
            how = "stopped" if result.stopped else "done"
            lines.append(f"Time {result.seconds:.2f} s · {result.drr_count} DRRs · {how}")
            if not running and self.status.content.startswith("Registering"):
                self.status.content = "Ready."
        elif run.abandoned:
            lines.append("Stopped before the first iteration.")
        else:
            lines.append("Roadmap from the C-arm sensors (machine-based registration).")
        if error:
            lines.append(f"<span style='color:#ff6b6b'>⚠ {error}</span>")
        if self._mesh_key is not None and self.status.content.startswith("Loading"):
            self.status.content = "Ready."
        return readout, badge, "  \n".join(lines)
