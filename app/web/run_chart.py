"""The Play run tab's chart: the played run's estimated (roadmap) and true motion and each frame's
latency, drawn a few times a second."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

import numpy as np

from registration.core.geometry import CArm, matrix_to_offsets

if TYPE_CHECKING:
    from registration.core.tracking import FrameEstimate

#: The chart is drawn at most this often (per second) while a run plays.
CHART_HZ = 5.0
#: The app's charts' padding (px: top, right, bottom, left): the top tick's label stays inside.
CHART_PADDING = (14, 10, 0, 0)


def motion_chart(gui: Any) -> Any:
    """The played run's estimated (roadmap) and true motion and each frame's latency."""
    return gui.add_uplot(
        data=(np.zeros(1), *(np.full(1, np.nan) for _ in range(5))),
        series=(
            {"label": "t (s)"},
            {"label": "true tx", "stroke": "#74c0fc", "width": 1, "scale": "mm"},
            {"label": "roadmap tx", "stroke": "#1c7ed6", "width": 2, "scale": "mm"},
            {"label": "true ty", "stroke": "#ffa8a8", "width": 1, "scale": "mm"},
            {"label": "roadmap ty", "stroke": "#e03131", "width": 2, "scale": "mm"},
            {
                "label": "latency (ms)",
                "stroke": "#ffd43b",
                "width": 1,
                "scale": "ms",
                "paths": None,
                "points": {"show": True, "size": 3},
            },
        ),  # fmt: skip
        scales={"x": {"time": False}, "mm": {"auto": True}, "ms": {"auto": True, "distr": 3}},
        axes=(
            {"stroke": "#adb5bd", "grid": {"stroke": "#2c2e33"}},
            {"scale": "mm", "stroke": "#adb5bd", "grid": {"stroke": "#2c2e33"}},
            # the log axis: labelled decades without a tick mark at every 1-9 multiple
            {"scale": "ms", "side": 1, "stroke": "#ffd43b", "grid": {"show": False}, "ticks": {"show": False}},
        ),
        title="Estimated (roadmap) and true motion (mm, view frame); latency (ms, log)",
        height=220,
        padding=CHART_PADDING,  # room for the top tick's label
    )


class ChartSeries:
    """The played run's chart: per frame its time, the true and shown tx and ty (view frame, mm)
    and its latency; drawn at most ``CHART_HZ`` times a second."""

    def __init__(self, chart: Any) -> None:
        self.chart = chart
        self.series: dict[str, list[float]] = {k: [] for k in ("t", "true_x", "shown_x", "true_y", "shown_y", "ms")}
        self._drawn = 0.0

    def add(
        self, est: FrameEstimate, shown: np.ndarray, truth: np.ndarray | None, geometry: CArm, *, last: bool
    ) -> None:
        true_xy = matrix_to_offsets(truth, geometry)[:2] if truth is not None else (np.nan, np.nan)
        shown_xy = matrix_to_offsets(shown, geometry)[:2]
        values = (est.t_s, true_xy[0], shown_xy[0], true_xy[1], shown_xy[1], est.latency_ms)
        for key, value in zip(self.series, values, strict=True):
            self.series[key].append(float(value))
        now = time.perf_counter()
        if now - self._drawn >= 1.0 / CHART_HZ or last:
            self.show()
            self._drawn = now

    def show(self) -> None:
        self.chart.data = tuple(np.asarray(v) for v in self.series.values())
