"""A report that stays, for a tracked fluoroscopy run: strip charts, per-frame decisions, and the
last frame compared in place with the DRR at the pose the roadmap shows.

:func:`write_track_report` writes a folder (through a temporary sibling, as
:func:`registration.studies.qa_report.write_registration_report`) holding ``report.html``, its
PNGs and ``result.json`` (the ``track`` document). Numbers carry ``data-key`` attributes naming
their place in ``result.json`` (``summary.applied``, ``frames.12.confidence``, ...).
"""

from __future__ import annotations

import html
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from registration.core.confidence import DEFAULT_RULE
from registration.core.drr import DRRRenderer
from registration.core.geometry import CArm, matrix_to_offsets
from registration.core.images import XRayImage
from registration.core.volume import Volume
from registration.io.dicom import atomic_folder, json_dumps
from registration.studies import qa_evidence, qa_report

#: Status colours of the strip charts and the table.
STATUS_RGB = {"applied": "#2b8a3e", "withheld": "#e8590c", "unchanged": "#adb5bd"}
PATH_RGB = {"check": "#868e96", "refine": "#2f9e44", "capture": "#7048e8"}


def strip_charts(
    document: Mapping[str, Any], geometry: CArm, truth: NDArray | None = None, *, rule_threshold: float | None = None
) -> bytes:
    """The roadmap's pose over the run (the six offsets of plane A's view frame, the truth's
    beside them when known), each frame's decision and confidence, and its latency."""
    plt = qa_evidence.pyplot()
    frames = list(document["frames"])
    t = np.array([f["t_s"] for f in frames], dtype=float)
    shown = np.array([matrix_to_offsets(np.asarray(f["patient_motion"]), geometry) for f in frames])
    fig, axes = plt.subplots(4, 1, figsize=(10, 8.6), sharex=True, gridspec_kw={"height_ratios": [2.2, 2.2, 1.2, 1.2]})
    colors = ("#1c7ed6", "#e03131", "#f08c00")
    for row, (names, unit) in enumerate(((("tx", "ty", "tz"), "mm"), (("rx", "ry", "rz"), "deg"))):
        ax = axes[row]
        for k, name in enumerate(names):
            slot = 3 * row + k
            if truth is not None:
                true = np.array([matrix_to_offsets(np.asarray(truth[f["frame"]]), geometry)[slot] for f in frames])
                ax.plot(t, true, color=colors[k], lw=0.9, alpha=0.45, label=f"true {name}")
            ax.step(t, shown[:, slot], where="post", color=colors[k], lw=1.6, label=f"roadmap {name}")
        ax.set_ylabel(f"{unit} (view frame)", fontsize=8)
        ax.legend(ncol=6, fontsize=7, loc="upper left")
    one_plane = " (one plane: tz, along the beam, is not estimated)" if document.get("planes", 1) == 1 else ""
    axes[0].set_title(f"The roadmap's pose over the run (steps: the last applied estimate){one_plane}", fontsize=9)
    ax = axes[2]
    for status, color in STATUS_RGB.items():
        pts = [(f["t_s"], f["confidence"]) for f in frames if f["status"] == status and f.get("confidence") is not None]
        if pts:
            ax.plot(*zip(*pts, strict=True), "o", ms=3.5, color=color, label=status)
        bare = [f["t_s"] for f in frames if f["status"] == status and f.get("confidence") is None]
        if bare:
            ax.plot(bare, [-0.05] * len(bare), "|", ms=7, color=color, label=f"{status} (no estimate)")
    threshold = DEFAULT_RULE.threshold if rule_threshold is None else rule_threshold
    ax.axhline(threshold, color="#495057", lw=0.8, ls="--")
    ax.set_ylim(-0.1, 1.05)
    ax.set_ylabel("confidence", fontsize=8)
    ax.legend(ncol=4, fontsize=7, loc="lower left")
    ax = axes[3]
    lat = np.array([f["latency_ms"] for f in frames], dtype=float)
    ax.scatter(t, np.maximum(lat, 0.1), s=7, c=[PATH_RGB.get(f["path"], "#000") for f in frames])
    ax.set_yscale("log")
    from matplotlib.ticker import FormatStrFormatter

    ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
    ax.yaxis.set_minor_formatter(FormatStrFormatter(""))
    ax.set_ylabel("latency (ms)", fontsize=8)
    ax.set_xlabel("time (s); latency dots: grey check, green refine, purple full capture", fontsize=8)
    for a in axes:
        a.tick_params(labelsize=7)
    fig.tight_layout()
    return qa_evidence.png_of(fig)


