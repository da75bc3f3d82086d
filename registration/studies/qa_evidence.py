"""The confidence's evidence as pictures: the measure around an estimate, the depth scan, the
rotation check, and which of them a withheld estimate failed.

:func:`parameter_profiles` evaluates the gradient difference exactly as
:func:`registration.core.tracking.registration_evidence` does for the margins (the image
block-averaged to about 128 px, the support mask, the renderer's level nearest 128 voxels),
along each of the five parameters through the estimate, so that the plots show the margins the
confidence reads (``PERTURB_MM`` / ``PERTURB_DEG`` along each parameter, ``ROTATION_PROBE_DEG``
along rx and ry) and more: the out-of-plane rotations are followed to +-``ROTATION_SPAN_DEG``,
beyond the rotation check's starts (+-6 degrees), where a rival optimum shows as a second peak.
Values are relative to the measure at the estimate, ``(f - f_est) / |f_est|``, the unit of the
evidence ``margin``, ``rotation_margin`` and ``rival_gain``.

:func:`evidence_figures` draws them (matplotlib, PNG bytes): one small line plot per parameter
with the margin's probe points and the rule's threshold, the depth scan's tz curve with the
region its term withholds, and the reason of a withheld estimate written on the plot it comes
from (:func:`withheld_term`).
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core.confidence import (
    DEFAULT_RULE,
    PERTURB_DEG,
    PERTURB_MM,
    ROTATION_PROBE_DEG,
    ConfidenceRule,
    Evidence,
)
from registration.core.drr import DRRRenderer
from registration.core.geometry import check_rigid, offsets_to_matrix
from registration.core.images import XRayImage
from registration.core.problem import support_mask
from registration.core.similarity import GradientDifference
from registration.core.volume import Volume

#: As ``registration_evidence``: image about this many pixels across, volume level nearest this
#: many voxels, support margin (mm).
PROFILE_IMAGE_PX = 128
PROFILE_VOLUME_VOXELS = 128
PROFILE_MARGIN_MM = 4.0
#: Spans of the profiles: translations and rz (mm, deg) and the out-of-plane rotations (deg).
TRANSLATION_SPAN_MM = 4.0
ROTATION_SPAN_DEG = 4.0
OUT_OF_PLANE_SPAN_DEG = 10.0
PROFILE_STEP = 0.5
#: The five parameters of a single view, their slot in the six view-frame offsets and unit.
PARAMETERS = (("tx", 0, "mm"), ("ty", 1, "mm"), ("rx", 3, "deg"), ("ry", 4, "deg"), ("rz", 5, "deg"))

#: Which picture each confidence term is read from (``withheld_term``'s keys).
TERM_PICTURES = {
    "margin": "the parameter profiles (their margins at +-1)",
    "rotation_margin": "the rx / ry profiles (their margins at +-3 deg)",
    "rival": "the rx / ry profiles (the rotation check's rival)",
    "depth": "the depth probe (in-plane shift when tz may move)",
    "depth_pull": "the depth probe (its tz)",
    "depth_scan": "the depth scan (where along the beam the measure peaks)",
    "edges": "the image's edges",
    "agreement": "the capture runs",
    "planes": "the two planes' estimates",
    "deficit": "the measure's level over the run",
    "beam": "the evidence's beam_margin (how much the other plane's measure falls when the estimate moves "
    "along one plane's beam)",
    "planes_apart": "the parameter profiles (their margins at +-1), the planes' own captures having disagreed",
    "depth_far": "the far look (the measure 28-76 mm along the beam against within 24 mm of the estimate)",
    "spine": "the evidence's spine_pull_mm (how far the head alone, without the spine below the skull base, "
    "moves the estimate)",
}
#: The terms whose picture the report frames in red when they withheld an estimate.
FRAMED_TERMS = frozenset({"margin", "rotation_margin", "rival", "depth", "depth_pull", "depth_scan", "depth_far"})


@dataclass(frozen=True)
class Profile:
    """The measure along one parameter through the estimate (offsets in the view frame)."""

    name: str
    unit: str
    offsets: tuple[float, ...]
    #: (f - f_est) / |f_est| at each offset: 0 at the estimate, < 0 where the measure is lower.
    relative: tuple[float, ...]

    def margin(self, step: float) -> float:
        """The relative margin over the better of the two poses at +-``step`` (> 0: the
        estimate is above both), as the evidence computes it."""
        values = dict(zip(self.offsets, self.relative, strict=True))
        return -max(values[float(step)], values[float(-step)])

    def to_dict(self) -> dict:
        return {"name": self.name, "unit": self.unit, "offsets": list(self.offsets), "relative": list(self.relative)}


def _grid(span: float, extra: tuple[float, ...]) -> tuple[float, ...]:
    values = set(np.round(np.arange(-span, span + 1e-9, PROFILE_STEP), 6).tolist())
    values |= {float(e) for e in extra} | {-float(e) for e in extra}
    return tuple(sorted(float(v) for v in values))


def parameter_profiles(volume: Volume, xray: XRayImage, motion: ArrayLike, *, renderer: DRRRenderer) -> list[Profile]:
    """The relative measure along tx, ty, rx, ry, rz through ``motion`` (see the module's
    docstring): 17 points along tx, ty, rz (+-4 mm / deg), 41 along rx, ry (+-10 deg), plus the
    confidence's probe points; about 130 DRRs at ~128 px."""
    m = check_rigid(motion, name="motion")
    level = renderer.level_nearest(PROFILE_VOLUME_VOXELS)
    g = xray.geometry
    factor = max(1, round(g.cols / PROFILE_IMAGE_PX))
    while factor > 1 and (g.rows % factor or g.cols % factor):
        factor -= 1
    small = xray.downsample(factor) if factor > 1 else xray
    mask = support_mask(volume, small.geometry, m, PROFILE_MARGIN_MM) & small.mask
    if mask.sum() < 0.25 * small.mask.sum():
        mask = small.mask
    measure = GradientDifference(small.image, mask)

    def f(pose: NDArray) -> float:
        return float(measure(renderer.render(small.geometry, pose, level=level, mask=mask)))

    f_est = f(m)
    scale = max(abs(f_est), 1e-12)
    out = []
    for name, slot, unit in PARAMETERS:
        out_of_plane = name in ("rx", "ry")
        if unit == "mm":
            grid = _grid(TRANSLATION_SPAN_MM, (PERTURB_MM,))
        else:
            span = OUT_OF_PLANE_SPAN_DEG if out_of_plane else ROTATION_SPAN_DEG
            grid = _grid(span, (PERTURB_DEG, ROTATION_PROBE_DEG) if out_of_plane else (PERTURB_DEG,))
        rel = []
        for v in grid:
            if v == 0.0:
                rel.append(0.0)
                continue
            o = np.zeros(6)
            o[slot] = v
            rel.append((f(offsets_to_matrix(o, g) @ m) - f_est) / scale)
        out.append(Profile(name, unit, grid, tuple(float(r) for r in rel)))
    return out


