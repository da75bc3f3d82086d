"""A report that stays: one registration (one plane or two) as a self-contained HTML page.

:func:`write_registration_report` writes a folder holding ``report.html``, the PNGs it shows
and ``result.json`` (the document the page's numbers come from): for each plane the image, the
DRR at the estimate and at the machine-based (initial) pose, the overlays of
:mod:`registration.studies.qa_images`; the evidence plots of
:mod:`registration.studies.qa_evidence`; the convergence; the numbers (pose, similarity,
confidence and its evidence, residual when a truth was given); the inputs (series and instance
UIDs, geometry, iso-center, volume grid); the software version. The folder is written through
a temporary sibling and renamed (nothing half-written). The patient's name and ID appear only
with ``identify``; file paths too (a folder is often named after the patient).

Every number printed in the page carries a ``data-key`` attribute naming its place in
``result.json`` (``similarity``, ``offsets.tx``, ``confidence_evidence.margin``, ...), so that a
reader (or a test) can check the page against the document.
"""

from __future__ import annotations

import html
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from registration import __version__
from registration.core.drr import DRRRenderer
from registration.core.images import XRayImage
from registration.core.volume import Volume
from registration.io.dicom import atomic_folder, json_dumps
from registration.studies import qa_evidence, qa_images

#: The pictures' size (pixels across) at most.
REPORT_PX = 512
REPORT_HTML = "report.html"
REPORT_JSON = "result.json"


@dataclass(frozen=True)
class Anatomy:
    """The vessel surface the roadmap outlines (world mm at the volume's pose) and its vertex spacing."""

    vertices_mm: NDArray[np.float64]
    spacing_mm: float


@dataclass
class Page:
    sections: list[str] = field(default_factory=list)
    files: dict[str, bytes] = field(default_factory=dict)

    def image(self, name: str, png: bytes | None, caption: str, *, wide: bool = False) -> str:
        """A figure showing ``png`` (kept as the file ``name``); ``wide``: at its own size."""
        if png is None:
            return ""
        self.files[name] = png
        return (
            f'<figure class="{"wide" if wide else "tile"}"><img src="{html.escape(name)}" alt="{html.escape(caption)}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>"
        )


def _png_rgb(rgb: NDArray[np.uint8]) -> bytes:
    ok, buf = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError("could not encode a picture as PNG")
    return buf.tobytes()


def _finest_level(renderer: DRRRenderer) -> int:
    return next(k for k in range(renderer.n_levels) if renderer.has_level(k))


def _shown(view: XRayImage) -> XRayImage:
    """The view block-averaged to at most REPORT_PX across."""
    factor = max(1, math.ceil(max(view.geometry.rows, view.geometry.cols) / REPORT_PX))
    while factor > 1 and (view.geometry.rows % factor or view.geometry.cols % factor):
        factor += 1
    return view.downsample(factor) if factor > 1 else view


def number(value: object, key: str, fmt: str = ".4f") -> str:
    if value is None:
        return f'<span data-key="{key}">–</span>'
    if isinstance(value, bool):
        return f'<span data-key="{key}">{"yes" if value else "no"}</span>'
    if isinstance(value, (int, np.integer)):
        return f'<span data-key="{key}">{int(value)}</span>'
    if isinstance(value, (float, np.floating)):
        return f'<span data-key="{key}">{float(value):{fmt}}</span>'
    return f'<span data-key="{key}">{html.escape(str(value))}</span>'


def table(rows: Sequence[tuple[str, str]]) -> str:
    return "<table>" + "".join(f"<tr><th>{html.escape(k)}</th><td>{v}</td></tr>" for k, v in rows) + "</table>"


