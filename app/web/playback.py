"""The "Play run" panel: a fluoroscopy run played at its frame times, the roadmap following.

A simulated run of the phantom (:mod:`registration.sim.fluoro`: still periods, drift, sudden
moves, breathing, a guidewire advancing; honest images) is played at its real frame times while
the tracker (:class:`registration.core.tracking.Tracker`) follows the patient. Each shown frame
carries the roadmap (the vessel outline at the last applied pose) and the product's message on
top of the image ("motion corrected 3.2 mm, 1.1°", "motion detected, correction withheld"), and
the 3-D scene follows it (the volume's surfaces at that pose, the run's C-arm with the frame on
its detector, the true pose as the ghost: :class:`app.web.presenter.FollowedPose`); a strip chart
shows the estimated (shown) and true motion and the per-frame latency. Frames that arrive
while the engine is busy are skipped (the picture always shows the newest frame).

In Biplane mode the phantom's run has both planes (plane B at the C-arm tab's plane B angles),
tracked together; both frames are shown side by side and both C-arms follow in the scene.

Play, Pause and Stop control one shared playback: every browser tab watches the same run
(the panel's widgets are server-level). The work runs on the panel's own thread. "Upload a
run (.dcm)" plays the user's multi-frame XA/RF run (read with its frame times by
:func:`registration.io.dicom.read_xray_run`, then the temporary file is deleted) against the
session's current volume, about the iso-center a registration of that data uses (the data's:
``--isocenter``, the volume's IsocenterPosition, the Data tab's field); it has no truth, so the
strip chart shows the roadmap's motion only.
A multi-frame run the app's DICOM node receives (``roadmap3d app --listen-port P --allow AE``)
becomes the run to play the same way, read in the same sandbox (:meth:`PlaybackPanel.load_run_file`, wired
in :mod:`app.web.gui`).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import viser

from app.web import views
from app.web.panels import BasePanel, PanelContext
from app.web.presenter import FollowedPose
from app.web.run_chart import ChartSeries, motion_chart
from app.web.status import corrected_text, correction
from registration.core.blas import one_blas_thread
from registration.core.geometry import CArm

if TYPE_CHECKING:
    from registration.core.tracking import FrameEstimate

log = logging.getLogger(__name__)

#: Size of the shown frame (pixels).
DISPLAY_PX = 384
#: What the tab says before the phantom's run plays.
PHANTOM_RUN_TEXT = "A 20 s fluoroscopy run of the phantom (both planes in Biplane mode): press **Play**."
#: Size of the frame on the 3-D scene's detector (pixels, as the Roadmap tab's).
DETECTOR_PX = 256
#: Message colours (as the Roadmap tab's badge).
GREEN, ORANGE, GRAY = (64, 192, 87), (253, 126, 20), (134, 142, 150)


def motion_message(est: FrameEstimate, previous: np.ndarray, geometry: CArm) -> tuple[str, tuple[int, int, int]]:
    """The product's message for one frame and its colour (the words of :mod:`app.web.status`)."""
    if est.status == "applied":
        return corrected_text(*correction(previous, est.patient_motion, geometry.isocenter_mm)), GREEN
    if est.status == "withheld":
        return "motion detected, correction withheld", ORANGE
    return "no motion", GRAY


