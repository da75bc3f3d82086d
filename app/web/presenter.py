"""The presenter: one thread that turns the session's state into pictures, scene poses and text.

It watches :attr:`Session.version` and the run's progress and redraws at up to
:data:`LIVE_HZ`, so slow work (re-forming an X-ray image) never blocks a callback and a
fast-moving slider only costs the latest frame. Everything it shows goes to the widgets of
the :class:`~app.web.layout.Layout` and to the :class:`~app.web.scene.Scene`, batched in one
``server.atomic()`` block per frame.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from app.web import status, views
from app.web.layout import Layout, badge
from app.web.plane_pictures import PlanePictures
from app.web.scene import Scene
from app.web.session import Session
from registration.core.geometry import CArm, matrix_to_offsets
from registration.io.meshes import NO_VESSELS_NOTE

if TYPE_CHECKING:
    import viser

    from app.web.data import DataSource
    from app.web.panels import Panel
    from app.web.qa_panel import ComparePanel, CompareSettings

log = logging.getLogger(__name__)

#: Live updates during a run (at least 5 per second).
LIVE_HZ = 10.0


@dataclass(frozen=True, eq=False)
class FollowedPose:
    """What the 3-D scene shows while a fluoroscopy run plays (the Play run panel), instead of the
    session: the anatomy of the volume the run is tracked against, at the pose the roadmap shows
    for the newest frame (the last applied one: a withheld frame changes nothing), the run's
    C-arm with that frame on its detector, and the frame's true pose as the ghost (None: no truth).
    After the run (``playing`` False) the scene keeps its last frame until the session changes.
    """

    frame: int
    patient_motion: np.ndarray
    truth: np.ndarray | None
    geometry: CArm
    detector_image: np.ndarray | None
    data: DataSource
    volume_format_cm: float
    #: Plane B's C-arm and frame of a biplane run (None: one plane; the session's plane B stays).
    geometry_b: CArm | None = None
    detector_image_b: np.ndarray | None = None
    #: False once the run ended: the scene keeps this frame until the session changes.
    playing: bool = True


class Presenter:
    """Draws the session into ``layout`` and ``scene`` on its own thread."""

    def __init__(
        self,
        server: viser.ViserServer,
        session: Session,
        layout: Layout,
        scene: Scene,
        *,
        message: Callable[..., None],
        tick: Callable[[float, bool], None],
        show_source: Callable[[], None],
    ) -> None:
        self.server = server
        self.session = session
        self.layout = layout
        self.scene = scene
        self.message = message
        #: the controller's per-frame hook (run ended, Auto-correct due); its second argument: the
        #: session's current state is on screen
        self.tick = tick
        self.show_source = show_source
        self.panels: Sequence[Panel] = ()
        #: The Compare tab (overlay mode, zoom, camera), None: the vessel outline, no zoom.
        self.compare: ComparePanel | None = None
        self._camera_key: tuple | None = None
        self._frame_request = 0
        self.shown_version = -1
        self.shown_geometry: CArm | None = None
        self.frames_shown = 0
        self.live_updates: deque[float] = deque(maxlen=10_000)  # times of live frames (tests, measurements)
        #: Which of the run's progress reports (1-based, the session's ``run.iterations``) each live
        #: frame showed, and how many reports no frame showed: the newest is drawn, older ones are
        #: skipped and counted, never queued (a slow browser or a busy machine costs frames, not lag).
        self.live_reports: deque[int] = deque(maxlen=10_000)
        self.live_skipped = 0
        self._live_run: object = None
        self._live_last_report = 0
        self._quit = threading.Event()
        self._wake = threading.Event()
        self._shown_progress: object = None
        self._last_live = 0.0
        self._mesh_key: tuple | None = None
        self._shown_carm: tuple | None = None
        self.pictures = PlanePictures(session, layout, self.settings)
        self._shown_carm_b: tuple | None = None
        self._preview_version = -1
        self._plotted = False
        self._followed: FollowedPose | None = None
        self._followed_version = -1
        self._shown_followed: FollowedPose | None = None
        #: (frame, 4x4 pose) of every followed frame the scene showed (tests, measurements).
        self.followed_frames: deque[tuple[int, np.ndarray]] = deque(maxlen=10_000)
        self._thread = threading.Thread(target=self._loop, name="presenter", daemon=True)

    # ----- control --------------------------------------------------------------------------
    def wake(self) -> None:
        self._wake.set()

    def force_refresh(self) -> None:
        """Redraw at the next frame even if the session did not change."""
        self.shown_version = -1
        self._wake.set()

    def follow(self, pose: FollowedPose | None) -> None:
        """Let the scene follow a played run's newest frame (None: back to the session). Drawn at
        the next frame (<= LIVE_HZ): a pose that is replaced before then is never drawn."""
        with self.session.lock:
            self._followed_version = self.session.version
        if pose is None and self._followed is not None:
            self._shown_carm = None  # the session's C-arm(s) come back
            self._shown_carm_b = ("run",)  # never the session's key: its plane B is drawn or removed
            self._followed = None
            self.force_refresh()
        else:
            self._followed = pose

    @property
    def followed(self) -> FollowedPose | None:
        """The played run's frame the scene follows, or None (the scene shows the session)."""
        return self._followed

    def start(self) -> None:
        self.present()  # first frame before the loop starts (and before the URL is used)
        self._thread.start()

    def stop(self) -> None:
        self._quit.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout=3.0)

    def _loop(self) -> None:
        next_tick = time.monotonic()
        while not self._quit.is_set():
            next_tick = max(next_tick + 1.0 / LIVE_HZ, time.monotonic() - 1.0 / LIVE_HZ)
            self._wake.wait(max(0.0, next_tick - time.monotonic()))
            self._wake.clear()
            if self._quit.is_set():
                break
            try:
                self.present()
            except Exception as exc:
                log.exception("presenter failed")
                self.message(f"Cannot show this: {exc}", error=True)
                with self.session.lock:
                    self.shown_version = self.session.version  # don't retry the same failure forever

    # ----- one frame --------------------------------------------------------------------------
    def present(self) -> None:
        s = self.session
        with s.lock:
            version = s.version
            run = s.run
            progress = run.progress
            running = run.running
            settings = s.settings
        now = time.monotonic()
        live = running and progress is not None and progress is not self._shown_progress
        followed = self._followed
        if followed is not None and not followed.playing and version != self._followed_version:
            self.follow(None)  # the run ended and the session changed since: the scene shows the session
            followed = None
        if version == self.shown_version and not (live and now - self._last_live >= 0.8 / LIVE_HZ):  # timer jitter
            if followed is not None and followed is not self._shown_followed:
                with self.server.atomic():
                    self._show_followed(followed)
            self.tick(now, self.shown_version == s.version)
            return
        if followed is None:
            self._show_anatomy(s.data, settings.volume_format_cm)
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
            reports = len(run.iterations or ())  # the progress read above is the newest of these
        live = running and progress is not None and progress is not self._shown_progress  # a new report is drawn
        shown = progress.best_motion if running and progress is not None else estimate
        self._show(xray, np.asarray(shown, np.float64), truth, settings.volume_format_cm, live=running)
        if not is_preview:
            self.shown_version = version  # only now: tests and the loop read it as "on screen"
        self._shown_progress = progress
        if live:
            self._last_live = now
            self.live_updates.append(now)
            self._count_live(run, reports)
        self.tick(now, self.shown_version == s.version)

    def _show_anatomy(self, data: DataSource, volume_format_cm: float) -> None:
        shown = self._mesh_key
        if shown is None or shown[0] is not data or shown[1] != volume_format_cm:
            before = self.layout.status.content
            self.message("Loading the volume and its surfaces…")
            meshes = data.meshes(volume_format_cm)
            self.scene.set_anatomy(meshes)
            self.scene.frame_anatomy()  # the camera on the vessels (every open tab too)
            self._camera_key = None
            self.layout.vessel_info.content = (
                "" if "vessels" in meshes else f"<small>⚠ {NO_VESSELS_NOTE[:1].upper() + NO_VESSELS_NOTE[1:]}.</small>"
            )
            if self.layout.status.content.startswith("Loading the volume"):
                self.layout.status.content = before  # the status stayed on "Loading…" after an upload
            self._mesh_key = (data, volume_format_cm)  # the data object itself: an id could be reused
            self.show_source()

    def _show_followed(self, followed: FollowedPose) -> None:
        """The scene at a played run's frame (inside the caller's ``server.atomic()``)."""
        self._show_anatomy(followed.data, followed.volume_format_cm)
        g = followed.geometry
        carm_key = ("run", g.primary_deg, g.secondary_deg, g.sid_mm, round(g.field_diameter_mm, 3), g.isocenter_mm)
        if self._shown_carm != carm_key:
            self.scene.set_carm(g, followed.detector_image)
            self._shown_carm = carm_key
        elif followed.detector_image is not None:
            self.scene.set_detector_image(followed.detector_image)
        gb = followed.geometry_b
        if gb is not None:
            carm_b_key = ("run", gb.primary_deg, gb.secondary_deg, gb.sid_mm, round(gb.field_diameter_mm, 3))
            if self._shown_carm_b != carm_b_key:
                self.scene.set_carm(gb, followed.detector_image_b, plane_b=True)
                self._shown_carm_b = carm_b_key
            elif followed.detector_image_b is not None:
                self.scene.set_detector_image(followed.detector_image_b, plane_b=True)
        hidden = any(panel.hides_patient for panel in self.panels)
        self.scene.place(followed.patient_motion, followed.truth,
                         show_ghost=bool(self.layout.show_ghost.value) and not hidden)  # fmt: skip
        for handle in self.scene.patient:
            handle.visible = not hidden and ("vessel" in handle.name or bool(self.layout.show_skull.value))
        self._camera(g, followed.patient_motion, self.settings())  # "view from the source" follows the run's C-arm
        self._shown_followed = followed
        self.followed_frames.append((followed.frame, followed.patient_motion))

    def _count_live(self, run: object, reports: int) -> None:
        if run is not self._live_run:  # a new registration: its reports count from 1
            self._live_run, self._live_last_report = run, 0
        self.live_skipped += max(0, reports - self._live_last_report - 1)
        self._live_last_report = reports
        self.live_reports.append(reports)

    def settings(self) -> CompareSettings:
        """The Compare tab's settings (defaults without the tab)."""
        from app.web.qa_panel import CompareSettings

        return self.compare.settings() if self.compare is not None else CompareSettings()

    def _show(
        self, xray: Any, motion: np.ndarray, truth: np.ndarray | None, volume_format: float, *, live: bool
    ) -> None:
        s, ui = self.session, self.layout
        size = s.config.display_px
        geometry: CArm = xray.geometry
        biplane = s.biplane
        xray_b = s.xray_b() if biplane else None
        initial = np.eye(4)  # the machine-based pose: the roadmap from the C-arm sensors alone (before / after, ghost)
        composite, detector_image, gradient, drr, drr_mask = self.pictures.plane(
            xray, motion, volume_format, live=live, plane="A" if biplane else "", initial=initial
        )
        detector_b = None
        if xray_b is not None:
            row_b, detector_b, _, _, _ = self.pictures.plane(
                xray_b, motion, volume_format, live=live, plane="B", initial=initial
            )
            composite = views.stacked(composite, row_b)
        if ui.show_gradients.value:
            g1 = views.label(views.gray_rgb(gradient), "gradient: image")
            g2 = views.label(views.gray_rgb(views.resize(views.gradient_image(drr, drr_mask), size)), "gradient: DRR")
            composite = views.stacked(composite, views.side_by_side(g1, g2))
        readout, badge_html, details = self._texts(motion, truth)
        with s.lock:
            run = s.run
            it = list(run.iterations or [])
            sim = list(run.similarity or [])
            temp = list(run.temperature or [])
        hidden = any(panel.hides_patient for panel in self.panels)  # e.g. the dodecahedron is imaged on its own
        followed = self._followed
        with self.server.atomic():
            self._show_carms(geometry, detector_image, xray_b, detector_b, followed)
            settings = self.settings()
            if followed is None:
                self.scene.place(motion, truth, show_ghost=bool(ui.show_ghost.value) and not hidden,
                                 initial=initial, show_initial=settings.show_initial and not hidden)  # fmt: skip
                for handle in self.scene.patient:
                    handle.visible = not hidden and ("vessel" in handle.name or bool(ui.show_skull.value))
            self._camera(geometry, motion, settings)
            ui.images.image = composite
            ui.readout.content = readout
            ui.badge.content = badge_html
            ui.details.content = details
            if it or self._plotted:
                self._plot(it, sim, temp)
        self.frames_shown += 1

    def _show_carms(
        self, geometry: CArm, detector_image: np.ndarray, xray_b: Any, detector_b: np.ndarray | None,
        followed: FollowedPose | None,
    ) -> None:  # fmt: skip
        """The C-arms and their detector pictures in the 3-D scene (inside ``server.atomic()``): a
        played run owns the scene (after a one-plane run plane B stays the session's)."""
        # the iso-center too: a CT's is moved in the Data tab, and the C-arm and its marker follow it
        carm_key = (geometry.primary_deg, geometry.secondary_deg, geometry.sid_mm, round(geometry.field_diameter_mm, 3),
                    geometry.isocenter_mm)  # fmt: skip
        carm_b_key = None if xray_b is None else (xray_b.geometry.primary_deg, xray_b.geometry.secondary_deg)
        if followed is not None:
            self._show_followed(followed)
        elif self._shown_carm != carm_key:
            self.scene.set_carm(geometry, detector_image)
            self._shown_carm = carm_key
            self.shown_geometry = geometry
        else:
            self.scene.set_detector_image(detector_image)
        if followed is not None and followed.geometry_b is not None:
            return  # a biplane run owns plane B's C-arm too
        if carm_b_key != self._shown_carm_b:
            if xray_b is None:
                self.scene.remove_plane_b()
            else:
                self.scene.set_carm(xray_b.geometry, detector_b, plane_b=True)
            self._shown_carm_b = carm_b_key
        elif xray_b is not None:
            self.scene.set_detector_image(detector_b, plane_b=True)

    def _camera(self, geometry: CArm, motion: np.ndarray, settings: CompareSettings) -> None:
        """View from the source (following the C-arm), or back on the vessels when it is switched
        off or "Frame the vessels" was asked for (inside the caller's ``server.atomic()``)."""
        if settings.frame_request != self._frame_request:
            self._frame_request = settings.frame_request
            self.scene.frame_anatomy(motion)
        key = None
        if settings.view_from_source:
            key = (geometry.primary_deg, geometry.secondary_deg, geometry.sid_mm, geometry.isocenter_mm)
        if key != self._camera_key:
            if key is not None:
                self.scene.view_from_source(geometry)
            elif self._camera_key is not None:
                self.scene.frame_anatomy(motion)
            self._camera_key = key

    def _plot(self, it: list[int], sim: list[float], temp: list[float]) -> None:
        n = min(len(it), len(sim), len(temp))
        sim_arr = np.asarray(sim[:n], np.float64)
        sim_arr[~np.isfinite(sim_arr)] = np.nan
        temp_arr = np.asarray(temp[:n], np.float64)
        log_temp = np.full(n, np.nan)  # the final polish has no temperature: a gap, not a cliff
        log_temp[temp_arr > 0] = np.log10(temp_arr[temp_arr > 0])
        if n == 0:  # a new patient position: clear the last run's curves
            self.layout.plot.data = (np.zeros(1), np.full(1, np.nan), np.full(1, np.nan))
        else:
            self.layout.plot.data = (np.asarray(it[:n], np.float64), sim_arr, log_temp)
        self._plotted = n > 0

    def _texts(self, motion: np.ndarray, truth: np.ndarray | None) -> tuple[str, str, str]:
        s = self.session
        residual = s.residual(motion)
        with s.lock:
            run = s.run
            progress, result, running, error = run.progress, run.result, run.running, run.error
            assessment = run.assessment
            badge_text, badge_color = status.badge_state(run, residual, biplane=s.graded_biplane)
        if residual is None:
            o = matrix_to_offsets(motion, s.geometry())
            readout = (
                f"**Roadmap offset: {', '.join(status.signed(v, 2) for v in o[:3])} mm; "
                f"{', '.join(status.signed(v, 2) for v in o[3:])}°** (no ground truth for your data)"
            )
        elif s.graded_biplane:  # six offsets: the whole (3-D) translation counts, tz along plane A's beam too
            readout = (
                f"**{residual.readout()}** · out-of-plane {abs(residual.outofplane_mm):.2f} mm "
                "(along plane A's beam, seen by plane B)"
            )
        else:
            readout = f"**{residual.readout()}**"
        badge_html = badge(badge_text, badge_color)
        lines = []
        if running and progress is not None:
            lines.append(
                f"Time {progress.elapsed_s:.1f} s · {progress.drr_count} DRRs · "
                f"level {progress.level} · T = {progress.temperature:.3g}"
            )
        elif result is not None:
            how = "stopped" if result.stopped else "done"
            twice = " · searched again from the image shift" if getattr(result, "second_search", "") else ""
            if getattr(result, "held_by_landmarks", ""):
                twice += " · searched again near the landmarks"
            if getattr(result, "translation_first", False):
                twice += " · the translation-first candidate kept"
            if getattr(result, "fine_polished", False):
                twice += " · polished at full resolution"
            restart = getattr(result, "beam_restart", None)
            if restart is not None and restart.measure_again is not None:
                twice += " · searched again along the beam" + (" (kept)" if restart.kept else "")
            lines.append(f"Time {result.seconds:.2f} s · {result.drr_count} DRRs · {how}{twice}")
            if assessment is not None and assessment["applied"]:
                lines.append(f"Confidence {assessment['confidence']:.2f}: applied")
            elif assessment is not None:
                lines.append(
                    f"Confidence {assessment['confidence']:.2f}: withheld ({assessment['withheld_reason']}); "
                    "the roadmap keeps its pose"
                )
        elif run.abandoned:
            lines.append("Stopped before the first iteration.")
        else:
            lines.append("Roadmap from the C-arm sensors (machine-based registration).")
        if error:
            lines.append(f"<span style='color:#ff6b6b'>⚠ {error}</span>")
        return readout, badge_html, "  \n".join(lines)
