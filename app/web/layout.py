"""The app's layout: every panel, tab and widget, created once and never re-arranged.

Only *what is where*: no callbacks (:mod:`app.web.controller` binds them) and no drawing
(:mod:`app.web.presenter` fills the widgets). Two tab groups take the app's panels:

- ``view_tabs`` on the left, what the clinician looks at: **Roadmap** (the fluoro + DRR
  picture, the badge, the residual readout, the convergence plot), then the mounted panels
  (Calibration, ...);
- ``control_tabs`` on the right, under Register / Stop / Auto-correct: **Patient motion**,
  **C-arm**, **Data**, **Display**, then the mounted panels.

A new panel does not edit this file: it opens its tab with :meth:`Layout.view_tab` or
:meth:`Layout.control_tab` from its constructor (see :mod:`app.web.panels`).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import viser

from app.web.run_chart import CHART_PADDING
from app.web.session import ROTATION_RANGE_DEG, TRANSLATION_RANGE_MM
from app.web.session_state import PLANE_B_PRIMARY_DEG
from registration.core.geometry import DEFAULT_SID_MM, IMAGE_FORMATS_CM, OFFSET_NAMES, TABLE_I
from registration.sim.biplane import plane_b_spec

#: Widths of the two side panels (pixels).
VIEW_PANEL_PX = 600
CONTROL_PANEL_PX = 380
#: The Roadmap tab's picture before the first frame (fluoro + DRR side by side).
PLACEHOLDER_SHAPE = (384, 772, 3)

FORMAT_OPTIONS = tuple(f"{f:g} cm" for f in IMAGE_FORMATS_CM)
#: The tz slider in biplane mode: corrected now (plane B sees plane A's tz in its image plane).
TZ_CORRECTED_LABEL = "tz (mm) ✓ biplane"
OFFSET_LABELS = {
    "tx": "tx (mm)",
    "ty": "ty (mm)",
    "tz": "tz (mm)",
    "rx": "rx (°)",
    "ry": "ry (°)",
    "rz": "rz (°)",
}


def format_cm(option: str) -> float:
    """'27 cm' -> 27.0 (the format dropdowns' values)."""
    return float(option.split()[0])


def format_option(format_cm: float) -> str:
    """27.0 -> '27 cm'."""
    return f"{format_cm:g} cm"


def badge(text: str, color: str) -> str:
    """The coloured status badge above the readout (HTML)."""
    return (
        f'<div style="display:flex;justify-content:flex-start;padding:2px 0 4px 0">'
        f'<span style="background:{color};color:#fff;font-weight:600;letter-spacing:0.04em;'
        f'padding:3px 10px;border-radius:4px;font-size:0.82em">{text}</span></div>'
    )


def offset_limit(index: int) -> float:
    """Slider range of offset ``index`` (0-2 translations in mm, 3-5 rotations in degrees)."""
    return TRANSLATION_RANGE_MM if index < 3 else ROTATION_RANGE_DEG


class Layout:
    """Creates the panels and widgets on ``server.gui`` and holds their handles."""

    def __init__(self, server: viser.ViserServer, *, max_upload_bytes: int) -> None:
        self.server = server
        self.gui = gui = server.gui
        gui.main_panel.dock_right()
        gui.main_panel.set_width(CONTROL_PANEL_PX)

        # Left: what the clinician looks at.
        self.view_panel = gui.add_panel()
        self.view_tabs = self.view_panel  # the left panel is itself a tab group
        with self.view_panel.add_tab("Roadmap", viser.Icon.PHOTO):
            self.images = gui.add_image(
                np.zeros(PLACEHOLDER_SHAPE, np.uint8), label=None, format="jpeg", jpeg_quality=88
            )
            self.badge = gui.add_html(badge("PREPARING", "#495057"))
            self.readout = gui.add_markdown("Residual: –")
            self.details = gui.add_markdown("")
            self.plot = self._convergence_plot()
        self.view_panel.dock_left()
        self.view_panel.set_width(VIEW_PANEL_PX)

        # Right: the controls.
        gui.add_markdown("**3D roadmap** · automatic patient-motion correction")
        self.volume_info = gui.add_markdown("")
        #: Empty, or why the volume has no vessel surface (a CT without contrast).
        self.vessel_info = gui.add_markdown("")
        self.register_button = gui.add_button("Register", color="green", icon=viser.Icon.TARGET)
        self.stop_button = gui.add_button("Stop", color="red", icon=viser.Icon.PLAYER_STOP, disabled=True)
        self.autocorrect = gui.add_checkbox(
            "Auto-correct", False, hint="Re-register whenever the patient moves, as the product does"
        )
        self.biplane = gui.add_checkbox(
            "Biplane",
            False,
            hint="Plane B, the lateral C-arm, images the patient at the same moment: registration then "
            "corrects all six offsets, tz (along plane A's beam) too (its angles: C-arm tab)",
        )
        self.status = gui.add_markdown("")
        self.control_tabs = tabs = gui.add_tab_group()
        with tabs.add_tab("Patient motion", viser.Icon.USER):
            self._motion_tab(gui)
        with tabs.add_tab("C-arm", viser.Icon.RADAR):
            self._carm_tab(gui)
        with tabs.add_tab("Data", viser.Icon.DATABASE):
            self._data_tab(gui, max_upload_bytes)
        with tabs.add_tab("Display", viser.Icon.EYE):
            self._display_tab(gui)

        self._control_groups()

    def _control_groups(self) -> None:
        """The controls disabled together (during a run; the C-arm's while the user's file fixes it;
        the iso-center's for the phantom)."""
        #: Disabled during a run, and while the user's file fixes the C-arm.
        self.carm_controls: list[Any] = [
            self.primary, self.secondary, self.sid, self.image_format, self.volume_format,
            self.kind, self.contrast, self.catheter, self.biplane, self.primary_b, self.secondary_b,
        ]  # fmt: skip
        #: Disabled during a run, and for the phantom (imaged about the world origin).
        self.isocenter_controls: list[Any] = [
            self.isocenter_field,
            self.isocenter_button,
            self.head_center_button,
            self.volume_center_button,
        ]
        #: Disabled during a run.
        self.motion_controls: list[Any] = [
            *self.offset_sliders,
            *self.table_buttons.values(),
            self.random_button,
            self.reset_button,
        ]

    def _convergence_plot(self) -> Any:
        """The annealing's best similarity and temperature, per iteration."""
        return self.gui.add_uplot(
            data=(np.zeros(1), np.full(1, np.nan), np.full(1, np.nan)),
            series=(
                {"label": "iteration"},
                {"label": "similarity", "stroke": "#4dabf7", "width": 2, "scale": "sim"},
                {"label": "log10 temperature", "stroke": "#ffa94d", "width": 1.5, "scale": "temp"},
            ),
            scales={"x": {"time": False}, "sim": {"auto": True}, "temp": {"auto": True}},
            axes=(
                {"stroke": "#adb5bd", "grid": {"stroke": "#2c2e33"}},
                {"scale": "sim", "stroke": "#4dabf7", "grid": {"stroke": "#2c2e33"}},
                {"scale": "temp", "side": 1, "stroke": "#ffa94d", "grid": {"show": False}},
            ),
            title="Convergence: gradient difference (best) and temperature",
            height=190,
            padding=CHART_PADDING,  # room for the top tick's label
        )

    def _motion_tab(self, gui: Any) -> None:
        """The patient-motion sliders, Table I's offsets, Random and Reset."""
        self.offset_sliders = [
            gui.add_slider(
                OFFSET_LABELS[name],
                -offset_limit(i),
                offset_limit(i),
                0.1,
                0.0,
                hint="Patient motion in the view frame (x = image columns, y = rows, z = toward the source)",
            )
            for i, name in enumerate(OFFSET_NAMES)
        ]
        gui.add_markdown("Table I of the paper (initial offsets):")
        self.table_buttons = {name: gui.add_button(name, hint=f"Table I offset {TABLE_I[name]}") for name in TABLE_I}
        self.random_button = gui.add_button("Random", hint="A random motion within 25 mm and 10°")
        self.reset_button = gui.add_button("Reset", hint="No patient motion; roadmap from the C-arm sensors")

    def _carm_tab(self, gui: Any) -> None:
        """The C-arm's angles, distances, formats and image type, and plane B's."""
        self.primary = gui.add_slider(
            "LAO/RAO (°)", -120.0, 120.0, 1.0, 0.0, hint="Primary angle: LAO positive, RAO negative"
        )
        self.secondary = gui.add_slider(
            "CRAN/CAUD (°)", -50.0, 50.0, 1.0, 0.0, hint="Secondary angle: CRAN positive, CAUD negative"
        )
        self.sid = gui.add_slider("SID (mm)", 900.0, 1300.0, 10.0, DEFAULT_SID_MM)
        self.image_format = gui.add_dropdown("Image format", FORMAT_OPTIONS, initial_value="27 cm")
        self.volume_format = gui.add_dropdown("Volume format", FORMAT_OPTIONS, initial_value="27 cm")
        self.kind = gui.add_dropdown("Image type", ("fluoro", "exposure"), initial_value="fluoro")
        self.contrast = gui.add_checkbox("Contrast in vessels", True)
        self.catheter = gui.add_checkbox("Catheter", False)
        spec = plane_b_spec()
        self.plane_b_folder = gui.add_folder("Plane B (lateral C-arm)", visible=False)
        with self.plane_b_folder:
            self.primary_b = gui.add_slider(
                "B: LAO/RAO (°)", 45.0, 135.0, 1.0, PLANE_B_PRIMARY_DEG, hint="Plane B's primary angle"
            )
            self.secondary_b = gui.add_slider(
                "B: CRAN/CAUD (°)", -40.0, 40.0, 1.0, 0.0, hint="Plane B's secondary angle"
            )
            gui.add_markdown(
                f"<small>Its own machine: SID {spec.sid_mm:g} mm, SOD {spec.sod_mm:g} mm, "
                f"{spec.image_format_cm:g} cm format; same image type.</small>"
            )

    def _data_tab(self, gui: Any, max_upload_bytes: int) -> None:
        """The user's data: upload, distances, field and region masks, the iso-center."""
        self.source = gui.add_markdown("")
        self.upload = gui.add_upload_button(
            "Upload your DICOM (.zip)",
            icon=viser.Icon.UPLOAD,
            mime_type="application/zip",
            hint="A zip with a 3DRA/CT volume (series, multi-frame or .npz) and one XA/RF image",
        )
        gui.add_markdown(
            f"<small>Limit {max_upload_bytes / 1e6:g} MB. Unpacked into a private temporary folder, read, "
            "then deleted. Your data has no ground truth: the motion controls move the roadmap.</small>"
        )
        self.upload_sid = gui.add_text(
            "SID (mm)",
            "",
            hint="Source-detector distance for an XA/RF file without DistanceSourceToDetector; "
            "a value here replaces the file's (with a warning). Empty: from the file.",
        )
        self.upload_sod = gui.add_text(
            "SOD (mm)",
            "",
            hint="Source-iso-center distance for an XA/RF file without DistanceSourceToPatient; "
            "a value here replaces the file's (with a warning). Empty: from the file.",
        )
        gui.add_markdown("<small>SID/SOD: only for images that lack the distances; then upload again.</small>")
        self.field_mask_upload = gui.add_upload_button(
            "Field mask (PNG/TIFF)",
            icon=viser.Icon.MASK,
            mime_type="image/*",
            hint="Your own mask of the image's usable field: the image's stored size, nonzero = usable; it narrows "
            "the field found from the file (as register --image-mask)",
        )
        self.region_upload = gui.add_upload_button(
            "Region mask (.npz, NIfTI, DICOM SEG)",
            icon=viser.Icon.BOX,
            hint="A label mask on the volume's grid: the registration follows the labelled voxels only (the "
            "cranium without the spine, say), as register --roi-mask",
        )
        self.isocenter_info = gui.add_markdown("")
        self.isocenter_field = gui.add_text(
            "Iso-center (mm)",
            "",
            hint="x, y, z in mm, the volume's patient coordinates (LPS), 'head' or 'volume center'; the image is "
            "placed about it and the next Register uses it",
        )
        self.isocenter_button = gui.add_button(
            "Set iso-center", icon=viser.Icon.CROSSHAIR, hint="Use the iso-center typed above"
        )
        self.head_center_button = gui.add_button(
            "Iso-center at the middle of the head",
            hint="The middle of the largest tissue within 180 mm of the volume's top (the head; a couch apart from "
            "it left out): where a neuro C-arm is aimed",
        )
        self.volume_center_button = gui.add_button(
            "Iso-center at the volume center", hint="The center of the volume's voxel grid"
        )
        self.phantom_button = gui.add_button("Back to the phantom", visible=False)

    def _display_tab(self, gui: Any) -> None:
        """What the views show besides the roadmap."""
        self.show_ghost = gui.add_checkbox("True position (ghost)", False)
        self.show_skull = gui.add_checkbox("Skull", True)
        self.show_gradients = gui.add_checkbox("Gradient images", False)
        self.show_field = gui.add_checkbox(
            "Usable field", False, hint="Shade what the registration leaves out of the X-ray image (blades, text)"
        )

    # ----- where new panels go ------------------------------------------------------------
    @contextmanager
    def view_tab(self, name: str, icon: Any = None) -> Iterator[None]:
        """Open a new tab on the left (after Roadmap and the panels mounted before); widgets
        added with ``server.gui`` inside the ``with`` block land in it."""
        with self.view_tabs.add_tab(name, icon):
            yield

    @contextmanager
    def control_tab(self, name: str, icon: Any = None) -> Iterator[None]:
        """Open a new tab on the right, after Patient motion, C-arm, Data and Display."""
        with self.control_tabs.add_tab(name, icon):
            yield
