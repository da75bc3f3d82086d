"""The registration's region of interest: the cranium without the cervical spine
(registration.core.roi), and a user's mask (registration.io.roi_masks)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from registration.core.geometry import CArm, rigid
from registration.core.register import RegistrationOptions, register
from registration.core.roi import (
    RegionOfInterest,
    cranium_region,
    followed_region,
    region_views,
    region_volume,
    roi_volume,
)
from registration.core.volume import Volume
from registration.io.roi_masks import read_roi_mask
from registration.studies.runs import axis_angle_matrix
from registration.studies.volume import find_real_ct, head_isocenter_mm


@pytest.fixture(scope="module")
def real_ct():
    path = find_real_ct()
    if path is None:
        pytest.skip("the shared real CT (../shared/data/real-ct/head-neck-ct or ROADMAP3D_REAL_CT) is not here")
    from registration.io import dicom

    return dicom.read_volume(path)


def _small_volume() -> Volume:
    data = np.full((8, 10, 12), -1000.0, dtype=np.float32)
    data[2:6, 3:7, 3:9] = 500.0
    return Volume(data, np.diag([1.0, 1.0, 2.0, 1.0]), label="box")


def test_outside_the_region_bone_becomes_soft_tissue() -> None:
    volume = _small_volume()
    mask = np.ones(volume.shape, dtype=bool)
    mask[:4] = False
    out = roi_volume(volume, RegionOfInterest(mask, "test"))
    assert (out.data[:4][volume.data[:4] > 40] == 40).all() and (out.data[4:] == volume.data[4:]).all()
    assert (out.data[volume.data < 40] == volume.data[volume.data < 40]).all()  # air stays air
    assert out.meta["roi"]["source"] == "test"


def test_a_users_npz_mask(tmp_path) -> None:
    volume = _small_volume()
    mask = np.zeros(volume.shape, dtype=np.uint8)
    mask[4:] = 3
    np.savez(tmp_path / "roi.npz", mask=mask)
    roi = read_roi_mask(tmp_path / "roi.npz", volume)
    assert roi.mask.sum() == mask.astype(bool).sum()
    np.savez(tmp_path / "bad.npz", mask=mask[1:])
    with pytest.raises(ValueError, match="bad.npz: mask shape"):
        read_roi_mask(tmp_path / "bad.npz", volume)
    np.savez(tmp_path / "other.npz", labels=mask)
    with pytest.raises(ValueError, match="no array named 'mask'"):
        read_roi_mask(tmp_path / "other.npz", volume)
    with pytest.raises(ValueError, match="must be .npz or NIfTI"):
        read_roi_mask(tmp_path / "roi.png", volume)


@pytest.mark.slow
def test_the_cranium_leaves_out_the_cervical_spine_only(real_ct) -> None:
    roi = cranium_region(real_ct)
    z = real_ct.index_to_world[2, 2] * np.arange(real_ct.shape[0]) + real_ct.index_to_world[2, 3]
    # the skull base of this CT lies 125-140 mm below the top of the scan (read off its sagittal
    # slices: the dens at about z -135 mm)
    assert roi.skull_base_z_mm is not None and -145.0 < roi.skull_base_z_mm < -120.0
    left = ~roi.mask
    assert not left[z >= roi.skull_base_z_mm].any()  # nothing of the cranium
    bone_left = left & (real_ct.data > 250)
    # the column: at least 80 ml of bone left out, all within 45 mm of the scan's midline
    assert bone_left.sum() * 3e-3 > 80.0
    ii = np.nonzero(bone_left)[2]
    assert np.abs(ii - real_ct.shape[2] / 2).max() < 90


def test_the_region_by_name_and_on_oblique_slices() -> None:
    volume = _small_volume()
    assert followed_region(volume, "none") is None and region_volume(volume, None) is volume
    with pytest.raises(ValueError, match="one of none, cranium"):
        followed_region(volume, "neck")
    # a grid turned about z: no axial slices to track the spine on, so the whole volume, said so
    c, s = np.cos(np.radians(20.0)), np.sin(np.radians(20.0))
    oblique = Volume(volume.data, np.array([[c, 0, -s, 0], [0, 1, 0, 0], [s, 0, c, 0], [0, 0, 0, 1.0]]), label="tilted")
    region = followed_region(oblique, "cranium")
    assert region is not None and region.mask.all() and region.skull_base_z_mm is None
    assert "oblique" in region.describe() and region_volume(oblique, region) is oblique


def test_the_pixels_that_see_mostly_the_neck_are_left_out() -> None:
    """A 'head' (a bone block above z 0) on a 'neck' (a bone column below it), seen from the
    front: the pixels whose rays cross the column alone leave the field, grown by
    OUTSIDE_GROW_MM; those that cross the head stay; a user's mask narrows nothing."""
    from registration.core.images import XRayImage
    from registration.core.roi import OUTSIDE_GROW_MM, OUTSIDE_VOXEL_MM, region_views

    data = np.full((80, 80, 80), -1000.0, dtype=np.float32)  # (k, j, i), 2 mm voxels, z from -80 to +78 mm
    data[40:70, 20:60, 15:65] = 800.0  # the head: z 0 to 58 mm, 100 mm wide
    data[10:40, 35:45, 35:45] = 800.0  # the neck: z -60 to -2 mm, 20 mm wide
    volume = Volume(data, np.array([[2.0, 0, 0, -80], [0, 2.0, 0, -80], [0, 0, 2.0, -80], [0, 0, 0, 1]]))
    carm = CArm.for_format(27.0, pixels=128)  # frontal, iso-center at the origin
    view = XRayImage(np.zeros((128, 128), dtype=np.float32), np.ones((128, 128), dtype=bool), carm)
    region = RegionOfInterest(np.ones(volume.shape, dtype=bool), "cranium", skull_base_z_mm=-1.0)
    (narrowed,), (found,) = region_views(volume, region, [view])
    left = ~narrowed.mask
    assert found.left_out_px == int(left.sum()) > 0 and found.field_px == 128 * 128

    # where the corners of each block land on the detector
    def box(i0, i1, j0, j1, k0, k1):  # noqa: ANN001, ANN202 - voxel index ranges
        ends = [(-80 + 2 * a, -80 + 2 * b) for a, b in ((i0, i1), (j0, j1), (k0, k1))]
        uv = carm.project(np.array([[x, y, z] for x in ends[0] for y in ends[1] for z in ends[2]]))
        return uv.min(axis=0), uv.max(axis=0)

    cols, rows = np.meshgrid(np.arange(128), np.arange(128))
    (nc0, nr0), (nc1, nr1) = box(35, 45, 35, 45, 10, 40)
    (hc0, hr0), (hc1, hr1) = box(15, 65, 20, 60, 40, 70)
    neck_only = (cols > nc0 + 1) & (cols < nc1 - 1) & (rows > nr0 + 1) & (rows < nr1 - 1)
    neck_only &= ~((cols >= hc0 - 1) & (cols <= hc1 + 1) & (rows >= hr0 - 1) & (rows <= hr1 + 1))
    assert neck_only.any() and left[neck_only].all()
    # the band: the growth, one coarse voxel of the share's volume (its rays interpolate) and two
    # pixels (the share is taken at half the image's size), all in pixels at the iso-center
    px_iso = carm.pixel_mm[0] * carm.sod_mm / carm.sid_mm
    band = (OUTSIDE_GROW_MM + OUTSIDE_VOXEL_MM) / px_iso + 2.0
    far = np.hypot(np.maximum(0, np.maximum(nc0 - cols, cols - nc1)), np.maximum(0, np.maximum(nr0 - rows, rows - nr1)))
    assert not left[far > band].any()  # nothing beyond the neck's projection and the band
    head = (cols > hc0 + 1) & (cols < hc1 - 1) & (rows > hr0 + 1) & (rows < hr1 - 1)
    assert left[head].sum() < 0.1 * head.sum()  # the head's pixels stay but for the band at the join
    # a user's mask narrows no field (its outside is rendered as soft tissue instead)
    mask = np.ones(volume.shape, dtype=bool)
    mask[:40] = False
    assert region_views(volume, RegionOfInterest(mask, "roi.npz"), [view]) == ([view], [])


