"""What reaches the detector besides the primary beam: collimator blades, scatter, the heel effect.

Applied to the mean transmission frame before the exposure control and the quantum noise
(:func:`registration.sim.xray.simulate_xray`'s ``detector_effects``), so that the noise behind a
blade and on the scatter background is the photons' own.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from registration.core.geometry import CArm
from registration.sim.clinical.effects import Blades, Heel, Scatter

#: Fraction of the field's diameter (centered) over which the scatter-to-primary ratio is set.
SPR_FIELD_FRACTION = 0.5


def _field_coordinates(geometry: CArm) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """Pixel offsets from the field center (rows, cols) in pixels and the field radius in pixels."""
    rows, cols = geometry.rows, geometry.cols
    y = (np.arange(rows) - (rows - 1) / 2.0)[:, None] * np.ones((1, cols))
    x = (np.arange(cols) - (cols - 1) / 2.0)[None, :] * np.ones((rows, 1))
    radius = geometry.field_diameter_mm / 2.0 / float(min(geometry.pixel_mm))
    return y, x, radius


def _edge(distance_px: NDArray[np.float64], penumbra_px: float) -> NDArray[np.float64]:
    """1 on the open side (distance > 0), 0 behind the blade, a penumbra of ``penumbra_px``."""
    if penumbra_px <= 0:
        return (distance_px > 0).astype(np.float64)
    return 0.5 * (1.0 + np.tanh(distance_px / penumbra_px))


def blade_maps(geometry: CArm, blades: Blades) -> tuple[NDArray[np.float64], NDArray[np.bool_], dict]:
    """(transmission factor per pixel, the open field (no blade, no wedge), where the edges are).

    Rectangular blades close ``closed`` of the field's half-width from each side, turned by
    ``rotation_deg``; the wedge closes ``wedge_closed`` of the field's diameter from the side at
    ``wedge_side_deg`` (0: the right, counter-clockwise on the screen); the iris keeps
    ``iris_fraction`` of the radius."""
    y, x, radius = _field_coordinates(geometry)
    factor = np.ones_like(x)
    open_field = np.ones(x.shape, dtype=bool)
    edges: dict = {"radius_px": radius}
    if "rectangular" in blades.shapes:
        a = math.radians(blades.rotation_deg)
        u = x * math.cos(a) + y * math.sin(a)  # along the turned columns
        v = -x * math.sin(a) + y * math.cos(a)  # along the turned rows
        left, right, top, bottom = (radius * (1.0 - c) for c in blades.closed)
        inside = np.ones_like(x)
        for dist in (u + left, right - u, v + top, bottom - v):
            inside *= _edge(dist, blades.penumbra_px)
        factor *= blades.transmission + (1.0 - blades.transmission) * inside
        open_field &= (u > -left) & (u < right) & (v > -top) & (v < bottom)
        edges["rectangle"] = {"left": -left, "right": right, "top": -top, "bottom": bottom,
                              "rotation_deg": blades.rotation_deg}  # fmt: skip
    if "wedge" in blades.shapes and blades.wedge_closed > 0:
        a = math.radians(blades.wedge_side_deg)
        # distance from the wedge's edge, positive toward the field's center (screen: up is -row)
        along = x * math.cos(a) - y * math.sin(a)
        edge_at = radius * (1.0 - 2.0 * blades.wedge_closed)
        inside = _edge(edge_at - along, blades.penumbra_px)
        factor *= blades.wedge_transmission + (1.0 - blades.wedge_transmission) * inside
        open_field &= along < edge_at
        edges["wedge"] = {"edge_px": edge_at, "side_deg": blades.wedge_side_deg}
    if "circular" in blades.shapes:
        r_iris = radius * blades.iris_fraction
        inside = _edge(r_iris - np.hypot(x, y), blades.penumbra_px)
        factor *= blades.transmission + (1.0 - blades.transmission) * inside
        open_field &= np.hypot(x, y) < r_iris
        edges["iris_radius_px"] = r_iris
    return factor, open_field, edges


def scatter_background(primary: NDArray[np.float64], field: NDArray[np.bool_], geometry: CArm,
                       scatter: Scatter) -> NDArray[np.float64]:  # fmt: skip
    """The scatter behind the grid: ``primary`` (collimated) blurred by a Gaussian of
    ``kernel_mm``, scaled to ``spr`` times the primary over the central field."""
    sigma_px = scatter.kernel_mm / float(min(geometry.pixel_mm))
    # blur a 4x-reduced frame (the kernel spans tens of pixels), then back to full size
    f = 4 if min(primary.shape) >= 64 else 1
    rows, cols = primary.shape
    pr, pc = (-rows) % f, (-cols) % f
    padded = np.pad(primary, ((0, pr), (0, pc)))
    small = padded.reshape(padded.shape[0] // f, f, padded.shape[1] // f, f).mean(axis=(1, 3))
    blurred = ndimage.gaussian_filter(small, sigma_px / f, mode="constant")
    shape = blurred.shape
    up = ndimage.zoom(blurred, (padded.shape[0] / shape[0], padded.shape[1] / shape[1]), order=1)[:rows, :cols]
    y, x, radius = _field_coordinates(geometry)
    central = field & (np.hypot(x, y) <= SPR_FIELD_FRACTION * radius)
    if not central.any():
        central = field
    p, s = float(primary[central].mean()), float(up[central].mean())
    if s <= 0 or scatter.spr == 0:
        return np.zeros_like(primary)
    return up * (scatter.spr * p / s)


def heel_factor(geometry: CArm, heel: Heel) -> NDArray[np.float64]:
    """Intensity factor of the heel effect: 1 at the field center, ``1 -+ tilt / 2`` at its edges."""
    y, x, radius = _field_coordinates(geometry)
    a = math.radians(heel.direction_deg)
    along = (x * math.cos(a) + y * math.sin(a)) / (2.0 * radius)
    return np.clip(1.0 + heel.tilt * along, 0.05, None)


class DetectorEffects:
    """The ``detector_effects`` callable for :func:`registration.sim.xray.simulate_xray`."""

    def __init__(self, geometry: CArm, *, blades: Blades | None, scatter: Scatter | None, heel: Heel | None) -> None:
        self.geometry = geometry
        self.blades, self.scatter, self.heel = blades, scatter, heel
        self.open_field = np.ones((geometry.rows, geometry.cols), dtype=bool)
        self.edges: dict = {}
        self.spr_measured: float | None = None

    def __call__(self, transmission: NDArray[np.float64], field: NDArray[np.bool_]) -> NDArray[np.float64]:
        primary = transmission
        if self.blades is not None:
            factor, self.open_field, self.edges = blade_maps(self.geometry, self.blades)
            primary = primary * factor
        total = primary
        if self.scatter is not None and self.scatter.spr > 0:
            background = scatter_background(primary, field, self.geometry, self.scatter)
            total = primary + background
            y, x, radius = _field_coordinates(self.geometry)
            central = field & (np.hypot(x, y) <= SPR_FIELD_FRACTION * radius)
            central = central if central.any() else field
            self.spr_measured = float(background[central].mean() / primary[central].mean())
        if self.heel is not None:
            total = total * heel_factor(self.geometry, self.heel)
        return np.where(field, total, 0.0)
