"""The studies' reports' shared parts: statistics, matplotlib figures (stamped with the data and the
revision), Markdown tables, the HTML page, the ROC plot and where the numbers came from.
"""

from __future__ import annotations

import html
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from registration import __version__

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


# --------------------------------------------------------------------------------------
# Plots
# --------------------------------------------------------------------------------------
def pyplot():  # noqa: ANN202 - matplotlib's pyplot module
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def stamp(fig, records: Sequence[dict]) -> None:  # noqa: ANN001
    """Software version, revision and study seed in a corner of every figure."""
    seeds = sorted({r.get("study_seed") for r in records if r.get("study_seed") is not None})
    seed = ", ".join(str(s) for s in seeds) if seeds else "?"
    rev = source_revision()
    text = f"roadmap3d {__version__}" + (f" ({rev})" if rev else "") + f", seed {seed}"
    fig.text(0.995, 0.003, text, ha="right", va="bottom", fontsize=6, color="#777777")


def binned(values: Sequence[float], edges: Sequence[float]) -> tuple[list[str], list[int]]:
    v = np.asarray(list(values), dtype=float)
    counts = [int(np.sum((v >= lo) & (v < hi))) for lo, hi in zip(edges[:-1], edges[1:], strict=True)]
    counts.append(int(np.sum(v >= edges[-1])))
    labels = [f"{lo:g}-{hi:g}" for lo, hi in zip(edges[:-1], edges[1:], strict=True)] + ["More"]
    return labels, counts


def bars(ax, values: Sequence[float], edges: Sequence[float], title: str, unit: str, color: str = "#4a7ab5") -> None:  # noqa: ANN001
    labels, counts = binned(values, edges)
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
    headroom(ax, max(counts))


def headroom(ax, top: int) -> None:  # noqa: ANN001
    from matplotlib.ticker import MaxNLocator

    ax.set_ylim(0, max(1.0, top * 1.15 + 0.3))
    ax.yaxis.set_major_locator(MaxNLocator(integer=True))


# --------------------------------------------------------------------------------------
# Reports
# --------------------------------------------------------------------------------------
def fmt_pct(x: float | None) -> str:
    return "-" if x is None else f"{100.0 * x:.1f} %"


def fmt_ms(s: dict | None, digits: int = 3) -> str:
    return "-" if not s else f"{s['mean']:.{digits}f} ± {s['std']:.{digits}f}"


def md_row(cells: Sequence[object]) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |"


def md_table(head: Sequence[str], rows: Sequence[Sequence[object]]) -> list[str]:
    return [md_row(head), md_row(["---"] * len(head)), *(md_row(r) for r in rows)]


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


def provenance(summary: dict) -> list[str]:
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


def write_report(out: Path, md: str, title: str) -> None:
    (out / "report.md").write_text(md)
    (out / "report.html").write_text(markdown_to_html(md, title))


def roc_plot(confidence: list[float], right: list[bool], threshold: float, path: Path, *, title: str) -> Path:
    """ROC curve of 'apply when confidence >= c', with the rule's operating point."""
    from registration.core.confidence import precision_recall, roc_curve

    plt = pyplot()
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


def fmt_mm(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f} mm"


def run_facts(records: Sequence[dict], config: dict, wall_seconds: float) -> dict:
    """What a study's summary says of its run: registration seconds and DRRs (median), wall time,
    the volume, the configuration and seed, the version and the revision the records came from."""
    return {
        "seconds_median": float(np.median([r["seconds"] for r in records])) if records else None,
        "seconds_total": float(sum(r["seconds"] for r in records)),
        "drr_count_median": float(np.median([r["drr_count"] for r in records])) if records else None,
        "wall_seconds": wall_seconds,
        "volume_label": records[0]["volume_label"] if records else "",
        "config": config,
        "seed": config.get("seed"),
        "version": __version__,
        "revision": records_revision(records),
    }
