"""X-ray images as TIFF or PNG with their C-arm geometry in a JSON side file.

A research image rarely comes as DICOM: the pixels are a TIFF or PNG, the geometry a few numbers
beside it. The side file (``geometry.json``, or by default the image's name with ``.json``)
states them; every key is checked, unknown keys are refused (a typo must not pass silently)::

    {
      "primary_deg": 0.0,            # LAO positive (CONVENTIONS §3)        required
      "secondary_deg": 0.0,          # CRAN positive                         required
      "sid_mm": 1200.0,              # source to detector                    required*
      "sod_mm": 800.0,               # source to iso-center                  required*
      "pixel_mm": [0.3, 0.3],        # (row, column) spacing at the detector, or one number
      "principal_point_px": [255.5, 255.5],  # (column, row) where the central ray meets the
                                     # detector, in the file's pixels; default the image center
      "flip_horizontal": false,      # the file is stored mirrored left-right: undone on reading
      "flip_vertical": false,        # the file is stored upside down: undone on reading
      "pixel_values": "intensity",   # "intensity" (linear, air bright: -log(I/I0) is taken)
                                     # or "line_integral" (attenuation, larger = more)
      "i0": null,                    # unattenuated intensity; default the field's brightest pixel
      "mask": null                   # a mask image (nonzero = inside the field), relative to
                                     # the JSON file; default: a constant border is outside
    }

``*`` ``sid_mm`` / ``sod_mm`` may instead be given by the caller (``--sid-mm`` / ``--sod-mm``).
After the flips the image follows CONVENTIONS §3: columns along u, rows along v (a frontal
image head up, the patient's right on the viewer's left). Errors are :class:`ImageFileError`
(a ``ValueError``) naming the file and the key.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from registration.core.geometry import CArm
from registration.core.images import XRayImage, line_integrals
from registration.io.dicom.limits import check_file_size, check_voxels

#: File name endings read here.
IMAGE_SUFFIXES = (".tif", ".tiff", ".png")
#: The keys of a geometry file and whether each is required.
GEOMETRY_KEYS = {
    "primary_deg": True,
    "secondary_deg": True,
    "sid_mm": False,
    "sod_mm": False,
    "pixel_mm": True,
    "principal_point_px": False,
    "flip_horizontal": False,
    "flip_vertical": False,
    "pixel_values": False,
    "i0": False,
    "mask": False,
}
PIXEL_VALUES = ("intensity", "line_integral")
#: The largest geometry file read (it holds a few numbers).
MAX_GEOMETRY_BYTES = 64 * 1024


class ImageFileError(ValueError):
    """An image or geometry file the project cannot use: the file and the problem."""

    def __init__(self, path: str | os.PathLike[str], message: str) -> None:
        self.path = str(path)
        super().__init__(f"{path}: {message}")


def is_image_file(path: str | os.PathLike[str]) -> bool:
    """True for a TIFF or PNG file name."""
    return Path(path).suffix.lower() in IMAGE_SUFFIXES


def default_geometry_path(image_path: str | os.PathLike[str]) -> Path:
    """The side file looked for when none is given: ``image.tif`` -> ``image.json``."""
    return Path(image_path).with_suffix(".json")


def read_pixels(path: str | os.PathLike[str]) -> NDArray[np.float64]:
    """The 2-D grayscale pixels of a TIFF (tifffile) or PNG (Pillow) file, as float64."""
    path = Path(path)
    if not path.is_file():
        raise ImageFileError(path, "no such file")
    check_file_size(path, path.stat().st_size)
    try:
        if path.suffix.lower() == ".png":
            from PIL import Image

            with Image.open(path) as im:
                check_voxels(path, (im.height, im.width), what="image size")
                if im.mode not in ("1", "L", "I", "I;16", "I;16B", "I;16L", "F"):
                    raise ImageFileError(path, f"PNG mode {im.mode}: a grayscale image is expected")
                pixels = np.asarray(im)
        else:
            import tifffile

            with tifffile.TiffFile(path) as tif:
                shape = tuple(int(n) for n in tif.series[0].shape)
                check_voxels(path, shape, what="image size")
                pixels = tif.series[0].asarray()
    except ImageFileError:
        raise
    except Exception as exc:
        raise ImageFileError(path, f"not a readable image ({type(exc).__name__}: {exc})") from None
    pixels = np.squeeze(np.asarray(pixels))
    if pixels.ndim != 2:
        raise ImageFileError(path, f"pixel array of shape {pixels.shape}: one grayscale image (rows, cols) expected")
    if not np.issubdtype(pixels.dtype, np.number) or np.iscomplexobj(pixels):
        raise ImageFileError(path, f"pixel type {pixels.dtype}: real numbers expected")
    return pixels.astype(np.float64)


def read_geometry(path: str | os.PathLike[str] | dict[str, Any]) -> dict[str, Any]:
    """The checked contents of a geometry file (or dict), missing optional keys filled in."""
    source = "geometry" if isinstance(path, dict) else str(path)
    if isinstance(path, dict):
        data = dict(path)
    else:
        p = Path(path)
        if not p.is_file():
            raise ImageFileError(p, "no such geometry file (give one with --geometry, or put <image>.json beside it)")
        if p.stat().st_size > MAX_GEOMETRY_BYTES:
            raise ImageFileError(p, f"{p.stat().st_size} bytes: a geometry file holds a few numbers")
        try:
            data = json.loads(p.read_text())
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ImageFileError(p, f"not valid JSON ({exc})") from None
        if not isinstance(data, dict):
            raise ImageFileError(p, "a JSON object {...} of geometry keys is expected")
    unknown = sorted(set(data) - set(GEOMETRY_KEYS))
    if unknown:
        raise ImageFileError(source, f"unknown key(s) {', '.join(unknown)} (known: {', '.join(GEOMETRY_KEYS)})")
    missing = [k for k, required in GEOMETRY_KEYS.items() if required and k not in data]
    if missing:
        raise ImageFileError(source, f"missing key(s) {', '.join(missing)}")
    out: dict[str, Any] = {"flip_horizontal": False, "flip_vertical": False, "pixel_values": "intensity"}
    out.update(data)
    for key in ("primary_deg", "secondary_deg", "sid_mm", "sod_mm", "i0"):
        if out.get(key) is not None:
            out[key] = _number(source, key, out[key])
    pixel = out["pixel_mm"]
    pixel = [pixel, pixel] if isinstance(pixel, int | float) else pixel
    if not isinstance(pixel, list) or len(pixel) != 2:
        raise ImageFileError(source, "pixel_mm: one number or [row spacing, column spacing] expected")
    out["pixel_mm"] = [_number(source, "pixel_mm", v) for v in pixel]
    if out.get("principal_point_px") is not None:
        pp = out["principal_point_px"]
        if not isinstance(pp, list) or len(pp) != 2:
            raise ImageFileError(source, "principal_point_px: [column, row] expected")
        out["principal_point_px"] = [_number(source, "principal_point_px", v) for v in pp]
    for key in ("flip_horizontal", "flip_vertical"):
        if not isinstance(out[key], bool):
            raise ImageFileError(source, f"{key}: true or false expected, got {out[key]!r}")
    if out["pixel_values"] not in PIXEL_VALUES:
        raise ImageFileError(source, f"pixel_values: one of {', '.join(PIXEL_VALUES)} expected")
    if out.get("mask") is not None and not isinstance(out["mask"], str):
        raise ImageFileError(source, "mask: a file name expected")
    return out


def _number(source: str, key: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ImageFileError(source, f"{key}: a finite number expected, got {value!r}")
    return float(value)


def _border_field(pixels: NDArray[np.float64]) -> NDArray[np.bool_]:
    """False where the pixels hold the corners' common value, connected to the border."""
    corners = {pixels[0, 0], pixels[0, -1], pixels[-1, 0], pixels[-1, -1]}
    if len(corners) != 1:
        return np.ones(pixels.shape, dtype=bool)
    labels, _ = ndimage.label(pixels == corners.pop())
    edge = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    outside = np.isin(labels, edge[edge > 0])
    return ~outside if not outside.all() else np.ones(pixels.shape, dtype=bool)


