"""See why a registration is right or wrong: the Compare tab, the Evidence tab and the report.

- **Compare** (right): what the fluoro tile draws over the image (:data:`OVERLAY_MODES` of
  :mod:`registration.studies.qa_images`: the vessel outline, the DRR's edges, a checkerboard of
  image and DRR, their difference, a before / after wipe between the machine-based and the
  registered pose), the checkerboard's squares, the wipe's line, zoom and pan, a large
  single-image layout for demos; the 3-D view's camera (frame the vessels, view from the source)
  and the machine-based pose's ghost; **Write report**: the last registration as a report folder
  (:func:`registration.studies.qa_report.write_registration_report`).
- **Evidence** (left): after each registration, the measure along each parameter around the
  estimate and the depth scan (:mod:`registration.studies.qa_evidence`), the plot that withheld
  a withheld estimate framed in red.

The presenter reads :meth:`ComparePanel.settings` for every frame it draws; the evidence and
the report are computed on this panel's own threads.
"""

from __future__ import annotations

import logging
import os
import threading
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import cv2
import matplotlib
import numpy as np
import viser

from app.web.layout import VIEW_PANEL_PX
from app.web.panels import BasePanel, PanelContext
from app.web.views import PANEL_RGB, PANEL_TEXT_RGB, hex_of
from registration.studies.qa_images import CHECKER_TILE_PX, OVERLAY_LABELS, OVERLAY_MODES

log = logging.getLogger(__name__)

#: Width of the left panel in the large single-image layout (pixels).
LARGE_PANEL_PX = 1000
#: Where the app's Write report puts its folders (``ROADMAP3D_REPORTS`` overrides).
REPORTS_ENV = "ROADMAP3D_REPORTS"
_MODE_OF_LABEL = {label: mode for mode, label in OVERLAY_LABELS.items()}
#: The app's dark panel behind the evidence plots, and matplotlib's settings that draw them on it
#: (the reports keep matplotlib's white).
_PAPER, _INK, _EDGE = hex_of(PANEL_RGB), hex_of(PANEL_TEXT_RGB), "#5c5f66"
DARK_PLOTS = {
    "figure.facecolor": _PAPER, "axes.facecolor": _PAPER, "savefig.facecolor": _PAPER,
    "text.color": _INK, "axes.labelcolor": _INK, "axes.titlecolor": _INK,
    "xtick.color": _INK, "ytick.color": _INK, "axes.edgecolor": _EDGE,
    "legend.facecolor": _PAPER, "legend.edgecolor": _EDGE,
}  # fmt: skip


def _blank() -> np.ndarray:
    return np.full((8, 8, 3), PANEL_RGB, np.uint8)


@dataclass(frozen=True)
class CompareSettings:
    """What the fluoro tile and the 3-D view show (the Compare tab's state)."""

    mode: str = "outline"
    checker_px: int = CHECKER_TILE_PX
    wipe: float = 0.5
    zoom: float = 1.0
    pan: tuple[float, float] = (0.5, 0.5)
    large: bool = False
    view_from_source: bool = False
    show_initial: bool = False
    #: Incremented by "Frame the vessels": the presenter frames the camera when it changes.
    frame_request: int = 0


def reports_folder() -> Path:
    """The folder the app writes reports into: ``$ROADMAP3D_REPORTS`` or ~/roadmap3d-reports."""
    return Path(os.environ.get(REPORTS_ENV) or Path.home() / "roadmap3d-reports")


def _png_to_rgb(png: bytes) -> np.ndarray:
    bgr = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    return np.ascontiguousarray(bgr[:, :, ::-1])


