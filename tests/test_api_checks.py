"""What a notebook user passes by mistake is refused before any work, with the argument named."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import registration as R
from registration.core.checks import NoInformationError
from registration.core.register import Level, RegistrationOptions
from registration.core.register.options import CAPTURE_SCHEDULE


@pytest.fixture(scope="module")
def example() -> R.Example:
    return R.load_example()


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        ({"options": {"bound_mm": 20}}, TypeError, r"options must be a RegistrationOptions \(Registrat"),
        ({"seed": -1}, ValueError, "seed must be a non-negative integer, got -1"),
        ({"seed": 1.5}, ValueError, "seed must be a non-negative integer, got 1.5"),
        ({"callback": True}, TypeError, "callback must be callable"),
        ({"landmarks": "picks.json"}, TypeError, "landmarks must be a LandmarkStart"),
        ({"preparation": "x"}, TypeError, "preparation must be a Preparation"),
        ({"vessel_points_mm": np.zeros((5, 2))}, ValueError, r"vessel_points_mm must be an \(N, 3\) array"),
        ({"vessel_points_mm": np.full((2, 3), np.nan)}, ValueError, "vessel_points_mm holds NaN"),
    ],
)  # fmt: skip
def test_register_names_the_argument_it_cannot_take(example, kwargs, error, message) -> None:
    with pytest.raises(error, match=message):
        R.register(example.volume, example.image, **kwargs)


def test_images_must_be_images(example) -> None:
    with pytest.raises(ValueError, match="views must be an XRayImage or a sequence of them, got NoneType"):
        R.register(example.volume, None)


@pytest.mark.parametrize("apart_deg", [0.0, 180.0, 1.0])
def test_views_along_one_line_are_not_a_biplane_pair(example, apart_deg: float) -> None:
    """The same image twice (or two frames of one plane) once crashed deep in the planes' combination
    with a singular matrix; views along (nearly) one line share no depth to register."""
    g = example.image.geometry
    other = R.render_drr(example.volume, g.with_angles(g.primary_deg + apart_deg, g.secondary_deg))
    with pytest.raises(ValueError, match=r"look along beams \d+\.\d deg apart: views registered together must"):
        R.register(example.volume, [example.image, other])


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"threads": 0}, "threads must be None"),
        ({"threads": 1.5}, "threads must be None"),
        ({"bound_mm": None}, "bound_mm and bound_deg must be positive finite numbers"),
        ({"bound_mm": float("inf")}, "bound_mm and bound_deg must be positive finite numbers"),
        ({"polish_reach": 5.0}, r"polish_reach must be two numbers \(mm, deg\), got 5.0"),
    ],
)
def test_options_name_the_value_they_refuse(options: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        RegistrationOptions(**options)


def test_levels_must_be_levels() -> None:
    with pytest.raises(TypeError, match="levels must be Level"):
        RegistrationOptions(levels=({"image_px": 32},))
    assert RegistrationOptions(threads=1).threads == 1  # what it takes
    assert RegistrationOptions(levels=(Level(32, 3, CAPTURE_SCHEDULE),), support_margin_mm=(15.0, 4.0))


def test_assess_takes_only_the_images_the_result_was_registered_on(example) -> None:
    result = R.register(example.volume, example.image, options=RegistrationOptions(polish=False))
    g = example.image.geometry
    lateral = R.render_drr(example.volume, g.with_angles(90.0, 0.0), example.truth_motion)
    with pytest.raises(ValueError, match="2 view.s. that are not the 1 the result was registered on"):
        R.assess(result, [example.image, lateral], example.volume)
    with pytest.raises(ValueError, match="not the 1 the result was registered on"):
        R.assess(result, lateral, example.volume)
    with pytest.raises(TypeError, match="result must be a RegistrationResult"):
        R.assess(None, example.image, example.volume)
    with pytest.raises(TypeError, match="preparation must be the registration's Preparation or the Volume"):
        R.assess(result, example.image, "volume.nii")


def test_a_volume_metres_from_the_field_is_refused_but_one_beside_it_is_searched(example) -> None:
    """A start that puts the volume where no ray of the detector meets it, even moved by the
    search's range, has nothing to register on (it used to search and be withheld for an unrelated
    reason); 30 cm beside the iso-center the head's own extent still reaches the field."""
    from registration.core.checks import check_in_field

    away = np.eye(4)
    away[0, 3] = 5000.0
    with pytest.raises(NoInformationError, match="does not project into the X-ray image's detector at the start"):
        R.register(example.volume, example.image, initial_motion=away)
    beside = np.eye(4)
    beside[0, 3] = 300.0
    check_in_field(example.volume, example.image, beside, 30.0)  # no error