def read_image_mask(path: str | os.PathLike[str], shape: tuple[int, int]) -> NDArray[np.bool_]:
    """A user's field mask: a PNG or TIFF of the image's stored size (rows, cols), nonzero = usable.

    A color PNG counts a pixel as usable when any channel (alpha aside) is nonzero.
    """
    path = Path(path)
    if not path.is_file():
        raise ImageFileError(path, "no such image mask file")
    if path.suffix.lower() == ".png":
        check_file_size(path, path.stat().st_size)
        try:
            from PIL import Image

            with Image.open(path) as im:
                check_voxels(path, (im.height, im.width), what="image size")
                pixels = np.asarray(im.convert("RGB") if im.mode in ("RGB", "RGBA", "P", "LA", "PA") else im)
        except ImageFileError:
            raise
        except Exception as exc:
            raise ImageFileError(path, f"not a readable PNG mask ({type(exc).__name__}: {exc})") from None
    elif is_image_file(path):
        pixels = read_pixels(path)
    else:
        raise ImageFileError(path, f"an image mask is a PNG or TIFF file ({', '.join(IMAGE_SUFFIXES)})")
    if pixels.ndim == 3:
        pixels = pixels.max(axis=-1)
    if pixels.shape != tuple(shape):
        raise ImageFileError(
            path, f"the image mask is {pixels.shape[0]}x{pixels.shape[1]} pixels; the image is {shape[0]}x{shape[1]}"
        )
    mask = np.asarray(pixels) != 0
    if not mask.any():
        raise ImageFileError(path, "the image mask marks no pixel as usable (nonzero = usable)")
    return mask


