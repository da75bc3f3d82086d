"""The vendor's display chain and the graphics on a clinical image.

From the log image (attenuation line integrals, CONVENTIONS §5) to stored pixels as many
systems keep them: edge enhancement (unsharp mask), a window, a monotone S-shaped look-up table
and a gamma, a polarity, a bit depth, lossy JPEG; then burned-in text and a ruler at full white,
and the graphics of an overlay plane (60xx) beside the pixels.
"""

from __future__ import annotations

import math
from datetime import date

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from registration.core.geometry import CArm
from registration.sim.clinical.effects import BurnedInText, Display, Overlay

#: Font of the burned-in text (OpenCV's Hershey simplex: a stroke font as on many consoles).
FONT = cv2.FONT_HERSHEY_SIMPLEX


def lut(x: NDArray[np.float64], display: Display) -> NDArray[np.float64]:
    """The display look-up table on windowed values ``x`` (0 and 1 at the window's ends):
    a logistic S-curve of steepness ``s_curve`` (none at 0) then a gamma; strictly increasing,
    values in [0, 1]."""
    x = np.asarray(x, dtype=np.float64)
    if display.s_curve > 0:
        c = display.s_curve
        lo, hi = 1.0 / (1.0 + math.exp(c / 2)), 1.0 / (1.0 + math.exp(-c / 2))
        # the logistic over the window, continued linearly past it so that nothing saturates early
        y = (1.0 / (1.0 + np.exp(-c * (np.clip(x, 0.0, 1.0) - 0.5))) - lo) / (hi - lo)
        slope_end = c * hi * (1 - hi) / (hi - lo)
        y = np.where(x > 1.0, 1.0 + slope_end * (x - 1.0), np.where(x < 0.0, slope_end * x, y))
    else:
        y = x
    # soft limits: values past the window approach 0 and 1 without a hard clip
    y = np.where(y > 1.0, 1.0 + 0.1 * np.tanh((y - 1.0) / 0.1), np.where(y < 0.0, 0.1 * np.tanh(y / 0.1), y))
    y = (y + 0.1) / 1.2  # into [0, 1]
    return np.clip(y, 0.0, 1.0) ** display.gamma


def display_pixels(
    attenuation: NDArray[np.float32],
    field: NDArray[np.bool_],
    open_field: NDArray[np.bool_],
    geometry: CArm,
    display: Display,
) -> tuple[NDArray[np.uint16], dict]:
    """Stored pixels (0 outside ``field``) and what was done. The window comes from the
    percentiles of the open field (the vendor knows where its blades are)."""
    att = np.where(field, attenuation, 0.0).astype(np.float64)
    if display.edge_amount > 0:
        sigma_px = display.edge_sigma_mm / float(min(geometry.pixel_mm))
        weight = ndimage.gaussian_filter(field.astype(np.float64), sigma_px)
        smooth = ndimage.gaussian_filter(att, sigma_px) / np.maximum(weight, 1e-6)
        att = att + display.edge_amount * (att - smooth)
    usable = field & open_field if (field & open_field).any() else field
    lo, hi = np.percentile(att[usable], display.window_percentiles)
    hi = max(hi, lo + 1e-6)
    y = lut((att - lo) / (hi - lo), display)  # 0: least attenuation
    top = (1 << display.bits) - 1
    level = (1.0 - y) if display.polarity == "bone_dark" else y
    # nothing in the field at exactly 0 (that is the collimator's value outside it)
    stored = np.where(field, np.clip(np.rint(level * top), 1, top), 0).astype(np.uint16)
    info = {"window": [float(lo), float(hi)], "max_value": top}
    if display.jpeg_quality is not None:
        stored, ratio = jpeg_round_trip(stored, display.bits, display.jpeg_quality)
        stored = np.where(field, np.maximum(stored, 1), 0).astype(np.uint16)
        info["jpeg_ratio"] = ratio
    return stored, info


def jpeg_round_trip(stored: NDArray[np.uint16], bits: int, quality: int) -> tuple[NDArray[np.uint16], float]:
    """Lossy JPEG (baseline, 8 bits) of the pixels and back. Above 8 bits the image is coded at
    8 bits and the coding error, scaled back, added to the original: the same blocks and ringing
    relative to the image's range."""
    top = (1 << bits) - 1
    eight = np.rint(stored.astype(np.float64) * 255.0 / top).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", eight, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("JPEG encoding failed")
    decoded = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE).astype(np.float64)
    ratio = eight.size / len(buf)
    if bits == 8:
        return decoded.astype(np.uint16), ratio
    error = (decoded - eight) * top / 255.0
    return np.clip(np.rint(stored + error), 0, top).astype(np.uint16), ratio