def plane_pictures(
    page: Page,
    view: XRayImage,
    plane: str,
    *,
    renderer: DRRRenderer,
    motion: NDArray,
    initial: NDArray,
    anatomy: Anatomy | None,
    checker_px: int,
    pose_name: str = "the registered pose",
    initial_name: str = "the machine-based (initial) pose",
) -> str:
    """One plane's pictures: the image, the DRR at ``motion`` and at ``initial``, every overlay mode."""
    shown = _shown(view)
    g = shown.geometry
    level = _finest_level(renderer)
    drr = renderer.render(g, motion, level=level)
    drr_initial = renderer.render(g, initial, level=level)
    mask = shown.mask
    outline = outline_initial = None
    if anatomy is not None:
        outline = qa_images.vessel_silhouette(anatomy.vertices_mm, motion, g, anatomy.spacing_mm)
        outline_initial = qa_images.vessel_silhouette(anatomy.vertices_mm, initial, g, anatomy.spacing_mm)
    tag = plane.lower().replace(" ", "_") + "_" if plane else ""
    title = f"{plane}: " if plane else ""
    gray = qa_images.to_gray(shown.image, mask)
    cells = [
        page.image(f"{tag}image.png", _png_rgb(qa_images.gray_rgb(gray)), f"{title}the X-ray image ({view.kind})"),
        page.image(
            f"{tag}drr.png",
            _png_rgb(qa_images.gray_rgb(qa_images.to_gray(drr, mask))),
            f"{title}DRR at {pose_name}",
        ),  # fmt: skip
        page.image(
            f"{tag}drr_initial.png",
            _png_rgb(qa_images.gray_rgb(qa_images.to_gray(drr_initial, mask))),
            f"{title}DRR at {initial_name}",
        ),  # fmt: skip
    ]
    for mode in qa_images.OVERLAY_MODES:
        if mode == "outline" and outline is None:
            continue
        rgb = qa_images.compare(mode, image=shown.image, drr=drr, mask=mask, outline=outline, drr_initial=drr_initial,
                                outline_initial=outline_initial, tile_px=checker_px, thickness=1)  # fmt: skip
        caption = f"{title}{qa_images.OVERLAY_LABELS[mode]}"
        if mode == "wipe":
            caption += f" (amber: roadmap at {initial_name})" if outline is not None else ""
        cells.append(page.image(f"{tag}overlay_{mode}.png", _png_rgb(rgb), caption))
    note = "" if anatomy is not None else "<p>No vessel surface in this volume: no roadmap outline.</p>"
    return f"<h3>{html.escape(plane or 'The image')}</h3>{note}<div class='grid'>{''.join(cells)}</div>"