def draw_message(rgb: np.ndarray, text: str, color: tuple[int, int, int]) -> np.ndarray:
    """The message on a coloured strip across the top of the image (in place). OpenCV's font
    has no degree sign: it is drawn as 'deg'."""
    h = max(22, rgb.shape[0] // 14)
    rgb[:h] = (0.35 * rgb[:h] + 0.65 * np.array(color)).astype(np.uint8)
    scale = h / 34.0
    cv2.putText(rgb, text.replace("°", " deg"), (8, int(h * 0.72)), cv2.FONT_HERSHEY_SIMPLEX, scale,
                (255, 255, 255), 1, cv2.LINE_AA)  # fmt: skip
    return rgb


def waiting_tile(text: str = "Press Play: the run's frames appear here") -> np.ndarray:
    """The Play run tile before a run plays: the app's dark panel with a line of text."""
    rgb = np.full((DISPLAY_PX, DISPLAY_PX, 3), views.PANEL_RGB, np.uint8)
    cv2.putText(rgb, text, (16, DISPLAY_PX // 2), cv2.FONT_HERSHEY_SIMPLEX, 0.5, views.PANEL_TEXT_RGB, 1, cv2.LINE_AA)
    return rgb


class UploadedRun:
    """A run read from the user's file: its frames, times and geometry (no truth)."""

    truth = None

    def __init__(self, frames: list, times_s: np.ndarray, geometry: CArm, name: str) -> None:
        self.frames, self.times_s, self.geometry, self.name = frames, times_s, geometry, name

    def about(self, isocenter_mm: tuple[float, float, float]) -> UploadedRun:
        """The run with every frame's C-arm placed about ``isocenter_mm`` (mm, world): what
        :func:`registration.io.dicom.read_xray_run` gives with that iso-center (the file does not
        state it; the reader places the frames about the world origin unless told)."""
        iso = tuple(float(v) for v in isocenter_mm)
        frames = [
            dataclasses.replace(f, geometry=dataclasses.replace(f.geometry, isocenter_mm=iso)) for f in self.frames
        ]
        return UploadedRun(frames, self.times_s, frames[0].geometry, self.name)

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, n: int) -> Any:
        return self.frames[n]


class PlaybackPanel(BasePanel):
    """The Play run tab (left) with its controls."""

    def __init__(self, ctx: PanelContext) -> None:
        self.ctx = ctx
        gui = ctx.server.gui
        with ctx.layout.view_tab("Play run", viser.Icon.PLAYER_PLAY):
            self.image = gui.add_image(waiting_tile(), label=None, format="jpeg", jpeg_quality=85)
            self.message = gui.add_markdown(PHANTOM_RUN_TEXT)
            with gui.add_folder("Playback", expand_by_default=True):
                self.play_button = gui.add_button("Play", color="green", icon=viser.Icon.PLAYER_PLAY)
                self.pause_button = gui.add_button("Pause", icon=viser.Icon.PLAYER_PAUSE, disabled=True)
                self.stop_button = gui.add_button("Stop", color="red", icon=viser.Icon.PLAYER_STOP, disabled=True)
                self.run_upload = gui.add_upload_button(
                    "Upload a run (.dcm)",
                    icon=viser.Icon.UPLOAD,
                    hint="A multi-frame XA/RF run with frame times, tracked against the current volume (no truth)",
                )
                self.phantom_run_button = gui.add_button("Back to the phantom's run", visible=False)
                self.report_button = gui.add_button(
                    "Write run report", icon=viser.Icon.FILE_ANALYTICS, disabled=True,
                    hint="The last played run as a report folder: strip charts, per-frame decisions, the last frame",
                )  # fmt: skip
            self.stats = gui.add_markdown("")
            self.chart = motion_chart(gui)
        self.play_button.on_click(ctx.guarded(lambda _e: self.play()))
        self.pause_button.on_click(ctx.guarded(lambda _e: self.toggle_pause()))
        self.stop_button.on_click(ctx.guarded(lambda _e: self.stop()))
        self.run_upload.on_upload(ctx.guarded(lambda _e: self.load_run(self.run_upload.value.name,
                                                                        self.run_upload.value.content)))  # fmt: skip
        self.phantom_run_button.on_click(ctx.guarded(lambda _e: self.use_phantom_run()))
        self.report_button.on_click(ctx.guarded(lambda _e: self.write_report()))
        #: What the last played run's report needs (runs, volume, renderer, vessels, skipped frames).
        self._played: dict[str, Any] | None = None
        #: The last run report written (tests, the status line).
        self.last_report: Any = None
        self._report_thread: threading.Thread | None = None
        #: An uploaded run (frames decoded, times, label) played instead of the phantom's.
        self.user_run: UploadedRun | None = None
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._resume = threading.Event()
        self._resume.set()
        #: The run to play (a :class:`~registration.studies.tracking.TrackingCase`): the quick
        #: study's 20 s run of the phantom; tests set a shorter one.
        from registration.studies.tracking import TrackingConfig

        self.case = TrackingConfig.quick_config().cases[0]
        #: What the playback did (tests and scripts read it).
        self.frames_shown = 0
        self.skipped = 0
        self.estimates: list[FrameEstimate] = []
        #: How many planes the last run played had (1, or 2 for a biplane run).
        self.planes = 0
        self.last_message = ""
        #: The last correction or withholding told in the status line ("frame 65 at 4.33 s: ...").
        self.last_told = ""
        self.finished = threading.Event()
        self._source: tuple[Any, float] = (ctx.phantom, self.case.volume_format_cm)
        self._followed: FollowedPose | None = None  # what the 3-D scene was last asked to show

    # ----- controls ---------------------------------------------------------------------
    @property
    def playing(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def paused(self) -> bool:
        return not self._resume.is_set()

    def play(self) -> None:
        with self._lock:
            if self.playing:
                if self.paused:
                    self.toggle_pause()
                return
            self._stop.clear()
            self._resume.set()
            self.finished.clear()
            self._thread = threading.Thread(target=self._run_guarded, name="play-run", daemon=True)
            self._thread.start()
        self._buttons(playing=True)
        what = "the phantom's run"
        if self.user_run is not None:
            iso = self.ctx.session.geometry().isocenter_mm
            what = f"the run {self.user_run.name} about the iso-center ({iso[0]:.2f}, {iso[1]:.2f}, {iso[2]:.2f}) mm"
        self.ctx.message(f"Play run: playing {what}, the roadmap follows it (Play run tab).")

    def toggle_pause(self) -> None:
        if not self.playing:
            return
        if self._resume.is_set():
            self._resume.clear()
            self.pause_button.label = "Resume"
        else:
            self._resume.set()
            self.pause_button.label = "Pause"

    def stop(self) -> None:
        self._stop.set()
        self._resume.set()

    def close(self) -> None:
        self.stop()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        if self._report_thread is not None:
            self._report_thread.join(timeout=30.0)

    # ----- the run's report -------------------------------------------------------------
    def write_report(self) -> None:
        """Write the last played run's report on a thread; the status line says where."""
        if self.playing:
            raise ValueError("Stop the run first: the report is of a finished run")
        if self._played is None or not self._played["estimates"]:
            raise ValueError("Play a run first: the report is of the last played run")
        if self._report_thread is not None and self._report_thread.is_alive():
            raise ValueError("A report is being written")
        self.ctx.message("Writing the run's report…")
        self._report_thread = threading.Thread(target=self._write_report, args=(self._played,), name="run-report",
                                               daemon=True)  # fmt: skip
        self._report_thread.start()

    def _write_report(self, played: dict[str, Any]) -> None:
        from datetime import UTC, datetime

        from app.web.qa_panel import reports_folder
        from registration.core.tracking import TrackingRun
        from registration.studies import qa_report, qa_track

        try:
            runs, estimates = played["runs"], played["estimates"]
            last = estimates[-1].frame
            tracked = TrackingRun(list(estimates), list(played["skipped"]), len(runs[0]), played["volume"].label,
                                  len(runs))  # fmt: skip
            document = tracked.to_dict()
            truth = getattr(runs[0], "truth", None)
            anatomy = qa_report.Anatomy(played["vertices"], played["spacing"]) if len(played["vertices"]) else None
            out = reports_folder() / f"run-{datetime.now(UTC).strftime('%Y%m%d-%H%M%S-%f')}"
            qa_track.write_track_report(
                out, document=document, volume=played["volume"], last_views=[r[last] for r in runs],
                renderer=played["renderer"], truth=None if truth is None else np.asarray(truth), anatomy=anatomy,
                command="roadmap3d demo: Play run, Write run report",
            )  # fmt: skip
        except Exception as exc:  # noqa: BLE001 - said in the page
            log.exception("run report failed")
            self.ctx.message(f"The run's report could not be written: {exc}", error=True)
            return
        self.last_report = out
        self.ctx.message(f"Run report written: {out / qa_report.REPORT_HTML}")

    def _buttons(self, *, playing: bool) -> None:
        self.play_button.disabled = playing
        self.pause_button.disabled = not playing
        self.stop_button.disabled = not playing
        self.report_button.disabled = playing or self._played is None
        if not playing:
            self.pause_button.label = "Pause"

    # ----- the run ----------------------------------------------------------------------
    def play_case(self) -> Any:
        """The phantom's run to play: :attr:`case`, with plane B at the C-arm tab's plane B angles
        when the app is in Biplane mode (both planes' runs, tracked together)."""
        st = self.ctx.session.settings
        if not self.ctx.session.biplane or self.case.plane_b_deg is not None:
            return self.case
        return dataclasses.replace(self.case, name=f"{self.case.name}-biplane",
                                   plane_b_deg=(float(st.primary_b_deg), float(st.secondary_b_deg)))  # fmt: skip

    def _load(self) -> tuple[list[Any], Any, Any, np.ndarray, float]:
        """The run's planes (one, or plane A and B; simulated once, cached on disk), the volume, its
        renderer, vessel vertices and their spacing; ``self._source`` becomes the data source and
        volume format they come from."""
        from registration.studies.tracking import case_runs

        if self.user_run is not None:
            session = self.ctx.session
            data = session.data
            fmt = session.settings.volume_format_cm
            # About the iso-center a single registration of this data uses (the data's: --isocenter,
            # the volume's IsocenterPosition, the Data tab; the phantom's world origin), as
            # ``roadmap3d track`` reads a run: the tracker, the messages and the chart read it there.
            run = self.user_run.about(session.geometry().isocenter_mm)
            vessels = data.meshes(fmt).get("vessels")
            vertices = np.zeros((0, 3)) if vessels is None else np.asarray(vessels.vertices)
            self._source = (data, fmt)
            # the user's volume prepared for the run's own field (its angles may not be the image's)
            renderer = data.renderer(fmt, views=[run[0]])
            return [run], data.volume(fmt), renderer, vertices, data.mesh_spacing_mm(fmt)
        case = self.play_case()
        start = time.perf_counter()

        def progress(done: int, total: int) -> None:
            if done % 15 == 0:
                self.message.content = (
                    f"Simulating the run's X-ray images: {done} of {total}, every plane's "
                    f"({time.perf_counter() - start:.0f} s so far; once, then cached)"
                )

        self.message.content = "Loading the run ..."
        runs = case_runs(case, progress=progress)
        phantom = self.ctx.phantom
        volume = phantom.volume(case.volume_format_cm)
        renderer = phantom.renderer(case.volume_format_cm)
        vessels = phantom.meshes(case.volume_format_cm).get("vessels")
        vertices = np.zeros((0, 3)) if vessels is None else np.asarray(vessels.vertices)
        self._source = (phantom, case.volume_format_cm)
        return list(runs), volume, renderer, vertices, phantom.mesh_spacing_mm(case.volume_format_cm)

    def load_run(self, name: str, content: bytes) -> bool:
        """Read an uploaded run (multi-frame XA/RF with frame times) in the upload sandbox (a
        separate process with capped memory and a time limit, as the Data tab's uploads); a
        refusal is a message in the page naming the file."""
        return self._read(name, content=content)

    def load_run_file(self, path: Any, name: str) -> bool:
        """Read a run from a file (one the app's DICOM node received) as the run to play, in the
        upload sandbox; a refusal is a message in the page."""
        from pathlib import Path

        return self._read(name, path=Path(path))

    def _read(self, name: str, *, content: bytes | None = None, path: Any = None) -> bool:
        from app.web.upload import read_run_upload

        if self.playing:
            raise ValueError("stop the run playing first")
        size = f" ({len(content) / 1e6:.1f} MB)" if content is not None else ""
        self.message.content = f"Reading the run **{name}**{size}…"
        try:
            run = read_run_upload(name, content=content, path=path, max_bytes=self.ctx.max_upload_bytes)
        except ValueError as exc:  # UploadError, DicomError: named, the run shown before stays
            text = str(exc) if str(exc).startswith(name) else f"{name}: {exc}"
            self.message.content = f"⚠ Run refused: {text}"
            self.ctx.message(f"Run refused: {text}", error=True)
            return False
        frames = run.frames
        self.user_run = UploadedRun(frames, run.times_s, frames[0].geometry, name)
        span = float(run.times_s[-1] - run.times_s[0])
        self.message.content = (
            f"Run **{name}**: {len(frames)} frames over {span:.1f} s ({run.times_from}); tracked against the "
            "current volume, no truth. Press **Play**."
        )
        self.phantom_run_button.visible = True
        return True

    def use_phantom_run(self) -> None:
        if self.playing:
            raise ValueError("stop the run playing first")
        self.user_run = None
        self.phantom_run_button.visible = False
        self.message.content = PHANTOM_RUN_TEXT

    def _run_guarded(self) -> None:
        try:
            self._run()
        except Exception as exc:  # noqa: BLE001 - shown in the page, logged with its traceback
            log.exception("play run failed")
            self.ctx.message(f"Play run failed: {exc}", error=True)
        finally:
            last = self._followed
            # the 3-D scene keeps the run's last frame until the session changes
            self.ctx.follow(None if last is None else dataclasses.replace(last, playing=False))
            self._buttons(playing=False)
            self.finished.set()

    def _run(self) -> None:
        from registration.core.tracking import Tracker

        runs, volume, renderer, vertices, spacing = self._load()
        run = runs[0]  # plane A: its times, truth and view frame

        def views_of(n: int) -> Any:  # one image per plane, taken at the same moment
            return [r[n] for r in runs] if len(runs) > 1 else run[n]

        geometry = run.geometry
        times = run.times_s
        n = len(run)
        self.frames_shown, self.skipped, self.estimates = 0, 0, []
        skipped: list[int] = []
        self._played = None
        self.last_told = ""
        self._followed = None
        self.planes = len(runs)
        chart = ChartSeries(self.chart)
        # BLAS on one thread while frames are tracked (registration.core.blas)
        with Tracker(volume, renderer=renderer) as tracker, one_blas_thread():
            tracker.warm_up(views_of(0))
            shown = tracker.shown_pose
            paused_s = 0.0
            t0 = time.perf_counter()
            i = 0
            while i < n and not self._stop.is_set():
                if not self._resume.is_set():
                    p0 = time.perf_counter()
                    self._resume.wait()
                    paused_s += time.perf_counter() - p0
                    continue
                run_time = time.perf_counter() - t0 - paused_s
                if run_time < times[i] - times[0]:
                    self._stop.wait(min(0.05, times[i] - times[0] - run_time))
                    continue
                newest = int(np.searchsorted(times - times[0], run_time, side="right")) - 1
                if newest > i:  # frames that arrived while busy: skipped, never queued
                    self.skipped += newest - i
                    skipped.extend(range(i, newest))
                    i = newest
                est = tracker.process(views_of(i), frame=i, t_s=float(times[i] - times[0]))
                self.estimates.append(est)
                text, color = motion_message(est, shown, geometry)
                shown = est.patient_motion
                self._show_frame(runs, i, est, text, color, vertices, spacing)
                truth = getattr(run, "truth", None)
                chart.add(est, shown, None if truth is None else truth[i], geometry, last=i == n - 1)
                i += 1
        chart.show()
        self._played = {"runs": runs, "volume": volume, "renderer": renderer, "vertices": np.asarray(vertices),
                        "spacing": float(spacing), "skipped": skipped, "estimates": list(self.estimates)}  # fmt: skip
        applied = sum(e.status == "applied" for e in self.estimates)
        withheld = sum(e.status == "withheld" for e in self.estimates)
        self.stats.content = (
            f"{'Stopped' if self._stop.is_set() else 'Finished'}: {self.frames_shown} frames shown, "
            f"{self.skipped} skipped (arrived while busy); {applied} corrections applied, {withheld} withheld."
        )
        last = f" Last: {self.last_told}." if self.last_told else ""
        self.ctx.message(f"Play run {self.stats.content[0].lower()}{self.stats.content[1:]}{last}")

    def _show_frame(self, runs: list[Any], i: int, est: FrameEstimate, text: str, color: tuple[int, int, int],
                    vertices: np.ndarray, spacing: float) -> None:  # fmt: skip
        planes = []  # each plane's frame with the roadmap outline at the shown pose
        for p, run in enumerate(runs):
            image = run[i]
            rgb = views.gray_rgb(views.resize(views.to_gray(image.image, image.mask), DISPLAY_PX))
            if len(vertices):
                view = image.geometry.resized(DISPLAY_PX, DISPLAY_PX)
                views.draw_outline(rgb, views.vessel_silhouette(vertices, est.patient_motion, view, spacing))
            if len(runs) > 1:
                views.label(rgb, f"PLANE {'AB'[p]}", corner="bottom-right")
            planes.append((image.geometry, rgb))
        picture = views.side_by_side(*(rgb for _, rgb in planes)) if len(planes) > 1 else planes[0][1].copy()
        draw_message(picture, text, color)
        views.label(picture, f"t = {est.t_s:5.2f} s  frame {i}  {est.latency_ms:.0f} ms", corner="bottom-left")
        self.image.image = picture
        # The 3-D scene follows: the volume's surfaces at the pose the roadmap shows (the last
        # applied one), the run's C-arm(s) with this frame on the detector, the true pose as the ghost.
        truth = getattr(runs[0], "truth", None)
        data, fmt = self._source
        geometry_b, rgb_b = planes[1] if len(planes) > 1 else (None, None)
        self._followed = FollowedPose(
            frame=i, patient_motion=np.array(est.patient_motion, np.float64),
            truth=None if truth is None else np.array(truth[i], np.float64), geometry=planes[0][0],
            detector_image=views.resize(planes[0][1], DETECTOR_PX), data=data, volume_format_cm=fmt,
            geometry_b=geometry_b, detector_image_b=None if rgb_b is None else views.resize(rgb_b, DETECTOR_PX),
        )  # fmt: skip
        self.ctx.follow(self._followed)
        run = runs[0]
        self.last_message = text
        if est.status in ("applied", "withheld"):  # an event: the status line tells it (not every frame)
            why = f" ({est.reason})" if est.status == "withheld" and est.reason else ""
            self.last_told = f"frame {i} at {est.t_s:.2f} s: {text}{why}"
            self.ctx.message(f"Play run, {self.last_told}.")
        self.message.content = (
            f"**{text}** · frame {i}/{len(run) - 1} at {est.t_s:.2f} s · {est.path} {est.latency_ms:.0f} ms"
            + (f" · confidence {est.confidence:.2f}" if est.confidence is not None else "")
            + (f" · {est.reason}" if est.reason else "")
        )
        self.frames_shown += 1
