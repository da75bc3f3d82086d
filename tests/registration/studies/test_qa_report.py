"""The comparison pictures, the evidence profiles and the registration report.

One honest 128 px exposure of the phantom (simulated from the analytic phantom, not by the
renderer that scores it) against its 64^3 3DRA stand-in (the same phantom, resampled)."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from registration.core.confidence import DEFAULT_RULE, Evidence
from registration.core.geometry import CArm, offsets_to_matrix
from registration.core.tracking import registration_evidence
from registration.studies import qa_evidence, qa_images, qa_report


@pytest.fixture(scope="module")
def scene():
    from registration.core.drr import DRRRenderer
    from registration.sim.phantom import make_head_phantom, registration_volume
    from registration.sim.xray import simulate_xray

    volume = registration_volume(make_head_phantom(seed=0, contrast=True), 27.0, voxels=64)
    geometry = CArm.for_format(27.0, pixels=128, primary_deg=20.0)
    xray = simulate_xray(make_head_phantom(seed=0, contrast=True), geometry, kind="exposure", seed=1)
    return volume, xray, DRRRenderer(volume, levels=2)


# ----- pictures ---------------------------------------------------------------------------
def test_checkerboard_alternates_squares_of_the_two_images():
    a, b = np.full((8, 8), 10, np.uint8), np.full((8, 8), 200, np.uint8)
    out = qa_images.checkerboard(a, b, 2)
    assert out.shape == (8, 8, 3)
    assert out[0, 0, 0] == 10 and out[0, 2, 0] == 200 and out[2, 0, 0] == 200 and out[2, 2, 0] == 10
    assert (out[..., 0] == 200).sum() == 32  # exactly half of the squares
    with pytest.raises(ValueError, match="tile_px"):
        qa_images.checkerboard(a, b, 0)


def test_difference_is_mid_gray_where_the_images_agree_and_dark_or_light_where_not():
    rng = np.random.default_rng(0)
    img = rng.normal(size=(32, 32)).astype(np.float32)
    mask = np.ones((32, 32), bool)
    same = qa_images.difference(img, img * 3.0 + 1.0, mask)  # the same structure at another scale
    assert np.all(same == 128)
    other = img.copy()
    other[:16] = 0.0
    diff = qa_images.difference(img, other, mask)[..., 0].astype(int)
    assert np.abs(diff[:16] - 128).mean() > 20  # structure only in the image: away from gray


def test_wipe_takes_the_before_picture_left_of_the_line():
    before = np.zeros((4, 10, 3), np.uint8)
    after = np.full((4, 10, 3), 50, np.uint8)
    out = qa_images.wipe(before, after, 0.5)
    assert np.all(out[:, :4] == 0) and np.all(out[:, 6:] == 50)
    assert np.all(out[:, 4] == 255)  # the line itself


def test_edge_map_finds_the_rim_of_a_disc():
    rows, cols = np.mgrid[0:64, 0:64]
    r = np.hypot(rows - 32, cols - 32)
    disc = (r < 20).astype(np.float32)
    edges = qa_images.edge_map(disc)
    assert edges.any()
    assert np.all(np.abs(r[edges] - 20) < 2.5)  # on the rim (the Sobel kernel spreads it by a pixel)


def test_compare_renders_every_mode_and_refuses_others(scene):
    _volume, xray, renderer = scene
    drr = renderer.render(xray.geometry, offsets_to_matrix([3, 0, 0, 0, 0, 0], xray.geometry), level=0)
    pictures = {m: qa_images.compare(m, image=xray.image, drr=drr, mask=xray.mask) for m in qa_images.OVERLAY_MODES}
    for mode, rgb in pictures.items():
        assert rgb.shape == (128, 128, 3) and rgb.dtype == np.uint8, mode
        assert rgb[xray.mask].std() > 5, mode  # not blank
    keys = list(pictures)
    for i, a in enumerate(keys):
        for b in keys[i + 1 :]:
            changed = np.any(pictures[a] != pictures[b], axis=2)[xray.mask].mean()
            assert changed > 0.01, (a, b, changed)
    with pytest.raises(ValueError, match="overlay mode"):
        qa_images.compare("blend", image=xray.image, drr=drr, mask=xray.mask)


def test_zoom_enlarges_about_the_center():
    img = np.zeros((40, 40, 3), np.uint8)
    img[18:22, 18:22] = 255
    z = qa_images.zoomed(img, 2.0)
    assert z.shape == img.shape
    assert (z[..., 0] > 128).sum() > 3 * (img[..., 0] > 128).sum()  # the square is 4x the area


# ----- evidence ---------------------------------------------------------------------------
def test_profiles_carry_the_margins_the_confidence_reads(scene):
    volume, xray, renderer = scene
    motion = offsets_to_matrix([0.4, -0.3, 0.0, 1.0, -0.5, 0.5], xray.geometry)
    profiles = qa_evidence.parameter_profiles(volume, xray, motion, renderer=renderer)
    assert [p.name for p in profiles] == ["tx", "ty", "rx", "ry", "rz"]
    e = registration_evidence(volume, xray, motion, renderer=renderer)
    # the same DRRs and measure as the evidence: the margins agree to rounding
    mean_margin = np.mean([p.margin(1.0) for p in profiles])
    assert mean_margin == pytest.approx(e.margin, rel=1e-9, abs=1e-12)
    rotation = min(p.margin(3.0) for p in profiles if p.name in ("rx", "ry"))
    assert rotation == pytest.approx(e.rotation_margin, rel=1e-9, abs=1e-12)
    rx = next(p for p in profiles if p.name == "rx")
    assert min(rx.offsets) == -10.0 and max(rx.offsets) == 10.0 and 0.0 in rx.offsets


def test_profiles_peak_at_the_truth_and_not_beside_it(scene):
    volume, xray, renderer = scene
    at_truth = qa_evidence.parameter_profiles(volume, xray, np.eye(4), renderer=renderer)
    tx = next(p for p in at_truth if p.name == "tx")
    # at the truth the estimate is the profile's top within a step (0.5 mm: the DRR of a 4 mm voxel
    # volume is smooth at that scale)
    assert abs(tx.offsets[int(np.argmax(tx.relative))]) <= 0.5
    off = qa_evidence.parameter_profiles(volume, xray, offsets_to_matrix([3, 0, 0, 0, 0, 0], xray.geometry),
                                         renderer=renderer)  # fmt: skip
    tx_off = next(p for p in off if p.name == "tx")
    peak = tx_off.offsets[int(np.argmax(tx_off.relative))]
    assert peak == pytest.approx(-3.0, abs=1.0)  # the truth is 3 mm back along tx
    assert tx_off.margin(1.0) < 0  # and the confidence's margin sees it


def test_withheld_term_names_the_failing_term():
    good = Evidence(margin=0.02, rotation_margin=0.02, agreement=1.0, edges=0.3, depth_shift_mm=0.1)
    assert qa_evidence.withheld_term(good) is None
    flat = Evidence(margin=-0.002, rotation_margin=0.02, agreement=1.0, edges=0.3)
    assert qa_evidence.withheld_term(flat) == "margin"
    assert not DEFAULT_RULE.assess(flat).applied
    assert qa_evidence.withheld_term(flat.to_dict()) == "margin"
    assert qa_evidence.withheld_term(Evidence(veto="stopped")) == "veto"


# ----- the report ---------------------------------------------------------------------------
def _document(volume, xray, renderer, motion) -> dict:  # noqa: ANN001
    from registration.studies.cases import confidence_fields

    class Result:  # what confidence_fields reads of a registration result
        patient_motion = motion
        parameters = ("tx", "ty", "rx", "ry", "rz")
        capture_motions = ()
        rotation_check = None

    assessed = confidence_fields(volume, xray, Result(), renderer)
    offsets = dict(zip(("tx", "ty", "rx", "ry", "rz"), np.delete(_offsets(motion, xray.geometry), 2), strict=True))
    doc = {"patient_motion": motion.tolist(), "similarity": 1.2345678, "similarity_trace": [1.0, 1.1, 1.2],
           "drr_count": 321, "seconds": 0.5, "stopped": False, "offsets": offsets,
           "volume": {"path": "/data/Doe_John/volume"}}  # fmt: skip
    doc.update({k: assessed[k] for k in ("confidence", "applied", "withheld_reason", "confidence_evidence")})
    return doc, assessed


def _offsets(motion, geometry):  # noqa: ANN001, ANN202
    from registration.core.geometry import matrix_to_offsets

    return matrix_to_offsets(motion, geometry)


def test_report_of_a_withheld_estimate_names_its_reason_and_matches_its_numbers(scene, tmp_path):
    volume, xray, renderer = scene
    volume.meta.update({"patient_name": "Doe^John", "patient_id": "PID-77", "series_uid": "1.2.3.4"})
    wrong = offsets_to_matrix([4.0, 0.0, 0.0, 0.0, 0.0, 0.0], xray.geometry)  # 4 mm off the truth in tx
    doc, assessed = _document(volume, xray, renderer, wrong)
    assert not doc["applied"], doc  # a wrong estimate: its peak is elsewhere
    out = qa_report.write_registration_report(
        tmp_path / "rep", document=doc, volume=volume, views=[xray], renderer=renderer,
        depth_probe=assessed.get("depth_probe"), depth_scan=assessed.get("depth_scan"),
    )  # fmt: skip
    text = (out / qa_report.REPORT_HTML).read_text()
    assert doc["withheld_reason"] in text and "withheld" in text
    assert "Doe" not in text and "PID-77" not in text  # no patient unless asked
    saved = json.loads((out / qa_report.REPORT_JSON).read_text())
    assert "Doe" not in json.dumps(saved)  # the file paths are left out too
    assert "1.2.3.4" in text  # the series UID is there
    numbers = qa_report.read_report_numbers(text)
    assert {"similarity", "confidence", "offsets.tx", "confidence_evidence.margin", "drr_count"} <= set(numbers)
    for key, shown in numbers.items():
        if key in ("withheld_reason", "software.version"):
            continue
        value = qa_report.document_value(saved, key)
        if isinstance(value, bool):
            assert shown == ("yes" if value else "no"), key
        elif value is not None:
            decimals = len(shown.split(".")[1]) if "." in shown else 0
            assert float(shown) == pytest.approx(float(value), abs=0.51 * 10.0**-decimals), key
    pngs = sorted(p.name for p in out.glob("*.png"))
    overlays = [f"overlay_{m}.png" for m in qa_images.OVERLAY_MODES if m != "outline"]  # no vessel surface given
    for name in ("image.png", "drr.png", "drr_initial.png", "evidence_profiles.png", "evidence_depth.png",
                 "convergence.png", *overlays):  # fmt: skip
        assert name in pngs, name
        assert f'src="{name}"' in text
    from PIL import Image

    for name in pngs:
        with Image.open(out / name) as im:
            im.load()  # opens and decodes
            assert im.size[0] > 50 and im.size[1] > 50
    # identify: the patient is named
    named = qa_report.write_registration_report(
        tmp_path / "named", document=doc, volume=volume, views=[xray], renderer=renderer, identify=True
    )
    assert "Doe^John" in (named / qa_report.REPORT_HTML).read_text()
    # atomic and never over a report: a folder with files is refused and left as it was
    with pytest.raises(ValueError, match="not empty"):
        qa_report.write_registration_report(out, document=doc, volume=volume, views=[xray], renderer=renderer)
    assert (out / qa_report.REPORT_HTML).read_text() == text
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary folder left


def test_report_of_the_truth_is_applied(scene, tmp_path):
    volume, xray, renderer = scene
    doc, _ = _document(volume, xray, renderer, np.eye(4))
    assert doc["applied"], doc
    out = qa_report.write_registration_report(tmp_path / "ok", document=doc, volume=volume, views=[xray],
                                              renderer=renderer)  # fmt: skip
    text = (out / qa_report.REPORT_HTML).read_text()
    assert "applied" in text and "Withheld because" not in text


def test_track_report_lists_the_decisions_and_matches_the_document(scene, tmp_path):
    from registration.studies import qa_track

    volume, xray, renderer = scene
    g = xray.geometry
    moved = offsets_to_matrix([1.0, 0.5, 0.0, 0.0, 0.0, 1.0], g).tolist()

    def frame(n: int, status: str, pose: list, confidence: float | None, reason: str = "") -> dict:
        return {"frame": n, "t_s": n / 15.0, "status": status, "patient_motion": pose, "path": "refine",
                "confidence": confidence, "reason": reason, "latency_ms": 12.5 + n}  # fmt: skip

    eye = np.eye(4).tolist()
    frames = [frame(0, "unchanged", eye, None), frame(1, "withheld", eye, 0.12, "the capture runs disagree"),
              frame(2, "applied", moved, 0.93), frame(3, "unchanged", moved, None)]  # fmt: skip
    doc = {"frames": frames, "planes": 1, "frame_count": 4, "skipped": [], "volume": {"path": "/p/Doe/vol"},
           "summary": {"frames": 4, "processed": 4, "applied": 1, "withheld": 1, "unchanged": 2}}  # fmt: skip
    truth = np.stack([np.eye(4), np.eye(4), np.asarray(moved), np.asarray(moved)])
    out = qa_track.write_track_report(tmp_path / "track", document=doc, volume=volume, last_views=[xray],
                                      renderer=renderer, truth=truth)  # fmt: skip
    text = (out / qa_report.REPORT_HTML).read_text()
    assert "the capture runs disagree" in text and "withheld" in text
    saved = json.loads((out / qa_report.REPORT_JSON).read_text())
    assert "Doe" not in json.dumps(saved) and "Doe" not in text
    numbers = qa_report.read_report_numbers(text)
    assert numbers["frames.1.confidence"] == "0.120" and numbers["summary.applied"] == "1"
    assert "frames.0.confidence" not in numbers  # unchanged frames are counted, not listed
    for key, shown in numbers.items():
        if key != "software.version":
            assert float(shown) == pytest.approx(float(qa_report.document_value(saved, key)), abs=0.051), key
    from PIL import Image

    with Image.open(out / "strip_charts.png") as im:
        im.load()
        assert im.size[0] > 500
    assert (out / "overlay_checkerboard.png").exists()


def test_a_depth_scan_the_confidence_did_not_make_is_scanned_for_the_picture_and_marked(scene):
    """One view's estimate that the registration corrected along the beam is not scanned by its
    assessment; the QA picture scans it then (all 25 offsets) and says the confidence did not
    weigh it. The assessment's own scan is drawn as it is; two views have none."""
    volume, xray, renderer = scene
    own = {"tz_mm": 1.0, "offsets_mm": [-2.0, 0.0, 2.0], "similarity": [0.1, 0.2, 0.1], "stopped": False}
    assert qa_evidence.pictured_scan(own, [xray], np.eye(4), renderer, one_view=True) == (own, True)
    assert qa_evidence.pictured_scan(None, [xray, xray], np.eye(4), renderer, one_view=False) == (None, True)
    scan, weighed = qa_evidence.pictured_scan(None, [xray], np.eye(4), renderer, one_view=True)
    assert weighed is False and len(scan["offsets_mm"]) == 25 and not scan["stopped"]
    # the truth: the high-passed measure peaks within two 2-mm steps of it on this 4.2 mm-voxel
    # volume (measured: -0.58 mm)
    assert abs(scan["tz_mm"]) < 4.0, scan["tz_mm"]
    png = qa_evidence.depth_figure(scan, None, weighed=False)
    assert png is not None and png[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_far_look_is_drawn_below_the_scan_and_framed_when_it_withheld(scene):
    """One view's far look (17 offsets to 76 mm) drawn under the depth scan, alone when there is
    no scan, and framed with the reason when its term withheld the estimate; the report says
    where to read it."""
    from PIL import Image

    from registration.core.depth import depth_far, scan_level
    from registration.core.geometry import offsets_to_matrix

    _, xray, renderer = scene
    # an estimate 60 mm toward the source: the measure is higher far along the beam (the truth)
    far = depth_far(renderer, xray, offsets_to_matrix([0.0, 0.0, 60.0, 0.0, 0.0, 0.0], xray.geometry),
                    volume_level=scan_level(renderer)).to_dict()  # fmt: skip
    assert far["gain"] > 0.0 and len(far["offsets_mm"]) == 17
    scan = {"tz_mm": 1.0, "offsets_mm": [-2.0, 0.0, 2.0], "similarity": [0.1, 0.2, 0.1], "stopped": False}
    reason = "the measure is as high far along the beam as at the estimate"
    both = qa_evidence.depth_figure(scan, None, far=far, reason=reason, term="depth_far")
    alone = qa_evidence.depth_figure(None, None, far=far)
    just_scan = qa_evidence.depth_figure(scan, None)
    sizes = [Image.open(io.BytesIO(png)).size for png in (both, alone, just_scan)]
    assert sizes[0][1] > 1.8 * sizes[2][1] and sizes[1][1] < 0.6 * sizes[0][1], sizes  # two panels, then one
    assert qa_evidence.depth_figure(None, None) is None  # two views: no picture
    assert qa_evidence.withheld_term({"depth_far_gain": far["gain"], "margin": 0.01}) == "depth_far"
    assert "far look" in qa_evidence.TERM_PICTURES["depth_far"] and "depth_far" in qa_evidence.FRAMED_TERMS
