"""Summaries, plots and reports of the validation studies (:mod:`registration.studies.runs`).

Plots follow the paper: a Table II-style heatmap per image kind (pass/fail colour and the
in-plane residual at the iso-center per cell, the non-clinically-relevant subset hatched
blue), Fig. 6-style histograms of the translational residual (narrow bins at the left, a
"More" bin for failures), and Fig. 7-style translation and rotation histograms for the
clinical study. ``report.md`` and ``report.html`` set our numbers beside the paper's.
"""

from __future__ import annotations

import html
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from registration import __version__

#: The paper's numbers (Homan et al., section III and Tables II-III).
PAPER_PHANTOM = {
    "success_rate_exposure": 0.84,
    "success_rate_fluoro": 0.83,
    "success_rate_clinically_relevant": 0.97,
    "table3": {
        "all": {
            "rotation_all": (1.330, 2.646, 0.010, 42.601),
            "rotation_successful": (0.659, 0.686, 0.010, 5.630),
            "translation_all": (1.519, 3.204, 0.005, 33.068),
            "translation_successful": (0.283, 0.211, 0.005, 1.410),
        },
        "clinically_relevant": {
            "rotation_all": (0.952, 1.852, 0.010, 22.284),
            "rotation_successful": (0.590, 0.596, 0.010, 4.572),
            "translation_all": (0.657, 2.238, 0.005, 33.068),
            "translation_successful": (0.276, 0.218, 0.005, 1.410),
        },
    },
}
PAPER_CLINICAL = {
    "translation_success_rate": 0.871,
    "rotation_success_rate": 0.839,
    "contrast": {"translation_success_rate": 0.924, "rotation_success_rate": 0.866},
    "no_contrast": {"translation_success_rate": 0.818, "rotation_success_rate": 0.812},
    "inplane_residual_mm": (0.89, 2.79),
    "rotation_residual_deg": (2.63, 4.76),
    "inplane_residual_mm_successful": (0.24, 0.21),
    "rotation_residual_deg_successful": (1.11, 0.68),
    "offset_translation_mm": (12.54, 6.79),
    "offset_inplane_mm": (10.28, 6.07),
    "offset_outofplane_mm": (6.09, 4.91),
    "offset_rotation_deg": (5.19, 2.79),
}
#: Our targets (shared/DESIGN.md).
TARGETS = {
    "success_rate_clinically_relevant": 0.99,
    "success_rate": 0.90,
    "clinical_success_rate": 0.95,
    "residual_mm": 0.25,
    "residual_deg": 0.5,
}

#: Fig. 6/7 bin edges: narrow at the left (as the paper), then a "More" bin.
TRANSLATION_BINS_MM = (0.0, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0)
ROTATION_BINS_DEG = (0.0, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 1.5, 2.0, 2.5, 3.0)


# --------------------------------------------------------------------------------------
# Statistics
# --------------------------------------------------------------------------------------
def stats(values: Sequence[float]) -> dict | None:
    """mean, std, min, max (None when empty)."""
    v = np.asarray(list(values), dtype=float)
    if v.size == 0:
        return None
    return {
        "mean": float(v.mean()),
        "std": float(v.std()),
        "min": float(v.min()),
        "max": float(v.max()),
        "n": int(v.size),
    }


def rate(records: Sequence[dict], key: str = "success") -> float | None:
    return None if not records else sum(bool(r[key]) for r in records) / len(records)


def table3(records: Sequence[dict]) -> dict:
    """Table III rows: rotation / in-plane translation, all / successful."""
    ok = [r for r in records if r["success"]]
    return {
        "rotation_all": stats([r["rotation_residual_deg"] for r in records]),
        "rotation_successful": stats([r["rotation_residual_deg"] for r in ok]),
        "translation_all": stats([r["inplane_residual_mm"] for r in records]),
        "translation_successful": stats([r["inplane_residual_mm"] for r in ok]),
        "total_translation_all": stats([r["translation_residual_mm"] for r in records]),
    }


def _breakdown(records: Sequence[dict], key: str) -> dict:
    out: dict = {}
    for r in records:
        out.setdefault(str(r[key]), []).append(r)
    return {k: {"runs": len(v), "success_rate": rate(v)} for k, v in sorted(out.items(), key=lambda kv: _num(kv[0]))}


def _num(s: str) -> tuple:
    try:
        return (0, float(s), "")
    except ValueError:
        return (1, 0.0, s)


def applied_summary(records: Sequence[dict]) -> dict:
    """Applied precision (applied estimates that succeeded) and recall (successes that were
    applied), over the records that carry a decision (CONVENTIONS §7, issue 13)."""
    decided = [r for r in records if "applied" in r]
    applied = [r for r in decided if r["applied"]]
    right = [r for r in decided if r["success"]]
    both = [r for r in applied if r["success"]]
    errors = [r["inplane_residual_mm"] for r in applied if r.get("inplane_residual_mm") is not None]
    return {
        "applied_precision": len(both) / len(applied) if applied else None,
        "applied_recall": len(both) / len(right) if right else None,
        "applied": len(applied),
        "withheld": len(decided) - len(applied),
        "applied_wrong": [r.get("case_id") for r in applied if not r["success"]],
        "max_inplane_error_applied_mm": float(max(errors)) if errors else None,
        "applied_worse_than_2mm": sum(e >= 2.0 for e in errors),
    }


