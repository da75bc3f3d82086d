"""The 2-D pictures of the panel: fluoroscopy with the roadmap outline, DRR, gradient images.

Pure functions from engine arrays to ``(H, W, 3)`` uint8 RGB (viser's image widgets crash on
2-D arrays). Display follows the radiology habit: more attenuation is darker.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from registration.core.geometry import CArm, apply

RGB = np.ndarray

#: Roadmap outline colour (paper Fig. 5: red) and the background outside the collimated field.
OUTLINE_RGB = (255, 48, 48)
LABEL_RGB = (230, 230, 230)


def to_gray(attenuation: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Attenuation line integrals -> uint8 gray, dark = attenuating, black outside ``mask``."""
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


def resize(img: np.ndarray, size: int) -> np.ndarray:
    if img.shape[0] == size and img.shape[1] == size:
        return img
    interp = cv2.INTER_AREA if img.shape[0] > size else cv2.INTER_LINEAR
    return cv2.resize(img, (size, size), interpolation=interp)


def vessel_silhouette(vertices_mm: np.ndarray, motion: np.ndarray, geometry: CArm, spacing_mm: float) -> np.ndarray:
    """Filled silhouette (uint8 0/1, rows x cols) of a surface mesh moved by ``motion``.

    The mesh vertices are splatted into the image and closed with a disk as wide as the
    projected vertex spacing, which fills the outline of a closed surface.
    """
    mask = np.zeros((geometry.rows, geometry.cols), np.uint8)
    if len(vertices_mm) == 0:
        return mask
    pts = geometry.project(apply(motion, vertices_mm))
    cols = np.rint(pts[:, 0]).astype(np.int64)
    rows = np.rint(pts[:, 1]).astype(np.int64)
    ok = (cols >= 0) & (cols < geometry.cols) & (rows >= 0) & (rows < geometry.rows)
    mask[rows[ok], cols[ok]] = 1
    spacing_px = spacing_mm * geometry.magnification / min(geometry.pixel_mm)
    radius = max(1, int(math.ceil(spacing_px * 0.75)))
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    return cv2.morphologyEx(mask, cv2.MORPH_CLOSE, disk, iterations=1)


def draw_outline(rgb: RGB, silhouette: np.ndarray, *, thickness: int = 1) -> RGB:
    """Draw the outline of ``silhouette`` in red over ``rgb`` (in place) and return it."""
    contours, _ = cv2.findContours(silhouette, cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(rgb, contours, -1, OUTLINE_RGB, thickness, lineType=cv2.LINE_AA)
    return rgb


def shade_outside(rgb: RGB, mask: np.ndarray) -> RGB:
    """Darken and tint blue what lies outside ``mask`` (the usable field), and outline the field
    in yellow, in place."""
    outside = ~np.asarray(mask, dtype=bool)
    if outside.any():
        tinted = rgb[outside].astype(np.float32) * 0.35 + np.array([20.0, 40.0, 110.0], np.float32)
        rgb[outside] = np.clip(tinted, 0, 255).astype(np.uint8)
        contours, _ = cv2.findContours((~outside).astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(rgb, contours, -1, (255, 210, 0), 1)
    return rgb


def gradient_image(attenuation: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Magnitude of the Sobel gradient (what gradient difference compares), uint8."""
    img = np.asarray(attenuation, dtype=np.float32)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    mag = np.hypot(gx, gy)
    if mask is not None:
        inner = cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        mag[~inner] = 0
        values = mag[inner]
    else:
        values = mag.ravel()
    hi = float(np.percentile(values, 99.0)) if values.size else 1.0
    return (np.clip(mag / max(hi, 1e-6), 0, 1) * 255).astype(np.uint8)


def label(rgb: RGB, text: str, *, corner: str = "top-left") -> RGB:
    """A small caption on a dark strip in a corner of a tile (in place)."""
    scale = max(0.4, rgb.shape[0] / 800.0)
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    x = 6 if corner.endswith("left") else rgb.shape[1] - w - 10
    y = h + 7 if corner.startswith("top") else rgb.shape[0] - base - 5
    y0, y1 = max(0, y - h - 4), min(rgb.shape[0], y + base + 3)
    x0, x1 = max(0, x - 4), min(rgb.shape[1], x + w + 4)
    rgb[y0:y1, x0:x1] = (rgb[y0:y1, x0:x1] * 0.35).astype(np.uint8)
    cv2.putText(rgb, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, LABEL_RGB, 1, cv2.LINE_AA)
    return rgb


def angles_text(geometry: CArm) -> str:
    """C-arm angles the way the console shows them, e.g. "LAO 30 CRAN 10" (ASCII for OpenCV)."""
    a, b = geometry.primary_deg, geometry.secondary_deg
    return f"{'LAO' if a >= 0 else 'RAO'} {abs(a):.0f}  {'CRAN' if b >= 0 else 'CAUD'} {abs(b):.0f}"


def gray_rgb(gray: np.ndarray) -> RGB:
    return np.ascontiguousarray(np.repeat(gray[:, :, None], 3, axis=2))


def side_by_side(*tiles: RGB, gap: int = 4) -> RGB:
    """Tiles of equal height next to each other on a dark background."""
    height = max(t.shape[0] for t in tiles)
    width = sum(t.shape[1] for t in tiles) + gap * (len(tiles) - 1)
    out = np.full((height, width, 3), 26, np.uint8)
    x = 0
    for tile in tiles:
        out[: tile.shape[0], x : x + tile.shape[1]] = tile
        x += tile.shape[1] + gap
    return out


def stacked(*rows: RGB, gap: int = 4) -> RGB:
    width = max(r.shape[1] for r in rows)
    height = sum(r.shape[0] for r in rows) + gap * (len(rows) - 1)
    out = np.full((height, width, 3), 26, np.uint8)
    y = 0
    for row in rows:
        out[y : y + row.shape[0], : row.shape[1]] = row
        y += row.shape[0] + gap
    return out
