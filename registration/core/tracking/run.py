"""A run replayed at its frame times: frames that arrive while the tracker is busy are skipped."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core.blas import with_one_blas_thread
from registration.core.drr import DRRRenderer
from registration.core.images import XRayImage
from registration.core.tracking.options import FrameEstimate, TrackingOptions
from registration.core.tracking.tracker import Tracker
from registration.core.volume import Volume

Array = NDArray[np.float64]


@dataclass
class TrackingRun:
    """The outcome of :func:`track_run`: processed frames, skipped frames, the volume's label."""

    frames: list[FrameEstimate]
    skipped: list[int]
    frame_count: int
    volume_label: str
    planes: int

    def __repr__(self) -> str:
        """A line a notebook shows: what happened to the run's frames (``summary()`` has the rest)."""
        status = {k: sum(f.status == k for f in self.frames) for k in ("applied", "withheld", "unchanged")}
        latency = f", {np.median([f.latency_ms for f in self.frames]):.0f} ms per frame (median)" if self.frames else ""
        planes = f", {self.planes} planes" if self.planes > 1 else ""
        return (f"{type(self).__name__}({len(self.frames)} of {self.frame_count} frames processed, "
                f"{len(self.skipped)} skipped; {status['applied']} applied, {status['withheld']} withheld, "
                f"{status['unchanged']} unchanged{latency}{planes})")  # fmt: skip

    def summary(self) -> dict:
        lat = np.array([f.latency_ms for f in self.frames]) if self.frames else np.zeros(0)
        refine = np.array([f.latency_ms for f in self.frames if f.path in ("check", "refine")])
        capture = np.array([f.latency_ms for f in self.frames if f.path == "capture"])
        cpu = np.array([f.cpu_ms for f in self.frames])
        cpu_refine = np.array([f.cpu_ms for f in self.frames if f.path in ("check", "refine")])
        cpu_capture = np.array([f.cpu_ms for f in self.frames if f.path == "capture"])

        def q(a: np.ndarray, p: float) -> float | None:
            return float(np.percentile(a, p)) if len(a) else None

        return {
            "frames": self.frame_count,
            "processed": len(self.frames),
            "skipped": len(self.skipped),
            "applied": sum(f.status == "applied" for f in self.frames),
            "withheld": sum(f.status == "withheld" for f in self.frames),
            "unchanged": sum(f.status == "unchanged" for f in self.frames),
            "captures": sum(f.path == "capture" for f in self.frames),
            "refines": sum(f.path == "refine" for f in self.frames),
            "reprepared": sum(f.reprepared for f in self.frames),
            "ms_per_frame_median": q(lat, 50),
            "ms_per_frame_p95": q(lat, 95),
            "refine_path_ms_median": q(refine, 50),
            "refine_path_ms_p95": q(refine, 95),
            "capture_ms_median": q(capture, 50),
            "cpu_ms_per_frame_median": q(cpu, 50),
            "cpu_ms_per_frame_p95": q(cpu, 95),
            "refine_path_cpu_ms_p95": q(cpu_refine, 95),
            "capture_cpu_ms_median": q(cpu_capture, 50),
        }

    def to_dict(self) -> dict:
        return {
            "frames": [f.to_dict() for f in self.frames],
            "skipped": list(self.skipped),
            "frame_count": self.frame_count,
            "planes": self.planes,
            "volume_label": self.volume_label,
            "summary": self.summary(),
        }


@with_one_blas_thread
def track_run(
    volume: Volume,
    runs: Sequence[Sequence[XRayImage]],
    times_s: ArrayLike,
    *,
    options: TrackingOptions | None = None,
    initial_motion: ArrayLike | None = None,
    renderer: DRRRenderer | None = None,
    seed: int = 0,
    realtime: bool = True,
    wait: bool = False,
    clock: Callable[[], float] | None = None,
    on_frame: Callable[[FrameEstimate], bool | None] | None = None,
) -> TrackingRun:
    """Track a run of one plane (``runs = [run]``) or two synchronised planes.

    ``realtime``: frames arrive at ``times_s``; when the engine finishes a frame it takes the
    newest frame that has arrived and skips the ones in between (never queued); with
    ``realtime=False`` every frame is processed (a replay, deterministic). ``wait``: sleep
    until each frame's time (a live replay, e.g. for the app); otherwise time is virtual: the
    replay runs as fast as it can while the measured processing times decide what is skipped.
    ``clock``: the time source of the processing times (tests inject a deterministic one).
    ``on_frame``: called with every :class:`FrameEstimate`; return True to stop.
    """
    runs = list(runs)
    if not 1 <= len(runs) <= 2:
        raise ValueError(f"one or two planes, got {len(runs)}")
    times = np.asarray(times_s, dtype=np.float64).reshape(-1)
    n = len(times)
    if any(len(r) != n for r in runs):
        raise ValueError(f"every plane needs one frame per time ({n}); got {[len(r) for r in runs]}")
    if n == 0:
        raise ValueError("the run has no frames")
    if not np.all(np.isfinite(times)) or np.any(np.diff(times) < 0):
        raise ValueError("frame times must be finite and non-decreasing")
    clock = clock or time.perf_counter
    estimates: list[FrameEstimate] = []
    skipped: list[int] = []
    # a replay's decisions must not depend on how fast a crop is prepared again: it waits for it
    tracker = Tracker(volume, options=options, initial_motion=initial_motion, renderer=renderer, seed=seed,
                      wait_for_preparation=not realtime)  # fmt: skip
    tracker.warm_up([r[0] for r in runs])
    wall0 = time.perf_counter()
    try:
        now = times[0]
        i = 0
        while i < n:
            if wait:
                ahead = times[i] - (time.perf_counter() - wall0) - times[0]
                if ahead > 0:
                    time.sleep(ahead)
            c0 = clock()
            est = tracker.process([r[i] for r in runs], frame=i, t_s=float(times[i] - times[0]))
            busy = clock() - c0
            if clock is not time.perf_counter:
                est.latency_ms = busy * 1e3
            estimates.append(est)
            if on_frame is not None and on_frame(est):
                break
            if not realtime:
                i += 1
                continue
            now = (time.perf_counter() - wall0 + times[0]) if wait else max(now, times[i]) + busy
            newest = int(np.searchsorted(times, now, side="right")) - 1
            nxt = max(i + 1, newest)
            skipped.extend(range(i + 1, min(nxt, n)))
            i = nxt
    finally:
        tracker.close()
    return TrackingRun(estimates, skipped, n, volume.label, len(runs))
