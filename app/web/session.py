"""The app's state and its registration worker, independent of viser (testable on its own).

One :class:`Session` holds what every browser tab sees: the C-arm settings, the true patient
motion (what the simulated patient did), the current estimate of it (what the roadmap uses),
the X-ray image formed from both, and the registration run in progress. Callbacks change it
under its lock; readers take consistent snapshots.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from app.web.data import AppConfig, DataSource, PhantomData, XRayImage, simulate_xray
from app.web.session_state import CArmSettings, RunState
from registration.core.geometry import (
    TABLE_I,
    CArm,
    check_rigid,
    matrix_to_offsets,
    offsets_to_matrix,
)
from registration.core.landmarks import LandmarkStart
from registration.core.metrics import Residual, residuals
from registration.core.register import (
    Progress,
    RegistrationResult,
    register,
    registration_plan,
)

log = logging.getLogger(__name__)

Array = np.ndarray

#: Slider ranges of the six patient-motion offsets (mm, deg).
TRANSLATION_RANGE_MM = 30.0
ROTATION_RANGE_DEG = 15.0
#: How long Stop waits for the optimizer to notice before the run is let go (within the 0.5 s Stop promises).
STOP_GRACE_S = 0.3
#: The ``Random`` button's offsets: translation up to 25 mm, rotation up to 10 degrees.
RANDOM_MAX_MM = 25.0
RANDOM_MAX_DEG = 10.0
#: Plane B's quantum noise is its own stream: the seed is offset by this (the two frames of one
#: moment, CONVENTIONS §6).
PLANE_B_NOISE_SEED_OFFSET = 7919


class Session:
    """The shared state of the demo and its registration worker."""

    def __init__(self, data: DataSource, config: AppConfig | None = None) -> None:
        self.data: DataSource = data
        self.config = config or data.config
        self.lock = threading.RLock()
        self.settings = CArmSettings()
        self.true_motion: Array = np.eye(4)
        self.estimate: Array = np.eye(4)
        #: The landmark start the roadmap was put at (start_from); the registration from that pose
        #: is checked against its landmarks.
        self.landmark_start: LandmarkStart | None = None
        self.run = RunState()
        #: bumped on every change of settings, motion or estimate (the presenter watches it)
        self.version = 0
        self._xray_key: tuple | None = None
        self._xray: XRayImage | None = None
        self._xray_b_key: tuple | None = None
        self._xray_b: XRayImage | None = None
        self._xray_lock = threading.Lock()
        self._worker: threading.Thread | None = None
        self._rng = np.random.default_rng(self.config.seed + 1)

    # ----- geometry and images ----------------------------------------------------------
    @property
    def has_truth(self) -> bool:
        """The built-in phantom knows the true motion; the user's data does not."""
        return self.data.has_truth

    def geometry(self) -> CArm:
        with self.lock:
            if self.data.fixed_xray is not None:
                return self.data.fixed_xray.geometry.nominal()
            return self.settings.geometry(self.config.pixels)

    def use_data(self, data: DataSource) -> None:
        """Switch to other data (an upload): motion, estimate and run start afresh."""
        with self.lock:
            self._refuse_while_running()
            self.data = data
            self.true_motion = np.eye(4)
            self.estimate = np.eye(4)
            self.run = RunState()
            self._changed()

    def set_isocenter(self, isocenter_mm: tuple[float, float, float], source: str) -> None:
        """Place the user's image about another iso-center (mm, world; ``source``: where it came
        from). The roadmap restarts from the sensor pose: a pose found about the old iso-center
        belongs to another geometry. Refused while a registration runs and for the phantom (its
        C-arm's iso-center is the world origin, where its images are formed)."""
        from app.web.data import FileData

        with self.lock:
            self._refuse_while_running()
            if not isinstance(self.data, FileData):
                raise ValueError(
                    "the phantom is imaged about the world origin: the iso-center field is for your data "
                    "(--volume/--image, an upload or the PACS)"
                )
            self.data.set_isocenter(isocenter_mm, source)
            self.estimate = np.eye(4)
            self.run = RunState()
            self._changed()

    def set_region(self, path: str | os.PathLike[str], name: str) -> None:
        """Register only a region of the user's volume (:meth:`FileData.set_region`); refused while
        a registration runs and for the phantom."""
        from app.web.data import FileData

        with self.lock:
            self._refuse_while_running()
            if not isinstance(self.data, FileData):
                raise ValueError(
                    "the phantom is registered whole: a region mask is for your data (an upload or the PACS)"
                )
            self.data.set_region(path, name)
            self.run = RunState()
            self._changed()

    def set_image_mask(self, path: str | os.PathLike[str]) -> None:
        """Narrow the user's image field by a mask file (:meth:`FileData.set_user_mask`); the roadmap
        keeps its pose. Refused while a registration runs and for the phantom (its field is known)."""
        from app.web.data import FileData

        with self.lock:
            self._refuse_while_running()
            if not isinstance(self.data, FileData):
                raise ValueError("the phantom's field is known: a field mask is for your data (an upload or the PACS)")
            self.data.set_user_mask(path)
            self.run = RunState()
            self._changed()

    @property
    def biplane(self) -> bool:
        """Biplane mode is on (never for the user's data: one file, one plane)."""
        return self.settings.biplane and self.data.fixed_xray is None

    @property
    def graded_biplane(self) -> bool:
        """Whether the estimate is graded as two views' (the whole 3-D translation): the shown
        result's own views when there is one (ticking Biplane afterwards does not re-grade a
        single-plane result), else the mode."""
        with self.lock:
            result = self.run.result
        if result is not None:
            return len(getattr(result, "views", ())) > 1
        return self.biplane

    def _xray_state(self) -> tuple[CArmSettings, Array, tuple]:
        with self.lock:
            settings, motion = self.settings, self.true_motion.copy()
        return settings, motion, (settings.plane_a(), motion.tobytes())

    def _simulate(
        self, settings: CArmSettings, motion: Array, *, pixels: int, supersample: int, plane_b: bool = False
    ) -> XRayImage:
        data = self.data
        if not isinstance(data, PhantomData):  # a source without a phantom brings its own image
            raise ValueError(f"{data.source}: no phantom to form X-ray images from")
        geometry = settings.geometry_b(pixels) if plane_b else settings.geometry(pixels)
        return simulate_xray(
            data.phantom(settings.contrast),
            geometry,
            motion=motion,
            kind=settings.kind,
            catheter=settings.catheter,
            seed=self.config.seed + (PLANE_B_NOISE_SEED_OFFSET if plane_b else 0),
            supersample=supersample,
        )

    def xray_b(self) -> XRayImage:
        """Plane B's image of the same moment (same patient motion, its own noise), re-formed on change."""
        with self.lock:
            settings, motion = self.settings, self.true_motion.copy()
        key = (settings.plane_a(), settings.primary_b_deg, settings.secondary_b_deg, motion.tobytes())
        with self._xray_lock:
            if key != self._xray_b_key or self._xray_b is None:
                self._xray_b = self._simulate(settings, motion, pixels=self.config.pixels, supersample=2, plane_b=True)
                self._xray_b_key = key
            return self._xray_b

    def views(self) -> list[XRayImage]:
        """What a registration now compares with: plane A's image, and plane B's in biplane mode."""
        return [self.xray(), self.xray_b()] if self.biplane else [self.xray()]

    def xray(self) -> XRayImage:
        """The X-ray image for the current settings and true motion (re-formed on change)."""
        if self.data.fixed_xray is not None:
            return self.data.fixed_xray
        settings, motion, key = self._xray_state()
        with self._xray_lock:
            if key != self._xray_key or self._xray is None:
                self._xray = self._simulate(settings, motion, pixels=self.config.pixels, supersample=2)
                self._xray_key = key
            return self._xray

    def xray_ready(self) -> bool:
        """Whether :meth:`xray` would return at once."""
        if self.data.fixed_xray is not None:
            return True
        return self._xray_key == self._xray_state()[2]

    def xray_preview(self) -> XRayImage:
        """A quick, coarser image of the current state (shown while :meth:`xray` is formed)."""
        settings, motion, _ = self._xray_state()
        return self._simulate(settings, motion, pixels=max(64, self.config.pixels // 2), supersample=1)

    def residual(self, estimate: Array | None = None) -> Residual | None:
        """Residual of ``estimate`` (default: the current one) against the truth; None without truth."""
        if not self.has_truth:
            return None
        with self.lock:
            est = self.estimate if estimate is None else estimate
            return residuals(
                est, self.true_motion, self.geometry(), self.data.vessel_points_mm(), optimizes_tz=self.graded_biplane
            )

    # ----- changes ----------------------------------------------------------------------
    def _changed(self) -> None:
        self.version += 1

    def update_settings(self, **changes: object) -> None:
        """Change C-arm settings; the patient stays where it is in the room (world frame)."""
        with self.lock:
            self._refuse_while_running()
            if self.data.fixed_xray is not None:
                raise ValueError("the C-arm geometry comes from your X-ray file and cannot be changed here")
            new = replace(self.settings, **changes)  # type: ignore[arg-type]
            new.geometry(self.config.pixels)  # validate before accepting
            self.settings = new
            self._changed()

    def offsets(self) -> Array:
        """The motion the sliders show, (tx, ty, tz, rx, ry, rz) in the current view frame.

        The true patient motion for the phantom; the roadmap's pose (the estimate) for the
        user's data, which has no truth.
        """
        with self.lock:
            moved = self.true_motion if self.has_truth else self.estimate
            return matrix_to_offsets(moved, self.geometry())

    def set_offsets(self, offsets: Array | tuple[float, ...], *, reset_estimate: bool = False) -> None:
        """Move the patient: offsets in the current view frame (Table I convention)."""
        o = np.asarray(offsets, dtype=np.float64)
        if o.shape != (6,) or not np.all(np.isfinite(o)):
            raise ValueError("patient motion needs six finite numbers")
        if np.any(np.abs(o[:3]) > TRANSLATION_RANGE_MM + 1e-9) or np.any(np.abs(o[3:]) > ROTATION_RANGE_DEG + 1e-9):
            raise ValueError(
                f"patient motion is limited to ±{TRANSLATION_RANGE_MM:g} mm and ±{ROTATION_RANGE_DEG:g}° per axis"
            )
        with self.lock:
            self._refuse_while_running()
            if not self.has_truth:
                self.estimate = offsets_to_matrix(o, self.geometry())
                self.run = RunState()
                self._changed()
                return
            self.true_motion = offsets_to_matrix(o, self.geometry())
            if reset_estimate:
                self.estimate = np.eye(4)
                self.run = RunState()
            self._changed()

    def start_from(self, motion: Array, landmarks: LandmarkStart | None = None) -> None:
        """Put the roadmap at ``motion`` (a start found another way, e.g. from landmarks: their
        :class:`~registration.core.landmarks.LandmarkStart`); the next registration refines it
        and, from landmarks, is checked against them."""
        m = check_rigid(motion, name="start")
        with self.lock:
            self._refuse_while_running()
            self.estimate = m
            self.landmark_start = landmarks
            self.run = RunState()
            self._changed()

    def apply_table_offset(self, name: str) -> None:
        """T1..T4 of Table I; the roadmap restarts from the machine-based registration."""
        self.set_offsets(TABLE_I[name], reset_estimate=True)

    def random_offset(self) -> Array:
        """A random motion within 25 mm and 10 degrees (as the paper's clinical study)."""
        direction = self._rng.normal(size=3)
        t = direction / np.linalg.norm(direction) * RANDOM_MAX_MM * self._rng.uniform() ** (1 / 3)
        axis = self._rng.normal(size=3)
        r = axis / np.linalg.norm(axis) * RANDOM_MAX_DEG * self._rng.uniform()
        offsets = np.concatenate([t, r])
        self.set_offsets(offsets, reset_estimate=True)
        return offsets

    def reset(self) -> None:
        """No patient motion, roadmap at the machine-based registration."""
        self.set_offsets(np.zeros(6), reset_estimate=True)

    def _refuse_while_running(self) -> None:
        if self.run.running:
            raise ValueError("a registration is running: press Stop first")

    # ----- the registration worker ------------------------------------------------------
    @property
    def running(self) -> bool:
        return self.run.running

    def start_registration(self, on_done: Callable[[], None] | None = None, *, trigger: str = "Register") -> bool:
        """Start registering on a worker thread; False if one is already running. ``trigger``
        names who started it ("Register", "Auto-correct") for the status line."""
        with self.lock:
            if self.run.running:
                return False
            initial = self.estimate.copy()
            start = self.landmark_start
            # the landmarks judge a registration only from the pose they gave
            landmarks = start if start is not None and np.allclose(start.patient_motion, initial) else None
            self.run = RunState(
                running=True, iterations=[], similarity=[], temperature=[], started_s=time.perf_counter(),
                initial_motion=initial.copy(), isocenter_mm=self.geometry().isocenter_mm, trigger=trigger,
            )  # fmt: skip
            truth = self.true_motion.copy() if self.has_truth else None
            volume_format = self.settings.volume_format_cm
            run = self.run
            self._changed()
            # Started under the lock: whoever sees ``running`` and calls wait() gets this worker,
            # never the previous one or one not yet started.
            worker = threading.Thread(
                target=self._register,
                args=(run, initial, truth, volume_format, on_done, landmarks),
                name="registration",
                daemon=True,
            )
            worker.start()
            self._worker = worker
        return True

    def _register(
        self,
        run: RunState,
        initial: Array,
        truth: Array | None,
        volume_format: float,
        on_done: Callable[[], None] | None,
        landmarks: LandmarkStart | None = None,
    ) -> None:
        callback = self._progress_recorder(run)
        assessment = None
        try:
            full_views = self.views()  # biplane: plane A first, offsets in its view frame
            data = self.data
            region_views = getattr(data, "region_views", None)  # the user's data: the neck's pixels left out
            views = region_views(full_views, initial) if region_views is not None else full_views
            run.views = views
            volume = data.volume(volume_format)
            # the user's volume: prepared for these views and this start (app.data.FileData.prepared)
            renderer = data.renderer(volume_format, views=full_views, initial_motion=initial)
            if log.isEnabledFor(logging.INFO):  # the plan this registration runs, as register --explain prints it
                plan = registration_plan(volume, views, initial_motion=initial, renderer=renderer, landmarks=landmarks)
                log.info("registration plan:\n%s", plan.describe())
            result = register(
                volume,
                views if len(views) > 1 else views[0],
                initial_motion=initial,
                seed=self.config.seed,
                callback=callback,
                truth=truth,
                vessel_points_mm=data.vessel_points_mm(),
                renderer=renderer,
                landmarks=landmarks,
            )
            skull_spine = None
            if not result.stopped and not getattr(result, "at_bounds", ()) and math.isfinite(result.similarity):
                # assessed on the whole fields, as register does (the rule was calibrated on them)
                assessment = self._assess(full_views, result, volume_format, initial, landmarks)
                skull_spine = self._skull_spine(views, full_views, result)
        except Exception as exc:  # shown in the page, never a dead worker thread
            with self.lock:
                if run.abandoned:
                    return
                if isinstance(exc, ValueError):  # the input's fault (cannot register: ...): no traceback
                    log.warning("registration refused: %s", exc)
                else:
                    log.exception("registration failed")
                run.error = f"Registration failed: {exc}"
                run.running = False
                self._changed()
        else:
            with self.lock:
                if run.abandoned:  # Stop already ended this run for the user
                    return
                self._finish(run, result, assessment, skull_spine)
        if on_done is not None:
            on_done()

    def _progress_recorder(self, run: RunState) -> Callable[[Progress], bool]:
        """The registration's callback: each iteration's best similarity and temperature into
        ``run`` (the convergence plot); True (stop) once Stop was pressed."""
        count = 0

        def callback(progress: Progress) -> bool:
            nonlocal count
            count += 1
            with self.lock:
                assert run.iterations is not None and run.similarity is not None and run.temperature is not None
                run.iterations.append(count)
                run.similarity.append(float(progress.best_similarity))
                run.temperature.append(float(progress.temperature))
                run.progress = progress
            return run.stop.is_set()

        return callback

    def _finish(self, run: RunState, result: RegistrationResult, assessment: dict | None, skull_spine: Any) -> None:
        """A finished registration into ``run`` (under the lock); the estimate applied when it is
        a registration and the confidence applies it (withheld: a wrong correction is worse than
        none, the roadmap keeps its pose)."""
        run.result = result
        run.assessment = assessment
        run.skull_spine = skull_spine
        if not math.isfinite(result.similarity):
            run.error = "Registration found no usable overlap between the DRR and the image."
        elif getattr(result, "at_bounds", ()):  # inputs without information drift there
            run.error = (
                f"Not registered: the estimate ended at the search bounds ({', '.join(result.at_bounds)}); "
                "the roadmap keeps its pose."
            )
        elif assessment is None or assessment["applied"]:
            self.estimate = np.asarray(result.patient_motion, dtype=np.float64)
        if run.stop_requested_s is not None:
            run.stop_latency_s = time.perf_counter() - run.stop_requested_s
        run.running = False
        self._changed()

    def _skull_spine(self, views: list[XRayImage], full_views: list[XRayImage], result: RegistrationResult) -> Any:
        """The skull-and-spine check after a registration on the user's region (as ``register``
        runs it: the whole volume on the whole fields near the estimate); None when the region
        left nothing out."""
        region = getattr(self.data, "region", None)
        narrowed = any(v.mask.sum() != f.mask.sum() for v, f in zip(views, full_views, strict=True))
        if region is None or not (narrowed or (region.source != "cranium" and region.left_out_ml > 0)):
            return None
        from registration.core.skull_spine import skull_spine_check

        return skull_spine_check(self.data.whole_volume, full_views, result.patient_motion, seed=self.config.seed)

    def _assess(
        self,
        views: list[XRayImage],
        result: RegistrationResult,
        volume_format: float,
        initial: Array,
        landmarks: LandmarkStart | None = None,
    ) -> dict | None:
        """The estimate's confidence and decision, as ``register --confidence`` and the studies
        assess it (:func:`registration.core.assess.assess_on`); None (the estimate is
        applied, as before the rule) when the assessment itself fails, which is logged."""
        from registration.core.assess import assess_on
        from registration.core.depth import scan_level
        from registration.studies.cases import assessment_fields

        try:
            renderer = self.data.evidence_renderer(volume_format, views, initial)
            # one view's far look at the depth correction's level of the registration's own renderer
            far_level = scan_level(self.data.renderer(volume_format, views, initial))
            return assessment_fields(assess_on(result, views, self.data.volume(volume_format), renderer,
                                               landmarks=landmarks, far_level=far_level))  # fmt: skip
        except Exception:  # noqa: BLE001 - the registration stands; the page says it was not assessed
            log.exception("confidence assessment failed")
            return None

    def stop_registration(self, *, wait: bool = False, timeout: float = 5.0) -> None:
        """Stop the run: at the optimizer's next iteration, or at once if it has not reached one.

        A run still preparing after STOP_GRACE_S (before its first iteration nothing can stop
        it) is let go: it ends for the user now, keeps the pose shown, and its result is dropped.
        """
        with self.lock:
            run = self.run
            if run.running and run.stop_requested_s is None:
                run.stop_requested_s = time.perf_counter()
            run.stop.set()
        worker = self._worker
        if worker is None or worker is threading.current_thread():
            return
        worker.join(timeout if wait else STOP_GRACE_S)
        if worker.is_alive():
            with self.lock:
                if run.running and self.run is run:
                    run.abandoned = True
                    run.running = False
                    run.stop_latency_s = time.perf_counter() - (run.stop_requested_s or time.perf_counter())
                    if run.progress is not None:
                        self.estimate = np.asarray(run.progress.best_motion, dtype=np.float64)
                    self._changed()

    def wait(self, timeout: float = 60.0) -> bool:
        """Wait for the running registration to end; True if it did."""
        with self.lock:
            worker = self._worker
        if worker is None:
            return True
        worker.join(timeout)
        return not worker.is_alive()
