"""``roadmap3d track`` and the app's file data on the real head CT (../shared/data/real-ct/head-neck-ct,
outside the repository; skipped without it): both render the registration's prepared levels
(cropped to what the field reaches, isotropic in mm), as ``roadmap3d register`` does, not a
pyramid of the whole 23.5 M-voxel CT, and still find the motion the images were formed with."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from app import cli
from app.web.data import AppConfig, FileData
from registration.core.geometry import CArm, rigid
from registration.io import dicom
from registration.studies.runs import axis_angle_matrix
from registration.studies.volume import (
    REAL_CT_RELATIVE,
    VolumeImager,
    VolumeStudyConfig,
    _views,
    case_motion,
    find_real_ct,
    volume_cases,
)

REAL_CT = find_real_ct()
pytestmark = [
    pytest.mark.skipif(
        REAL_CT is None, reason=f"the real head CT is not here ({REAL_CT_RELATIVE} beside the project; see its README)"
    ),
    pytest.mark.slow,
]
ISO = (247.5, -276.0, -90.0)  # the studies' iso-center inside the skull (head_isocenter_mm)


@pytest.fixture(scope="module")
def ct():
    volume = dicom.read_volume(REAL_CT)
    return volume, VolumeImager(volume, ISO)


def _prepared_levels(renderer, volume) -> list[int]:
    """Voxels of each level the renderer holds; the whole CT's own grid (level 0) is not among them."""
    assert not renderer.has_level(0)
    return [int(np.prod(renderer.level_volume(k).shape)) for k in range(renderer.n_levels) if renderer.has_level(k)]


def _moved(t_mm: tuple[float, float, float], axis: tuple[float, float, float], deg: float) -> np.ndarray:
    c = np.asarray(ISO)
    return rigid(None, np.asarray(t_mm)) @ rigid(None, c) @ axis_angle_matrix(axis, deg) @ rigid(None, -c)


def test_track_on_the_real_ct_renders_the_prepared_levels(ct, tmp_path: Path, capsys, monkeypatch) -> None:
    volume, imager = ct
    monkeypatch.setenv("ROADMAP3D_CACHE", str(tmp_path / "cache"))
    # four 128-px fluoro frames formed from the CT (a best case: the same volume): registered at
    # the start (the tracker's initial pose), then the head moved 2.5 mm / 1.5 mm in-plane and 1 deg
    geometry = replace(CArm.for_format(27.0, pixels=128, primary_deg=20.0, secondary_deg=-10.0), isocenter_mm=ISO)
    motions = [np.eye(4)] * 2 + [_moved((2.5, -1.5, 0.0), (0.0, 0.0, 1.0), 1.0)] * 2
    frames = [imager.image(geometry, m, kind="fluoro", seed=10 + n) for n, m in enumerate(motions)]
    dicom.write_xray_run(frames, tmp_path / "run.dcm", times_s=np.arange(4) / 15.0, description="run from the CT")
    truth = {"frames": [{"frame": n, "patient_motion": m.tolist()} for n, m in enumerate(motions)]}
    (tmp_path / "truth.json").write_text(json.dumps(truth))
    import registration.core.tracking as tracking

    seen = []
    real_track_run = tracking.track_run

    def spy(*args, **kwargs):
        seen.append(kwargs.get("renderer"))
        return real_track_run(*args, **kwargs)

    monkeypatch.setattr(tracking, "track_run", spy)
    with pytest.raises(SystemExit) as info:
        cli.main(
            ["track", "--volume", str(REAL_CT), "--run", str(tmp_path / "run.dcm"),
             "--truth", str(tmp_path / "truth.json"), "--isocenter", "247.5,-276,-90", "--every-frame",
             "--out", str(tmp_path / "track.json")]
        )  # fmt: skip
    out, err = capsys.readouterr()
    assert info.value.code == 0, out + err
    assert "prepared the volume for the run's field" in err
    # the tracker rendered the prepared levels: each far below the CT's 23.5 M voxels (2 and 4 mm
    # isotropic over the field's reach: 4.2 M and 0.52 M when measured)
    (renderer,) = seen
    voxels = _prepared_levels(renderer, volume)
    assert sum(voxels) < 0.25 * np.prod(volume.shape), voxels
    assert min(voxels) < 0.05 * np.prod(volume.shape), voxels  # the tracking and capture level
    doc = json.loads((tmp_path / "track.json").read_text())
    statuses = [f["status"] for f in doc["frames"]]
    assert statuses[1] == "unchanged" and "applied" in statuses[2:], statuses
    # the single-plane criterion of CONVENTIONS §4: the pose shown after the move is < 1 mm in-plane
    # (0.07 mm when measured; the tracking level's voxels are 4 mm, the refinement sub-voxel)
    assert doc["frames"][-1]["shown_error_mm"] < 1.0, doc["frames"][-1]
    assert doc["frames"][-1]["shown_rotation_deg"] < 3.0


