"""The optional calibration view: the dodecahedron phantom, its calibration shot, the rotational run.

Off by default and free while off: nothing is computed or added to the scene until the
checkbox is ticked. Then

- the scene shows the dodecahedron (20 lead spheres at their 3-D positions around the
  iso-center, the marker sphere larger, its edges as thin lines) instead of the patient, as it
  is imaged on its own;
- the panel shows its simulated X-ray image at the current C-arm angles (the true, bent
  geometry) with the detected spheres circled, the projections the angle sensors predict
  (nominal) and those of the fitted geometry, and the errors in mm at the iso-center region
  (:func:`registration.sim.bending.machine_based_error_mm`);
- a frame slider steps through a rotational run of the head phantom (from the cache, or
  simulated at low resolution on demand with progress).

Long work runs on one worker thread that always serves the latest request.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import viser

from app.web import views
from app.web.data import PhantomData
from app.web.panels import PanelContext
from app.web.scene import M_PER_MM
from registration.core.geometry import CArm
from registration.sim.bending import default_bending, machine_based_error_mm
from registration.sim.calibration import machine_based_geometry
from registration.sim.dodecahedron import CalibrationShot, Dodecahedron, calibration_shot
from registration.sim.rotational_run import RUN_ARC_DEG, RunRecipe, RunStopped

log = logging.getLogger(__name__)

#: Size of the calibration image tile in the panel (pixels).
TILE_PX = 384
#: The spheres are drawn this much larger than they are (2.5 mm lead beads vanish in a head-sized scene).
SPHERE_DISPLAY_SCALE = 2.5

DETECTED_RGB = (64, 192, 87)
NOMINAL_RGB = (255, 212, 59)
FITTED_RGB = (255, 64, 64)
LEAD_RGB = (190, 196, 206)
MARKER_RGB = (255, 146, 43)

Message = Callable[[str], None]


@dataclass(frozen=True)
class RunFrames:
    """A rotational run as the view shows it: attenuation images and nominal primary angles."""

    images: np.ndarray
    masks: np.ndarray
    primary_deg: np.ndarray
    image_format_cm: float

    def __len__(self) -> int:
        return int(self.images.shape[0])


def _edges(vertices: np.ndarray) -> np.ndarray:
    """The 30 edges of a dodecahedron: pairs of vertices at the shortest distance, (30, 2, 3)."""
    d = np.linalg.norm(vertices[:, None] - vertices[None], axis=2)
    shortest = d[d > 1e-9].min()
    i, j = np.nonzero(np.triu(np.abs(d - shortest) < 1e-6 * shortest + 1e-9, k=1))
    return np.stack([vertices[i], vertices[j]], axis=1)


def shot_errors_mm(shot: CalibrationShot) -> dict[str, float]:
    """Errors at the iso-center region against the true view: calibrated, sensors only, table."""
    table = machine_based_geometry(shot.nominal.primary_deg, shot.nominal.secondary_deg, nominal=shot.nominal)
    return {
        "calibrated": shot.error_mm,
        "nominal": machine_based_error_mm(shot.true, shot.nominal),
        "table": machine_based_error_mm(shot.true, table),
    }


def shot_picture(shot: CalibrationShot, phantom: Dodecahedron, size: int = TILE_PX) -> np.ndarray:
    """The calibration image (dark = lead) cropped round the phantom, with the detected spheres
    circled (green), the nominal projections (yellow crosses) and the fitted ones (red dots)."""
    vertices = phantom.vertices_mm
    nominal_px = shot.nominal.project(vertices)
    fitted_px = shot.calibration.geometry.project(vertices)
    detected = shot.calibration.detected.centers_px
    center = nominal_px.mean(axis=0)
    half = float(np.max(np.abs(np.vstack([nominal_px, fitted_px]) - center))) + 24.0
    c0, r0 = (int(round(v - half)) for v in center)
    side = int(round(2 * half))
    gray = views.to_gray(shot.image, shot.mask)
    crop = np.zeros((side, side), np.uint8)
    rs, cs = max(r0, 0), max(c0, 0)
    re_, ce = min(r0 + side, gray.shape[0]), min(c0 + side, gray.shape[1])
    crop[rs - r0 : re_ - r0, cs - c0 : ce - c0] = gray[rs:re_, cs:ce]
    scale = size / side
    rgb = views.gray_rgb(cv2.resize(crop, (size, size), interpolation=cv2.INTER_LINEAR))

    def at(p: np.ndarray) -> tuple[int, int]:
        return int(round((p[0] - c0 + 0.5) * scale - 0.5)), int(round((p[1] - r0 + 0.5) * scale - 0.5))

    radius_px = phantom.radii_mm * shot.nominal.magnification / min(shot.nominal.pixel_mm) * scale
    for p in detected:
        cv2.circle(rgb, at(p), int(max(6, radius_px.max() + 5)), DETECTED_RGB, 1, cv2.LINE_AA)
    for p in nominal_px:
        cv2.drawMarker(rgb, at(p), NOMINAL_RGB, cv2.MARKER_CROSS, 9, 1, cv2.LINE_AA)
    for p in fitted_px:
        cv2.circle(rgb, at(p), 2, FITTED_RGB, -1, cv2.LINE_AA)
    views.label(rgb, f"DODECAHEDRON  {views.angles_text(shot.nominal)}")
    views.label(rgb, "green: detected  yellow: sensors  red: fitted", corner="bottom-left")
    return rgb


def run_geometry(frames: RunFrames, index: int) -> tuple[CArm, CArm]:
    """(nominal, true) geometry of a frame of the run."""
    nominal = CArm.for_format(
        frames.image_format_cm, pixels=frames.images.shape[1], primary_deg=float(frames.primary_deg[index])
    )
    return nominal, default_bending().true_geometry(nominal)


class CalibrationView:
    """Builds the calibration tab's widgets (inside the caller's tab context) and serves them."""

    def __init__(
        self,
        server: viser.ViserServer,
        data: PhantomData,
        *,
        angles: Callable[[], tuple[float, float, float]],
        message: Message,
        on_toggle: Callable[[], None] | None = None,
    ) -> None:
        self.server = server
        self.data = data
        self.angles = angles  # (primary_deg, secondary_deg, volume_format_cm) of the C-arm now
        self.message = message
        self.on_toggle = on_toggle  # the app redraws the scene (the patient is hidden while this is on)
        self.phantom = Dodecahedron()
        self.shot: CalibrationShot | None = None
        self.errors: dict[str, float] | None = None
        self.frames: RunFrames | None = None
        self.shots_computed = 0
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._quit = threading.Event()
        self._want_shot: tuple[float, float] | None = None
        self._want_run: float | None = None
        self._scene_nodes: list[Any] = []
        self._worker: threading.Thread | None = None
        self.idle = threading.Event()
        self.idle.set()

        gui = server.gui
        self.enabled = gui.add_checkbox(
            "Show the calibration",
            False,
            hint="The dodecahedron phantom in the scene, its X-ray at the current C-arm angles with the detected "
            "spheres, and the rotational run (computed only while this is on)",
        )
        self.intro = gui.add_markdown(
            "<small>Off. The 3DRA is reconstructed from a rotational run whose geometry was calibrated with "
            "a dodecahedron of 20 lead spheres (the paper's Fig. 1). Tick the box to see both.</small>"
        )
        self.image = gui.add_image(np.zeros((TILE_PX, TILE_PX, 3), np.uint8), label=None, format="jpeg", visible=False)
        self.readout = gui.add_markdown("", visible=False)
        self.run_folder = gui.add_folder("Rotational run", visible=False)
        with self.run_folder:
            self.run_button = gui.add_button(
                "Simulate the rotational run", icon=viser.Icon.PLAYER_PLAY, hint="Low resolution, cached afterwards"
            )
            self.run_bar = gui.add_progress_bar(0.0, visible=False)
            self.frame = gui.add_slider("Frame", 0, 1, 1, 0, disabled=True, visible=False)
            self.run_image = gui.add_image(np.zeros((256, 256, 3), np.uint8), label=None, format="jpeg", visible=False)
            self.run_readout = gui.add_markdown("")
        self.enabled.on_update(lambda _e: self._on_enabled())
        self.run_button.on_click(lambda _e: self.request_run())
        self.frame.on_update(lambda _e: self._show_frame())

    # ----- requests (any thread) ----------------------------------------------------------
    def _on_enabled(self) -> None:
        on = bool(self.enabled.value)
        self.intro.visible = not on
        for handle in (self.image, self.readout, self.run_folder):
            handle.visible = on
        if on:
            self._ensure_scene()
            self.refresh()
            fmt = self.angles()[2]
            if self.frames is None or self.frames.image_format_cm != fmt:
                if self.run_cached(fmt):
                    self.request_run()
                else:
                    self.run_readout.content = (
                        f"<small>Not simulated yet: {self.data.config.run_projections} views over "
                        f"{RUN_ARC_DEG:g}° at {self.data.config.run_pixels} px (a few seconds).</small>"
                    )
        for node in self._scene_nodes:
            node.visible = on
        if self.on_toggle is not None:
            self.on_toggle()

    def refresh(self) -> None:
        """The C-arm moved (or the view was turned on): re-image the phantom at its angles."""
        if not self.enabled.value:
            return
        primary, secondary, _fmt = self.angles()
        with self._lock:
            self._want_shot = (primary, secondary)
        self._kick()

    def request_run(self) -> None:
        """Load (or simulate, with progress) the rotational run of the current volume format."""
        with self._lock:
            self._want_run = self.angles()[2]
        self.run_button.disabled = True
        self._kick()

    def close(self) -> None:
        self._quit.set()
        self._wake.set()
        if self._worker is not None:
            self._worker.join(timeout=3.0)

    def _kick(self) -> None:
        self.idle.clear()
        if self._worker is None:
            self._worker = threading.Thread(target=self._work_loop, name="calibration", daemon=True)
            self._worker.start()
        self._wake.set()

    # ----- the worker ------------------------------------------------------------------------
    def _work_loop(self) -> None:
        while not self._quit.is_set():
            self._wake.wait()
            self._wake.clear()
            while not self._quit.is_set():
                with self._lock:
                    shot, run = self._want_shot, self._want_run
                    self._want_shot = self._want_run = None
                if shot is None and run is None:
                    break
                try:
                    if shot is not None:
                        self._compute_shot(*shot)
                    if run is not None:
                        self._load_run(run)
                except Exception as exc:  # shown in the page, the worker lives on
                    log.exception("calibration view failed")
                    self.message(f"Calibration view: {exc}")
                    self.run_button.disabled = False
                    self.run_bar.visible = False
            with self._lock:
                if self._want_shot is None and self._want_run is None:
                    self.idle.set()

    def _compute_shot(self, primary_deg: float, secondary_deg: float) -> None:
        self.readout.content = f"Imaging the dodecahedron at {primary_deg:+.0f}°, {secondary_deg:+.0f}°…"
        try:
            shot = calibration_shot(primary_deg, secondary_deg, phantom=self.phantom)
        except ValueError as exc:  # too few spheres matched at this view
            self.readout.content = f"<span style='color:#ff6b6b'>⚠ No calibration at this view: {exc}</span>"
            return
        errors = shot_errors_mm(shot)
        picture = shot_picture(shot, self.phantom)
        cal = shot.calibration
        with self.server.atomic():
            self.image.image = picture
            self.readout.content = (
                f"**Calibration error: {errors['calibrated']:.2f} mm** (fitted vs true geometry at the iso-center "
                f"region)  \n{len(cal.detected)} spheres detected, {cal.spheres_used} used, reprojection "
                f"{cal.rms_px:.2f} px RMS, marker {'found' if cal.marker_found else 'not found'}  \n"
                f"<small>Sensors alone (no calibration): {errors['nominal']:.2f} mm · machine-based table "
                f"(20° grid, interpolated): {errors['table']:.2f} mm</small>"
            )
        self.shot, self.errors = shot, errors
        self.shots_computed += 1

    def run_recipe(self, volume_format_cm: float) -> RunRecipe:
        """The rotational run the view shows: the engine's run of the phantom, at low resolution."""
        config = self.data.config
        return RunRecipe(
            phantom_seed=config.seed,
            image_format_cm=float(volume_format_cm),
            projections=config.run_projections,
            arc_deg=RUN_ARC_DEG,
            pixels=config.run_pixels,
            kind="exposure",
            seed=config.seed,
            supersample=1,
        )

    def run_cached(self, volume_format_cm: float) -> bool:
        return self.run_recipe(volume_format_cm).is_cached()

    def _load_run(self, volume_format_cm: float) -> None:
        recipe = self.run_recipe(volume_format_cm)
        start = time.monotonic()

        def progress(done: int, total: int) -> bool:
            if done == 1:
                self.run_bar.visible = True
            self.run_bar.value = 100.0 * done / total
            self.run_readout.content = (
                f"Simulating the rotational run: view {done} of {total} "
                f"({time.monotonic() - start:.0f} s; cached afterwards)"
            )
            return self._quit.is_set()

        self.run_bar.value = 0.0
        self.run_readout.content = "Loading the rotational run…"
        try:
            images, masks = recipe.images(progress=progress)
        except RunStopped:
            return  # the app is closing
        self.frames = RunFrames(images, masks, recipe.angles(), float(volume_format_cm))
        with self.server.atomic():
            self.run_bar.visible = False
            self.run_button.disabled = False
            self.run_button.label = "Simulated (cached)"
            self.frame.max = len(self.frames) - 1
            self.frame.disabled = False
            self.frame.visible = True
            self.run_image.visible = True
        self._show_frame()

    def _show_frame(self) -> None:
        frames = self.frames
        if frames is None:
            return
        index = int(np.clip(round(float(self.frame.value)), 0, len(frames) - 1))
        nominal, true = run_geometry(frames, index)
        rgb = views.gray_rgb(views.resize(views.to_gray(frames.images[index], frames.masks[index]), 256))
        views.label(rgb, f"RUN {index + 1}/{len(frames)}  {views.angles_text(nominal)}")
        bend = machine_based_error_mm(true, nominal)
        with self.server.atomic():
            self.run_image.image = rgb
            self.run_readout.content = (
                f"Frame {index + 1} of {len(frames)} · primary {frames.primary_deg[index]:+.1f}° · "
                f"{frames.image_format_cm:g} cm · the arm's bending here: {bend:.2f} mm (what calibration corrects)"
            )

    # ----- the scene ---------------------------------------------------------------------------
    def _ensure_scene(self) -> None:
        if self._scene_nodes:
            return
        scene = self.server.scene
        vertices = self.phantom.vertices_mm
        radii = self.phantom.radii_mm * SPHERE_DISPLAY_SCALE
        for index, (p, r) in enumerate(zip(vertices, radii, strict=True)):
            self._scene_nodes.append(
                scene.add_icosphere(
                    f"/calibration/sphere_{index:02d}",
                    radius=float(r) * M_PER_MM,
                    color=MARKER_RGB if index == 0 else LEAD_RGB,
                    subdivisions=2,
                    position=tuple(p * M_PER_MM),
                )
            )
        edges = _edges(vertices) * M_PER_MM
        self._scene_nodes.append(
            scene.add_line_segments("/calibration/edges", edges.astype(np.float32), (150, 160, 175), thickness=0.001)
        )
        self._scene_nodes.append(
            scene.add_label(
                "/calibration/label",
                "calibration phantom",
                position=(0.0, -math.ceil(self.phantom.circumradius_mm + 8) * M_PER_MM, 0.0),
                font_screen_scale=0.8,
            )
        )


class CalibrationPanel(CalibrationView):
    """The calibration view mounted as the app's "Calibration" tab (:mod:`app.web.panels`)."""

    def __init__(self, ctx: PanelContext) -> None:
        session = ctx.session

        def angles() -> tuple[float, float, float]:
            with session.lock:
                st = session.settings
            return st.primary_deg, st.secondary_deg, st.volume_format_cm

        with ctx.layout.view_tab("Calibration", viser.Icon.GRID_DOTS):
            super().__init__(ctx.server, ctx.phantom, angles=angles, message=ctx.message, on_toggle=ctx.refresh)

    @property
    def hides_patient(self) -> bool:
        """While on, the dodecahedron is imaged on its own: the patient leaves the scene."""
        return bool(self.enabled.value)

    def settings_changed(self) -> None:
        self.refresh()