def _field(pixels: np.ndarray, base: Path, geo: dict[str, Any]) -> tuple[np.ndarray, str]:
    """The image's usable field: the side file's mask file, else a constant border; and its source."""
    if geo.get("mask"):
        mask_path = base / geo["mask"]
        mask = read_pixels(mask_path) != 0
        if mask.shape != pixels.shape:
            raise ImageFileError(mask_path, f"mask shape {mask.shape} differs from the image's {pixels.shape}")
        return mask, f"mask file {mask_path.name}"
    mask = _border_field(pixels)
    return mask, "constant border" if not mask.all() else "whole image"


def read_image_file(
    path: str | os.PathLike[str],
    *,
    geometry: str | os.PathLike[str] | dict[str, Any] | None = None,
    isocenter_mm: ArrayLike = (0.0, 0.0, 0.0),
    sid_mm: float | None = None,
    sod_mm: float | None = None,
) -> XRayImage:
    """A TIFF/PNG X-ray image as attenuation line integrals with its field mask and C-arm.

    ``geometry``: the side file (or its contents as a dict); default ``<image>.json``.
    ``sid_mm`` / ``sod_mm`` replace the file's distances (or supply missing ones).
    """
    path = Path(path)
    if not is_image_file(path):
        raise ImageFileError(path, f"not a TIFF or PNG file name ({', '.join(IMAGE_SUFFIXES)})")
    geo_source = default_geometry_path(path) if geometry is None else geometry
    geo = read_geometry(geo_source)
    base = Path(geo_source).parent if not isinstance(geo_source, dict) else path.parent
    pixels = read_pixels(path)
    rows, cols = pixels.shape
    mask, mask_from = _field(pixels, base, geo)
    cx, cy = geo.get("principal_point_px") or ((cols - 1) / 2.0, (rows - 1) / 2.0)
    if geo["flip_horizontal"]:
        pixels, mask, cx = pixels[:, ::-1], mask[:, ::-1], cols - 1 - cx
    if geo["flip_vertical"]:
        pixels, mask, cy = pixels[::-1], mask[::-1], rows - 1 - cy
    sid = sid_mm if sid_mm is not None else geo.get("sid_mm")
    sod = sod_mm if sod_mm is not None else geo.get("sod_mm")
    if sid is None or sod is None:
        raise ImageFileError(str(geo_source), "sid_mm and sod_mm are needed (in the file or as --sid-mm/--sod-mm)")
    try:
        carm = CArm(
            primary_deg=geo["primary_deg"],
            secondary_deg=geo["secondary_deg"],
            sid_mm=sid,
            sod_mm=sod,
            rows=rows,
            cols=cols,
            pixel_mm=tuple(geo["pixel_mm"]),
            isocenter_mm=tuple(np.asarray(isocenter_mm, dtype=np.float64).reshape(3)),
        )
        carm = with_principal_point(carm, (cx, cy))
        if geo["pixel_values"] == "intensity":
            image = line_integrals(pixels, mask=mask, i0=geo.get("i0"))
        else:
            image = pixels.astype(np.float32)
        image = np.where(mask, image, np.float32(0.0)).astype(np.float32)
        meta = {
            "source": str(path),
            "format": path.suffix.lower().lstrip(".").upper().replace("TIF", "TIFF").replace("TIFFF", "TIFF"),
            "geometry_from": str(geo_source) if not isinstance(geo_source, dict) else "geometry dict",
            "mask_from": mask_from,
            "pixel_values": geo["pixel_values"],
            "flips": [k for k in ("flip_horizontal", "flip_vertical") if geo[k]],
        }
        return XRayImage(
            image=np.ascontiguousarray(image), mask=np.ascontiguousarray(mask), geometry=carm, kind="dicom", meta=meta
        )
    except ValueError as exc:
        raise ImageFileError(path, str(exc)) from None