def test_file_data_registers_the_real_ct_with_the_prepared_levels(ct, tmp_path: Path, monkeypatch) -> None:
    volume, imager = ct
    monkeypatch.setenv("ROADMAP3D_CACHE", str(tmp_path / "cache"))
    from registration.core.register import register

    config = VolumeStudyConfig(cases=1, seed=0)  # 384-px fluoro, 27 cm, <= 25 mm / 10 deg
    case = volume_cases(config)[0]
    truth = case_motion(case, ISO)
    image = imager.image(_views(config, case, ISO)[0], truth, kind=config.kind, seed=case.seed)
    data = FileData(volume, image, source="CT + a fluoro formed from it (test)", config=AppConfig())
    shown = data.renderer(27.0)  # what the app prepares at start (the DRR thumbnail's renderer)
    # what the session registers with: prepared for its views and start; the same preparation
    renderer = data.renderer(27.0, views=[image], initial_motion=np.eye(4))
    assert renderer is shown
    voxels = _prepared_levels(renderer, volume)
    assert sum(voxels) < 0.25 * np.prod(volume.shape), voxels
    result = register(volume, image, renderer=renderer, truth=truth, seed=case.seed)
    # the single-plane criterion of CONVENTIONS §4: in-plane residual < 1 mm, rotation < 3 deg
    assert result.residual.inplane_mm < 1.0 and result.residual.rotation_deg < 3.0, result.residual


def test_app_places_the_real_ct_at_the_given_isocenter(ct, tmp_path: Path, monkeypatch) -> None:
    """``roadmap3d app --volume CT --image XA --isocenter x,y,z`` reads the image about that
    iso-center, as ``register`` does (without it the world origin, 300 mm outside this CT's
    head, is the iso-center and no registration can find the head), and registers it."""
    volume, imager = ct
    monkeypatch.setenv("ROADMAP3D_CACHE", str(tmp_path / "cache"))
    from registration.core.register import register
    from registration.io.dicom.xray_write import write_xray

    config = VolumeStudyConfig(cases=1, seed=0)
    case = volume_cases(config)[0]
    truth = case_motion(case, ISO)
    image = imager.image(_views(config, case, ISO)[0], truth, kind=config.kind, seed=case.seed)
    path = tmp_path / "xa.dcm"
    write_xray(image, path)
    text = ",".join(str(v) for v in ISO)
    data = FileData.from_paths(REAL_CT, path, frame=None, config=AppConfig(), isocenter=text)
    np.testing.assert_allclose(data.fixed_xray.geometry.isocenter_mm, ISO)
    assert "(247.50, -276.00, -90.00) mm, from --isocenter" == data.isocenter_text
    default = FileData.from_paths(REAL_CT, path, frame=None, config=AppConfig())
    np.testing.assert_allclose(default.fixed_xray.geometry.isocenter_mm, (0.0, 0.0, 0.0))  # no tag: origin
    result = register(data.volume(), data.fixed_xray, renderer=data.renderer(27.0), truth=truth, seed=case.seed)
    # CONVENTIONS §4, single plane: in-plane residual < 1 mm, rotation < 3 deg
    assert result.residual.inplane_mm < 1.0 and result.residual.rotation_deg < 3.0, result.residual


def test_the_real_cts_skull_is_drawn_in_one_piece(ct) -> None:
    """The app's bone surface of the real CT (1 x 1 x 3 mm voxels, a 511 mm field): the skull and
    spine one piece holding nearly every face. Striding the voxels (8: 8 x 8 x 24 mm cells) drew
    71 loose plates, the largest 10 % of the faces."""
    import trimesh

    volume, imager = ct
    image = imager.image(replace(CArm.for_format(27.0, pixels=64), isocenter_mm=ISO), np.eye(4), kind="fluoro", seed=0)
    bone = FileData(volume, image, source="real CT (test)", config=AppConfig()).meshes()["bone"]
    pieces = sorted((len(c) for c in trimesh.graph.connected_components(bone.face_adjacency, min_len=1)), reverse=True)
    # 96 % when measured: the rest are bones apart from the skull in this field (shoulder tips, a
    # metal marker on the head holder, bits of facial bone), none of them noise specks
    assert pieces[0] > 0.9 * len(bone.faces), pieces[:5]
    assert len(bone.faces) < 120_000  # drawn as extracted (the scene's face budget)


def test_the_real_ct_without_contrast_has_no_vessel_surface(ct) -> None:
    """The shared CT has no contrast agent: the app draws no vessels for it. Before the vessel rules
    of registration.io.meshes (bone distance, soft-tissue surround, length) it drew 24 red pieces
    (10,184 voxels of bone partial volume and a calcification) about the face, sinuses and spine."""
    volume, imager = ct
    image = imager.image(replace(CArm.for_format(27.0, pixels=64), isocenter_mm=ISO), np.eye(4), kind="fluoro", seed=0)
    meshes = FileData(volume, image, source="real CT (test)", config=AppConfig()).meshes()
    assert "vessels" not in meshes and "bone" in meshes
