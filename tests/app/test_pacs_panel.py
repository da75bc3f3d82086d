"""The app's PACS tab (app/web/pacs_panel.py) against a real Orthanc: the issue's "done when".

The app lists the stored studies, loads the 3DRA and the fluoro image from the PACS, registers,
stores the REG object (and the overlay) back; the REG object read back from Orthanc holds the
motion the app's estimate had.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.web.gui import RoadmapApp
from app.web.pacs_panel import PacsPanel
from registration.io import dicom
from registration.io.pacs import Pacs, PacsSettings
from tests.orthanc import OrthancServer


@pytest.mark.slow  # a whole registration
def test_app_lists_loads_registers_and_stores(
    fresh: RoadmapApp, orthanc: OrthancServer, small_export: Path, tmp_path: Path
) -> None:
    app = fresh
    orthanc.clear()
    settings = PacsSettings(orthanc.dicomweb_url, username=orthanc.username, password=orthanc.password)
    Pacs(settings).store(sorted(small_export.rglob("*.dcm")))
    (panel,) = [p for p in app.panels if isinstance(p, PacsPanel)]
    panel._settings, panel._pacs = settings, None  # the test's Orthanc instead of ROADMAP3D_PACS_URL
    try:
        panel.refresh_button.value = True  # "List studies"
        assert panel.wait(30)
        assert panel.patient.value.endswith("(ROADMAP3D)") and len(panel.study.options) == 1
        assert any("CT" in o for o in panel.volume_series.options)
        # plane A's fluoro (plane B's is in the export too, described as such)
        panel.image_series.value = next(o for o in panel.image_series.options if "fluoro" in o and "plane B" not in o)
        panel.load_button.value = True
        assert panel.wait(60), "loading did not finish"
        assert app.session.data.source.startswith("PACS ") and "Error" not in panel.status.content
        shown = dicom.read_xray(small_export / "xa_fluoro.dcm")
        assert np.array_equal(app.session.data.fixed_xray.image, shown.image)

        app.register_button.value = True
        assert app.session.wait(120), "registration did not finish"
        estimate = np.array(app.session.estimate)
        run = app.session.run
        assert run.result is not None and run.assessment is not None and run.error is None, run.error
        if run.assessment["applied"]:  # the roadmap moved to the estimate (T4 is 7-8 mm / 5-7 deg away)
            np.testing.assert_array_equal(estimate, run.result.patient_motion)
            assert not np.allclose(estimate, np.eye(4))
        else:  # withheld (this 48^3 / 96 px export's estimate was 1.6 mm / 3.9 deg off at 62e86d2): it stays
            np.testing.assert_array_equal(estimate, np.eye(4))

        panel.store_button.value = True
        assert panel.wait(60)
        assert "Stored the registration" in panel.status.content, panel.status.content
        pacs = Pacs(settings)
        (study,) = pacs.studies()
        reg_series = next(s for s in pacs.series(study.study_uid) if s.modality == "REG")
        folder = pacs.retrieve_series(study.study_uid, reg_series.series_uid, tmp_path / "reg")
        reg = dicom.read_registration(next(folder.iterdir()))
        # DS strings of 16 characters: ~1e-10 relative
        assert np.allclose(reg.patient_motion, estimate, atol=1e-6)
        # the audit trail: the load and the store, each with its outcome and the study's UIDs, no name
        from registration.io.audit import audit_log

        lines = [line for line in audit_log().lines() if line["action"] in ("pacs-load", "pacs-store")][-2:]
        assert [(line["action"], line["result"]) for line in lines] == [("pacs-load", "ok"), ("pacs-store", "ok")]
        assert all(line["study_uid"] == study.study_uid for line in lines)
        assert lines[1]["instance_uid"] == reg.sop_instance_uid  # the REG object stored
        name = str(dicom.read_xray(small_export / "xa_fluoro.dcm").meta.get("patient_name", "ROADMAP3D"))
        assert all(name not in str(line) for line in lines)
    finally:
        app.phantom_button.value = True  # back to the phantom for the other app tests
        panel._settings, panel._pacs = None, None


def test_store_needs_data_from_the_pacs(fresh: RoadmapApp) -> None:
    (panel,) = [p for p in fresh.panels if isinstance(p, PacsPanel)]
    panel.store_button.value = True
    assert panel.wait(10)
    assert "Load a volume and an image from the PACS first" in panel.status.content


def test_a_c_store_reaches_the_app(fresh: RoadmapApp, small_export: Path) -> None:
    """The app's DICOM node: when pynetdicom's StoreSCU sees success, the app already has the image
    (the node reports before it answers); unknown AE titles are refused; the image can be shown."""
    from pynetdicom import AE
    from pynetdicom.sop_class import XRayAngiographicImageStorage  # type: ignore[attr-defined]

    app = fresh
    (panel,) = [p for p in app.panels if isinstance(p, PacsPanel)]
    port = panel.start_node(allowed=("CARM",), port=0)
    try:
        intruder = AE(ae_title="INTRUDER")
        intruder.add_requested_context(XRayAngiographicImageStorage)
        assert intruder.associate("127.0.0.1", port, ae_title="ROADMAP3D").is_rejected
        assert panel.received is None

        ae = AE(ae_title="CARM")
        ae.add_requested_context(XRayAngiographicImageStorage)
        assoc = ae.associate("127.0.0.1", port, ae_title="ROADMAP3D")
        assert assoc.is_established
        assert assoc.send_c_store(dicom.read_dataset(small_export / "xa_fluoro.dcm")).Status == 0x0000
        assoc.release()
        # no waiting: the app was told before the C-STORE was answered
        assert panel.received is not None and panel.received.calling_ae == "CARM"
        assert "Received XA from CARM" in panel.node_info.content and not panel.use_received.disabled

        panel.use_received.value = True
        sent = dicom.read_xray(small_export / "xa_fluoro.dcm")
        assert np.array_equal(app.session.data.fixed_xray.image, sent.image)
        assert app.session.data.source.startswith("C-arm CARM")
    finally:
        app.phantom_button.value = True
        panel.close()  # stops the node, removes its private folder


def test_a_received_run_goes_to_play_run(fresh: RoadmapApp, small_export: Path, tmp_path: Path) -> None:
    """A multi-frame run C-STOREd to the app's node becomes the Play run panel's run (frames, times)."""
    from pynetdicom import AE
    from pynetdicom.sop_class import XRayAngiographicImageStorage  # type: ignore[attr-defined]

    app = fresh
    (panel,) = [p for p in app.panels if isinstance(p, PacsPanel)]
    playback = app.playback
    image = dicom.read_xray(small_export / "xa_fluoro.dcm")
    times_s = [0.0, 1 / 15, 2 / 15, 3 / 15]
    run_file = dicom.write_xray_run([image] * 4, tmp_path / "run.dcm", times_s=times_s)
    port = panel.start_node(allowed=("CARM",), port=0)
    try:
        ae = AE(ae_title="CARM")
        ae.add_requested_context(XRayAngiographicImageStorage)
        assoc = ae.associate("127.0.0.1", port, ae_title="ROADMAP3D")
        assert assoc.is_established
        assert assoc.send_c_store(dicom.read_dataset(run_file)).Status == 0x0000
        assoc.release()
        # the node reports before it answers: the run is loaded when the sender sees success
        run = playback.user_run
        assert run is not None and len(run) == 4 and "from CARM" in run.name
        # frame times as sent (DICOM stores them in ms: a few decimals)
        assert np.allclose(run.times_s - run.times_s[0], times_s, atol=1e-3)
        assert np.array_equal(run[2].image, image.image)
        assert "4 frames" in playback.message.content and playback.phantom_run_button.visible
    finally:
        playback.use_phantom_run()
        app.phantom_button.value = True
        panel.close()


def test_list_studies_waits_for_a_pacs(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """Without a PACS (no settings, no ROADMAP3D_PACS_URL, no config file) "List studies" is
    disabled: a click used to put "no PACS URL: ... write it into <the server's path>" on the
    app's status line; given one, or a config file, it is enabled."""
    panel = object.__new__(PacsPanel)
    panel._settings = None
    monkeypatch.delenv("ROADMAP3D_PACS_URL", raising=False)
    monkeypatch.setenv("ROADMAP3D_PACS_CONFIG", str(tmp_path / "pacs.json"))
    assert not panel._configured() and "No PACS configured" in panel._server_line()
    (tmp_path / "pacs.json").write_text('{"url": "http://pacs.example/dicom-web"}')
    assert panel._configured() and "config file" in panel._server_line()
    (tmp_path / "pacs.json").unlink()
    monkeypatch.setenv("ROADMAP3D_PACS_URL", "http://pacs.example/dicom-web")
    assert panel._configured() and "pacs.example" in panel._server_line()