def jpeg_bytes(stored8: NDArray[np.uint16], quality: int) -> bytes:
    """The baseline JPEG of 8-bit pixels (what a DICOM file with JPEG Baseline holds)."""
    ok, buf = cv2.imencode(".jpg", stored8.astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return bytes(buf)


def _text_lines(geometry: CArm, seed: int) -> tuple[list[str], list[str], str]:
    rng = np.random.default_rng([seed, 23])
    day = date(2024, 1, 1).toordinal() + int(rng.integers(0, 700))
    when = date.fromordinal(day)
    a, b = geometry.primary_deg, geometry.secondary_deg
    left = [
        "ANON^PATIENT",
        f"ID {int(rng.integers(10**6, 10**7))}",
        f"{when:%d-%b-%Y} {int(rng.integers(7, 19)):02d}:{int(rng.integers(0, 60)):02d}",
        "NEURO 3D ROADMAP",
        "ROOM 2",
        "Dr. X",
        "DOB 01-JAN-1960",
        "F",
    ]
    right = [
        f"{'LAO' if a >= 0 else 'RAO'} {abs(a):.0f}",
        f"{'CRAN' if b >= 0 else 'CAUD'} {abs(b):.0f}",
        f"{int(rng.choice([7, 10, 15, 30]))} fr/s",
        f"{int(rng.integers(65, 90))} kV {int(rng.integers(5, 40))} mA",
        f"FD {geometry.field_diameter_mm / 10:.0f} cm",
        "FLUORO LOW",
        "ZOOM 1.0",
        "SID " + f"{geometry.sid_mm:.0f}",
    ]
    inside = f"{'LAO' if a >= 0 else 'RAO'} {abs(a):.0f}  {'CRAN' if b >= 0 else 'CAUD'} {abs(b):.0f}"
    return left, right, inside


def text_mask(geometry: CArm, text: BurnedInText, *, seed: int = 0) -> NDArray[np.bool_]:
    """Pixels of the burned-in text blocks and ruler (True where drawn)."""
    rows, cols = geometry.rows, geometry.cols
    canvas = np.zeros((rows, cols), dtype=np.uint8)
    height_px = rows / 40.0 * text.font_scale
    scale = height_px / 22.0  # Hershey simplex: ~22 px tall at scale 1
    thick = max(1, round(scale * 1.6))
    left, right, inside = _text_lines(geometry, seed)
    step = round(height_px * 1.5)
    margin = max(2, round(rows * 0.01))
    for n, line in enumerate(left[: text.lines]):
        cv2.putText(canvas, line, (margin, margin + round(height_px) + n * step), FONT, scale, 255, thick, cv2.LINE_AA)
    for n, line in enumerate(right[: text.lines]):
        (w, _), _ = cv2.getTextSize(line, FONT, scale, thick)
        cv2.putText(canvas, line, (cols - margin - w, rows - margin - n * step), FONT, scale, 255, thick, cv2.LINE_AA)
    if text.inside_field and text.lines > 0:
        (w, _), _ = cv2.getTextSize(inside, FONT, scale, thick)
        cv2.putText(canvas, inside, ((cols - w) // 2, round(rows * 0.82)), FONT, scale, 255, thick, cv2.LINE_AA)
    if text.ruler:
        _draw_ruler(canvas, geometry, thick)
    return canvas >= 128


def _draw_ruler(canvas: NDArray[np.uint8], geometry: CArm, thick: int) -> None:
    """A vertical scale along the right of the field: 10 mm ticks at the iso-center, 50 mm longer."""
    rows, cols = canvas.shape
    mm_per_px = float(geometry.pixel_mm[0]) * geometry.sod_mm / geometry.sid_mm
    x = round(cols * 0.86)
    y0, y1 = round(rows * 0.3), round(rows * 0.7)
    cv2.line(canvas, (x, y0), (x, y1), 255, thick)
    n = 0
    y = float(y0)
    while y <= y1:
        length = round(cols * (0.03 if n % 5 == 0 else 0.015))
        cv2.line(canvas, (x, round(y)), (x - length, round(y)), 255, thick)
        y += 10.0 / mm_per_px
        n += 1


def overlay_mask(geometry: CArm, overlay: Overlay, *, seed: int = 0) -> NDArray[np.bool_]:
    """Graphics of an overlay plane: a side marker, an annotation arrow with a label, a scale."""
    rows, cols = geometry.rows, geometry.cols
    canvas = np.zeros((rows, cols), dtype=np.uint8)
    height_px = rows / 30.0 * overlay.font_scale
    scale = height_px / 22.0
    thick = max(1, round(scale * 1.6))
    cv2.putText(canvas, "R", (round(cols * 0.2), round(rows * 0.5)), FONT, scale * 1.5, 255, thick + 1, cv2.LINE_AA)
    tip = (round(cols * 0.55), round(rows * 0.45))
    cv2.arrowedLine(canvas, (round(cols * 0.7), round(rows * 0.3)), tip, 255, thick, cv2.LINE_AA, tipLength=0.2)
    cv2.putText(canvas, "ANEURYSM", (round(cols * 0.62), round(rows * 0.27)), FONT, scale, 255, thick, cv2.LINE_AA)
    cv2.line(canvas, (round(cols * 0.3), round(rows * 0.75)), (round(cols * 0.5), round(rows * 0.75)), 255, thick)
    return canvas >= 128