def _numbers(doc: Mapping[str, Any]) -> str:
    rows = [("similarity (gradient difference)", number(doc.get("similarity"), "similarity"))]
    for name, value in dict(doc.get("offsets") or {}).items():
        unit = "mm" if name.startswith("t") else "deg"
        rows.append((f"{name} ({unit}, view frame)", number(value, f"offsets.{name}", "+.3f")))
    if doc.get("depth_tz_mm") is not None:
        rows.append(("tz from the depth correction (mm)", number(doc["depth_tz_mm"], "depth_tz_mm", "+.3f")))
    rows += [
        ("DRRs rendered", number(doc.get("drr_count"), "drr_count")),
        ("seconds", number(doc.get("seconds"), "seconds", ".2f")),
        ("stopped", number(doc.get("stopped"), "stopped")),
    ]
    if doc.get("rotation_check") is not None:
        rc = doc["rotation_check"]
        checks = number(rc.get("checks"), "rotation_check.checks")
        if rc.get("margin") is not None:
            margin = number(rc["margin"], "rotation_check.margin", ".4f")
            said = " (a sharp peak of its own: no polish ran)" if rc.get("skipped") else ""
            rows.append(("rotation check: margin over rx, ry at +-3 deg", margin + said))
        rows.append(("rotation check: checks / moves", f"{checks} / {number(rc.get('moves'), 'rotation_check.moves')}"))
        rows.append(
            ("rotation check: best rival (relative)", number(rc.get("rival_gain"), "rotation_check.rival_gain", ".5f"))
        )
    if doc.get("geometry_source") is not None:
        said = number(doc["geometry_source"], "geometry_source")
        if doc["geometry_source"] == "nominal":
            said += " (the files' positioner angles and distances; no C-arm calibration applied)"
        rows.append(("C-arm geometry", said))
    if doc.get("landmark_start") is not None:
        rms = number(doc["landmark_start"].get("reprojection_rms_px"), "landmark_start.reprojection_rms_px", ".2f")
        rows.append(("start from landmarks: reprojection error (px rms)", rms))
    if doc.get("region") is not None:  # the part of the patient followed (docs/clinical-images.md)
        region = doc["region"]
        base = region.get("skull_base_z_mm")
        said = html.escape(str(region.get("source", "")))
        if region.get("source") == "cranium":
            found = "" if base is None else number(base, "region.skull_base_z_mm", ".0f")
            said += f": the head above the skull base at z {found} mm" if found else " (no neck found: every pixel)"
        fields = region.get("fields") or []
        left = [
            f"{number(f.get('left_out_px'), f'region.fields.{i}.left_out_px')} of "
            f"{number(f.get('field_px'), f'region.fields.{i}.field_px')} px"
            for i, f in enumerate(fields)
        ]
        if left:
            said += "; left out of the measure (they see mostly the neck): " + ", ".join(left)
        rows.append(("region followed", said))
    if doc.get("skull_spine") is not None:
        ss = doc["skull_spine"]
        agree = "agree" if ss.get("agree") else "DISAGREE (the neck moved relative to the head)"
        shift = number(ss.get("shift_mm"), "skull_spine.shift_mm", ".2f")
        rows.append((f"skull and spine: {agree}; the whole volume's fit moves (mm {ss.get('criterion', '')})", shift))
    motion = np.asarray(doc["patient_motion"], dtype=float)
    matrix = "<br>".join(
        " ".join(number(motion[i, j], f"patient_motion.{i}.{j}", "+.5f") for j in range(4)) for i in range(4)
    )
    rows.append(("patient motion (4x4, mm, CONVENTIONS §4)", f"<code>{matrix}</code>"))
    if doc.get("residual") is not None:
        r = doc["residual"]
        for key in ("translation_mm", "inplane_mm", "outofplane_mm", "rotation_deg", "mtre_mm"):
            if r.get(key) is not None:
                rows.append((f"residual vs truth: {key}", number(r[key], f"residual.{key}", ".3f")))
        rows.append(("success (< 1 mm, < 3 deg)", number(doc.get("success"), "success")))
    return table(rows)


def _decision(doc: Mapping[str, Any]) -> str:
    if "applied" not in doc:
        return "<p class='verdict'>No confidence assessed.</p>"
    conf = number(doc.get("confidence"), "confidence", ".3f")
    if doc["applied"]:
        return f"<p class='verdict ok'>Confidence {conf}: <b>applied</b>.</p>"
    reason = html.escape(str(doc.get("withheld_reason") or "low confidence"))
    return (
        f"<p class='verdict withheld'>Confidence {conf}: <b>withheld</b>: "
        f"<span data-key='withheld_reason'>{reason}</span>. The roadmap keeps its pose.</p>"
    )


def _evidence(page: Page, doc: Mapping[str, Any], profiles: Sequence[tuple[str, list]], probe, scan,  # noqa: ANN001
              weighed: bool = True, far: Mapping[str, Any] | None = None) -> str:  # fmt: skip
    ev = dict(doc.get("confidence_evidence") or {})
    term = qa_evidence.withheld_term(ev) if ev else None
    reason = str(doc.get("withheld_reason") or "")
    parts = ["<h2>Evidence</h2>"]
    if term is not None:
        where = qa_evidence.TERM_PICTURES.get(term, "the decision's veto" if term == "veto" else term)
        framed = " (framed in red below)" if term in qa_evidence.FRAMED_TERMS else " (below)"
        parts.append(f"<p class='withheld'>Withheld because {html.escape(reason)}: read it in {html.escape(where)}"
                     f"{framed}.</p>")  # fmt: skip
    if ev:
        rows = [(k, number(v, f"confidence_evidence.{k}", ".5f")) for k, v in ev.items() if v is not None]
        parts.append(table(rows))
    for plane, profs in profiles:
        png = qa_evidence.profiles_figure(profs, evidence=ev, reason=reason)
        tag = plane.lower().replace(" ", "_") + "_" if plane else ""
        caption = f"{plane + ': ' if plane else ''}the measure along each parameter around the estimate"
        parts.append(page.image(f"{tag}evidence_profiles.png", png, caption, wide=True))
    depth = qa_evidence.depth_figure(scan, probe, far=far, reason=reason, term=term, weighed=weighed)
    parts.append(
        page.image(
            "evidence_depth.png",
            depth,
            "the depth scan along the beam"
            + (" and the depth probe" if probe else "")
            + ("; below, the far look" if far else ""),
            wide=True,
        )  # fmt: skip
    )
    if term == "edges":
        parts.append("<p class='withheld'>Too few edges: compare the image with its gradient above.</p>")
    return "".join(parts)