def _decisions(frames: Sequence[Mapping[str, Any]]) -> str:
    """One row per frame that was not 'unchanged' (those are counted in the summary)."""
    rows = []
    for n, f in enumerate(frames):
        if f["status"] == "unchanged":
            continue
        color = STATUS_RGB.get(f["status"], "#000")
        conf = qa_report.number(f.get("confidence"), f"frames.{n}.confidence", ".3f")
        rows.append(
            f"<tr><td>{qa_report.number(f['frame'], f'frames.{n}.frame')}</td>"
            f"<td>{qa_report.number(f['t_s'], f'frames.{n}.t_s', '.2f')}</td>"
            f"<td style='color:{color};font-weight:600'>{html.escape(f['status'])}</td>"
            f"<td>{html.escape(f['path'])}</td><td>{conf}</td>"
            f"<td>{qa_report.number(f['latency_ms'], f'frames.{n}.latency_ms', '.1f')}</td>"
            f"<td>{html.escape(f.get('reason') or '')}</td></tr>"
        )
    head = "<tr><th>frame</th><th>t (s)</th><th>decision</th><th>path</th><th>confidence</th><th>latency (ms)</th>"
    head += "<th>why withheld</th></tr>"
    if not rows:
        return "<p>No frame moved the roadmap or was withheld: every frame was unchanged.</p>"
    return f"<table>{head}{''.join(rows)}</table>"


def _summary(summary: Mapping[str, Any]) -> str:
    keys = (
        ("frames", "frames", "d"), ("processed", "processed", "d"), ("skipped", "skipped (arrived while busy)", "d"),
        ("applied", "applied", "d"), ("withheld", "withheld", "d"), ("unchanged", "unchanged", "d"),
        ("captures", "full captures", "d"), ("ms_per_frame_median", "latency median (ms)", ".1f"),
        ("ms_per_frame_p95", "latency p95 (ms)", ".1f"),
        ("tracking_error_mm_median", "applied estimates vs truth, median (mm)", ".3f"),
        ("max_error_applied_mm", "applied estimates vs truth, max (mm)", ".3f"),
        ("applied_precision", "applied precision", ".3f"), ("applied_recall", "applied recall", ".3f"),
    )  # fmt: skip
    rows = [(label, qa_report.number(summary.get(k), f"summary.{k}", fmt if fmt != "d" else ".0f"))
            for k, label, fmt in keys if k in summary]  # fmt: skip
    return qa_report.table(rows)


def write_track_report(
    out: str | Path,
    *,
    document: Mapping[str, Any],
    volume: Volume,
    last_views: Sequence[XRayImage],
    renderer: DRRRenderer,
    truth: NDArray | None = None,
    anatomy: qa_report.Anatomy | None = None,
    identify: bool = False,
    command: str | None = None,
) -> Path:
    """Write the report of a tracked run into the folder ``out`` (absent or empty).
    ``document``: the ``track`` JSON; ``last_views``: the run's last frame of each plane (compared
    with the DRR at the last shown pose); ``truth``: (frames, 4, 4) true motions when known."""
    out = Path(out)
    doc = dict(document)
    frames = list(doc["frames"])
    if not frames:
        raise ValueError("a tracked run without frames has nothing to report")
    geometry = last_views[0].geometry
    page = qa_report.Page()
    planes = "biplane" if len(last_views) == 2 else "one plane"
    body = [f"<h1>Tracking report ({planes}, {len(frames)} frames processed)</h1>", "<h2>Summary</h2>"]
    body.append(_summary(dict(doc.get("summary") or {})))
    chart = strip_charts(doc, geometry, truth)
    body.append("<h2>Over the run</h2>" + page.image("strip_charts.png", chart, "pose, decisions, latency", wide=True))
    body.append("<h2>Decisions (frames that moved the roadmap or were withheld)</h2>" + _decisions(frames))
    last = np.asarray(frames[-1]["patient_motion"], dtype=np.float64)
    body.append(f"<h2>The last frame ({frames[-1]['frame']}) at the pose the roadmap shows</h2>")
    names = ("PLANE A", "PLANE B") if len(last_views) == 2 else ("",)
    for view, plane in zip(last_views, names, strict=True):
        body.append(
            qa_report.plane_pictures(
                page, view, plane, renderer=renderer, motion=last, initial=np.eye(4), anatomy=anatomy, checker_px=24,
                pose_name="the pose the roadmap shows", initial_name="the machine-based pose (the run's start)",
            )
        )  # fmt: skip
    body.append(qa_report.inputs_section(volume, last_views, doc, identify))
    body.append(qa_report.footer(command))
    saved = dict(doc)
    if not identify:
        for key in ("volume", "runs"):
            saved.pop(key, None)  # file paths may name the patient
    with atomic_folder(out) as tmp:
        for name, data in page.files.items():
            (tmp / name).write_bytes(data)
        (tmp / qa_report.REPORT_JSON).write_text(json_dumps(saved))
        (tmp / qa_report.REPORT_HTML).write_text(qa_report.page_html("Tracking report", "".join(body)))
    return out