@pytest.mark.slow
def test_a_found_cranium_is_stored_and_read_back(real_ct, tmp_path) -> None:
    from registration.io.cache import PreparationCache

    store = PreparationCache(tmp_path)
    found = followed_region(real_ct, "cranium", store=store)
    assert len(list(tmp_path.glob("cranium-*.npz"))) == 1
    again = followed_region(real_ct, "cranium", store=store)
    assert np.array_equal(found.mask, again.mask) and again.skull_base_z_mm == found.skull_base_z_mm
    assert again.left_out_ml == pytest.approx(found.left_out_ml) and found.left_out_ml > 100.0
    assert "the head above the skull base at z -132 mm" in again.describe()


@pytest.mark.slow
def test_a_bent_neck_leaves_the_heads_estimate(real_ct) -> None:
    """The image: the CT moved by a clinical offset with its neck bent by 5 deg (flexion at
    C1/C2, the spine following 0.4 of the motion: registration.sim.clinical, volume_xray's
    integrator, not the scoring DRR); registered as ``register`` does by default (the cranium:
    the pixels that see mostly the neck left out) the head's estimate is within 1 mm in-plane."""
    from registration.sim.clinical import ClinicalEffects, ClinicalImager, Neck

    iso = head_isocenter_mm(real_ct)
    c = np.asarray(iso)
    truth = (
        rigid(None, np.array([6.0, -4.0, 5.0]))
        @ rigid(None, c)
        @ axis_angle_matrix((0.3, 0.9, 0.3), 4.0)
        @ rigid(None, -c)
    )
    carm = replace(CArm.for_format(27.0, pixels=384, primary_deg=20.0, secondary_deg=10.0), isocenter_mm=iso)
    imager = ClinicalImager(real_ct, iso, ClinicalEffects(neck=Neck(flexion_deg=5.0, rotation_deg=0.0)), catheter=False)
    image = imager.image(carm, truth, seed=7).clean_xray()
    (narrowed,), (found,) = region_views(real_ct, followed_region(real_ct, "cranium"), [image])
    assert found.left_out_px > 0
    result = register(real_ct, narrowed, truth=truth, seed=7, options=RegistrationOptions())
    # the head's motion is the truth: the skull moved rigidly with it
    assert result.residual.inplane_mm < 1.0 and result.residual.rotation_deg < 3.0, result.residual


