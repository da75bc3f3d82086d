"""The dodecahedron calibration phantom: imaging it, finding its spheres, fitting a view's geometry.

The paper's Fig. 1: 20 lead spheres at the vertices of a dodecahedron (one larger marker),
imaged at a view, give that view's true projection. :class:`SpherePhantom` holds analytic
spheres with exact line integrals (the dodecahedron is one, the FDK tests use others);
:func:`simulate_sphere_image`, :func:`detect_spheres` (OpenCV connected components, weighted
centroids), :func:`match_spheres` (Hungarian matching to the nominally projected vertices) and
:func:`calibrate_view` (Levenberg-Marquardt over the nine deviation parameters of
:mod:`registration.sim.bending`) calibrate one view; :func:`calibration_shot` is one view for
display.

Conventions (frames, angles, units) are those of ``shared/CONVENTIONS.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage
from scipy.optimize import least_squares, linear_sum_assignment

from registration.core.geometry import CArm, rotation_x, rotation_y, rotation_z
from registration.core.volume import MU_WATER_PER_MM
from registration.sim.bending import (
    BendingModel,
    default_bending,
    deviation_vector,
    machine_based_error_mm,
    with_deviation,
)

Array = NDArray[np.float64]

#: Image format (cm) and pixels of the calibration views (a fixed detector mode; the
#: deviation parameters are in millimetres and degrees, so they hold for every format).
CALIBRATION_FORMAT_CM = 22.0
CALIBRATION_PIXELS = 512

#: Mean photon count per pixel of a calibration exposure (unattenuated).
CALIBRATION_PHOTONS = 20000.0


# --------------------------------------------------------------------------------------
# Analytic spheres
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SpherePhantom:
    """Uniform spheres with exact line integrals (chord length x attenuation).

    ``mu_per_mm`` is each sphere's attenuation *added* to what lies around it, so a bead inside
    a water sphere has ``mu_bead - mu_water``. Centers in world mm.
    """

    centers_mm: Array
    radii_mm: Array
    mu_per_mm: Array

    def __post_init__(self) -> None:
        c = np.asarray(self.centers_mm, dtype=np.float64).reshape(-1, 3)
        r = np.asarray(self.radii_mm, dtype=np.float64).reshape(-1)
        mu = np.broadcast_to(np.asarray(self.mu_per_mm, dtype=np.float64), r.shape).copy()
        if c.shape[0] != r.shape[0]:
            raise ValueError(f"{c.shape[0]} centers but {r.shape[0]} radii")
        if not (np.all(np.isfinite(c)) and np.all(np.isfinite(r)) and np.all(np.isfinite(mu))):
            raise ValueError("sphere centers, radii and attenuations must be finite")
        if np.any(r <= 0):
            raise ValueError(f"sphere radii must be positive, got {r.tolist()}")
        object.__setattr__(self, "centers_mm", c)
        object.__setattr__(self, "radii_mm", r)
        object.__setattr__(self, "mu_per_mm", mu)

    def line_integrals(self, sources: ArrayLike, targets: ArrayLike) -> NDArray[np.float32]:
        """Integral of attenuation (dimensionless) along segments source -> target, shape (...)."""
        s = np.asarray(sources, dtype=np.float64)
        t = np.asarray(targets, dtype=np.float64)
        s, t = np.broadcast_arrays(s, t)
        shape = s.shape[:-1]
        s = s.reshape(-1, 3)
        t = t.reshape(-1, 3)
        seg = t - s
        length = np.linalg.norm(seg, axis=1)
        e = seg / length[:, None]
        out = np.zeros(s.shape[0])
        for center, radius, mu in zip(self.centers_mm, self.radii_mm, self.mu_per_mm, strict=True):
            w = center - s
            along = np.einsum("ij,ij->i", w, e)
            d2 = np.einsum("ij,ij->i", w, w) - along * along
            half = np.sqrt(np.maximum(radius * radius - d2, 0.0))
            # clip the chord to the segment (spheres lie between source and detector in practice)
            lo = np.clip(along - half, 0.0, length)
            hi = np.clip(along + half, 0.0, length)
            out += mu * (hi - lo)
        return out.reshape(shape).astype(np.float32)

    def subset(self, index: ArrayLike) -> SpherePhantom:
        """The spheres selected by ``index``."""
        idx = np.asarray(index)
        return SpherePhantom(self.centers_mm[idx], self.radii_mm[idx], self.mu_per_mm[idx])

    def hu_at(self, points_mm: ArrayLike, *, mu_water_per_mm: float = MU_WATER_PER_MM) -> NDArray[np.float32]:
        """Hounsfield units at world points (air -1000 outside every sphere)."""
        p = np.asarray(points_mm, dtype=np.float64)
        mu = np.zeros(p.shape[:-1])
        for center, radius, m in zip(self.centers_mm, self.radii_mm, self.mu_per_mm, strict=True):
            mu += m * (np.sum((p - center) ** 2, axis=-1) <= radius * radius)
        return (1000.0 * (mu / mu_water_per_mm - 1.0)).astype(np.float32)


#: Linear attenuation of lead at the calibration's effective energy (~60 keV), 1/mm.
LEAD_MU_PER_MM = 5.0


@dataclass(frozen=True)
class Dodecahedron:
    """The calibration phantom (the paper's Fig. 1): lead spheres at a dodecahedron's vertices.

    20 spheres of ``sphere_diameter_mm`` on a regular dodecahedron of ``circumradius_mm``
    centered at the iso-center, turned by ``orientation_deg`` (Rz @ Ry @ Rx, degrees): chosen
    by a random search so that in every view of the calibration grid and of the propeller arc
    at least 14 spheres project clear of all others. Vertex 0 carries a larger sphere
    (``marker_diameter_mm``): the regular dodecahedron has 120 symmetries, the marker breaks
    them so the phantom's pose is unique in any single image (the paper's "uniquely
    determined"); our matching uses the nominal projection and checks the marker.
    """

    circumradius_mm: float = 40.0
    sphere_diameter_mm: float = 2.5
    marker_diameter_mm: float = 4.0
    mu_per_mm: float = LEAD_MU_PER_MM
    orientation_deg: tuple[float, float, float] = (135.5, 79.1, 105.9)

    def __post_init__(self) -> None:
        if not (0 < self.sphere_diameter_mm < self.circumradius_mm):
            raise ValueError(
                f"sphere_diameter_mm must be positive and below circumradius_mm, got "
                f"{self.sphere_diameter_mm} and {self.circumradius_mm}"
            )
        if self.marker_diameter_mm <= 0:
            raise ValueError(f"marker_diameter_mm must be positive, got {self.marker_diameter_mm}")

    @property
    def vertices_mm(self) -> Array:
        """The 20 sphere centers in world mm, shape (20, 3); vertex 0 carries the marker."""
        phi = (1.0 + math.sqrt(5.0)) / 2.0
        pts = [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
        for s1 in (-1, 1):
            for s2 in (-1, 1):
                pts += [(0.0, s1 / phi, s2 * phi), (s1 / phi, s2 * phi, 0.0), (s1 * phi, 0.0, s2 / phi)]
        v = np.array(pts, dtype=np.float64) * (self.circumradius_mm / math.sqrt(3.0))
        ox, oy, oz = self.orientation_deg
        rot = rotation_z(oz) @ rotation_y(oy) @ rotation_x(ox)
        return v @ rot.T

    @property
    def radii_mm(self) -> Array:
        r = np.full(20, self.sphere_diameter_mm / 2.0)
        r[0] = self.marker_diameter_mm / 2.0
        return r

    def spheres(self) -> SpherePhantom:
        return SpherePhantom(self.vertices_mm, self.radii_mm, np.full(20, self.mu_per_mm))


# --------------------------------------------------------------------------------------
# Images of spheres
# --------------------------------------------------------------------------------------
def simulate_sphere_image(
    phantom: SpherePhantom,
    geometry: CArm,
    *,
    supersample: int = 2,
    photons: float | None = None,
    blur_px: float = 0.0,
    background: float = 0.0,
    seed: int = 0,
    full_frame: bool = False,
) -> NDArray[np.float32]:
    """Attenuation image (CONVENTIONS §5: -log(I/I0)) of spheres seen by ``geometry``.

    Exact line integrals from the source to ``supersample`` x ``supersample`` points per pixel
    (averaged as intensities, as a detector pixel does); ``background`` adds a uniform
    attenuation (the phantom's holder); ``photons`` (unattenuated counts per pixel) adds Poisson
    quantum noise, ``blur_px`` a Gaussian detector blur (sigma, pixels). Only pixels near the
    spheres' projections are traced unless ``full_frame``; elsewhere the image is ``background``.
    The collimated field is not applied (callers mask).
    """
    if supersample < 1 or int(supersample) != supersample:
        raise ValueError(f"supersample must be a positive integer, got {supersample}")
    if photons is not None and not photons > 0:
        raise ValueError(f"photons must be positive, got {photons}")
    rows, cols = geometry.rows, geometry.cols
    transmitted = np.full((rows, cols), math.exp(-background))
    source = geometry.source_mm
    offs = (np.arange(supersample) + 0.5) / supersample - 0.5
    everything = np.arange(phantom.radii_mm.size)
    boxes: list[tuple[int, int, int, int, NDArray[np.int64]]] = []
    if full_frame:
        boxes.append((0, rows, 0, cols, everything))
    else:
        centers = geometry.project(phantom.centers_mm)
        dist = np.linalg.norm(phantom.centers_mm - source, axis=1)
        mag = geometry.sid_mm / np.maximum(dist, 1e-6)
        rad_px = phantom.radii_mm * mag / min(geometry.pixel_mm) * 1.05 + 3.0
        for (c, r), rp in zip(centers, rad_px, strict=True):
            r0, r1 = max(int(math.floor(r - rp)), 0), min(int(math.ceil(r + rp)) + 1, rows)
            c0, c1 = max(int(math.floor(c - rp)), 0), min(int(math.ceil(c + rp)) + 1, cols)
            if r1 > r0 and c1 > c0:
                # spheres whose projected disc reaches this box
                near = (
                    (centers[:, 0] + rad_px > c0)
                    & (centers[:, 0] - rad_px < c1)
                    & (centers[:, 1] + rad_px > r0)
                    & (centers[:, 1] - rad_px < r1)
                )
                boxes.append((r0, r1, c0, c1, np.flatnonzero(near)))
    done = np.zeros((rows, cols), dtype=bool)
    for r0, r1, c0, c1, which in boxes:
        sub_phantom = phantom if which.size == everything.size else phantom.subset(which)
        sub_done = done[r0:r1, c0:c1]
        rr, cc = np.mgrid[r0:r1, c0:c1]
        grid_c = (cc[None, None] + offs[None, :, None, None]).repeat(supersample, axis=0)
        grid_r = (rr[None, None] + offs[:, None, None, None]).repeat(supersample, axis=1)
        targets = geometry.pixel_to_world(grid_c, grid_r)
        acc = np.exp(-sub_phantom.line_integrals(source, targets).astype(np.float64)).mean(axis=(0, 1))
        sub = transmitted[r0:r1, c0:c1]
        sub[~sub_done] = (acc * math.exp(-background))[~sub_done]
        sub_done[:] = True
    if photons is not None:
        rng = np.random.default_rng(seed)
        counts = rng.poisson(transmitted * photons).astype(np.float64)
        transmitted = np.maximum(counts, 0.5) / photons
    line = -np.log(np.clip(transmitted, 1e-12, None))
    if blur_px > 0:
        line = ndimage.gaussian_filter(line, blur_px, mode="nearest")
    return line.astype(np.float32)


# --------------------------------------------------------------------------------------
# Detection and matching
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DetectedSpheres:
    """Blobs found in an image: subpixel centers (col, row), areas (px) and summed signal."""

    centers_px: Array
    areas_px: Array
    mass: Array

    def __len__(self) -> int:
        return int(self.centers_px.shape[0])


def detect_spheres(
    image: ArrayLike,
    *,
    mask: ArrayLike | None = None,
    threshold: float | None = None,
    min_area_px: int = 3,
) -> DetectedSpheres:
    """Find the bright (attenuating) blobs of small spheres in an attenuation image.

    The background (median inside ``mask``) is subtracted; pixels above ``threshold`` (default:
    half of the robust maximum above background) form blobs through
    ``cv2.connectedComponentsWithStats``; each blob's center is the signal-weighted centroid
    over its bounding box grown by two pixels (subpixel accurate for round blobs).
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"image must be 2-D, got shape {img.shape}")
    m = np.ones(img.shape, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    if m.shape != img.shape:
        raise ValueError(f"mask shape {m.shape} differs from image shape {img.shape}")
    if not m.any():
        raise ValueError("mask is empty: no pixel to search")
    signal = np.where(m, img - np.median(img[m]), 0.0)
    if threshold is None:
        top = np.percentile(signal[m], 99.95)
        threshold = 0.5 * top
    if threshold <= 0:
        return DetectedSpheres(np.zeros((0, 2)), np.zeros(0), np.zeros(0))
    binary = (signal > threshold).astype(np.uint8)
    count, _labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
    centers, areas, masses = [], [], []
    rows, cols = img.shape
    for label in range(1, count):
        x, y, w, h, area = (int(v) for v in stats[label])
        if area < min_area_px:
            continue
        r0, r1 = max(y - 2, 0), min(y + h + 2, rows)
        c0, c1 = max(x - 2, 0), min(x + w + 2, cols)
        patch = np.clip(signal[r0:r1, c0:c1], 0.0, None)
        total = patch.sum()
        if total <= 0:
            continue
        rr, cc = np.mgrid[r0:r1, c0:c1]
        centers.append(((patch * cc).sum() / total, (patch * rr).sum() / total))
        areas.append(area)
        masses.append(total)
    return DetectedSpheres(np.array(centers).reshape(-1, 2), np.array(areas, float), np.array(masses, float))


def match_spheres(
    detected_px: ArrayLike,
    predicted_px: ArrayLike,
    radii_px: ArrayLike,
    *,
    gate_px: float,
    margin_px: float = 3.0,
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Pair detected blobs with predicted vertex projections (Hungarian assignment).

    A vertex is *isolated* when its predicted disc (``radii_px``) stays ``margin_px`` clear of
    every other vertex's; the others are left out (their blobs may merge, their identity is
    ambiguous), and so is a detection that lies close to one of them. Pairs farther apart
    than ``gate_px`` are rejected. Returns (vertex indices, detection indices).
    """
    det = np.asarray(detected_px, dtype=np.float64).reshape(-1, 2)
    pred = np.asarray(predicted_px, dtype=np.float64).reshape(-1, 2)
    rad = np.broadcast_to(np.asarray(radii_px, dtype=np.float64), (pred.shape[0],))
    if det.shape[0] == 0 or pred.shape[0] == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    clear = np.linalg.norm(pred[:, None] - pred[None], axis=2) - (rad[:, None] + rad[None] + margin_px)
    np.fill_diagonal(clear, np.inf)
    isolated = np.flatnonzero(clear.min(axis=1) > 0)
    crowded = np.setdiff1d(np.arange(pred.shape[0]), isolated)
    if isolated.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    cost = np.linalg.norm(pred[isolated, None] - det[None], axis=2)
    vi, di = linear_sum_assignment(cost)
    keep = cost[vi, di] <= gate_px
    if crowded.size:
        near = np.linalg.norm(det[di][:, None] - pred[crowded][None], axis=2) - rad[crowded][None]
        keep &= near.min(axis=1) > rad[isolated[vi]] + margin_px
    return isolated[vi[keep]].astype(np.int64), di[keep].astype(np.int64)


# --------------------------------------------------------------------------------------
# One view's calibration
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ViewCalibration:
    """The estimated true geometry of one view and how well it fits."""

    geometry: CArm
    rms_px: float
    spheres_used: int
    detected: DetectedSpheres
    vertex_index: NDArray[np.int64]
    detection_index: NDArray[np.int64]
    marker_found: bool

    @property
    def deviation(self) -> Array:
        return deviation_vector(self.geometry)


#: Scale of the weak prior that keeps poorly observed deviation combinations near zero
#: (mm for shifts, degrees for tilts) and its weight in pixels of residual per scale unit.
_PRIOR_SCALE = np.array([20.0, 20.0, 20.0, 20.0, 20.0, 20.0, 2.0, 2.0, 2.0])
_PRIOR_WEIGHT_PX = 0.02


def calibrate_view(
    image: ArrayLike,
    nominal: CArm,
    *,
    phantom: Dodecahedron | None = None,
    mask: ArrayLike | None = None,
    gate_mm: float = 12.0,
    max_rms_px: float = 0.5,
) -> ViewCalibration:
    """Estimate a view's true geometry from its image of the dodecahedron phantom.

    The spheres are detected (:func:`detect_spheres`), matched to the vertices projected with
    the nominal geometry (:func:`match_spheres`, gate ``gate_mm`` at the detector), and the
    nine deviation parameters (:data:`DEVIATION_NAMES`) are found by Levenberg-Marquardt
    (``scipy.optimize.least_squares``) minimising the reprojection error in pixels with a weak
    prior toward the nominal geometry. Matches off by more than 3 x the median residual (and
    > 0.5 px) are dropped and the fit repeated once. Raises ValueError when fewer than seven
    spheres can be used (the fit would be under-determined) or when the final reprojection
    RMS exceeds ``max_rms_px`` (the blobs are not the phantom's spheres).
    """
    phantom = phantom or Dodecahedron()
    img = np.asarray(image, dtype=np.float64)
    if img.shape != (nominal.rows, nominal.cols):
        raise ValueError(f"image shape {img.shape} differs from the geometry's {nominal.rows}x{nominal.cols}")
    nominal = nominal.nominal()
    vertices = phantom.vertices_mm
    det = detect_spheres(img, mask=mask)
    predicted = nominal.project(vertices)
    pix = min(nominal.pixel_mm)
    radii_px = phantom.radii_mm * nominal.magnification / pix
    vi, di = match_spheres(det.centers_px, predicted, radii_px, gate_px=gate_mm / pix)
    if vi.size < 7:
        raise ValueError(
            f"only {vi.size} calibration spheres could be matched (need 7): is the dodecahedron "
            "in the image and the nominal geometry right?"
        )
    observed = det.centers_px[di]

    def residuals(x: Array, idx: NDArray[np.int64], obs: Array) -> Array:
        geom = with_deviation(nominal, x)
        r = (geom.project(vertices[idx]) - obs).ravel()
        return np.concatenate([r, _PRIOR_WEIGHT_PX * x / _PRIOR_SCALE])

    x = np.zeros(9)
    for _ in range(2):
        fit = least_squares(residuals, x, args=(vi, observed), method="lm", x_scale=_PRIOR_SCALE / 10)
        x = fit.x
        err = np.linalg.norm(fit.fun[: 2 * vi.size].reshape(-1, 2), axis=1)
        bad = err > max(3.0 * np.median(err), 0.5)
        if not bad.any() or (~bad).sum() < 7:
            break
        vi, di, observed = vi[~bad], di[~bad], observed[~bad]
    geom = with_deviation(nominal, x)
    err = np.linalg.norm(geom.project(vertices[vi]) - observed, axis=1)
    rms = float(np.sqrt(np.mean(err**2)))
    if rms > max_rms_px:
        raise ValueError(
            f"calibration failed: reprojection RMS {rms:.2f} px over {vi.size} spheres exceeds "
            f"{max_rms_px} px (is this an image of the dodecahedron phantom?)"
        )
    marker = bool(det.areas_px.size and 0 in vi and di[list(vi).index(0)] == int(np.argmax(det.areas_px)))
    return ViewCalibration(
        geometry=geom,
        rms_px=rms,
        spheres_used=int(vi.size),
        detected=det,
        vertex_index=vi,
        detection_index=di,
        marker_found=marker,
    )


def calibration_geometry(primary_deg: float, secondary_deg: float) -> CArm:
    """The nominal geometry of a calibration view (:data:`CALIBRATION_FORMAT_CM`)."""
    return CArm.for_format(
        CALIBRATION_FORMAT_CM, pixels=CALIBRATION_PIXELS, primary_deg=primary_deg, secondary_deg=secondary_deg
    )


def simulate_calibration_image(
    true_geometry: CArm, *, phantom: Dodecahedron | None = None, seed: int = 0
) -> NDArray[np.float32]:
    """An exposure of the dodecahedron with the true geometry: exact chords through the lead
    spheres, 2x2 supersampled pixels, 10 mm of acrylic holder, Poisson noise at
    :data:`CALIBRATION_PHOTONS` and a 0.6-pixel Gaussian detector blur."""
    phantom = phantom or Dodecahedron()
    return simulate_sphere_image(
        phantom.spheres(),
        true_geometry,
        supersample=2,
        photons=CALIBRATION_PHOTONS,
        blur_px=0.6,
        background=0.2,
        seed=seed,
    )


def calibrate_true_view(true_geometry: CArm, *, phantom: Dodecahedron | None = None, seed: int = 0) -> ViewCalibration:
    """Image the dodecahedron with ``true_geometry`` and calibrate from that image alone.

    The estimate sees only the image and the nominal angles; the returned geometry has
    ``true_geometry``'s detector (rows, cols, pixel size).
    """
    phantom = phantom or Dodecahedron()
    cal_nominal = calibration_geometry(true_geometry.primary_deg, true_geometry.secondary_deg)
    true_cal = with_deviation(cal_nominal, deviation_vector(true_geometry))
    image = simulate_calibration_image(true_cal, phantom=phantom, seed=seed)
    result = calibrate_view(image, cal_nominal, phantom=phantom, mask=cal_nominal.field_mask())
    geometry = with_deviation(true_geometry.nominal(), result.deviation)
    return replace(result, geometry=geometry)


@dataclass(frozen=True)
class CalibrationShot:
    """One calibration view for display: the image, the truth and what calibration found."""

    image: NDArray[np.float32]
    mask: NDArray[np.bool_]
    nominal: CArm
    true: CArm
    calibration: ViewCalibration

    @property
    def error_mm(self) -> float:
        """:func:`machine_based_error_mm` of the calibrated geometry against the truth."""
        return machine_based_error_mm(self.true, self.calibration.geometry)


def calibration_shot(
    primary_deg: float,
    secondary_deg: float = 0.0,
    *,
    bending: BendingModel | None = None,
    phantom: Dodecahedron | None = None,
    seed: int = 0,
) -> CalibrationShot:
    """Image the dodecahedron at nominal angles with the true (bent) geometry and calibrate
    that view (for the app's calibration view and for figures): the detected spheres are
    ``shot.calibration.detected``, the vertices used ``shot.calibration.vertex_index``."""
    bending = bending or default_bending()
    phantom = phantom or Dodecahedron()
    nominal = calibration_geometry(primary_deg, secondary_deg)
    true = bending.true_geometry(nominal)
    image = simulate_calibration_image(true, phantom=phantom, seed=seed)
    mask = nominal.field_mask()
    result = calibrate_view(image, nominal, phantom=phantom, mask=mask)
    return CalibrationShot(np.where(mask, image, 0.0).astype(np.float32), mask, nominal, true, result)