def phantom_summary(records: Sequence[dict], *, config: dict, wall_seconds: float) -> dict:
    """The phantom study's numbers (the ``--json`` object)."""
    grid = [r for r in records if r.get("variant", "standard") == "standard"]
    facial = [r for r in records if r.get("variant") == "facial"]
    relevant = [r for r in grid if r["clinically_relevant"]]
    by_kind = {}
    for kind in sorted({r["image_kind"] for r in records}):
        g = [r for r in grid if r["image_kind"] == kind]
        by_kind[kind] = {
            "runs": len(g),
            "success_rate": rate(g),
            "success_rate_clinically_relevant": rate([r for r in g if r["clinically_relevant"]]),
            "runs_clinically_relevant": sum(r["clinically_relevant"] for r in g),
        }
    failures = [r for r in records if not r["success"]]
    return {
        "study": "phantom",
        "runs": len(records),
        "runs_grid": len(grid),
        "runs_clinically_relevant": len(relevant),
        "success_rate": rate(grid),
        "success_rate_clinically_relevant": rate(relevant),
        "success_rate_facial_volume": rate(facial),
        "runs_facial_volume": len(facial),
        "success_rate_total_translation": rate(grid, "success_total"),
        **applied_summary(records),
        "by_kind": by_kind,
        "by_offset": _breakdown(grid, "offset"),
        "by_volume_format": _breakdown(grid, "volume_format_cm"),
        "by_image_format": _breakdown(grid, "image_format_cm"),
        "table3": {
            "all": table3(records),
            "clinically_relevant": table3([r for r in records if r["clinically_relevant"]]),
        },
        "failures": [
            {k: r.get(k) for k in ("case_id", "inplane_residual_mm", "rotation_residual_deg", "outofplane_residual_mm")}
            for r in failures
        ],
        "seconds_median": float(np.median([r["seconds"] for r in records])) if records else None,
        "seconds_total": float(sum(r["seconds"] for r in records)),
        "drr_count_median": float(np.median([r["drr_count"] for r in records])) if records else None,
        "wall_seconds": wall_seconds,
        "volume_label": records[0]["volume_label"] if records else "",
        "config": config,
        "seed": config.get("seed"),
        "version": __version__,
        "revision": records_revision(records),
        "paper": {k: v for k, v in PAPER_PHANTOM.items() if k != "table3"},
        "targets": {k: TARGETS[k] for k in ("success_rate_clinically_relevant", "success_rate")},
    }


def _clinical_group(records: Sequence[dict]) -> dict:
    ok = [r for r in records if r["success"]]
    return {
        "runs": len(records),
        "translation_success_rate": rate(records, "translation_success"),
        "rotation_success_rate": rate(records, "rotation_success"),
        "success_rate": rate(records),
        "inplane_residual_mm": stats([r["inplane_residual_mm"] for r in records]),
        "outofplane_residual_mm": stats([r["outofplane_residual_mm"] for r in records]),
        "rotation_residual_deg": stats([r["rotation_residual_deg"] for r in records]),
        "inplane_residual_mm_successful": stats([r["inplane_residual_mm"] for r in ok]),
        "rotation_residual_deg_successful": stats([r["rotation_residual_deg"] for r in ok]),
    }


def clinical_summary(records: Sequence[dict], *, config: dict, wall_seconds: float) -> dict:
    """The clinical study's numbers (the ``--json`` object)."""
    out = {"study": "clinical", **_clinical_group(records), **applied_summary(records)}
    out["contrast"] = _clinical_group([r for r in records if r["contrast"]])
    out["no_contrast"] = _clinical_group([r for r in records if not r["contrast"]])
    out["by_patient"] = {
        str(p): {
            "volume_format_cm": rs[0]["volume_format_cm"],
            "contrast": rs[0]["contrast"],
            "runs": len(rs),
            "translation_success_rate": rate(rs, "translation_success"),
            "rotation_success_rate": rate(rs, "rotation_success"),
        }
        for p in sorted({r["patient"] for r in records})
        for rs in [[r for r in records if r["patient"] == p]]
    }
    out["offsets"] = {
        k: stats([r[k] for r in records])
        for k in ("offset_translation_mm", "offset_inplane_mm", "offset_outofplane_mm", "offset_rotation_deg")
    }
    out["failures_by_offset"] = _failures_by_offset(records)
    out["failures"] = [
        {
            k: r.get(k)
            for k in (
                "case_id",
                "frame",
                "primary_deg",
                "offset_inplane_mm",
                "offset_outofplane_mm",
                "offset_rotation_deg",
                "inplane_residual_mm",
                "rotation_residual_deg",
            )
        }
        for r in records
        if not r["success"]
    ]
    out.update(
        {
            "seconds_median": float(np.median([r["seconds"] for r in records])) if records else None,
            "seconds_total": float(sum(r["seconds"] for r in records)),
            "drr_count_median": float(np.median([r["drr_count"] for r in records])) if records else None,
            "wall_seconds": wall_seconds,
            "volume_label": records[0]["volume_label"] if records else "",
            "config": config,
            "seed": config.get("seed"),
            "version": __version__,
            "revision": records_revision(records),
            "paper": PAPER_CLINICAL,
            "targets": {"translation_success_rate": TARGETS["clinical_success_rate"], "rotation_success_rate": 0.95},
        }
    )
    return out