def withheld_term(evidence: Mapping[str, object] | Evidence, rule: ConfidenceRule = DEFAULT_RULE) -> str | None:
    """The confidence term that withheld an estimate (the most negative, as
    :meth:`ConfidenceRule.assess` names its reason), "veto" for a veto, None when applied."""
    e = evidence if isinstance(evidence, Evidence) else Evidence(**dict(evidence))  # type: ignore[arg-type]
    if e.veto:
        return "veto"
    if rule.assess(e).applied:
        return None
    terms = rule.terms(e)
    return min(terms, key=terms.get) if terms else None  # type: ignore[arg-type]


# --------------------------------------------------------------------------------------
# Figures
# --------------------------------------------------------------------------------------
def pyplot():  # noqa: ANN202 - matplotlib's pyplot module
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def png_of(fig) -> bytes:  # noqa: ANN001
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    pyplot().close(fig)
    return buf.getvalue()


WITHHELD_RGB = "#d6336c"


def _mark_withheld(ax, reason: str) -> None:  # noqa: ANN001
    """Frame ``ax`` in red and write the reason under it."""
    import textwrap

    for spine in ax.spines.values():
        spine.set_edgecolor(WITHHELD_RGB)
        spine.set_linewidth(2.5)
    text = textwrap.fill(f"withheld: {reason}" if reason else "withheld here", 42)
    ax.text(0.5, -0.3, text, transform=ax.transAxes, ha="center", va="top", fontsize=6.5, color=WITHHELD_RGB)


