"""The 2-D pictures of the panel: fluoroscopy with the roadmap outline, DRR, gradient images.

Pure functions from engine arrays to ``(H, W, 3)`` uint8 RGB (viser's image widgets crash on
2-D arrays). Display follows the radiology habit: more attenuation is darker. The pictures the
registration report draws too (gray levels, the roadmap's outline, gradients, captions) are
:mod:`registration.studies.qa_images`'s; the panel's own layout is here.
"""

from __future__ import annotations

import cv2
import numpy as np

from registration.core.geometry import CArm
from registration.studies.qa_images import (
    draw_outline,
    gradient_image,
    gray_rgb,
    label,
    resize,
    to_gray,
    vessel_silhouette,
)

RGB = np.ndarray

#: The app's dark panel and its text (Mantine's dark theme, as viser draws it), for tiles and plots.
PANEL_RGB = (37, 38, 43)
PANEL_TEXT_RGB = (193, 194, 197)


def hex_of(rgb: tuple[int, int, int]) -> str:
    return "#{:02x}{:02x}{:02x}".format(*rgb)


__all__ = [
    "angles_text",
    "draw_outline",
    "gradient_image",
    "gray_rgb",
    "label",
    "resize",
    "shade_outside",
    "side_by_side",
    "stacked",
    "to_gray",
    "vessel_silhouette",
]


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


def angles_text(geometry: CArm) -> str:
    """C-arm angles the way the console shows them, e.g. "LAO 30 CRAN 10" (ASCII for OpenCV)."""
    a, b = geometry.primary_deg, geometry.secondary_deg
    return f"{'LAO' if a >= 0 else 'RAO'} {abs(a):.0f}  {'CRAN' if b >= 0 else 'CAUD'} {abs(b):.0f}"


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
