"""The volume study's outputs: results.jsonl, summary.json and report.md (per arm: success, precision,
recall and residuals, the images' origin said).
"""

from __future__ import annotations

import json
from pathlib import Path


def write_outputs(out: Path, records: list[dict], summary: dict) -> None:
    """results.jsonl, summary.json and report.md in ``out`` (written whole, then renamed)."""
    out.mkdir(parents=True, exist_ok=True)
    files = {
        "results.jsonl": "".join(json.dumps(r) + "\n" for r in records),
        "summary.json": json.dumps(summary, indent=1) + "\n",
        "report.md": report_markdown(records, summary),
    }
    for name, text in files.items():
        tmp = out / f".{name}.tmp"
        tmp.write_text(text)
        tmp.replace(out / name)


def report_markdown(records: list[dict], summary: dict) -> str:
    cfg = summary["config"]
    lines = [
        "# Registration on a user's volume (`roadmap3d validate volume`)",
        "",
        f"**Best case**: {summary['images']}.",
        "",
        f"Volume: {summary['volume']} ({' x '.join(map(str, summary['volume_shape']))} voxels of "
        f"{' x '.join(f'{s:.3g}' for s in summary['volume_spacing_mm'])} mm), iso-center "
        f"({', '.join(f'{c:.1f}' for c in summary['isocenter_mm'])}) mm. {cfg['cases']} cases, seed {cfg['seed']}, "
        f"{'biplane' if cfg['biplane'] else 'single plane'}, {cfg['pixels']}-px {cfg['kind']} images of a "
        f"{cfg['image_format_cm']:g} cm format, offsets <= {cfg['max_mm']:g} mm / {cfg['max_deg']:g} deg; "
        f"realism {cfg.get('realism', 'clean')}, strengths {', '.join(f'{x:g}' for x in cfg.get('strengths', [1.0]))}; "
        f"roadmap3d {summary['version']}, revision {summary['revision']}.",
        "",
        f"Success ({summary['success_criterion']}): **{100 * summary['success_rate']:.1f} %** of {summary['runs']}; "
        f"median in-plane residual {summary['inplane_residual_mm_median']:.2f} mm, rotation "
        f"{summary['rotation_residual_deg_median']:.2f} deg, out of plane "
        f"{summary['outofplane_residual_mm_median']:.2f} mm; "
        f"median {summary['seconds_median']:.2f} s a registration with the volume prepared, "
        f"{summary['prepare_seconds']:.2f} s preparing it for a view.",
        "",
    ]
    arms = summary.get("arms") or []
    if len(arms) > 1 or any(a["effects"] for a in arms):
        pct = lambda v: "-" if v is None else f"{100 * v:.0f} %"  # noqa: E731
        lines += [
            "Per arm (effects of `registration.sim.clinical` at the strength given; precision: applied estimates "
            "that are right; recall: right estimates that were applied):",
            "",
            "| arm | strength | runs | success | applied | precision | recall | worst applied mm | median mm "
            "| worst mm | field from |",
            "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |",
        ]
        for a in arms:
            worst_applied = "-" if a["max_applied_error_mm"] is None else f"{a['max_applied_error_mm']:.2f}"
            lines.append(
                f"| {a['arm']} | {a['strength']:g} | {a['runs']} | {pct(a['success_rate'])} | "
                f"{'-' if a['applied'] is None else a['applied']} | {pct(a['applied_precision'])} | "
                f"{pct(a['applied_recall'])} | {worst_applied} | {a['residual_mm_median']:.2f} | "
                f"{a['worst_residual_mm']:.2f} | {_field_from(a)} |"
            )
        lines.append("")
    lines += [
        "| arm | case | LAO/RAO | CRAN/CAUD | offset mm (in-plane / out) | offset deg | in-plane mm | 3-D mm "
        "| rot deg | s | ok | decision |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | :-: | --- |",
    ]
    for r in records:
        decision = (
            "-" if "applied" not in r else ("applied" if r["applied"] else f"withheld: {r.get('withheld_reason')}")
        )
        arm = r.get("arm", "clean") + ("" if not r.get("effects") else f" @ {r.get('strength', 1.0):g}")
        lines.append(
            f"| {arm} | {r['case']} | {r['primary_deg']:+.1f} | {r['secondary_deg']:+.1f} | "
            f"{r['offset_inplane_mm']:.1f} / {r['offset_outofplane_mm']:.1f} | {r['offset_rotation_deg']:.1f} | "
            f"{r['inplane_residual_mm']:.2f} | {r['translation_residual_mm']:.2f} | {r['rotation_residual_deg']:.2f} | "
            f"{r['seconds']:.2f} | {'yes' if r['success'] else 'NO'} | {decision} |"
        )
    return "\n".join(lines) + "\n"


def _field_from(arm: dict) -> str:
    """How the reader found the field: each part with the number of images it was found on."""
    parts = arm.get("mask_parts")
    if parts is None:  # a summary written before the parts were counted
        return ", ".join(arm.get("mask_from") or []) or "-"
    return ", ".join(f"{part} ({n} of {arm['runs']})" for part, n in parts.items()) or "-"