def _failures_by_offset(records: Sequence[dict]) -> dict:
    """Success rate by in-plane offset length and by offset rotation (where do we miss?)."""
    out = {}
    for key, edges in (
        ("offset_inplane_mm", (0.0, 5.0, 10.0, 15.0, 20.0, 25.0)),
        ("offset_outofplane_mm", (0.0, 5.0, 10.0, 15.0, 20.0, 25.0)),
        ("offset_rotation_deg", (0.0, 2.5, 5.0, 7.5, 10.0)),
    ):
        rows = {}
        for i, (lo, hi) in enumerate(zip(edges[:-1], edges[1:], strict=True)):
            last = i == len(edges) - 2
            sel = [r for r in records if lo <= r[key] and (r[key] < hi or last)]
            rows[f"{lo:g}-{hi:g}"] = {"runs": len(sel), "success_rate": rate(sel)}
        out[key] = rows
    return out


# --------------------------------------------------------------------------------------
# Plots
# --------------------------------------------------------------------------------------
def _plt():  # noqa: ANN202 - matplotlib's pyplot module
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def heatmap(records: Sequence[dict], kind: str, path: Path, *, title_extra: str = "") -> Path | None:
    """Table II for one image kind: rows volume format x offset, columns image format."""
    rows_rec = [r for r in records if r["image_kind"] == kind]
    if not rows_rec:
        return None
    plt = _plt()
    from matplotlib.patches import Rectangle

    offsets = sorted({r["offset"] for r in rows_rec})
    images = sorted({r["image_format_cm"] for r in rows_rec})
    blocks = [
        ("standard", v) for v in sorted({r["volume_format_cm"] for r in rows_rec if r.get("variant") != "facial"})
    ]
    if any(r.get("variant") == "facial" for r in rows_rec):
        blocks.append(("facial", 22.0))
    cell = {
        (r.get("variant", "standard"), r["volume_format_cm"], r["offset"], r["image_format_cm"]): r for r in rows_rec
    }
    n_rows = len(blocks) * len(offsets)
    fig, ax = plt.subplots(figsize=(max(5.0, 1.0 + 1.05 * len(images)), 1.8 + 0.3 * n_rows))
    green, red, grey = "#5cb85c", "#d9534f", "#dddddd"
    for bi, (variant, vol) in enumerate(blocks):
        for oi, off in enumerate(offsets):
            y = bi * len(offsets) + oi
            for xi, img in enumerate(images):
                r = cell.get((variant, vol, off, img))
                color = grey if r is None else (green if r["success"] else red)
                ax.add_patch(Rectangle((xi, y), 1, 1, facecolor=color, edgecolor="white", lw=0.8))
                if r is None:
                    ax.text(xi + 0.5, y + 0.5, "not run", ha="center", va="center", fontsize=6, color="#777777")
                    continue
                if r is not None:
                    txt = f"{r['inplane_residual_mm']:.2f}"
                    if not r["success"] and r["inplane_residual_mm"] < 1.0:
                        txt += f"\n{r['rotation_residual_deg']:.1f}°"
                    ax.text(xi + 0.5, y + 0.5, txt, ha="center", va="center", fontsize=6.5)
                relevant = variant == "standard" and _relevant(vol, img)
                if variant == "facial":
                    relevant = _relevant(vol, img)
                if not relevant:
                    ax.add_patch(
                        Rectangle(
                            (xi, y), 1, 1, facecolor="#337ab7", alpha=0.28, hatch="///", edgecolor="#1f4e79", lw=0
                        )
                    )
        ax.axhline(bi * len(offsets), color="black", lw=1.2)
    ax.set_xlim(0, len(images))
    ax.set_ylim(n_rows, 0)
    ax.set_xticks(np.arange(len(images)) + 0.5, [f"{i:g}" for i in images])
    ax.xaxis.tick_top()
    ax.set_xlabel("image format (cm)")
    ax.xaxis.set_label_position("top")
    ylabels = [f"{'22F' if variant == 'facial' else f'{vol:g}'}  {off}" for variant, vol in blocks for off in offsets]
    ax.set_yticks(np.arange(n_rows) + 0.5, ylabels, fontsize=7)
    ax.set_ylabel("volume format (cm), offset")
    ax.set_title(
        f"Table II ({kind}): in-plane residual at the iso-center (mm)\n"
        "green: < 1 mm and < 3° (red: fails; rotation shown when it alone fails)\n"
        "hatched blue: not clinically relevant; 22F: 22 cm volume with the face" + title_extra,
        fontsize=8,
    )
    fig.tight_layout()
    _stamp(fig, records)
    fig.savefig(path, dpi=130)
    plt.close(fig)
    return path


def _stamp(fig, records: Sequence[dict]) -> None:  # noqa: ANN001
    """Software version, revision and study seed in a corner of every figure."""
    seeds = sorted({r.get("study_seed") for r in records if r.get("study_seed") is not None})
    seed = ", ".join(str(s) for s in seeds) if seeds else "?"
    rev = source_revision()
    text = f"roadmap3d {__version__}" + (f" ({rev})" if rev else "") + f", seed {seed}"
    fig.text(0.995, 0.003, text, ha="right", va="bottom", fontsize=6, color="#777777")


def _relevant(vol: float, img: float) -> bool:
    from registration.core.geometry import clinically_relevant

    return clinically_relevant(vol, img)


def _binned(values: Sequence[float], edges: Sequence[float]) -> tuple[list[str], list[int]]:
    v = np.asarray(list(values), dtype=float)
    counts = [int(np.sum((v >= lo) & (v < hi))) for lo, hi in zip(edges[:-1], edges[1:], strict=True)]
    counts.append(int(np.sum(v >= edges[-1])))
    labels = [f"{lo:g}-{hi:g}" for lo, hi in zip(edges[:-1], edges[1:], strict=True)] + ["More"]
    return labels, counts