def profiles_figure(
    profiles: list[Profile],
    *,
    evidence: Mapping[str, object] | None = None,
    reason: str = "",
    rule: ConfidenceRule = DEFAULT_RULE,
    columns: int | None = None,
) -> bytes:
    """One small plot per parameter: the relative measure, the estimate at 0, the margin's probe
    points (+-1 mm / deg; +-3 deg along rx, ry), the level the rule asks the peak to stand above
    them (``margin_good``; ``rotation_margin_good`` for rx, ry), the rotation check's best rival
    (rx, ry) when it found one; the plot(s) a withheld estimate failed framed and captioned."""
    plt = pyplot()
    ev = dict(evidence or {})
    term = withheld_term(ev, rule) if ev else None
    cols = len(profiles) if columns is None else max(1, min(columns, len(profiles)))
    rows = math.ceil(len(profiles) / cols)
    fig, grid = plt.subplots(rows, cols, figsize=(2.3 * cols, 2.9 * rows), squeeze=False)
    axes = grid.ravel()
    for ax in axes[len(profiles) :]:
        ax.set_visible(False)
    axes = axes[: len(profiles)]
    rival = ev.get("rival_gain")
    for ax, p in zip(axes, profiles, strict=True):
        x, y = np.asarray(p.offsets), np.asarray(p.relative) * 1e3
        ax.plot(x, y, color="#1c7ed6", lw=1.4)
        ax.axvline(0.0, color="#495057", lw=0.8, ls=":")
        out_of_plane = p.name in ("rx", "ry")
        steps = [PERTURB_MM if p.unit == "mm" else PERTURB_DEG] + ([ROTATION_PROBE_DEG] if out_of_plane else [])
        for s in steps:
            pts = [(v, r) for v, r in zip(x, y, strict=True) if abs(abs(v) - s) < 1e-9]
            ax.plot([q[0] for q in pts], [q[1] for q in pts], "o", ms=3.5, color="#f08c00")
        ax.axhline(-1e3 * rule.margin_good, color="#f08c00", lw=0.7, ls="--")
        if out_of_plane:
            ax.axhline(-1e3 * rule.rotation_margin_good, color="#e8590c", lw=0.7, ls="-.")
            if isinstance(rival, (int, float)) and math.isfinite(rival):
                ax.axhline(1e3 * float(rival), color="#7048e8", lw=0.9, ls="-")
                ax.text(x[0], 1e3 * float(rival), " rotation check's rival", fontsize=6, color="#7048e8", va="bottom")
        ax.set_title(f"{p.name} ({'°' if p.unit == 'deg' else p.unit})", fontsize=9)
        ax.tick_params(labelsize=7)
        fails = (term == "margin" and not out_of_plane and p.margin(steps[0]) < rule.margin_good) or (
            term in ("rotation_margin", "rival") and out_of_plane
        )
        if term == "margin" and not any(
            q.margin(PERTURB_MM if q.unit == "mm" else PERTURB_DEG) < rule.margin_good for q in profiles
        ):
            fails = True  # the mean margin failed though no single one did: every plot shares it
        if fails:
            _mark_withheld(ax, reason)
    for ax in grid[:, 0]:
        ax.set_ylabel("measure − the estimate's (×10⁻³)", fontsize=7)
    title = "Gradient difference around the estimate (orange dots: the confidence's margin probes; dashed: the margin"
    fig.suptitle(f"{title} it asks for)" if cols > 3 else f"{title}\nit asks for)", fontsize=8)
    fig.tight_layout(rect=(0, 0, 1, 0.92 if rows == 1 else 0.94))
    return png_of(fig)


def pictured_scan(
    scan: Mapping[str, object] | None,
    views: Sequence[XRayImage],
    motion: ArrayLike,
    renderer: DRRRenderer,
    *,
    one_view: bool,
) -> tuple[Mapping[str, object] | None, bool]:
    """The depth scan to draw and whether the confidence weighed it: the assessment's own; for one
    view's estimate that the registration corrected along the beam itself (the assessment does not
    scan it), a full scan made here for the picture alone. Two views: none."""
    if scan or not one_view or len(views) != 1:
        return scan, True
    from registration.core.depth import depth_scan

    return depth_scan(renderer, views[0], np.asarray(motion, dtype=np.float64)).to_dict(), False