def inputs_section(volume: Volume, views: Sequence[XRayImage], doc: Mapping[str, Any], identify: bool) -> str:
    vm = volume.meta
    rows = [
        ("volume", html.escape(volume.label)),
        (
            "volume grid",
            f"{volume.shape[2]} x {volume.shape[1]} x {volume.shape[0]} voxels of "
            + " x ".join(f"{s:.3g}" for s in volume.spacing_mm)
            + " mm",
        ),  # fmt: skip
        ("volume series UID", html.escape(str(vm.get("series_uid") or "–"))),
        ("volume frame of reference UID", html.escape(str(vm.get("frame_of_reference_uid") or "–"))),
        ("study UID", html.escape(str(vm.get("study_uid") or "–"))),
    ]
    if identify:
        rows += [("patient name", html.escape(str(vm.get("patient_name") or "–"))),
                 ("patient ID", html.escape(str(vm.get("patient_id") or "–"))),
                 ("volume file", html.escape(str(vm.get("source") or "–")))]  # fmt: skip
    for n, v in enumerate(views):
        g = v.geometry
        name = str(v.meta.get("plane") or (f"image {n + 1}" if len(views) > 1 else "image"))
        rows += [
            (
                f"{name}: series / instance UID",
                html.escape(f"{v.meta.get('series_uid') or '–'} / {v.meta.get('sop_instance_uid') or '–'}"),
            ),  # fmt: skip
            (f"{name}: frame, kind", html.escape(f"{v.meta.get('frame', 0)}, {v.kind}")),
            (
                f"{name}: geometry",
                html.escape(
                    f"primary {g.primary_deg:+.2f} deg, secondary {g.secondary_deg:+.2f} deg, SID {g.sid_mm:.1f} mm, "
                    f"SOD {g.sod_mm:.1f} mm, {g.cols} x {g.rows} px of {g.pixel_mm[1]:.4g} x {g.pixel_mm[0]:.4g} mm"
                ),
            ),
            (f"{name}: iso-center (mm)", html.escape(", ".join(f"{c:.2f}" for c in g.isocenter_mm))),
        ]
        if identify:
            rows.append((f"{name}: file", html.escape(str(v.meta.get("source") or "–"))))
    if doc.get("isocenter_from"):
        rows.append(("iso-center from", html.escape(str(doc["isocenter_from"]))))
    return "<h2>Inputs</h2>" + table(rows)


_STYLE = (
    "body{font-family:sans-serif;max-width:1200px;margin:1.5em auto;line-height:1.35;color:#212529}"
    "table{border-collapse:collapse;margin:0.5em 0}th,td{border:1px solid #ced4da;padding:2px 8px;font-size:88%;"
    "text-align:left;vertical-align:top}th{background:#f1f3f5;font-weight:600}"
    ".grid{display:flex;flex-wrap:wrap;gap:8px}figure{margin:0.4em 0}figure.tile,figure.tile img{width:300px}"
    "figure.wide img{max-width:100%}figcaption{font-size:80%;color:#495057}"
    ".verdict{font-size:115%}.ok{color:#2b8a3e}.withheld{color:#c2255c}code{font-size:85%}"
    "footer{margin-top:2em;font-size:80%;color:#868e96}"
)


def page_html(title: str, body: str) -> str:
    return (
        f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
        f"<style>{_STYLE}</style></head><body>{body}</body></html>"
    )


def footer(command: str | None) -> str:
    from registration.studies.report_kit import source_revision

    rev = source_revision()
    when = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    cmd = f"<br>command: <code>{html.escape(command)}</code>" if command else ""
    return (
        f"<footer>roadmap3d <span data-key='software.version'>{__version__}</span>"
        f"{f' ({html.escape(rev)})' if rev else ''}, written {when}{cmd}</footer>"
    )


