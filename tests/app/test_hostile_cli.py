"""The command line under the hostile and broken inputs of issue 15: `error: ...` naming the
file or the option, exit code 2, no traceback, nothing written, no registration started."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pydicom
import pytest

from app import cli
from registration.core.volume import Volume
from registration.io import dicom
from tests.registration.io.test_dicom import ct_slice, ramp, xa_file

pytestmark = [
    pytest.mark.filterwarnings("ignore:.*using the whole image as the field:UserWarning"),
    pytest.mark.filterwarnings("ignore:Invalid value for VR DS:UserWarning"),
]


def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as info:
        cli.main(argv)
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return int(info.value.code or 0), out, err


@pytest.fixture
def inputs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> dict[str, Path]:
    """A small valid volume and XA image; the registration itself must never start."""
    rng = np.random.default_rng(0)
    volume = Volume(rng.normal(0, 300, (8, 8, 8)).astype(np.float32), np.diag([2.0, 2.0, 2.0, 1.0]), label="v")
    import registration.core.register as core_register

    def no_registration(*_args, **_kwargs):
        raise AssertionError("the registration started although the input was refused")

    monkeypatch.setattr(core_register, "register", no_registration)
    return {
        "volume": dicom.write_npz(volume, tmp_path / "v.npz"),
        "image": xa_file(tmp_path / "xa.dcm", ramp((16, 16))),
        "tmp": tmp_path,
    }


def _register(inputs: dict[str, Path], *extra: str) -> list[str]:
    return ["register", "--volume", str(inputs["volume"]), "--image", str(inputs["image"]), *extra]


def test_deeply_nested_initial_motion_json_is_a_message(inputs, capsys) -> None:
    """--initial-motion with deeply nested JSON raised RecursionError."""
    path = inputs["tmp"] / "nested.json"
    path.write_text("[" * 200_000 + "]" * 200_000)
    code, _, err = run(_register(inputs, "--initial-motion", str(path)), capsys)
    assert code == 2 and err.splitlines()[-1].startswith("error: ") and str(path) in err and "nests" in err


def test_initial_translation_of_1e12_mm_is_refused(inputs, capsys) -> None:
    motion = np.eye(4)
    motion[0, 3] = 1e12
    path = inputs["tmp"] / "far.json"
    path.write_text(json.dumps({"patient_motion": motion.tolist()}))
    code, _, err = run(_register(inputs, "--initial-motion", str(path)), capsys)
    assert code == 2 and str(path) in err and "1e+12 mm" in err


@pytest.mark.parametrize("where", ["missing folder", "a file as folder"])
def test_unwritable_out_is_found_before_the_registration(inputs, capsys, where: str) -> None:
    """An unwritable --out was found only after the registration ran, naming the .tmp file."""
    blocker = inputs["tmp"] / "plain-file"
    blocker.write_text("x")
    out = inputs["tmp"] / "no" / "such" / "r.json" if where == "missing folder" else blocker / "r.json"
    code, _, err = run(_register(inputs, "--out", str(out)), capsys)
    assert code == 2 and str(out) in err and "--out" in err and ".tmp" not in err


def test_out_dicom_is_checked_too(inputs, capsys) -> None:
    out = inputs["tmp"] / "missing" / "reg.dcm"
    code, _, err = run(_register(inputs, "--out-dicom", str(out)), capsys)
    assert code == 2 and "--out-dicom" in err


def test_pixel_spacing_1e300_is_refused_by_info_and_register(inputs, capsys) -> None:
    """PixelSpacing 1e300 passed `info`, then `register` raised OverflowError."""
    folder = inputs["tmp"] / "ct"
    folder.mkdir()
    for k in range(3):
        path = ct_slice(folder / f"{k}.dcm", ramp((6, 6), k), ipp=(0, 0, 2.0 * k))
        ds = pydicom.dcmread(path)
        ds.PixelSpacing = ["1e300", "1e300"]
        ds.save_as(path)
    code, _, err = run(["register", "--volume", str(folder), "--image", str(inputs["image"])], capsys)
    assert code == 2 and "PixelSpacing (0028,0030)" in err and "out of range" in err


def test_arithmetic_errors_still_end_in_a_message(monkeypatch, capsys) -> None:
    """Anything no check caught (OverflowError, RecursionError, ...) is `error:` and exit 2."""
    import app.cli.commands

    def overflow(**_kwargs):
        raise OverflowError("cannot convert float infinity to integer")

    monkeypatch.setattr(app.cli.commands, "run_info", lambda *a, **k: overflow())
    code, _, err = run(["info", "whatever.dcm"], capsys)
    assert code == 2 and err.startswith("error: OverflowError") and "ROADMAP3D_DEBUG=1" in err
    assert "on the input of: roadmap3d info whatever.dcm" in err  # names the file given


def test_an_all_zero_volume_cannot_be_registered_and_nothing_is_written(tmp_path: Path, capsys) -> None:
    volume = Volume(np.zeros((8, 8, 8), np.float32), np.diag([2.0, 2.0, 2.0, 1.0]), label="zeros")
    path = dicom.write_npz(volume, tmp_path / "zeros.npz")
    image = xa_file(tmp_path / "xa.dcm", ramp((16, 16)))
    out = tmp_path / "result.json"
    code, _, err = run(["register", "--volume", str(path), "--image", str(image), "--out", str(out)], capsys)
    assert code == 2 and "error: cannot register: the volume 'zeros' is constant" in err
    assert not out.exists()


@pytest.mark.parametrize(
    "argv",
    [["bench", "--quick", "--seed", "-1"], ["validate", "capture", "--quick", "--seed", "-2"],
     ["validate", "phantom", "--quick", "--seed", "-1"], ["phantom-run", "--seed", "-1", "--out", "run"]],
)  # fmt: skip
def test_a_negative_seed_is_refused_before_any_work(argv: list[str], tmp_path: Path, capsys, monkeypatch) -> None:
    """Every command with ``--seed`` refuses a negative one up front, naming the option (numpy
    takes none: the bench stopped on it minutes in, with a message that named nothing)."""
    monkeypatch.chdir(tmp_path)
    code, out, err = run(argv, capsys)
    assert code == 2 and err.startswith("error: --seed must be a non-negative integer, got -")
    assert "..." not in err and not any(tmp_path.iterdir())  # no progress, nothing written
