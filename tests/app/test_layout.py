"""The app's seams: data sources share one declared interface; a new panel mounts by the hook."""

from __future__ import annotations

import numpy as np
import viser

from app.web.data import DataSource, FileData, PhantomData
from app.web.gui import PANELS, RoadmapApp
from app.web.main import make_server
from app.web.panels import BasePanel, Panel, PanelContext
from app.web.session import Session


def test_phantom_and_file_data_implement_the_data_source_protocol(app: RoadmapApp) -> None:
    phantom = app._phantom_data  # noqa: SLF001
    assert isinstance(phantom, PhantomData) and isinstance(phantom, DataSource)
    volume = phantom.volume(27.0)
    xray = app.session.xray()
    files = FileData(volume, xray, source="test", config=phantom.config)
    assert isinstance(files, DataSource)
    assert files.has_truth is False and files.fixed_xray is xray and files.vessel_points_mm() is None


class CountingPanel(BasePanel):
    """A panel as app/web/playback.py or app/web/pacs_panel.py would write it."""

    def __init__(self, ctx: PanelContext) -> None:
        self.ctx = ctx
        self.changes = 0
        self.closed = False
        with ctx.layout.view_tab("Test panel", viser.Icon.PLAYER_PLAY):
            self.button = ctx.server.gui.add_button("Say hello")
        with ctx.layout.control_tab("Test controls"):
            self.hide = ctx.server.gui.add_checkbox("Hide the patient", False)
        self.button.on_click(ctx.guarded(lambda _e: ctx.message("hello from the panel")))

    @property
    def hides_patient(self) -> bool:
        return bool(self.hide.value)

    def settings_changed(self) -> None:
        self.changes += 1

    def close(self) -> None:
        self.closed = True


def test_a_new_panel_mounts_with_one_line(app: RoadmapApp) -> None:
    server = make_server("127.0.0.1", 0)
    session = Session(app._phantom_data, app.session.config)  # noqa: SLF001 - the data is built already
    built = RoadmapApp(server, session, panels=(*PANELS, CountingPanel))
    try:
        panel = built.panels[-1]
        assert isinstance(panel, CountingPanel) and isinstance(panel, Panel)
        built.start()
        panel.button.value = True  # its callback reaches the status line
        assert "hello from the panel" in built.status.content
        built.primary.value = 20.0  # C-arm changes reach every panel
        assert panel.changes == 1 and session.settings.primary_deg == 20.0
        panel.hide.value = True
        built.presenter.force_refresh()
        built.presenter.present()
        assert built.scene.patient and not any(h.visible for h in built.scene.patient)
        assert np.allclose(session.true_motion, np.eye(4))
    finally:
        built.close()
        server.stop()
    assert panel.closed


def test_the_command_line_offers_the_engines_volume_sources() -> None:
    """The CLI's choices are typing.Literal declarations: they must stay the engine's list."""
    import typing

    from app.cli import configs, options
    from registration.sim.threedra import VOLUME_SOURCES

    for hints in (typing.get_type_hints(options.PhantomStudy), typing.get_type_hints(configs.Phantom),
                  typing.get_type_hints(configs.PhantomRun)):  # fmt: skip
        assert typing.get_args(hints["volume_source"]) == VOLUME_SOURCES


def test_the_data_tab_supplies_distances_a_file_lacks(fresh: RoadmapApp, tmp_path) -> None:
    """An XA image without DistanceSourceToDetector/ToPatient: refused with a hint, then read with
    the SID/SOD typed into the Data tab (the geometry then has exactly those distances)."""
    import io
    import zipfile

    import pydicom

    from app.web.data import simulate_xray
    from registration.io.dicom import write_npz, write_xray

    app = fresh
    phantom = app._phantom_data  # noqa: SLF001
    write_npz(phantom.volume(27.0), tmp_path / "volume.npz")
    geometry = app.session.settings.geometry(128)
    write_xray(simulate_xray(phantom.phantom(True), geometry, supersample=1), tmp_path / "image.dcm")
    ds = pydicom.dcmread(tmp_path / "image.dcm")
    del ds.DistanceSourceToDetector, ds.DistanceSourceToPatient
    if "EstimatedRadiographicMagnificationFactor" in ds:
        del ds.EstimatedRadiographicMagnificationFactor
    ds.save_as(tmp_path / "image.dcm")
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name in ("volume.npz", "image.dcm"):
            zf.write(tmp_path / name, arcname=name)
    content = buf.getvalue()
    before = app.session.data
    try:
        assert not app.load_upload("case.zip", content)
        assert "DistanceSourceToDetector" in app.status.content and "Data (SID/SOD)" in app.status.content
        assert app.session.data is before
        app.upload_sid.value = "twelve hundred"
        assert not app.load_upload("case.zip", content) and "SID must be a number" in app.status.content
        app.upload_sid.value = str(geometry.sid_mm)
        app.upload_sod.value = f"{geometry.sod_mm} mm"
        assert app.load_upload("case.zip", content), app.status.content
        read = app.session.data.fixed_xray.geometry
        assert (read.sid_mm, read.sod_mm) == (geometry.sid_mm, geometry.sod_mm)
        assert "Image field: shutter tags (circular), constant border; " in app.volume_info.content
        # the distances typed are the file's nominal geometry: the page says no calibration is applied
        assert "C-arm geometry: nominal" in app.volume_info.content and f"SID {geometry.sid_mm:.0f} mm" in (
            app.volume_info.content
        )
        assert "C-arm geometry nominal" in app.status.content
    finally:
        app.upload_sid.value = app.upload_sod.value = ""
        app.phantom_button.value = True
    assert app.session.data is app._phantom_data  # noqa: SLF001