def with_principal_point(carm: CArm, principal_point_px: tuple[float, float]) -> CArm:
    """``carm`` with its detector shifted so the central ray meets pixel ``(column, row)``."""
    from dataclasses import replace

    cx, cy = principal_point_px
    du = ((carm.cols - 1) / 2.0 - cx) * carm.pixel_mm[1]
    dv = ((carm.rows - 1) / 2.0 - cy) * carm.pixel_mm[0]
    if du == 0 and dv == 0:
        return carm
    shift = du * carm.u + dv * carm.v
    return replace(carm, detector_shift_mm=(float(shift[0]), float(shift[1]), float(shift[2])))


def write_image_file(xray: XRayImage, path: str | os.PathLike[str]) -> tuple[Path, Path]:
    """Write ``xray`` as a float32 TIFF of its line integrals, ``<name>.json`` and a mask PNG.

    What :func:`read_image_file` reads back to the same image, mask and geometry (for a
    geometry without shifts other than a principal point, and without tilts).
    """
    import tifffile
    from PIL import Image

    path = Path(path)
    if path.suffix.lower() not in (".tif", ".tiff"):
        raise ImageFileError(path, "the image is written as TIFF (.tif or .tiff)")
    g = xray.geometry
    if any(g.source_shift_mm) or any(g.detector_tilt_deg):
        raise ImageFileError(path, "a geometry with source shifts or detector tilts has no place in the side file")
    shift = np.asarray(g.detector_shift_mm)
    cx = (g.cols - 1) / 2.0 - float(shift @ g.u) / g.pixel_mm[1]
    cy = (g.rows - 1) / 2.0 - float(shift @ g.v) / g.pixel_mm[0]
    mask_path = path.with_name(path.stem + "-mask.png")
    geometry = {
        "primary_deg": g.primary_deg,
        "secondary_deg": g.secondary_deg,
        "sid_mm": g.sid_mm,
        "sod_mm": g.sod_mm,
        "pixel_mm": list(g.pixel_mm),
        "principal_point_px": [cx, cy],
        "pixel_values": "line_integral",
        "mask": mask_path.name,
    }
    tifffile.imwrite(path, np.where(xray.mask, xray.image, 0).astype(np.float32))
    Image.fromarray(xray.mask.astype(np.uint8) * 255).save(mask_path)
    json_path = default_geometry_path(path)
    json_path.write_text(json.dumps(geometry, indent=2) + "\n")
    return path, json_path