def test_residuals_and_examples_and_files_name_their_argument(example, tmp_path: Path) -> None:
    m = example.truth_motion
    with pytest.raises(TypeError, match=r"geometry must be a CArm \(an image's .geometry\), got XRayImage"):
        R.residuals(m, m, example.image)
    with pytest.raises(ValueError, match=r"vessel_points_mm must be an \(N, 3\) array"):
        R.residuals(m, m, example.image.geometry, np.zeros((6, 2)))
    with pytest.raises(ValueError, match="pixels must be an integer >= 16"):
        R.load_example(pixels=0)
    missing = tmp_path / "no-such-folder" / "v.nii.gz"
    with pytest.raises(ValueError, match=f"no such folder: {tmp_path / 'no-such-folder'}"):
        example.volume.to_file(missing)
    assert not missing.parent.exists()


def test_a_mask_of_another_shape_is_named(example) -> None:
    with pytest.raises(ValueError, match=r"mask has shape \(4, 4\), the image \(8, 8\)"):
        R.XRayImage.from_array(carm=example.image.geometry.resized(8, 8), line_integrals=np.ones((8, 8)),
                               mask=np.ones((4, 4), dtype=bool))  # fmt: skip


def test_from_array_takes_real_intensities_and_a_positive_i0(example) -> None:
    carm = example.image.geometry.resized(8, 8)
    with pytest.raises(ValueError, match="intensity must be >= 0"):
        R.XRayImage.from_array(carm=carm, intensity=-np.ones((8, 8)))
    with pytest.raises(ValueError, match="must hold real numbers, got dtype complex128"):
        R.XRayImage.from_array(carm=carm, line_integrals=np.ones((8, 8)) * (1 + 1j))
    with pytest.raises(ValueError, match=r"i0 \(the unattenuated intensity\) must be a positive number"):
        R.XRayImage.from_array(carm=carm, intensity=np.ones((8, 8)), i0=0.0)
    image = R.XRayImage.from_array(carm=carm, intensity=np.full((8, 8), 50.0), i0=100.0)
    assert np.allclose(image.image, np.log(2.0))  # -log(I / I0)


def test_a_volume_or_field_too_small_says_how_much_is_needed(example) -> None:
    tiny = R.Volume.from_array(np.zeros((4, 4, 4)), np.eye(4))
    with pytest.raises(ValueError, match=r"too small to downsample by 4: at least 8 voxels along each axis"):
        tiny.downsample(4)
    strip = np.zeros(example.image.shape, dtype=bool)
    strip[:, 100:104] = True  # a field 4 pixels wide
    thin = R.XRayImage.from_array(carm=example.image.geometry, line_integrals=example.image.image, mask=strip)
    with pytest.raises(ValueError, match=r"the image's field \(1024 pixels of 256x256\) holds no 8x8 block"):
        thin.downsample(8)


def test_track_takes_one_plane_or_a_biplane_pair_of_frame_lists(example, monkeypatch) -> None:
    """A biplane run given as [frames_a, frames_b] reaches the tracker as two planes (it was taken
    as one plane of two 'frames' and refused with a frame count that named nothing)."""
    import registration.api as api

    seen = []
    monkeypatch.setattr(api, "track_run", lambda volume, runs, times, **kw: seen.append([len(r) for r in runs]))
    frames = [example.image, example.image, example.image]
    R.track(example.volume, frames, [0.0, 0.1, 0.2])
    R.track(example.volume, (frames, frames), [0.0, 0.1, 0.2])
    assert seen == [[3], [3, 3]]


def test_a_volume_beyond_float32_says_so_not_nan() -> None:
    # 1e39 is finite in float64 but not in the volume's float32: the message names the range
    data = np.zeros((4, 4, 4))
    data[1, 2, 3] = 1e39
    with pytest.raises(ValueError, match=r"1 voxels beyond float32's range"):
        R.Volume.from_array(data, np.eye(4))
    data[1, 2, 3] = np.nan
    with pytest.raises(ValueError, match="1 NaN or infinite voxels"):
        R.Volume.from_array(data, np.eye(4))