def depth_figure(
    scan: Mapping[str, object] | None,
    probe: Mapping[str, object] | None,
    *,
    far: Mapping[str, object] | None = None,
    reason: str = "",
    term: str | None = None,
    rule: ConfidenceRule = DEFAULT_RULE,
    weighed: bool = True,
) -> bytes | None:
    """The depth scan's tz curve (the high-passed measure along the beam, the estimate at 0,
    + toward the source) with its peak, the region beyond ``scan_free_mm`` its term withholds,
    and the depth probe's tz and in-plane shift; below it one view's far look (``far``:
    :class:`registration.core.depth.DepthFar`'s dict) when it ran. None without either (two
    views). ``weighed`` False: a scan the confidence did not read (:func:`pictured_scan`),
    drawn without the region."""
    if not scan and not far:
        return None
    plt = pyplot()
    rows = int(bool(scan)) + int(bool(far))
    fig, axes = plt.subplots(rows, 1, figsize=(7.0, 3.0 * rows), squeeze=False)
    if scan:
        _scan_panel(axes[0, 0], scan, probe, reason=reason, term=term, rule=rule, weighed=weighed)
    if far:
        _far_panel(axes[-1, 0], far, reason=reason, term=term, rule=rule)
    fig.tight_layout()
    return png_of(fig)


def _scan_panel(ax, scan, probe, *, reason, term, rule, weighed) -> None:  # noqa: ANN001
    x = np.asarray(scan["offsets_mm"], dtype=float)
    y = np.asarray(scan["similarity"], dtype=float)
    ax.plot(x, y, color="#1c7ed6", lw=1.4, marker=".", ms=3)
    peak = float(scan["tz_mm"])
    # a scan that stopped once its peak could not lie in the withheld region shows its best offset
    label = f"scan best {peak:+.1f} mm (peak at or above it)" if scan.get("stopped") else f"scan peak {peak:+.1f} mm"
    ax.axvline(peak, color="#2f9e44", lw=1.0, label=label)
    ax.axvline(0.0, color="#495057", lw=0.8, ls=":", label="estimate")
    if rule.scan_weight and weighed:
        ax.axvspan(x.min(), rule.scan_free_mm, color="#e03131", alpha=0.18, lw=0,  # light or dark paper
                   label=f"peak here withholds (< {rule.scan_free_mm:g} mm)")  # fmt: skip
    if probe:
        tz, shift = float(probe["tz_mm"]), float(probe["shift_mm"])
        ax.axvline(tz, color="#f08c00", lw=1.0, ls="--", label=f"depth probe tz {tz:+.1f} mm, shift {shift:.2f} mm")
    reach = float(np.abs(x).max())
    ax.set_xlim(-reach * 1.04, reach * 1.04)  # the scanned range either way, sampled or not
    _depth_axes(ax)
    title = "Depth: the measure along the beam"
    if not weighed:
        title += "\n(the registration corrected its depth; the confidence does not weigh this scan)"
    ax.set_title(title, fontsize=9)
    if term in ("depth_scan", "depth", "depth_pull"):
        _mark_withheld(ax, reason)


def _far_panel(ax, far, *, reason, term, rule) -> None:  # noqa: ANN001
    x = np.asarray(far["offsets_mm"], dtype=float)
    y = np.asarray(far["similarity"], dtype=float)
    near = float(far["near_mm"])
    ax.axvspan(-near, near, color="#868e96", alpha=0.18, lw=0, label=f"within {near:g} mm of the estimate")
    ax.plot(x, y, color="#1c7ed6", lw=1.4, marker=".", ms=4)
    ax.axvline(float(far["far_tz_mm"]), color="#f08c00", lw=1.0, ls="--",
               label=f"best beyond: {float(far['far_tz_mm']):+.0f} mm")  # fmt: skip
    ax.axvline(0.0, color="#495057", lw=0.8, ls=":", label="estimate")
    reach = float(np.abs(x).max())
    ax.set_xlim(-reach * 1.04, reach * 1.04)
    _depth_axes(ax)
    gain = float(far["gain"])
    ax.set_title(f"Far along the beam: best beyond less best within {gain:+.4f} (weighed above {rule.far_free:g})",
                 fontsize=9)  # fmt: skip
    if term == "depth_far":
        _mark_withheld(ax, reason)


def _depth_axes(ax) -> None:  # noqa: ANN001
    ax.set_xlabel("tz from the estimate (mm, + toward the source)", fontsize=8)
    ax.set_ylabel("high-passed GD", fontsize=8)
    ax.ticklabel_format(axis="y", useOffset=False)
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=6.5, loc="upper left", bbox_to_anchor=(1.02, 1.0))


def convergence_figure(trace: list[float], *, title: str = "Convergence") -> bytes:
    """The best similarity over the optimizer's iterations."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(4.6, 2.4))
    y = np.asarray(trace, dtype=float)
    ax.plot(np.arange(1, len(y) + 1), y, color="#1c7ed6", lw=1.3)
    ax.set_xlabel("iteration", fontsize=8)
    ax.set_ylabel("gradient difference (best)", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return png_of(fig)