def _bars(ax, values: Sequence[float], edges: Sequence[float], title: str, unit: str, color: str = "#4a7ab5") -> None:  # noqa: ANN001
    labels, counts = _binned(values, edges)
    x = np.arange(len(labels))
    colors = [color] * (len(labels) - 1) + ["#d9534f"]
    ax.bar(x, counts, color=colors)
    ax.set_xticks(x, labels, rotation=60, fontsize=7)
    ax.set_title(f"{title} (n = {len(list(values))})", fontsize=9)
    ax.set_xlabel(unit, fontsize=8)
    ax.set_ylabel("registrations", fontsize=8)
    for xi, c in zip(x, counts, strict=True):
        if c:
            ax.text(xi, c, str(c), ha="center", va="bottom", fontsize=6.5)
    _headroom(ax, max(counts))


def _headroom(ax, top: int) -> None:  # noqa: ANN001
    from matplotlib.ticker import MaxNLocator

    ax.set_ylim(0, max(1.0, top * 1.15 + 0.3))
    ax.yaxis.set_major_locator(MaxNLocator(integer=True))


def phantom_histograms(records: Sequence[dict], path: Path) -> Path:
    """Fig. 6: in-plane residual, (a) all exposure, (b) all fluoro, (c, d) clinically relevant."""
    plt = _plt()
    grid = [r for r in records if r.get("variant", "standard") == "standard"]
    kinds = [k for k in ("exposure", "fluoro") if any(r["image_kind"] == k for r in grid)] or ["exposure"]
    fig, axes = plt.subplots(2, len(kinds), figsize=(5.2 * len(kinds), 7), squeeze=False)
    panels = [
        ("(a) all, exposure", [r for r in grid if r["image_kind"] == "exposure"]),
        ("(b) all, fluoro", [r for r in grid if r["image_kind"] == "fluoro"]),
        (
            "(c) clinically relevant, exposure",
            [r for r in grid if r["image_kind"] == "exposure" and r["clinically_relevant"]],
        ),
        (
            "(d) clinically relevant, fluoro",
            [r for r in grid if r["image_kind"] == "fluoro" and r["clinically_relevant"]],
        ),
    ]
    panels = [p for p in panels if any(k in p[0] for k in kinds)]
    for ax, (title, rs) in zip(axes.ravel(), panels, strict=True):
        if not rs:
            ax.text(0.5, 0.5, "not in this run", ha="center", va="center", transform=ax.transAxes)
            ax.set_title(title, fontsize=9)
            ax.set_axis_off()
            continue
        _bars(ax, [r["inplane_residual_mm"] for r in rs], TRANSLATION_BINS_MM, title, "in-plane residual (mm)")
    fig.suptitle("Fig. 6: in-plane translational residual (phantom); red: 'More' (>= 1 mm)", fontsize=10)
    fig.tight_layout()
    _stamp(fig, records)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def clinical_histograms(records: Sequence[dict], path: Path) -> Path:
    """Fig. 7: in-plane translation and rotation residuals, with and without contrast stacked."""
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, key, edges, unit in (
        (axes[0], "inplane_residual_mm", TRANSLATION_BINS_MM, "in-plane residual (mm)"),
        (axes[1], "rotation_residual_deg", ROTATION_BINS_DEG, "rotational residual (deg)"),
    ):
        labels, with_c = _binned([r[key] for r in records if r["contrast"]], edges)
        _, without = _binned([r[key] for r in records if not r["contrast"]], edges)
        x = np.arange(len(labels))
        ax.bar(x, with_c, color="#4a7ab5", label="contrast")
        ax.bar(x, without, bottom=with_c, color="#9ecae1", label="no contrast")
        ax.set_xticks(x, labels, rotation=60, fontsize=7)
        ax.axvline(len(labels) - 1.5, color="#d9534f", ls="--", lw=1)
        ax.set_xlabel(unit, fontsize=8)
        ax.set_ylabel("registrations", fontsize=8)
        for xi, (a, b) in enumerate(zip(with_c, without, strict=True)):
            if a + b:
                ax.text(xi, a + b, str(a + b), ha="center", va="bottom", fontsize=6.5)
        _headroom(ax, max(a + b for a, b in zip(with_c, without, strict=True)))
        ax.legend(fontsize=7)
        ax.set_title(f"{unit.split(' (')[0]} (n = {len(records)}); right of the dashed line: fails", fontsize=9)
    fig.suptitle("Fig. 7: residual error, rotational-run ('clinical') study", fontsize=10)
    fig.tight_layout()
    _stamp(fig, records)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


# --------------------------------------------------------------------------------------
# Reports
# --------------------------------------------------------------------------------------
def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100.0 * x:.1f} %"


def _ms(s: dict | None, digits: int = 3) -> str:
    return "-" if not s else f"{s['mean']:.{digits}f} ± {s['std']:.{digits}f}"


def _row(cells: Sequence[object]) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |"


def _table(head: Sequence[str], rows: Sequence[Sequence[object]]) -> list[str]:
    return [_row(head), _row(["---"] * len(head)), *(_row(r) for r in rows)]