def write_registration_report(
    out: str | Path,
    *,
    document: Mapping[str, Any],
    volume: Volume,
    views: Sequence[XRayImage],
    renderer: DRRRenderer,
    initial_motion: NDArray | None = None,
    anatomy: Anatomy | None = None,
    depth_probe: Mapping[str, Any] | None = None,
    depth_scan: Mapping[str, Any] | None = None,
    depth_far: Mapping[str, Any] | None = None,
    identify: bool = False,
    checker_px: int = qa_images.CHECKER_TILE_PX // 2,
    command: str | None = None,
) -> Path:
    """Write the report of one registration into the folder ``out`` (absent or empty; written
    through a temporary sibling folder). ``document``: the result's JSON (as ``register --out``
    writes it, with the confidence fields when assessed); ``renderer``: DRRs for the pictures
    (its finest level) and the evidence (the level nearest 128 voxels, as the confidence);
    ``depth_probe`` / ``depth_scan`` / ``depth_far``: the confidence's (one plane). Returns ``out``."""
    out = Path(out)
    doc = dict(document)
    views = list(views)
    motion = np.asarray(doc["patient_motion"], dtype=np.float64)
    initial = np.eye(4) if initial_motion is None else np.asarray(initial_motion, dtype=np.float64)
    page = Page()
    planes = [str(v.meta.get("plane") or name) for v, name in zip(views, ("PLANE A", "PLANE B"), strict=False)]
    if len(views) == 1:
        planes = [""]
    title = "Registration report" + (" (biplane)" if len(views) == 2 else "")
    body = [f"<h1>{title}</h1>", _decision(doc), "<h2>Numbers</h2>", _numbers(doc), "<h2>Compare in place</h2>"]
    for view, plane in zip(views, planes, strict=True):
        body.append(plane_pictures(page, view, plane, renderer=renderer, motion=motion, initial=initial,
                                    anatomy=anatomy, checker_px=checker_px))  # fmt: skip
    profiles = [
        (plane, qa_evidence.parameter_profiles(volume, view, motion, renderer=renderer))
        for view, plane in zip(views, planes, strict=True)
    ]
    one_view = "tz" not in (doc.get("offsets") or {"tz": 0})
    scan, weighed = qa_evidence.pictured_scan(depth_scan, views, motion, renderer, one_view=one_view)
    body.append(_evidence(page, doc, profiles, depth_probe, scan, weighed, far=depth_far))
    if doc.get("similarity_trace"):
        trace = qa_evidence.convergence_figure(list(doc["similarity_trace"]))
        caption = (
            "the best gradient difference of each stage over the iterations (each pyramid level and polish "
            "starts again, on its own images)"
        )
        body.append("<h2>Convergence</h2>" + page.image("convergence.png", trace, caption, wide=True))
    body.append(inputs_section(volume, views, doc, identify))
    body.append(footer(command))
    text = page_html(title, "".join(body))
    saved = dict(doc)
    if not identify:
        for key in ("volume", "image", "images"):
            saved.pop(key, None)  # file paths may name the patient
    with atomic_folder(out) as tmp:
        for name, data in page.files.items():
            (tmp / name).write_bytes(data)
        (tmp / REPORT_JSON).write_text(json_dumps(saved))
        (tmp / REPORT_HTML).write_text(text)
    return out


def read_report_numbers(html_text: str) -> dict[str, str]:
    """The ``data-key`` numbers of a report page (key -> text as shown)."""
    import re

    return {m[1]: html.unescape(m[2]) for m in re.finditer(r"data-key=['\"]([^'\"]+)['\"]>([^<]*)<", html_text)}


def document_value(document: Mapping[str, Any], key: str) -> object:
    """The value at a ``data-key`` path of ``document`` (dots separate keys and list indices)."""
    node: Any = document
    for part in key.split("."):
        node = node[int(part)] if isinstance(node, list) else node[part]
    return node


__all__ = [
    "Anatomy",
    "REPORT_HTML",
    "REPORT_JSON",
    "document_value",
    "read_report_numbers",
    "write_registration_report",
]