def _write_seg(path, volume: Volume, mask: np.ndarray, *, shift_mm: float = 0.0) -> None:
    """A DICOM Segmentation (binary, one segment) of ``mask``'s non-empty slices, as a viewer
    such as 3D Slicer exports it: one frame per slice, its position and orientation per frame."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.pixels import pack_bits
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    from registration.io.roi_masks import SEGMENTATION_SOP_CLASS

    a = volume.index_to_world
    slices = [k for k in range(mask.shape[0]) if mask[k].any()]
    ds = Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.MediaStorageSOPClassUID = SEGMENTATION_SOP_CLASS
    ds.file_meta.MediaStorageSOPInstanceUID = generate_uid()
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.SOPClassUID, ds.SOPInstanceUID = SEGMENTATION_SOP_CLASS, ds.file_meta.MediaStorageSOPInstanceUID
    ds.Modality = "SEG"
    ds.Rows, ds.Columns, ds.NumberOfFrames = mask.shape[1], mask.shape[2], len(slices)
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.SamplesPerPixel = 1, 1, 0, 1
    ds.PixelRepresentation, ds.PhotometricInterpretation, ds.SegmentationType = 0, "MONOCHROME2", "BINARY"
    spacing = np.linalg.norm(a[:3, :2], axis=0)
    orientation = Dataset()
    orientation.ImageOrientationPatient = [*(a[:3, 0] / spacing[0]), *(a[:3, 1] / spacing[1])]
    measures = Dataset()
    measures.PixelSpacing = [float(spacing[1]), float(spacing[0])]  # row spacing, column spacing
    measures.SliceThickness = float(abs(a[2, 2]))
    shared = Dataset()
    shared.PlaneOrientationSequence, shared.PixelMeasuresSequence = [orientation], [measures]
    ds.SharedFunctionalGroupsSequence = [shared]
    groups = []
    for k in slices:
        position = Dataset()
        position.ImagePositionPatient = [float(v) for v in a[:3, 2] * k + a[:3, 3] + [shift_mm, 0.0, 0.0]]
        group = Dataset()
        group.PlanePositionSequence = [position]
        groups.append(group)
    ds.PerFrameFunctionalGroupsSequence = groups
    ds.PixelData = pack_bits(mask[slices].astype(np.uint8))
    ds.save_as(path, enforce_file_format=True)


def test_a_users_dicom_seg_mask(tmp_path) -> None:
    volume = _small_volume()
    mask = np.zeros(volume.shape, dtype=bool)
    mask[3:6, 2:8, 4:10] = True
    mask[5, 0, 0] = True  # a lone voxel in a corner: placed exactly
    _write_seg(tmp_path / "roi.dcm", volume, mask)
    roi = read_roi_mask(tmp_path / "roi.dcm", volume)
    np.testing.assert_array_equal(roi.mask, mask)  # voxel for voxel on the volume's grid
    _write_seg(tmp_path / "shifted.dcm", volume, mask, shift_mm=0.5)  # half a voxel off the grid
    with pytest.raises(ValueError, match="shifted.dcm: a frame at .* lies on none of the volume's slices"):
        read_roi_mask(tmp_path / "shifted.dcm", volume)
    other = Volume(volume.data, np.diag([1.5, 1.0, 2.0, 1.0]), label="other grid")
    with pytest.raises(ValueError, match="roi.dcm: a frame's orientation or pixel spacing is not the volume's"):
        read_roi_mask(tmp_path / "roi.dcm", other)
    (tmp_path / "not.dcm").write_bytes(b"\0" * 200)
    with pytest.raises(ValueError, match="not.dcm: not a readable DICOM file"):
        read_roi_mask(tmp_path / "not.dcm", volume)


def test_the_region_on_a_coarser_grid_is_the_nearest_voxels() -> None:
    """A level's grid (2 mm voxels, shifted) sees the region at its voxels' nearest volume voxel,
    and what lies outside the volume is in the region; an oblique grid gives the same answer
    through the general path."""
    from registration.core.roi import region_on_grid

    volume = _small_volume()  # 12 x 10 x 8 voxels of 1 x 1 x 2 mm
    mask = np.ones(volume.shape, dtype=bool)
    mask[2:5, 1:6, 4:10] = False
    roi = RegionOfInterest(mask, "test")
    grid = Volume(np.zeros((5, 6, 7), np.float32), np.diag([2.0, 2.0, 4.0, 1.0]) @ rigid(None, (-0.5, 0.0, 0.0)),
                  label="grid")  # fmt: skip
    got = region_on_grid(roi, volume, grid)
    kk, jj, ii = np.meshgrid(*(np.arange(n) for n in grid.shape), indexing="ij")
    world = np.stack([ii, jj, kk, np.ones_like(ii)], -1) @ grid.index_to_world.T
    idx = np.rint(world @ np.linalg.inv(volume.index_to_world).T)[..., :3].astype(int)  # (i, j, k)
    inside = np.all((idx >= 0) & (idx < np.array(volume.shape[::-1])), axis=-1)
    want = np.ones(grid.shape, dtype=bool)
    want[inside] = mask[idx[inside][:, 2], idx[inside][:, 1], idx[inside][:, 0]]
    assert np.array_equal(got, want) and not got.all()
    turned = Volume(grid.data, grid.index_to_world @ rigid(None, (0.0, 0.0, 0.0)), label="turned")
    turned.index_to_world[:3, :2] = turned.index_to_world[:3, :2] @ np.array([[1.0, 1e-7], [-1e-7, 1.0]])
    assert np.array_equal(region_on_grid(roi, volume, turned), want)


@pytest.mark.slow
def test_the_head_alone_moves_an_estimate_off_the_head_back(real_ct) -> None:
    """The image: the CT moved by a clinical offset with its neck bent 10 deg and the spine left
    behind (registration.sim.clinical, volume_xray's integrator, not the scoring DRR). The
    head-alone probe (skull_spine.spine_pull) leaves the head's true pose where it is, and moves
    an estimate 1.5 mm and 1 deg off it (where a spine's pull leaves a rigid fit) back by that
    much."""
    from registration.core.geometry import apply, offsets_to_matrix
    from registration.core.preparation import Preparation
    from registration.core.skull_spine import spine_pull
    from registration.sim.clinical import ClinicalEffects, ClinicalImager, Neck

    iso = head_isocenter_mm(real_ct)
    c = np.asarray(iso)
    turn = axis_angle_matrix((0.2, 0.3, 0.9), 3.0)
    truth = rigid(None, np.array([-5.0, 3.0, 4.0])) @ rigid(None, c) @ turn @ rigid(None, -c)
    carm = replace(CArm.for_format(27.0, pixels=384, primary_deg=-30.0, secondary_deg=5.0), isocenter_mm=iso)
    neck = Neck(flexion_deg=10.0, rotation_deg=4.0, follow=0.0)
    view = (
        ClinicalImager(real_ct, iso, ClinicalEffects(neck=neck), catheter=False).image(carm, truth, seed=3).clean_xray()
    )
    preparation = Preparation.of(real_ct, view)
    # the head's pose stays: within 0.3 mm in-plane (the local search's jitter at 2 mm voxels),
    # and a first search that little moved is enough
    stays = spine_pull(preparation.prepared, view, truth, enough_mm=0.3)
    assert stays is not None and stays.shift_mm < 0.3 and len(stays.moves_mm) == 1, stays
    off = offsets_to_matrix((1.2, -0.9, 0.0, 0.0, 0.0, 1.0), carm) @ truth
    d = apply(off, c) - apply(truth, c)
    moved = float(np.linalg.norm(d - (d @ carm.direction) * carm.direction))
    found = spine_pull(preparation.prepared, view, off)
    # back by what it was moved (1.5 mm), within 0.35 mm (that jitter and the 2 mm voxels)
    assert found is not None and found.shift_mm == pytest.approx(moved, abs=0.35), (found, moved)
    assert found.rotation_deg == pytest.approx(1.0, abs=0.5)