class ComparePanel(BasePanel):
    """The Compare and Evidence tabs (see the module's docstring)."""

    def __init__(self, ctx: PanelContext) -> None:
        self.ctx = ctx
        gui = ctx.server.gui
        with ctx.layout.view_tab("Evidence", viser.Icon.CHART_LINE):
            self.evidence_text = gui.add_markdown("Register to see the evidence the confidence reads.")
            self.profiles_image = gui.add_image(_blank(), label=None, format="png")
            self.profiles_b_image = gui.add_image(_blank(), label=None, format="png",
                                                  visible=False)  # fmt: skip
            self.depth_image = gui.add_image(_blank(), label=None, format="png")
        with ctx.layout.control_tab("Compare", viser.Icon.LAYERS_INTERSECT):
            self.overlay = gui.add_dropdown(
                "Overlay",
                tuple(OVERLAY_LABELS[m] for m in OVERLAY_MODES),
                initial_value=OVERLAY_LABELS["outline"],
                hint="What the fluoro tile draws over the X-ray image",
            )
            self.checker = gui.add_slider("Checker size (px)", 8, 128, 8, CHECKER_TILE_PX)
            self.wipe = gui.add_slider(
                "Before / after",
                0.0,
                1.0,
                0.02,
                0.5,
                hint="Left of the line: machine-based pose; right: registered",
            )
            self.zoom = gui.add_slider("Zoom", 1.0, 4.0, 0.25, 1.0)
            self.pan_x = gui.add_slider("Pan x", 0.0, 1.0, 0.02, 0.5)
            self.pan_y = gui.add_slider("Pan y", 0.0, 1.0, 0.02, 0.5)
            self.large = gui.add_checkbox("Large image", False, hint="The fluoro tile alone and larger (demos)")
            gui.add_markdown("**3-D view**")
            self.frame_button = gui.add_button("Frame the vessels", icon=viser.Icon.FOCUS_CENTERED)
            self.view_from_source = gui.add_checkbox(
                "View from the source", False, hint="The camera at the X-ray source, following the C-arm"
            )
            self.show_initial = gui.add_checkbox(
                "Machine-based pose (ghost)", False, hint="The vessels where the C-arm sensors alone put them"
            )
            gui.add_markdown("**Report**")
            self.report_button = gui.add_button("Write report", icon=viser.Icon.FILE_ANALYTICS)
            self.report_info = gui.add_markdown(f"<small>Into {reports_folder()}</small>")
        self._lock = threading.Lock()
        self._settings = CompareSettings()
        for control in (self.overlay, self.checker, self.wipe, self.zoom, self.pan_x, self.pan_y,
                        self.view_from_source, self.show_initial):  # fmt: skip
            control.on_update(ctx.guarded(lambda _e: self._changed()))
        self.large.on_update(ctx.guarded(lambda _e: self._on_large()))
        self.frame_button.on_click(ctx.guarded(lambda _e: self._frame()))
        self.report_button.on_click(ctx.guarded(lambda _e: self.write_report()))
        self._quit = threading.Event()
        self._shown_run: object = None
        #: The last report folder written (tests, the status line).
        self.last_report: Path | None = None
        #: Whether the last evidence shown has plane B's pictures (tests read it).
        self.plane_b_shown = False
        self._report_thread: threading.Thread | None = None
        self._watcher = threading.Thread(target=self._watch, name="evidence", daemon=True)
        self._watcher.start()

    # ----- settings -----------------------------------------------------------------------
    def settings(self) -> CompareSettings:
        with self._lock:
            return self._settings

    def _changed(self) -> None:
        with self._lock:
            self._settings = CompareSettings(
                mode=_MODE_OF_LABEL.get(str(self.overlay.value), "outline"),
                checker_px=int(self.checker.value),
                wipe=float(self.wipe.value),
                zoom=float(self.zoom.value),
                pan=(float(self.pan_x.value), float(self.pan_y.value)),
                large=bool(self.large.value),
                view_from_source=bool(self.view_from_source.value),
                show_initial=bool(self.show_initial.value),
                frame_request=self._settings.frame_request,
            )
        self.ctx.refresh()

    def _on_large(self) -> None:
        self.ctx.layout.view_panel.set_width(LARGE_PANEL_PX if self.large.value else VIEW_PANEL_PX)
        self._changed()

    def _frame(self) -> None:
        if self.view_from_source.value:
            self.view_from_source.value = False  # runs _changed
        with self._lock:
            s = self._settings
            self._settings = CompareSettings(**{**s.__dict__, "frame_request": s.frame_request + 1})
        self.ctx.refresh()

    # ----- evidence -------------------------------------------------------------------------
    def _watch(self) -> None:
        while not self._quit.wait(0.3):
            s = self.ctx.session
            with s.lock:
                run = s.run
                ready = not run.running and run.result is not None and run is not self._shown_run
            if not ready:
                continue
            self._shown_run = run
            try:
                self._show_evidence(run)
            except Exception as exc:  # noqa: BLE001 - the evidence is an extra: the page says why it is missing
                log.exception("evidence failed")
                self.evidence_text.content = f"The evidence could not be drawn: {exc}"

    def _show_evidence(self, run: object) -> None:
        from registration.studies import qa_evidence

        s = self.ctx.session
        result, assessment = run.result, run.assessment  # type: ignore[attr-defined]
        if result.stopped or assessment is None:
            self.evidence_text.content = "No evidence: the registration was stopped or not assessed."
            return
        self.evidence_text.content = "Computing the evidence…"
        views = run.views or s.views()  # type: ignore[attr-defined]
        volume_format = s.settings.volume_format_cm
        initial = run.initial_motion  # type: ignore[attr-defined]
        renderer = s.data.evidence_renderer(volume_format, views, initial)
        volume = s.data.volume(volume_format)
        evidence = assessment.get("confidence_evidence") or {}
        reason = assessment.get("withheld_reason") or ""
        profiles = qa_evidence.parameter_profiles(volume, views[0], result.patient_motion, renderer=renderer)
        with matplotlib.rc_context(DARK_PLOTS):
            png = qa_evidence.profiles_figure(profiles, evidence=evidence, reason=reason, columns=3)
        term = qa_evidence.withheld_term(evidence) if evidence else None
        scan, weighed = qa_evidence.pictured_scan(assessment.get("depth_scan"), views, result.patient_motion,
                                                  renderer, one_view="tz" not in tuple(result.parameters))  # fmt: skip
        with matplotlib.rc_context(DARK_PLOTS):
            depth = qa_evidence.depth_figure(scan, assessment.get("depth_probe"), far=assessment.get("depth_far"),
                                             reason=reason, term=term, weighed=weighed)  # fmt: skip
        self.profiles_image.image = _png_to_rgb(png)
        if len(views) > 1:  # biplane: plane B's measure around the same estimate
            profiles_b = qa_evidence.parameter_profiles(volume, views[1], result.patient_motion, renderer=renderer)
            with matplotlib.rc_context(DARK_PLOTS):
                png_b = qa_evidence.profiles_figure(profiles_b, evidence=evidence, reason=reason, columns=3)
            self.profiles_b_image.image = _png_to_rgb(png_b)
        self.profiles_b_image.visible = len(views) > 1
        self.plane_b_shown = len(views) > 1
        self.depth_image.image = _png_to_rgb(depth) if depth is not None else _blank()
        verdict = (
            f"Confidence {assessment['confidence']:.2f}: **applied**."
            if assessment["applied"]
            else f"Confidence {assessment['confidence']:.2f}: **withheld**: {reason}. "
            f"Read it in {qa_evidence.TERM_PICTURES.get(term or '', 'the evidence')} (framed in red)."
        )
        plane = " (plane A, then plane B)" if len(views) > 1 else ""
        self.evidence_text.content = (
            f"{verdict}  \n<small>The measure along each parameter around the estimate{plane}, relative to its "
            "value there (orange dots: the confidence's margin probes; dashed: the margin it asks for), and along "
            "the beam.</small>"
        )

    # ----- report ---------------------------------------------------------------------------
    def write_report(self) -> None:
        """Write the last registration's report on a thread; the status line says where."""
        s = self.ctx.session
        with s.lock:
            run = s.run
            if run.running or run.result is None:
                raise ValueError("Register first: the report is of the last registration")
        if self._report_thread is not None and self._report_thread.is_alive():
            raise ValueError("A report is being written")
        self.ctx.message("Writing the report…")
        self._report_thread = threading.Thread(target=self._write, args=(run,), name="report", daemon=True)
        self._report_thread.start()

    def _write(self, run: object) -> None:
        from registration.studies import qa_report

        s = self.ctx.session
        try:
            result, assessment = run.result, run.assessment  # type: ignore[attr-defined]
            views = run.views or s.views()  # type: ignore[attr-defined]
            volume_format = s.settings.volume_format_cm
            initial = run.initial_motion  # type: ignore[attr-defined]
            document = result.to_dict()
            if assessment is not None:
                keys = ("confidence", "applied", "withheld_reason", "confidence_evidence")
                document.update({k: assessment[k] for k in keys})
            meshes = s.data.meshes(volume_format)
            anatomy = None
            if "vessels" in meshes:
                anatomy = qa_report.Anatomy(
                    np.asarray(meshes["vessels"].vertices), float(s.data.mesh_spacing_mm(volume_format))
                )
            stamp = datetime.now(UTC).strftime("%Y%m%d-%H%M%S-%f")
            out = reports_folder() / f"registration-{stamp}"
            qa_report.write_registration_report(
                out, document=document, volume=s.data.volume(volume_format), views=views,
                renderer=s.data.evidence_renderer(volume_format, views, initial), initial_motion=initial,
                anatomy=anatomy, depth_probe=(assessment or {}).get("depth_probe"),
                depth_scan=(assessment or {}).get("depth_scan"), depth_far=(assessment or {}).get("depth_far"),
                command="roadmap3d demo: Write report",
            )  # fmt: skip
        except Exception as exc:  # noqa: BLE001 - said in the page
            log.exception("report failed")
            self.ctx.message(f"The report could not be written: {exc}", error=True)
            return
        self.last_report = out
        self.report_info.content = f"<small>Last report: {out / qa_report.REPORT_HTML}</small>"
        self.ctx.message(f"Report written: {out / qa_report.REPORT_HTML}")

    def close(self) -> None:
        self._quit.set()
        if self._watcher.is_alive():
            self._watcher.join(timeout=5.0)
        if self._report_thread is not None:
            self._report_thread.join(timeout=30.0)