def source_revision() -> str:
    """``git describe --always --dirty`` of the source tree, or "" outside a checkout."""
    import subprocess

    try:
        out = subprocess.run(
            ["git", "describe", "--always", "--dirty"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=10,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return ""
    return out.stdout.strip() if out.returncode == 0 else ""


def records_revision(records: Sequence[dict]) -> str:
    """The source revision(s) the records were computed with (or today's, marked as such)."""
    revisions = sorted({r["revision"] for r in records if r.get("revision")})
    if revisions:
        return ", ".join(revisions)
    current = source_revision()
    return f"{current} at report time" if current else ""


def _provenance(summary: dict) -> list[str]:
    cfg = summary["config"]
    return [
        f"roadmap3d {summary['version']}"
        + (f" (source {summary['revision']})" if summary.get("revision") else "")
        + f", seed {summary['seed']}, "
        f"{'quick' if cfg.get('quick') else 'full'} configuration; "
        f"{summary['runs']} registrations, wall time {summary['wall_seconds'] / 60:.1f} min (every invocation "
        f"that ran registrations, volume builds included), median {summary['seconds_median'] or 0:.2f} s and "
        f"{summary['drr_count_median'] or 0:.0f} DRRs per registration.",
        "",
        f"Registration volume: {summary['volume_label']}.",
        "",
        "Configuration: `" + ", ".join(f"{k}={v}" for k, v in cfg.items()) + "`",
    ]


def phantom_report_md(records: Sequence[dict], summary: dict, images: dict[str, str]) -> str:
    t3p = PAPER_PHANTOM["table3"]
    lines = [
        "# Phantom study: Tables II-III and Fig. 6 (Homan et al.) reproduced",
        "",
        *_provenance(summary),
        "",
        "Success: in-plane residual at the iso-center < 1 mm and rotational residual < 3° (single view: the",
        "out-of-plane translation is not optimised). Clinically relevant subset (paper II.C): neither format",
        "15 or 19 cm, and volume format >= image format.",
        "",
        "## Success rates beside the paper",
        "",
    ]
    rows = []
    for kind, paper_all in (("exposure", 0.84), ("fluoro", 0.83)):
        k = summary["by_kind"].get(kind)
        if k:
            rows.append(
                [
                    kind,
                    f"{_pct(k['success_rate'])} ({k['runs']})",
                    _pct(paper_all),
                    f"{_pct(k['success_rate_clinically_relevant'])} ({k['runs_clinically_relevant']})",
                    "97 %",
                ]
            )
    rows.append(
        [
            "**both**",
            f"**{_pct(summary['success_rate'])}** ({summary['runs_grid']})",
            "83.5 %",
            f"**{_pct(summary['success_rate_clinically_relevant'])}** ({summary['runs_clinically_relevant']})",
            "97 %",
        ]
    )
    lines += _table(
        ["images", "ours, all formats run (n)", "paper, all", "ours, clinically relevant (n)", "paper"], rows
    )
    lines += [
        "",
        f"Targets (DESIGN.md): >= 99 % clinically relevant, >= 90 % all formats. Alternative 22 cm volume with the "
        f"facial structures: {_pct(summary['success_rate_facial_volume'])} of {summary['runs_facial_volume']}.",
        "",
        "## Table II",
        "",
    ]
    for kind in ("exposure", "fluoro"):
        if kind in images:
            lines += [f"![Table II, {kind}]({images[kind]})", ""]
    lines += ["## Table III: residual error (rotation deg, in-plane translation mm)", ""]
    t3 = summary["table3"]
    rows = []
    names = {
        "rotation_all": "Rotation (all)",
        "rotation_successful": "Rotation (successful)",
        "translation_all": "Translation (all)",
        "translation_successful": "Translation (successful)",
    }
    for key, name in names.items():
        row: list[object] = [name]
        for subset in ("all", "clinically_relevant"):
            s = t3[subset][key]
            p = t3p[subset][key]
            row += [
                "-" if not s else f"{s['mean']:.3f} / {s['std']:.3f} / {s['min']:.3f} / {s['max']:.3f}",
                f"{p[0]:.3f} / {p[1]:.3f} / {p[2]:.3f} / {p[3]:.3f}",
            ]
        rows.append(row)
    lines += _table(
        ["mean / std / min / max", "ours, all", "paper, all", "ours, clinically relevant", "paper, clin. relevant"],
        rows,
    )
    lines += [
        "",
        "Table III here covers every registration of this run (the facial-volume ones included, as the paper's",
        '"all phantom experiments").',
        "",
        "## Fig. 6",
        "",
        f"![Fig. 6]({images['hist']})",
        "",
        "## Where we miss",
        "",
    ]
    for key, name in (
        ("by_offset", "offset"),
        ("by_volume_format", "volume format (cm)"),
        ("by_image_format", "image format (cm)"),
    ):
        rows = [[k, v["runs"], _pct(v["success_rate"])] for k, v in summary[key].items()]
        lines += _table([name, "runs", "success"], rows) + [""]
    fails = summary["failures"]
    if fails:
        lines += [f"{len(fails)} failed registrations:", ""]
        lines += _table(
            ["case", "in-plane (mm)", "rotation (deg)", "out-of-plane (mm)"],
            [
                [
                    f"`{f['case_id']}`",
                    f"{f['inplane_residual_mm']:.2f}",
                    f"{f['rotation_residual_deg']:.2f}",
                    f"{f['outofplane_residual_mm']:.2f}",
                ]
                for f in fails
            ],
        )
    else:
        lines += ["No failed registration."]
    return "\n".join(lines) + "\n"


CLINICAL_METHOD = (
    "Each virtual patient (a phantom variant) has its own simulated rotational run (images formed with the",
    "true, bent C-arm geometry) and its FDK reconstruction (from the calibrated geometry). A random frame of",
    "the run is registered to the reconstruction from a pose offset by a random translation (length uniform",
    "in [0, 25] mm, random direction) and rotation (uniform in [0, 10]° about a random axis through the",
    "iso-center); the truth is the calibrated geometry of that frame. Translation success: in-plane residual",
    "< 1 mm; rotation success: < 3°.",
)


def clinical_report_md(
    records: Sequence[dict],
    summary: dict,
    images: dict[str, str],
    *,
    title: str = "Rotational-run ('clinical') study: Fig. 7 (Homan et al. III.B) reproduced",
    method: Sequence[str] = CLINICAL_METHOD,
) -> str:
    """The report (``method``: the paragraph saying what was registered; the rotational-run
    validation of an archived run passes its own)."""
    p = PAPER_CLINICAL
    lines = [
        f"# {title}",
        "",
        *_provenance(summary),
        "",
        *method,
        "",
        "## Success rates beside the paper",
        "",
    ]
    rows = []
    for name, ours, paper in (
        ("all", summary, p),
        ("with contrast", summary["contrast"], p["contrast"]),
        ("without contrast", summary["no_contrast"], p["no_contrast"]),
    ):
        rows.append(
            [
                name,
                ours["runs"],
                _pct(ours["translation_success_rate"]),
                _pct(paper["translation_success_rate"]),
                _pct(ours["rotation_success_rate"]),
                _pct(paper["rotation_success_rate"]),
            ]
        )
    lines += _table(["runs", "n", "translation < 1 mm", "paper", "rotation < 3°", "paper"], rows)
    lines += [
        "",
        "Target (DESIGN.md): >= 95 % on both criteria.",
        "",
        "## Residuals (mean ± std)",
        "",
    ]
    lines += _table(
        ["", "ours", "paper"],
        [
            [
                "in-plane translation, all (mm)",
                _ms(summary["inplane_residual_mm"], 2),
                f"{p['inplane_residual_mm'][0]} ± {p['inplane_residual_mm'][1]}",
            ],
            [
                "rotation, all (deg)",
                _ms(summary["rotation_residual_deg"], 2),
                f"{p['rotation_residual_deg'][0]} ± {p['rotation_residual_deg'][1]}",
            ],
            [
                "in-plane translation, successful (mm)",
                _ms(summary["inplane_residual_mm_successful"], 2),
                f"{p['inplane_residual_mm_successful'][0]} ± {p['inplane_residual_mm_successful'][1]}",
            ],
            [
                "rotation, successful (deg)",
                _ms(summary["rotation_residual_deg_successful"], 2),
                f"{p['rotation_residual_deg_successful'][0]} ± {p['rotation_residual_deg_successful'][1]}",
            ],
            ["out-of-plane translation, all (mm; not optimised)", _ms(summary["outofplane_residual_mm"], 2), "-"],
        ],
    )
    lines += ["", "## Offsets applied (mean ± std)", ""]
    lines += _table(
        ["", "ours", "paper"],
        [
            [name, _ms(summary["offsets"][key], 2), f"{p[key][0]} ± {p[key][1]}"]
            for key, name in (
                ("offset_translation_mm", "translation length (mm)"),
                ("offset_inplane_mm", "in-plane part (mm)"),
                ("offset_outofplane_mm", "out-of-plane part (mm)"),
                ("offset_rotation_deg", "rotation (deg)"),
            )
        ],
    )
    lines += ["", "## Fig. 7", "", f"![Fig. 7]({images['hist']})", "", "## Where we miss", ""]
    rows = [
        [
            k,
            v["volume_format_cm"],
            "yes" if v["contrast"] else "no",
            v["runs"],
            _pct(v["translation_success_rate"]),
            _pct(v["rotation_success_rate"]),
        ]
        for k, v in summary["by_patient"].items()
    ]
    lines += _table(["patient", "format (cm)", "contrast", "runs", "translation", "rotation"], rows) + [""]
    for key, name in (
        ("offset_inplane_mm", "in-plane offset (mm)"),
        ("offset_outofplane_mm", "out-of-plane offset (mm; not optimised)"),
        ("offset_rotation_deg", "rotation offset (deg)"),
    ):
        rows = [[k, v["runs"], _pct(v["success_rate"])] for k, v in summary["failures_by_offset"][key].items()]
        lines += _table([name, "runs", "success (both)"], rows) + [""]
    fails = summary["failures"]
    if fails:
        lines += [f"{len(fails)} failed registrations:", ""]
        lines += _table(
            [
                "case",
                "frame (primary deg)",
                "offset in-plane (mm)",
                "offset out-of-plane (mm)",
                "offset rotation (deg)",
                "residual in-plane (mm)",
                "residual rotation (deg)",
            ],
            [
                [
                    f"`{f['case_id']}`",
                    f"{f['frame']} ({f['primary_deg']:.0f})",
                    f"{f['offset_inplane_mm']:.1f}",
                    f"{f['offset_outofplane_mm']:.1f}",
                    f"{f['offset_rotation_deg']:.1f}",
                    f"{f['inplane_residual_mm']:.2f}",
                    f"{f['rotation_residual_deg']:.2f}",
                ]
                for f in fails
            ],
        )
    else:
        lines += ["No failed registration."]
    return "\n".join(lines) + "\n"


def markdown_to_html(text: str, title: str) -> str:
    """The small Markdown subset the reports use (headings, tables, images, paragraphs)."""

    def inline(s: str) -> str:
        s = html.escape(s, quote=False)
        s = re.sub(r"!\[([^\]]*)\]\(([^)]+)\)", r'<img alt="\1" src="\2" style="max-width:100%">', s)
        s = re.sub(r"\*\*([^*]+)\*\*", r"<b>\1</b>", s)
        return re.sub(r"`([^`]+)`", r"<code>\1</code>", s)

    out = [
        "<!doctype html>",
        f"<html><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
        "<style>body{font-family:sans-serif;max-width:1100px;margin:2em auto;line-height:1.4}"
        "table{border-collapse:collapse;margin:0.5em 0}td,th{border:1px solid #ccc;padding:2px 8px;font-size:90%}"
        "code{font-size:85%}</style></head><body>",
    ]
    lines = text.splitlines()
    i = 0
    para: list[str] = []

    def flush() -> None:
        if para:
            out.append("<p>" + " ".join(inline(p) for p in para) + "</p>")
            para.clear()

    while i < len(lines):
        line = lines[i]
        if line.startswith("#"):
            flush()
            level = len(line) - len(line.lstrip("#"))
            out.append(f"<h{level}>{inline(line[level:].strip())}</h{level}>")
        elif line.startswith("|"):
            flush()
            table = []
            while i < len(lines) and lines[i].startswith("|"):
                table.append([c.strip() for c in lines[i].strip().strip("|").split("|")])
                i += 1
            out.append("<table>")
            out.append("<tr>" + "".join(f"<th>{inline(c)}</th>" for c in table[0]) + "</tr>")
            for row in table[2:]:
                out.append("<tr>" + "".join(f"<td>{inline(c)}</td>" for c in row) + "</tr>")
            out.append("</table>")
            continue
        elif not line.strip():
            flush()
        else:
            para.append(line)
        i += 1
    flush()
    out.append("</body></html>")
    return "\n".join(out) + "\n"


def _write(out: Path, md: str, title: str) -> None:
    (out / "report.md").write_text(md)
    (out / "report.html").write_text(markdown_to_html(md, title))


def roc_plot(confidence: list[float], right: list[bool], threshold: float, path: Path, *, title: str) -> Path:
    """ROC curve of 'apply when confidence >= c', with the rule's operating point."""
    from registration.core.confidence import precision_recall, roc_curve

    plt = _plt()
    roc = roc_curve(confidence, right)
    fig, ax = plt.subplots(figsize=(5, 5))
    ax.plot(roc["fpr"], roc["tpr"], color="#1f77b4", lw=1.8, label=f"AUC {roc['auc']:.3f}")
    ax.plot([0, 1], [0, 1], color="#aaa", lw=0.8, ls=":")
    applied = [c >= threshold for c in confidence]
    r = np.asarray(right, dtype=bool)
    a = np.asarray(applied, dtype=bool)
    fpr = float((a & ~r).sum() / max((~r).sum(), 1))
    tpr = float((a & r).sum() / max(r.sum(), 1))
    p, rc = precision_recall(applied, right)
    label = f"rule (c >= {threshold:.2f}): precision {100 * (p or 0):.1f} %, recall {100 * (rc or 0):.1f} %"
    ax.plot([fpr], [tpr], "o", color="#d62728", label=label)
    ax.set_xlabel("false positive rate (wrong estimates applied)")
    ax.set_ylabel("true positive rate (right estimates applied)")
    ax.set_title(f"{title}\n{roc['positives']} right, {roc['negatives']} wrong estimates", fontsize=10)
    ax.legend(fontsize=8, loc="lower right")
    ax.set_xlim(-0.02, 1.02)
    ax.set_ylim(-0.02, 1.02)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def confidence_section(records: Sequence[dict], out: Path, images: dict[str, str], title: str) -> str:
    """The ROC plot of the records' confidence against their success, and its markdown section."""
    from registration.core.confidence import DEFAULT_RULE

    decided = [r for r in records if r.get("confidence") is not None]
    if not decided:
        return ""
    roc_plot([r["confidence"] for r in decided], [bool(r["success"]) for r in decided], DEFAULT_RULE.threshold,
             out / "roc.png", title=title)  # fmt: skip
    images["roc"] = "roc.png"
    s = applied_summary(decided)
    lines = [
        "",
        "## Confidence: which estimates would move the roadmap",
        "",
        "Every registration gets a confidence (`registration.core.confidence`: the margin of the measure over "
        "poses perturbed by 1 mm / 1 degree, for one plane also its margin over the out-of-plane rotations "
        "perturbed by 3 degrees and how far the in-plane estimate moves when the volume may also move along "
        "the beam (the depth probe: a wrong magnification), agreement of the capture runs, edges in the field) "
        f"and is applied when it reaches {DEFAULT_RULE.threshold:g}. {s['applied']} applied, {s['withheld']} "
        f"withheld; applied precision {_pct(s['applied_precision'])} (applied estimates that are right; target "
        f"99 %), recall {_pct(s['applied_recall'])} (right estimates that were applied; target 90 %); worst "
        f"applied in-plane error {_fmt_mm(s['max_inplane_error_applied_mm'])} (target < 2 mm). The rule's "
        "single-plane terms were calibrated on the clinical study's seeds 0 and 1 (140 registrations); "
        "results on those seeds are not a test of it.",
        "",
        "![ROC](roc.png)",
        "",
    ]
    wrong = [r for r in decided if r["applied"] and not r["success"]]
    if wrong:
        lines += ["Applied although wrong:", "", "| case | in-plane (mm) | rotation (deg) | confidence |",
                  "| --- | --- | --- | --- |"]  # fmt: skip
        lines += [
            f"| {r.get('case_id')} | {r.get('inplane_residual_mm', float('nan')):.2f} | "
            f"{r.get('rotation_residual_deg', float('nan')):.2f} | {r['confidence']:.2f} |"
            for r in wrong
        ]
        lines.append("")
    reasons: dict[str, list[bool]] = {}
    for r in decided:
        if not r["applied"]:
            reasons.setdefault(r.get("withheld_reason") or "low confidence", []).append(bool(r["success"]))
    if reasons:
        lines += ["| withheld because | estimates | of them right |", "| --- | --- | --- |"]
        lines += [f"| {k} | {len(v)} | {sum(v)} |" for k, v in sorted(reasons.items(), key=lambda kv: -len(kv[1]))]
        lines.append("")
    probed = [r for r in decided if "depth_success" in r]
    if probed:
        fixed = sum(r["depth_success"] and not r["success"] for r in probed)
        broken = sum(r["success"] and not r["depth_success"] for r in probed)
        lines += [
            f"The depth probe's own pose (six parameters, polished from the result; not applied), scored like "
            f"the result: {_pct(rate(probed, 'depth_success'))} successful against "
            f"{_pct(rate(probed, 'success'))} ({fixed} failures it would fix, {broken} successes it would "
            f"break); in-plane residual median "
            f"{_fmt_mm(float(np.median([r['depth_inplane_residual_mm'] for r in probed])))} against "
            f"{_fmt_mm(float(np.median([r['inplane_residual_mm'] for r in probed])))}.",
            "",
        ]
    return "\n".join(lines)


def _fmt_mm(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f} mm"


def write_phantom_report(records: Sequence[dict], summary: dict, out: Path) -> dict[str, str]:
    """Heatmaps, histograms, report.md/html and summary.json into ``out``."""
    import json

    out = Path(out)
    images: dict[str, str] = {}
    if records:
        for kind in ("exposure", "fluoro"):
            if heatmap(records, kind, out / f"table2_{kind}.png"):
                images[kind] = f"table2_{kind}.png"
        phantom_histograms(records, out / "fig6_histograms.png")
        images["hist"] = "fig6_histograms.png"
    else:
        images["hist"] = ""
    md = phantom_report_md(records, summary, images)
    md += confidence_section(records, out, images, "phantom study: confidence of the registrations")
    _write(out, md, "roadmap3d phantom study")
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    return images


def write_clinical_report(
    records: Sequence[dict],
    summary: dict,
    out: Path,
    *,
    title: str | None = None,
    method: Sequence[str] | None = None,
) -> dict[str, str]:
    import json

    out = Path(out)
    images = {"hist": ""}
    if records:
        clinical_histograms(records, out / "fig7_histograms.png")
        images["hist"] = "fig7_histograms.png"
    extra: dict[str, Any] = {}
    if title is not None:
        extra["title"] = title
    if method is not None:
        extra["method"] = method
    md = clinical_report_md(records, summary, images, **extra)
    md += confidence_section(records, out, images, f"{title or 'clinical study'}: confidence of the registrations")
    _write(out, md, f"roadmap3d {title or 'clinical study'}")
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    return images


def summary_lines(summary: dict) -> list[str]:
    """A few human-readable lines for the terminal."""
    head = f"roadmap3d {summary['version']}, seed {summary['seed']}: {summary['runs']} registrations"
    if summary["study"] == "phantom":
        lines = [
            head,
            f"success, all formats run: {_pct(summary['success_rate'])} (paper 84 % exposure / 83 % fluoro)",
            f"success, clinically relevant: {_pct(summary['success_rate_clinically_relevant'])} (paper 97 %)",
        ]
        if summary["runs_facial_volume"]:
            lines.append(f"success, facial 22 cm volume: {_pct(summary['success_rate_facial_volume'])}")
        s = summary["table3"]["all"]["translation_successful"]
        r = summary["table3"]["all"]["rotation_successful"]
        if s and r:
            lines.append(f"residual of successful runs: {_ms(s)} mm, {_ms(r)} deg (paper 0.283 mm, 0.659 deg)")
    else:
        lines = [
            head,
            f"translation < 1 mm: {_pct(summary['translation_success_rate'])} (paper 87.1 %), "
            f"rotation < 3 deg: {_pct(summary['rotation_success_rate'])} (paper 83.9 %)",
            f"with contrast {_pct(summary['contrast']['translation_success_rate'])} / "
            f"{_pct(summary['contrast']['rotation_success_rate'])}, without "
            f"{_pct(summary['no_contrast']['translation_success_rate'])} / "
            f"{_pct(summary['no_contrast']['rotation_success_rate'])} (paper 92.4/86.6, 81.8/81.2)",
        ]
    if summary.get("applied_precision") is not None or summary.get("applied_recall") is not None:
        lines.append(
            f"confidence: {summary['applied']} applied, {summary['withheld']} withheld; applied precision "
            f"{_pct(summary['applied_precision'])} (target 99 %), recall {_pct(summary['applied_recall'])} "
            "(target 90 %)"
        )
    lines.append(
        f"median {summary['seconds_median'] or 0:.2f} s per registration, wall {summary['wall_seconds']:.0f} s"
    )
    return lines
