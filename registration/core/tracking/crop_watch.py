"""The tracker's watch on its crop: the margin left for a capture from the applied pose, and the
crop prepared again around that pose in a thread of its own when the margin falls short."""

from __future__ import annotations

import threading
import time

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core.prepare import Crop, PreparedVolume, Reach, recrop
from registration.core.register import RegistrationOptions
from registration.core.tracking.options import TrackingOptions

Array = NDArray[np.float64]


class CropWatch:
    """The tracker's crop: its margin at the applied pose and its re-preparation in a thread.

    ``check`` (after a frame, cheap: a few 4x4 products) starts :func:`registration.core.prepare.recrop`
    around the applied pose when a capture from it would search beyond the crop's reach
    (:meth:`registration.core.prepare.Crop.margin` < 0 in mm or degrees); ``take`` (before a
    frame) returns the new preparation once it is ready (``wait``: waits for a pending one)."""

    def __init__(self, crop: Crop | None, capture: RegistrationOptions, options: TrackingOptions, *,
                 wait: bool) -> None:  # fmt: skip
        self.crop = crop
        self.active = options.reprepare
        self.capture = capture
        self.slack = (options.reprepare_slack_mm, options.reprepare_slack_deg)
        self.tolerance = (options.reprepare_tolerance_mm, options.reprepare_tolerance_deg)
        self.wait = wait
        self.swaps = 0
        #: What the frame that swapped a crop in reports (FrameEstimate.crop).
        self.event: dict | None = None
        self._thread: threading.Thread | None = None
        self._done: PreparedVolume | BaseException | None = None
        self._started: tuple[int, float] = (0, 0.0)
        self._failed = False
        #: The last pose checked and its margin (the applied pose changes only when an estimate is applied).
        self._last: tuple[Array, int, tuple[float, float]] | None = None
        self._searches: dict[int, Reach] = {}

    def search(self, planes: int) -> Reach:
        """The reach of a capture's search of ``planes`` views (about the pose it starts from)."""
        reach = self._searches.get(planes)
        if reach is None:
            c = self.capture
            reach = Reach.of_search(c.bound_mm, c.bound_deg, translations=3 if c.optimizes_tz(planes) else 2)
            self._searches[planes] = reach
        return reach

    def check(self, pose: Array, isocenter_mm: ArrayLike, planes: int, frame: int) -> tuple[float, float] | None:
        """The crop's margin for a capture from ``pose`` (None: nothing is cropped away);
        starts a re-preparation when it is negative."""
        crop = self.crop
        if crop is None or crop.complete:
            return None
        last = self._last
        if last is not None and last[1] == planes and np.array_equal(last[0], pose):
            mm, deg = last[2]
        else:
            mm, deg = crop.margin(pose, self.search(planes))
            self._last = (np.array(pose, dtype=np.float64), planes, (mm, deg))
        short = mm < -self.tolerance[0] or deg < -self.tolerance[1]
        if short and self.active and self._thread is None and not self._failed:
            reach = self.search(planes).grown(*self.slack)
            center = np.array(pose, dtype=np.float64)
            self._started = (int(frame), time.perf_counter())

            def job() -> None:
                try:
                    self._done = recrop(crop, center, reach)
                except BaseException as exc:  # noqa: BLE001 - reported by the frame that takes it
                    self._done = exc

            self._thread = threading.Thread(target=job, name="roadmap3d-recrop", daemon=True)
            self._thread.start()
        return mm, deg

    def take(self) -> PreparedVolume | None:
        """The new preparation, once ready (None otherwise); records the event."""
        thread = self._thread
        if thread is None:
            return None
        if self.wait:
            thread.join()
        elif thread.is_alive():
            return None
        thread.join()
        done, self._done, self._thread = self._done, None, None
        frame, t0 = self._started
        if not isinstance(done, PreparedVolume):
            self._failed = True  # keep the old crop; do not retry on every frame
            self.event = {"error": f"the crop could not be prepared again: {done}", "started_frame": frame}
            return None
        self.swaps += 1
        self.crop = done.crop
        self._last = None
        self.event = {
            "started_frame": frame,
            "ready_after_ms": (time.perf_counter() - t0) * 1e3,
            "prepare_ms": done.seconds * 1e3,
            "box_lo": list(done.box_lo),
            "box_hi": list(done.box_hi),
            "voxels_per_level": done.voxels_per_level,
            "complete": done.crop.complete if done.crop is not None else None,
            "reach": {"translation_mm": done.reach.translation_mm, "rotation_deg": done.reach.rotation_deg},
        }
        return done

    def close(self) -> None:
        if self._thread is not None:
            self._thread.join()


# --------------------------------------------------------------------------------------
# A whole run at its frame times
# --------------------------------------------------------------------------------------
