"""The public face: ``import registration`` is light, names what a user calls, and its examples run.

Every docstring example of the public modules runs here as a doctest (the quick-start example
registers the phantom and checks the residual against the known motion). The API's
constructors are checked against the readers they wrap and against CONVENTIONS §8 by hand.
"""

from __future__ import annotations

import doctest
import importlib
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

#: Modules whose docstring examples are part of the documentation and must run.
DOCTEST_MODULES = [
    "registration",
    "registration.api",
    "registration.core.images",
    "registration.io.volume_files",
    "registration.io.transforms",
]


def test_import_registration_loads_neither_numba_nor_viser() -> None:
    code = (
        "import sys, registration; "
        "assert 'numba' not in sys.modules and 'viser' not in sys.modules, sorted(sys.modules); "
        "print(sorted(registration.__all__))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "'register'" in out and "'load_example'" in out


def test_all_names_resolve_and_are_documented() -> None:
    import registration

    for name in registration.__all__:
        value = getattr(registration, name)
        assert (value.__doc__ or "").strip(), f"registration.{name} has no docstring"
    assert set(registration.__all__) <= set(dir(registration))
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        registration.nothing  # noqa: B018


@pytest.mark.slow
@pytest.mark.parametrize("module", DOCTEST_MODULES)
def test_docstring_examples_run(module: str) -> None:
    result = doctest.testmod(importlib.import_module(module), optionflags=doctest.ELLIPSIS, verbose=False)
    assert result.attempted > 0, f"{module} has no examples"
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples of {module} failed (see the output)"


def test_volume_from_array_follows_conventions() -> None:
    import registration

    data_ijk = np.arange(4 * 5 * 6, dtype=np.float32).reshape(4, 5, 6)
    affine_ras = np.array([[0.9, 0, 0.1, -10], [0, 1.1, 0, 20], [0.05, 0, 3, 30], [0, 0, 0, 1.0]])
    v = registration.Volume.from_array(data_ijk, affine_ras, frame="RAS")
    i, j, k = 3, 1, 2
    assert v.data[k, j, i] == data_ijk[i, j, k]
    np.testing.assert_allclose(v.index_to_world @ [i, j, k, 1], np.diag([-1, -1, 1, 1]) @ affine_ras @ [i, j, k, 1])
    lps = registration.Volume.from_array(v.data, v.index_to_world)  # the project's own order and frame
    np.testing.assert_array_equal(lps.data, v.data)
    with pytest.raises(ValueError, match="frame must be"):
        registration.Volume.from_array(data_ijk, affine_ras, frame="RAI")


def test_what_a_notebook_prints_is_one_line_of_facts() -> None:
    """A volume, an image and a result print as one short line of their facts (not their arrays)."""
    import registration
    from registration.core.geometry import CArm
    from registration.core.metrics import residuals
    from registration.core.register.result import RegistrationResult

    data = np.full((40, 30, 20), -1000.0, dtype=np.float32)
    data[5, 6, 7] = 2500.0
    volume = registration.Volume(data=data, index_to_world=np.diag([0.5, 0.5, 2.5, 1.0]), label="a CT")
    assert repr(volume) == ("Volume(20x30x40 voxels (i, j, k), spacing (0.5, 0.5, 2.5) mm, values -1000 to 2500, "
                            "label='a CT')")  # fmt: skip
    carm = CArm(primary_deg=30.0, secondary_deg=-5.0, rows=64, cols=48)
    mask = np.zeros((64, 48), dtype=bool)
    mask[:32] = True  # half the pixels
    image = registration.XRayImage(np.zeros((64, 48), np.float32), mask, carm, meta={"source": "xa.dcm"})
    text = repr(image)
    assert text.startswith("XRayImage(fluoro, 48x64 px, field 50 % of the pixels, primary +30.0 deg, secondary -5.0")
    assert text.endswith("source 'xa.dcm')") and "array" not in text
    truth = np.eye(4)
    truth[:3, 3] = (0.3, 0.4, 0.0)  # 0.5 mm across plane A's beam (primary 30: not along x alone)
    result = RegistrationResult(
        patient_motion=np.eye(4), similarity=1.23456, similarity_trace=[0.0] * 500, drr_count=1214, seconds=0.6123,
        stopped=False, offsets=np.array([1.0, -2.0, 0.5, 0.25, -3.0]), geometry=carm, volume_label="a CT",
        residual=residuals(np.eye(4), truth, carm), depth_tz_mm=-0.75,
    )  # fmt: skip
    text = repr(result)
    assert text.startswith("RegistrationResult(tx +1.00 mm, ty -2.00 mm, tz -0.75 mm, rx +0.50 deg, ry +0.25 deg, "
                           "rz -3.00 deg; similarity 1.235, 1,214 DRRs in 0.61 s; residual ")  # fmt: skip
    assert f"{result.residual.translation_mm:.2f} mm total" in text and len(text) < 250
    evidence = {"margin": 0.0263585, "edges": None}
    decision = registration.Assessment(0.8807970779778823, False, "the planes disagree", evidence)
    assert repr(decision) == "Assessment(withheld, confidence 0.88: the planes disagree; evidence: margin 0.0264)"


@pytest.mark.slow
def test_a_preparation_prints_its_levels_not_its_voxels() -> None:
    import registration
    from registration.core.preparation import Preparation

    example = registration.load_example()
    preparation = Preparation.of(example.volume, example.image)
    text = repr(preparation)
    levels = ", ".join(f"{s:.3g}" for s in preparation.prepared.spacing_mm)
    assert text.startswith(f"Preparation({example.volume!r}; levels at ({levels}) mm for 1 view, ")
    assert len(text) < 400 and "array" not in text


def test_files_through_the_api(tmp_path: Path) -> None:
    import registration

    v = registration.Volume.from_array(np.random.default_rng(0).normal(size=(6, 5, 4)), np.diag([1.0, 1.0, 2.0, 1.0]))
    back = registration.Volume.from_file(v.to_file(tmp_path / "v.nii.gz"))
    assert isinstance(back, registration.Volume)
    np.testing.assert_array_equal(back.data, v.data)
    carm = registration.CArm(rows=16, cols=16)
    with pytest.raises(ValueError, match="exactly one of"):
        registration.XRayImage.from_array(carm=carm)
    li = registration.XRayImage.from_array(line_integrals=np.ones((16, 16)), carm=carm, mask=np.eye(16, dtype=bool))
    assert li.mask.sum() == 16 and li.image[0, 1] == 0.0 and li.image[0, 0] == 1.0


@pytest.mark.slow
def test_shipped_example_is_what_the_simulation_makes() -> None:
    from registration.api import SHIPPED_EXAMPLE, load_example, simulate_example

    assert SHIPPED_EXAMPLE.is_file()
    shipped, fresh = load_example(), simulate_example("T4", pixels=256, seed=0)
    np.testing.assert_array_equal(shipped.volume.data, fresh.volume.data)
    np.testing.assert_array_equal(shipped.volume.index_to_world, fresh.volume.index_to_world)
    np.testing.assert_array_equal(shipped.image.mask, fresh.image.mask)
    # the same seeded simulation; compiled kernels may round the last float32 bit differently elsewhere
    np.testing.assert_allclose(shipped.image.image, fresh.image.image, rtol=0, atol=1e-5)
    assert shipped.image.geometry == fresh.image.geometry
    np.testing.assert_array_equal(shipped.truth_motion, fresh.truth_motion)


@pytest.mark.slow
def test_register_and_assess_with_one_preparation() -> None:
    import registration

    ex = registration.load_example()
    preparation = registration.Preparation.of(ex.volume, ex.image)
    result = registration.register(ex.volume, ex.image, preparation=preparation)
    error = registration.residuals(result.patient_motion, ex.truth_motion, ex.image.geometry)
    assert error.success  # the shipped T4 case: 0.05 mm in-plane, 0.15 deg seen
    decision = registration.assess(result, ex.image, preparation)
    assert decision.applied and decision.confidence > 0.5, decision
    np.testing.assert_array_equal(registration.register(ex.volume, ex.image).patient_motion, result.patient_motion)


def test_an_xa_without_its_pixel_size_or_distances_is_read_with_them_given(tmp_path: Path) -> None:
    """A file without ImagerPixelSpacing and DistanceSourceToDetector (as the shared coronary XA
    lacks them) is refused with the Python argument named, and read with them given, by
    ``from_dicom`` and by ``from_file``; the C-arm then has exactly the given values."""
    import registration
    from registration.io.dicom import DicomError
    from tests.registration.io.test_dicom import xa_file

    stored = np.tile(np.linspace(100, 3000, 32), (32, 1)).astype(np.uint16)
    path = xa_file(tmp_path / "xa.dcm", stored, sid=None, imager_spacing=None)
    with pytest.raises(DicomError, match=r"supply it with pixel_mm \(--pixel-mm\)"):
        registration.XRayImage.from_dicom(path, sid_mm=1000.0)
    for read in (registration.XRayImage.from_dicom, registration.XRayImage.from_file):
        image = read(path, sid_mm=1000.0, sod_mm=750.0, pixel_mm=0.3)
        assert image.geometry.pixel_mm == (0.3, 0.3) and image.geometry.sid_mm == 1000.0
        assert image.geometry.sod_mm == 750.0 and image.shape == (32, 32)
