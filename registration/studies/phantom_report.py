"""The phantom study's report (Table II-III and Fig. 6 of the paper): summary, heatmaps per image kind,
residual histograms, report.md and report.html with our numbers beside the paper's.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from registration.studies.report import TARGETS, applied_summary, confidence_section
from registration.studies.report_kit import (
    TRANSLATION_BINS_MM,
    bars,
    fmt_pct,
    md_table,
    provenance,
    pyplot,
    rate,
    run_facts,
    stamp,
    stats,
    write_report,
)

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
        **run_facts(records, config, wall_seconds),
        "paper": {k: v for k, v in PAPER_PHANTOM.items() if k != "table3"},
        "targets": {k: TARGETS[k] for k in ("success_rate_clinically_relevant", "success_rate")},
    }


def _heat_cell(ax, xi: int, y: int, r: dict | None, variant: str, vol: float, img: float) -> None:  # noqa: ANN001
    """One cell of Table II: green / red by success with the in-plane residual (and the rotation
    when it alone fails), grey when not run, hatched blue when not clinically relevant."""
    from matplotlib.patches import Rectangle

    green, red, grey = "#5cb85c", "#d9534f", "#dddddd"
    color = grey if r is None else (green if r["success"] else red)
    ax.add_patch(Rectangle((xi, y), 1, 1, facecolor=color, edgecolor="white", lw=0.8))
    if r is None:
        ax.text(xi + 0.5, y + 0.5, "not run", ha="center", va="center", fontsize=6, color="#777777")
        return
    txt = f"{r['inplane_residual_mm']:.2f}"
    if not r["success"] and r["inplane_residual_mm"] < 1.0:
        txt += f"\n{r['rotation_residual_deg']:.1f}°"
    ax.text(xi + 0.5, y + 0.5, txt, ha="center", va="center", fontsize=6.5)
    relevant = variant == "standard" and _relevant(vol, img)
    if variant == "facial":
        relevant = _relevant(vol, img)
    if not relevant:
        ax.add_patch(Rectangle((xi, y), 1, 1, facecolor="#337ab7", alpha=0.28, hatch="///", edgecolor="#1f4e79", lw=0))


def heatmap(records: Sequence[dict], kind: str, path: Path, *, title_extra: str = "") -> Path | None:
    """Table II for one image kind: rows volume format x offset, columns image format."""
    rows_rec = [r for r in records if r["image_kind"] == kind]
    if not rows_rec:
        return None
    plt = pyplot()

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
    for bi, (variant, vol) in enumerate(blocks):
        for oi, off in enumerate(offsets):
            y = bi * len(offsets) + oi
            for xi, img in enumerate(images):
                _heat_cell(ax, xi, y, cell.get((variant, vol, off, img)), variant, vol, img)
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
    stamp(fig, records)
    fig.savefig(path, dpi=130)
    plt.close(fig)
    return path


def _relevant(vol: float, img: float) -> bool:
    from registration.core.geometry import clinically_relevant

    return clinically_relevant(vol, img)


def phantom_histograms(records: Sequence[dict], path: Path) -> Path:
    """Fig. 6: in-plane residual, (a) all exposure, (b) all fluoro, (c, d) clinically relevant."""
    plt = pyplot()
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
        bars(ax, [r["inplane_residual_mm"] for r in rs], TRANSLATION_BINS_MM, title, "in-plane residual (mm)")
    fig.suptitle("Fig. 6: in-plane translational residual (phantom); red: 'More' (>= 1 mm)", fontsize=10)
    fig.tight_layout()
    stamp(fig, records)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _success_rows(summary: dict) -> list[list[object]]:
    """Success per image kind and both, all formats run and clinically relevant, beside the paper."""
    rows = []
    for kind, paper_all in (("exposure", 0.84), ("fluoro", 0.83)):
        k = summary["by_kind"].get(kind)
        if k:
            rows.append(
                [
                    kind,
                    f"{fmt_pct(k['success_rate'])} ({k['runs']})",
                    fmt_pct(paper_all),
                    f"{fmt_pct(k['success_rate_clinically_relevant'])} ({k['runs_clinically_relevant']})",
                    "97 %",
                ]
            )
    rows.append(
        [
            "**both**",
            f"**{fmt_pct(summary['success_rate'])}** ({summary['runs_grid']})",
            "83.5 %",
            f"**{fmt_pct(summary['success_rate_clinically_relevant'])}** ({summary['runs_clinically_relevant']})",
            "97 %",
        ]
    )
    return rows


def _table3_rows(summary: dict) -> list[list[object]]:
    """Table III's rows: residuals (mean / std / min / max), all and clinically relevant, beside the paper."""
    t3p = PAPER_PHANTOM["table3"]
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
    return rows


def _where_we_miss(summary: dict) -> list[str]:
    """Success per offset, volume format and image format, and every failed registration."""
    lines: list[str] = []
    for key, name in (
        ("by_offset", "offset"),
        ("by_volume_format", "volume format (cm)"),
        ("by_image_format", "image format (cm)"),
    ):
        rows = [[k, v["runs"], fmt_pct(v["success_rate"])] for k, v in summary[key].items()]
        lines += md_table([name, "runs", "success"], rows) + [""]
    fails = summary["failures"]
    if fails:
        lines += [f"{len(fails)} failed registrations:", ""]
        lines += md_table(
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
    return lines


def phantom_report_md(records: Sequence[dict], summary: dict, images: dict[str, str]) -> str:
    lines = [
        "# Phantom study: Tables II-III and Fig. 6 (Homan et al.) reproduced",
        "",
        *provenance(summary),
        "",
        "Success: in-plane residual at the iso-center < 1 mm and rotational residual < 3° (single view: the",
        "out-of-plane translation is not optimised). Clinically relevant subset (paper II.C): neither format",
        "15 or 19 cm, and volume format >= image format.",
        "",
        "## Success rates beside the paper",
        "",
    ]
    rows = _success_rows(summary)
    lines += md_table(
        ["images", "ours, all formats run (n)", "paper, all", "ours, clinically relevant (n)", "paper"], rows
    )
    lines += [
        "",
        f"Targets (DESIGN.md): >= 99 % clinically relevant, >= 90 % all formats. Alternative 22 cm volume with the "
        f"facial structures: {fmt_pct(summary['success_rate_facial_volume'])} of {summary['runs_facial_volume']}.",
        "",
        "## Table II",
        "",
    ]
    for kind in ("exposure", "fluoro"):
        if kind in images:
            lines += [f"![Table II, {kind}]({images[kind]})", ""]
    lines += ["## Table III: residual error (rotation deg, in-plane translation mm)", ""]
    rows = _table3_rows(summary)
    lines += md_table(
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
    lines += _where_we_miss(summary)
    return "\n".join(lines) + "\n"


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
    write_report(out, md, "roadmap3d phantom study")
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    return images
