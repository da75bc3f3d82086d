"""The web app assembled: layout, controller, presenter and the mounted panels.

The session is **shared**: every browser tab shows and controls the same patient, C-arm and
registration (server-level GUI and scene). The parts, each in its own module:

- :mod:`app.web.layout`: which widgets exist and where (the tab groups new panels open tabs in);
- :mod:`app.web.controller`: what the widgets do (callbacks change only the :class:`Session`);
- :mod:`app.web.presenter`: one thread that draws the session into the widgets and the scene;
- :mod:`app.web.panels`: optional panels (the calibration view, ...) mounted after the layout.

:class:`RoadmapApp` wires them together and keeps the handles tests and scripts use
(``app.register_button``, ``app.readout``, ...) on itself.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import viser

from app.web.calibration import CalibrationPanel
from app.web.controller import Controller
from app.web.landmarks import LandmarksPanel
from app.web.layout import Layout
from app.web.pacs_panel import PacsPanel
from app.web.panels import Panel, PanelContext, PanelFactory, mount
from app.web.playback import PlaybackPanel
from app.web.presenter import Presenter
from app.web.qa_panel import ComparePanel
from app.web.scene import Scene
from app.web.session import Session

if TYPE_CHECKING:
    from app.web.data import DataSource

#: The optional panels every app mounts, in tab order after the layout's own tabs (left:
#: Roadmap; right: Patient motion, C-arm, Data, Display). A new panel: one line here.
PANELS: tuple[PanelFactory, ...] = (CalibrationPanel, PacsPanel, PlaybackPanel, ComparePanel, LandmarksPanel)

#: Handles of the layout that are also reachable as ``app.<name>`` (tests, scripts, panels).
_LAYOUT_HANDLES = frozenset(
    """images badge readout details plot view_panel volume_info vessel_info register_button stop_button autocorrect
    status offset_sliders table_buttons random_button reset_button primary secondary sid image_format
    volume_format kind contrast catheter source upload phantom_button show_ghost show_skull show_gradients show_field
    field_mask_upload region_upload
    carm_controls motion_controls view_tabs control_tabs upload_sid upload_sod biplane primary_b secondary_b
    plane_b_folder isocenter_info isocenter_field isocenter_button head_center_button volume_center_button""".split()
)


class RoadmapApp:
    """Builds the GUI on ``server`` for ``session``, mounts ``panels`` and runs the presenter."""

    def __init__(
        self,
        server: viser.ViserServer,
        session: Session,
        *,
        phantom: DataSource | None = None,
        max_upload_mb: float = 512.0,
        panels: Sequence[PanelFactory] = PANELS,
    ) -> None:
        self.server = server
        self.session = session
        self.max_upload_bytes = int(max_upload_mb * 1e6)
        self._phantom_data = phantom if phantom is not None else session.data
        self.layout = Layout(server, max_upload_bytes=self.max_upload_bytes)
        self.scene = Scene(server)
        self.controller = Controller(
            server,
            session,
            self.layout,
            phantom=self._phantom_data,
            max_upload_bytes=self.max_upload_bytes,
            wake=lambda: self.presenter.wake(),
            force_refresh=lambda: self.presenter.force_refresh(),
        )
        self.presenter = Presenter(
            server,
            session,
            self.layout,
            self.scene,
            message=self.controller.message,
            tick=self.controller.tick,
            show_source=self.controller.show_source,
        )
        context = PanelContext(
            server=server,
            session=session,
            layout=self.layout,
            phantom=self._phantom_data,  # type: ignore[arg-type]
            message=self.controller.message,
            refresh=self.presenter.force_refresh,
            guarded=self.controller.guarded,
            max_upload_bytes=self.max_upload_bytes,
            follow=self.presenter.follow,
        )
        self.panels: list[Panel] = mount(tuple(panels), context)
        self._wire_panels()
        self.controller.panels = self.panels
        self.presenter.panels = self.panels
        self.presenter.compare = next((p for p in self.panels if isinstance(p, ComparePanel)), None)
        self.controller.bind()

    def _wire_panels(self) -> None:
        """A run the PACS tab's DICOM node receives becomes the Play run panel's run."""
        pacs = [p for p in self.panels if isinstance(p, PacsPanel)]
        playback = [p for p in self.panels if isinstance(p, PlaybackPanel)]
        if pacs and playback:
            pacs[0].run_receivers.append(playback[0].load_run_file)

    def __getattr__(self, name: str) -> Any:
        # Only reached for names not set on the app itself: the layout's widget handles.
        if name in _LAYOUT_HANDLES:
            return getattr(self.layout, name)
        raise AttributeError(f"{type(self).__name__!s} has no attribute {name!r}")

    # ----- what tests and scripts use ------------------------------------------------------
    @property
    def calibration(self) -> CalibrationPanel:
        """The calibration view (a mounted panel)."""
        return next(p for p in self.panels if isinstance(p, CalibrationPanel))

    @property
    def playback(self) -> PlaybackPanel:
        """The Play run panel (a mounted panel)."""
        return next(p for p in self.panels if isinstance(p, PlaybackPanel))

    @property
    def landmarks(self) -> LandmarksPanel:
        """The Landmarks panel (a mounted panel)."""
        return next(p for p in self.panels if isinstance(p, LandmarksPanel))

    @property
    def frames_shown(self) -> int:
        return self.presenter.frames_shown

    @property
    def live_updates(self) -> Any:
        return self.presenter.live_updates

    @property
    def _shown_version(self) -> int:
        return self.presenter.shown_version

    @property
    def _shown_geometry(self) -> Any:
        return self.presenter.shown_geometry

    def message(self, text: str, *, error: bool = False) -> None:
        self.controller.message(text, error=error)

    def start_registration(self) -> bool:
        return self.controller.start_registration()

    def load_upload(self, name: str, content: bytes) -> bool:
        return self.controller.load_upload(name, content)

    def _use_data(self, data: DataSource) -> None:
        self.controller.use_data(data)

    # ----- life cycle ----------------------------------------------------------------------
    def start(self) -> None:
        self.presenter.start()

    def close(self) -> None:
        for panel in self.panels:
            panel.close()
        self.presenter.stop()
        self.session.stop_registration(wait=True, timeout=3.0)
