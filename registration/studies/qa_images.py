"""Pictures that compare an X-ray image with the DRR at a pose, in place.

Pure functions from engine arrays to ``(H, W, 3)`` uint8 RGB, shared by the web app's fluoro
tile and the registration report (:mod:`registration.studies.qa_report`). Display follows the
radiology habit: more attenuation is darker. The overlay modes (:data:`OVERLAY_MODES`):

``outline``
    the roadmap: the vessel surface's silhouette at the pose, outlined in red (needs vessels);
``edges``
    the DRR's strongest edges (the gradient the measure compares) in green over the image;
``checkerboard``
    squares of the image and of the DRR alternating (``tile_px`` wide): edges that continue
    across the squares' borders are in place;
``difference``
    the image minus the DRR, each normalised inside the field (mean 0, unit spread): mid-gray
    where they agree, dark / light where one has structure the other lacks;
``wipe``
    before / after: left of a vertical line the comparison at the machine-based (initial) pose,
    right of it at the registered one (:func:`wipe`).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

from registration.core.geometry import CArm, apply

RGB = NDArray[np.uint8]

#: The overlay modes of the fluoro tile and the report, in the order the app offers them.
OVERLAY_MODES = ("outline", "edges", "checkerboard", "difference", "wipe")
OVERLAY_LABELS = {
    "outline": "vessel outline",
    "edges": "DRR edges over the image",
    "checkerboard": "checkerboard image / DRR",
    "difference": "difference image - DRR",
    "wipe": "before / after (machine-based | registered)",
}
#: Roadmap outline (paper Fig. 5: red), DRR edges (green), the initial pose's outline (amber).
OUTLINE_RGB = (255, 48, 48)
EDGE_RGB = (60, 235, 90)
INITIAL_RGB = (255, 190, 60)
WIPE_LINE_RGB = (255, 255, 255)
#: Share of the field's pixels drawn as DRR edges (the strongest gradients).
EDGE_SHARE = 0.08
#: Checkerboard squares (pixels of the shown tile) when not given.
CHECKER_TILE_PX = 48


def to_gray(attenuation: NDArray, mask: NDArray[np.bool_] | None = None) -> NDArray[np.uint8]:
    """Attenuation line integrals -> uint8 gray, dark = attenuating, black outside ``mask``
    (the field's 0.5-99.5 percentiles span 10-245)."""
    img = np.asarray(attenuation, dtype=np.float32)
    inside = img[mask] if mask is not None and mask.any() else img.ravel()
    if inside.size == 0:
        return np.zeros(img.shape, np.uint8)
    lo, hi = np.percentile(inside, [0.5, 99.5])
    scale = 1.0 / max(float(hi - lo), 1e-6)
    gray = 1.0 - np.clip((img - lo) * scale, 0.0, 1.0)
    out = (gray * 235.0 + 10.0).astype(np.uint8)
    if mask is not None:
        out[~mask] = 0
    return out


def gray_rgb(gray: NDArray[np.uint8]) -> RGB:
    return np.ascontiguousarray(np.repeat(np.asarray(gray, np.uint8)[:, :, None], 3, axis=2))


def resize(img: NDArray, size: int) -> NDArray:
    """``img`` resized to ``size`` x ``size`` (area averaging down, bilinear up)."""
    if img.shape[0] == size and img.shape[1] == size:
        return img
    interp = cv2.INTER_AREA if img.shape[0] > size else cv2.INTER_LINEAR
    return cv2.resize(img, (size, size), interpolation=interp)


def vessel_silhouette(vertices_mm: NDArray, motion: NDArray, geometry: CArm, spacing_mm: float) -> NDArray[np.uint8]:
    """Filled silhouette (uint8 0/1, rows x cols) of a surface mesh moved by ``motion``.

    The mesh vertices are splatted into the image and closed with a disk as wide as the
    projected vertex spacing, which fills the outline of a closed surface.
    """
    mask = np.zeros((geometry.rows, geometry.cols), np.uint8)
    if len(vertices_mm) == 0:
        return mask
    pts = geometry.project(apply(np.asarray(motion, np.float64), np.asarray(vertices_mm, np.float64)))
    cols = np.rint(pts[:, 0]).astype(np.int64)
    rows = np.rint(pts[:, 1]).astype(np.int64)
    ok = (cols >= 0) & (cols < geometry.cols) & (rows >= 0) & (rows < geometry.rows)
    mask[rows[ok], cols[ok]] = 1
    spacing_px = spacing_mm * geometry.magnification / min(geometry.pixel_mm)
    radius = max(1, int(math.ceil(spacing_px * 0.75)))
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    return cv2.morphologyEx(mask, cv2.MORPH_CLOSE, disk, iterations=1)


def draw_outline(rgb: RGB, silhouette: NDArray[np.uint8], *, color=OUTLINE_RGB, thickness: int = 1) -> RGB:  # noqa: ANN001
    """Draw the outline of ``silhouette`` over ``rgb`` (in place) and return it."""
    contours, _ = cv2.findContours(np.ascontiguousarray(silhouette, np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(rgb, contours, -1, color, thickness, lineType=cv2.LINE_AA)
    return rgb


def gradient_magnitude(attenuation: NDArray, mask: NDArray[np.bool_] | None = None) -> NDArray[np.float32]:
    """Sobel gradient magnitude (what the gradient difference compares), 0 outside the eroded field."""
    img = np.asarray(attenuation, dtype=np.float32)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    mag = np.hypot(gx, gy)
    if mask is not None:
        inner = cv2.erode(np.asarray(mask, np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        mag[~inner] = 0
    return mag


def gradient_image(attenuation: NDArray, mask: NDArray[np.bool_] | None = None) -> NDArray[np.uint8]:
    """The gradient magnitude as uint8 (its 99th percentile in the field white)."""
    mag = gradient_magnitude(attenuation, mask)
    values = mag[mag > 0] if mask is not None else mag.ravel()
    hi = float(np.percentile(values, 99.0)) if values.size else 1.0
    return (np.clip(mag / max(hi, 1e-6), 0, 1) * 255).astype(np.uint8)


def edge_map(drr: NDArray, mask: NDArray[np.bool_] | None = None, *, share: float = EDGE_SHARE) -> NDArray[np.bool_]:
    """The strongest ``share`` of the DRR's gradient magnitudes inside the field, thinned to
    about a pixel (a pixel is kept where it is the largest of its 3 x 3 neighbourhood along
    either axis)."""
    if not 0.0 < share < 1.0:
        raise ValueError(f"share must lie in (0, 1), got {share}")
    mag = gradient_magnitude(drr, mask)
    inside = mag[mag > 0]
    if inside.size == 0:
        return np.zeros(mag.shape, bool)
    strong = mag >= np.quantile(inside, 1.0 - share)
    ridge_x = (mag >= np.roll(mag, 1, axis=1)) & (mag >= np.roll(mag, -1, axis=1))
    ridge_y = (mag >= np.roll(mag, 1, axis=0)) & (mag >= np.roll(mag, -1, axis=0))
    return strong & (ridge_x | ridge_y) & (mag > 0)


def drr_edges(image_gray: NDArray[np.uint8], drr: NDArray, mask: NDArray[np.bool_] | None = None) -> RGB:
    """The DRR's edges (:func:`edge_map`, same shape as the image) in green over the image."""
    rgb = gray_rgb(image_gray)
    edges = edge_map(drr, mask)
    rgb[edges] = EDGE_RGB
    return rgb


def checkerboard(a: NDArray[np.uint8], b: NDArray[np.uint8], tile_px: int = CHECKER_TILE_PX) -> RGB:
    """Squares of ``a`` and ``b`` (gray or RGB, same shape) alternating, ``tile_px`` wide,
    ``a`` in the top-left square."""
    if tile_px < 1:
        raise ValueError(f"tile_px must be >= 1, got {tile_px}")
    a3 = gray_rgb(a) if a.ndim == 2 else np.asarray(a, np.uint8)
    b3 = gray_rgb(b) if b.ndim == 2 else np.asarray(b, np.uint8)
    if a3.shape != b3.shape:
        raise ValueError(f"checkerboard of two shapes {a3.shape} and {b3.shape}")
    rows, cols = np.indices(a3.shape[:2])
    take_b = ((rows // tile_px) + (cols // tile_px)) % 2 == 1
    return np.ascontiguousarray(np.where(take_b[:, :, None], b3, a3))


def _standardised(img: NDArray, mask: NDArray[np.bool_]) -> NDArray[np.float32]:
    x = np.asarray(img, np.float32)
    inside = x[mask]
    if inside.size < 2:
        return np.zeros_like(x)
    return (x - float(inside.mean())) / max(float(inside.std()), 1e-6)


def difference(image: NDArray, drr: NDArray, mask: NDArray[np.bool_] | None = None, *, spread: float = 2.5) -> RGB:
    """The image minus the DRR (attenuations, each standardised inside ``mask``), gray 128 where
    they agree, +-``spread`` standard deviations to black / white (display: attenuation dark);
    black outside the field."""
    m = np.ones(np.shape(image), bool) if mask is None else np.asarray(mask, bool)
    d = _standardised(image, m) - _standardised(drr, m)
    gray = np.rint(np.clip(128.0 - d * (127.0 / spread), 0, 255)).astype(np.uint8)
    gray[~m] = 0
    return gray_rgb(gray)


def wipe(before: RGB, after: RGB, fraction: float) -> RGB:
    """``before`` left of a vertical line at ``fraction`` of the width, ``after`` right of it."""
    if before.shape != after.shape:
        raise ValueError(f"wipe of two shapes {before.shape} and {after.shape}")
    f = float(np.clip(fraction, 0.0, 1.0))
    x = int(round(f * before.shape[1]))
    out = np.array(after, np.uint8, copy=True)
    out[:, :x] = before[:, :x]
    if 0 < x < out.shape[1]:
        out[:, max(0, x - 1) : x + 1] = WIPE_LINE_RGB
    return out


def label(rgb: RGB, text: str, *, corner: str = "top-left") -> RGB:
    """A small caption on a dark strip in a corner of a tile (in place; ASCII for OpenCV)."""
    scale = max(0.4, rgb.shape[0] / 800.0)
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    x = 6 if corner.endswith("left") else rgb.shape[1] - w - 10
    y = h + 7 if corner.startswith("top") else rgb.shape[0] - base - 5
    y0, y1 = max(0, y - h - 4), min(rgb.shape[0], y + base + 3)
    x0, x1 = max(0, x - 4), min(rgb.shape[1], x + w + 4)
    rgb[y0:y1, x0:x1] = (rgb[y0:y1, x0:x1] * 0.35).astype(np.uint8)
    cv2.putText(rgb, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (230, 230, 230), 1, cv2.LINE_AA)
    return rgb


def zoomed(rgb: RGB, zoom: float, center: tuple[float, float] = (0.5, 0.5)) -> RGB:
    """The part of ``rgb`` ``zoom`` times enlarged about ``center`` (fractions of width and
    height, kept inside the picture), at the picture's own size. ``zoom`` 1: ``rgb`` itself."""
    if not zoom >= 1.0:
        raise ValueError(f"zoom must be >= 1, got {zoom}")
    if zoom == 1.0:
        return rgb
    h, w = rgb.shape[:2]
    ch, cw = h / zoom, w / zoom
    cx = float(np.clip(center[0] * w, cw / 2, w - cw / 2))
    cy = float(np.clip(center[1] * h, ch / 2, h - ch / 2))
    x0, y0 = int(round(cx - cw / 2)), int(round(cy - ch / 2))
    crop = rgb[y0 : y0 + max(1, int(round(ch))), x0 : x0 + max(1, int(round(cw)))]
    return np.ascontiguousarray(cv2.resize(crop, (w, h), interpolation=cv2.INTER_LINEAR))


def compare(
    mode: str,
    *,
    image: NDArray,
    drr: NDArray,
    mask: NDArray[np.bool_],
    outline: NDArray[np.uint8] | None = None,
    drr_initial: NDArray | None = None,
    outline_initial: NDArray[np.uint8] | None = None,
    tile_px: int = CHECKER_TILE_PX,
    wipe_fraction: float = 0.5,
    thickness: int = 1,
) -> RGB:
    """One overlay mode (:data:`OVERLAY_MODES`) of ``image`` (attenuation) against ``drr`` (the
    DRR at the pose, same shape) in the field ``mask``. ``outline``: the vessels' silhouette at
    the pose (:func:`vessel_silhouette`); ``drr_initial`` / ``outline_initial``: the same at
    the machine-based pose, for ``wipe`` (the DRR's edges when there is no outline)."""
    if mode not in OVERLAY_MODES:
        raise ValueError(f"overlay mode must be one of {', '.join(OVERLAY_MODES)}, got {mode!r}")
    gray = to_gray(image, mask)
    if mode == "outline":
        rgb = gray_rgb(gray)
        if outline is not None:
            draw_outline(rgb, outline, thickness=thickness)
        return rgb
    if mode == "edges":
        return drr_edges(gray, drr, mask)
    if mode == "checkerboard":
        drr_gray = to_gray(drr, mask)
        return checkerboard(gray, drr_gray, tile_px)
    if mode == "difference":
        return difference(image, drr, mask)
    # wipe: the roadmap (or the DRR's edges) at the machine-based pose | at the registered one
    if outline is not None and outline_initial is not None:
        before = draw_outline(gray_rgb(gray), outline_initial, color=INITIAL_RGB, thickness=thickness)
        after = draw_outline(gray_rgb(gray), outline, thickness=thickness)
    else:
        before = drr_edges(gray, drr if drr_initial is None else drr_initial, mask)
        after = drr_edges(gray, drr, mask)
    return wipe(before, after, wipe_fraction)
