"""C-arm bending, dodecahedron calibration and the machine-based registration table.

Sections II.A and II.B of Homan et al.: the angle sensors of a C-arm report only the *nominal*
geometry (:meth:`registration.core.geometry.CArm.nominal`); gravity bends the arm so that the true
source and detector deviate from it by a few millimetres and a small detector tilt, depending
on the angles. A calibration phantom (20 lead spheres at the vertices of a dodecahedron, the
paper's Fig. 1) imaged at a view gives that view's true projection; calibrating a grid of views
20 degrees apart and interpolating between them gives the machine-based registration.

Pieces, each usable alone:

- :class:`BendingModel`: the simulated mechanics (seeded, smooth in the angles) giving the
  true geometry of a nominal view.
- :class:`SpherePhantom`: analytic spheres with exact line integrals (chord lengths); the
  dodecahedron (:meth:`Dodecahedron.spheres`) is one, the FDK tests use others.
- :func:`simulate_sphere_image`, :func:`detect_spheres`, :func:`match_spheres`,
  :func:`calibrate_view`: image, detection (OpenCV connected components, weighted centroids),
  Hungarian matching to the nominally projected vertices, Levenberg-Marquardt estimation of
  the nine deviation parameters of a :class:`~registration.core.geometry.CArm`.
- :class:`CalibrationTable`, :func:`build_calibration_table`, :func:`load_calibration_table`,
  :func:`machine_based_geometry`: the 20-degree grid (``assets/calibration_table.json``) and its
  bilinear interpolation.
- :func:`machine_based_error_mm`: the error measure of ``roadmap3d validate calibration``.
- :func:`calibration_shot`: one calibration view (image, truth, detected spheres) for display.

Conventions (frames, angles, units) are those of ``shared/CONVENTIONS.md``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage
from scipy.optimize import least_squares, linear_sum_assignment

from registration.core.geometry import ASSETS, CArm, rotation_x, rotation_y, rotation_z
from registration.core.volume import MU_WATER_PER_MM

if TYPE_CHECKING:
    pass

Array = NDArray[np.float64]

#: Names of the nine deviation parameters of a true geometry, in vector order.
DEVIATION_NAMES = (
    "source_dx_mm",
    "source_dy_mm",
    "source_dz_mm",
    "detector_dx_mm",
    "detector_dy_mm",
    "detector_dz_mm",
    "detector_tilt_x_deg",
    "detector_tilt_y_deg",
    "detector_tilt_z_deg",
)

#: Seed of the default system's bending (the C-arm that ``assets/calibration_table.json``
#: was measured on).
SYSTEM_BENDING_SEED = 0

#: The 20-degree calibration grid: rotation (primary) x angulation (secondary), degrees.
PRIMARY_GRID_DEG = tuple(float(a) for a in range(-120, 121, 20))
SECONDARY_GRID_DEG = tuple(float(b) for b in range(-60, 61, 20))

#: Image format (cm) and pixels of the calibration views (a fixed detector mode; the
#: deviation parameters are in millimetres and degrees, so they hold for every format).
CALIBRATION_FORMAT_CM = 22.0
CALIBRATION_PIXELS = 512

#: Mean photon count per pixel of a calibration exposure (unattenuated).
CALIBRATION_PHOTONS = 20000.0

TABLE_PATH = ASSETS / "calibration_table.json"

#: Radius (mm) of the iso-center region over which the machine-based error is measured.
ERROR_REGION_RADIUS_MM = 50.0


# --------------------------------------------------------------------------------------
# Deviation parameters <-> CArm
# --------------------------------------------------------------------------------------
def deviation_vector(geometry: CArm) -> Array:
    """The nine deviation parameters (:data:`DEVIATION_NAMES`) of a geometry."""
    return np.array([*geometry.source_shift_mm, *geometry.detector_shift_mm, *geometry.detector_tilt_deg])


def with_deviation(nominal: CArm, deviation: ArrayLike) -> CArm:
    """``nominal`` with its deviation fields set from a 9-vector (:data:`DEVIATION_NAMES`).

    Source and detector shifts are world millimetres; the tilt is in degrees about the view
    frame's axes (see :class:`~registration.core.geometry.CArm`).
    """
    x = np.asarray(deviation, dtype=np.float64).reshape(-1)
    if x.shape != (9,) or not np.all(np.isfinite(x)):
        raise ValueError(f"deviation must be nine finite numbers {DEVIATION_NAMES}, got {deviation}")
    return replace(
        nominal,
        source_shift_mm=tuple(x[0:3]),
        detector_shift_mm=tuple(x[3:6]),
        detector_tilt_deg=tuple(x[6:9]),
    )


# --------------------------------------------------------------------------------------
# C-arm mechanics
# --------------------------------------------------------------------------------------
def _basis(primary_deg: float, secondary_deg: float) -> Array:
    """Smooth angular basis: harmonics up to order 2 in the rotation, 1 in the angulation."""
    a, b = math.radians(primary_deg), math.radians(secondary_deg)
    return np.array(
        [
            1.0,
            math.cos(a),
            math.sin(a),
            math.cos(2 * a),
            math.sin(2 * a),
            math.cos(b),
            math.sin(b),
            math.cos(a) * math.sin(b),
            math.sin(a) * math.sin(b),
        ]
    )


#: Relative weight of each basis function in the random part (higher harmonics smaller).
_BASIS_WEIGHTS = np.array([0.5, 1.0, 1.0, 0.35, 0.35, 0.5, 0.6, 0.4, 0.4])


@dataclass(frozen=True)
class BendingModel:
    """Simulated gravitational bending of a C-arm, fixed per system by ``seed``.

    The deviation of the true from the nominal geometry is, for each of the nine parameters
    (:data:`DEVIATION_NAMES`), a smooth function of the nominal angles:

    - a *gravity sag* of the source and the detector toward the floor (world +y for the supine
      patient), largest when the source-detector axis is horizontal: amplitude x (1 - d_y^2)
      with d the nominal central-ray direction;
    - a seeded random combination of low angular harmonics (:func:`_basis`: up to order 2 in
      the rotation, 1 in the angulation), standing for the arm's and the bearings' compliance.

    Sizes: source shifts up to ~``source_amplitude_mm``, detector shifts up to
    ~``detector_amplitude_mm`` per axis, detector tilts ~0.1-0.5 degrees.
    """

    seed: int = SYSTEM_BENDING_SEED
    source_amplitude_mm: float = 2.0
    detector_amplitude_mm: float = 3.0
    tilt_amplitude_deg: float = 0.3
    _coefficients: Array = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in ("source_amplitude_mm", "detector_amplitude_mm", "tilt_amplitude_deg"):
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"{name} must be finite and >= 0, got {value}")
        rng = np.random.default_rng(np.random.SeedSequence([int(self.seed), 0xC0A4]))
        amplitude = np.array(
            [self.source_amplitude_mm] * 3 + [self.detector_amplitude_mm] * 3 + [self.tilt_amplitude_deg] * 3
        )
        # random part: 9 parameters x 9 basis functions, ~half the amplitude in RMS
        coeffs = rng.normal(size=(9, _BASIS_WEIGHTS.size)) * _BASIS_WEIGHTS
        coeffs *= (0.5 * amplitude / np.sqrt(np.sum(_BASIS_WEIGHTS**2) / 2.0))[:, None]
        object.__setattr__(self, "_coefficients", coeffs)

    def deviation(self, primary_deg: float, secondary_deg: float) -> Array:
        """The nine deviation parameters (:data:`DEVIATION_NAMES`) at nominal angles."""
        if not (math.isfinite(primary_deg) and math.isfinite(secondary_deg)):
            raise ValueError(f"angles must be finite, got {primary_deg}, {secondary_deg}")
        dev = self._coefficients @ _basis(primary_deg, secondary_deg)
        d = CArm(primary_deg=primary_deg, secondary_deg=secondary_deg).direction
        sag = 1.0 - d[1] ** 2  # 0 with a vertical beam, 1 with a horizontal one
        dev[1] += 0.8 * self.source_amplitude_mm * sag
        dev[4] += 0.8 * self.detector_amplitude_mm * sag
        return dev

    def true_geometry(self, nominal: CArm) -> CArm:
        """The true (bent) geometry of a nominal view: same angles, deviation fields set."""
        return with_deviation(nominal, self.deviation(nominal.primary_deg, nominal.secondary_deg))


def default_bending() -> BendingModel:
    """The bending of the default system (seed :data:`SYSTEM_BENDING_SEED`)."""
    return BendingModel(SYSTEM_BENDING_SEED)


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


# --------------------------------------------------------------------------------------
# The machine-based registration table
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CalibrationTable:
    """Deviation parameters measured on a grid of nominal angles, interpolated bilinearly.

    ``deviations[i, j]`` holds the nine parameters (:data:`DEVIATION_NAMES`) at
    ``primary_deg[i]``, ``secondary_deg[j]``.
    """

    primary_deg: Array
    secondary_deg: Array
    deviations: Array
    meta: dict = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        p = np.asarray(self.primary_deg, dtype=np.float64).reshape(-1)
        s = np.asarray(self.secondary_deg, dtype=np.float64).reshape(-1)
        d = np.asarray(self.deviations, dtype=np.float64)
        if p.size < 2 or s.size < 2 or np.any(np.diff(p) <= 0) or np.any(np.diff(s) <= 0):
            raise ValueError("grid angles must be strictly increasing with at least two values per axis")
        if d.shape != (p.size, s.size, 9) or not np.all(np.isfinite(d)):
            raise ValueError(f"deviations must be finite with shape {(p.size, s.size, 9)}, got {d.shape}")
        object.__setattr__(self, "primary_deg", p)
        object.__setattr__(self, "secondary_deg", s)
        object.__setattr__(self, "deviations", d)

    def deviation(self, primary_deg: float, secondary_deg: float) -> Array:
        """Bilinear interpolation of the nine parameters; ValueError outside the grid."""
        p, s = float(primary_deg), float(secondary_deg)
        eps = 1e-9
        if not (self.primary_deg[0] - eps <= p <= self.primary_deg[-1] + eps) or not (
            self.secondary_deg[0] - eps <= s <= self.secondary_deg[-1] + eps
        ):
            raise ValueError(
                f"angles ({p}, {s}) deg lie outside the calibrated range: primary "
                f"{self.primary_deg[0]}..{self.primary_deg[-1]}, secondary "
                f"{self.secondary_deg[0]}..{self.secondary_deg[-1]}"
            )
        i = int(np.clip(np.searchsorted(self.primary_deg, p) - 1, 0, self.primary_deg.size - 2))
        j = int(np.clip(np.searchsorted(self.secondary_deg, s) - 1, 0, self.secondary_deg.size - 2))
        tp = (p - self.primary_deg[i]) / (self.primary_deg[i + 1] - self.primary_deg[i])
        ts = (s - self.secondary_deg[j]) / (self.secondary_deg[j + 1] - self.secondary_deg[j])
        tp, ts = min(max(tp, 0.0), 1.0), min(max(ts, 0.0), 1.0)
        d = self.deviations
        return (
            (1 - tp) * (1 - ts) * d[i, j]
            + tp * (1 - ts) * d[i + 1, j]
            + (1 - tp) * ts * d[i, j + 1]
            + tp * ts * d[i + 1, j + 1]
        )

    def geometry(self, nominal: CArm) -> CArm:
        """The machine-based (calibrated, interpolated) geometry of a nominal view."""
        return with_deviation(nominal.nominal(), self.deviation(nominal.primary_deg, nominal.secondary_deg))

    def to_dict(self) -> dict[str, Any]:
        return {
            "description": (
                "Machine-based registration table: C-arm deviation parameters measured with the "
                "dodecahedron phantom on a grid of nominal angles; interpolate bilinearly."
            ),
            "parameters": list(DEVIATION_NAMES),
            "primary_deg": self.primary_deg.tolist(),
            "secondary_deg": self.secondary_deg.tolist(),
            "deviations": np.round(self.deviations, 5).tolist(),
            "meta": self.meta,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> CalibrationTable:
        try:
            if list(data["parameters"]) != list(DEVIATION_NAMES):
                raise ValueError(f"calibration table parameters {data['parameters']} != {DEVIATION_NAMES}")
            return cls(
                np.array(data["primary_deg"]),
                np.array(data["secondary_deg"]),
                np.array(data["deviations"]),
                meta=dict(data.get("meta", {})),
            )
        except KeyError as exc:
            raise ValueError(f"calibration table lacks the key {exc.args[0]!r}") from None

    def save(self, path: Path | str) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=1) + "\n")


def _view_seed(seed: int, primary_deg: float, secondary_deg: float) -> int:
    """Noise seed of a calibration view: fixed by the angles, whatever grid it belongs to."""
    key = [int(seed), int(round(primary_deg * 1000)) % 2**31, int(round(secondary_deg * 1000)) % 2**31]
    return int(np.random.SeedSequence(key).generate_state(1)[0])


def build_calibration_table(
    bending: BendingModel | None = None,
    *,
    primary_deg: ArrayLike = PRIMARY_GRID_DEG,
    secondary_deg: ArrayLike = SECONDARY_GRID_DEG,
    phantom: Dodecahedron | None = None,
    seed: int = 0,
) -> CalibrationTable:
    """Calibrate every grid view: image the dodecahedron with the true (bent) geometry,
    detect, match and fit (:func:`calibrate_true_view`). Deterministic for a given seed."""
    bending = bending or default_bending()
    phantom = phantom or Dodecahedron()
    p = np.asarray(primary_deg, dtype=np.float64)
    s = np.asarray(secondary_deg, dtype=np.float64)
    dev = np.zeros((p.size, s.size, 9))
    rms = []
    for i, a in enumerate(p):
        for j, b in enumerate(s):
            true = bending.true_geometry(calibration_geometry(a, b))
            result = calibrate_true_view(true, phantom=phantom, seed=_view_seed(seed, a, b))
            dev[i, j] = result.deviation
            rms.append(result.rms_px)
    meta = {
        "bending_seed": bending.seed,
        "noise_seed": seed,
        "format_cm": CALIBRATION_FORMAT_CM,
        "pixels": CALIBRATION_PIXELS,
        "max_rms_px": round(float(np.max(rms)), 4),
    }
    return CalibrationTable(p, s, dev, meta=meta)


_TABLES: dict[str, CalibrationTable] = {}


def load_calibration_table(path: Path | str | None = None) -> CalibrationTable:
    """The machine-based registration table (default ``assets/calibration_table.json``)."""
    key = str(path or TABLE_PATH)
    if key not in _TABLES:
        p = Path(key)
        if not p.exists():
            raise ValueError(f"calibration table {p} not found; build it with build_calibration_table().save(path)")
        _TABLES[key] = CalibrationTable.from_dict(json.loads(p.read_text()))
    return _TABLES[key]


def machine_based_geometry(
    primary_deg: float,
    secondary_deg: float,
    *,
    image_format_cm: float = 27.0,
    pixels: int = 512,
    nominal: CArm | None = None,
    table: CalibrationTable | None = None,
) -> CArm:
    """The machine-based registration: the geometry the calibration table predicts for the
    nominal angles, on the detector of ``nominal`` (default: ``image_format_cm``, ``pixels``)."""
    if nominal is None:
        nominal = CArm.for_format(image_format_cm, pixels=pixels)
    nominal = nominal.with_angles(primary_deg, secondary_deg)
    return (table or load_calibration_table()).geometry(nominal)


# --------------------------------------------------------------------------------------
# The error measure
# --------------------------------------------------------------------------------------
def _fibonacci_sphere(n: int) -> Array:
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    r = np.sqrt(1.0 - z * z)
    theta = math.pi * (1.0 + math.sqrt(5.0)) * k
    return np.column_stack([r * np.cos(theta), r * np.sin(theta), z])


def error_region_points(radius_mm: float = ERROR_REGION_RADIUS_MM) -> Array:
    """The iso-center, 100 points on the sphere of ``radius_mm`` and 50 on half that radius."""
    return np.vstack([np.zeros((1, 3)), radius_mm * _fibonacci_sphere(100), 0.5 * radius_mm * _fibonacci_sphere(50)])


def machine_based_error_mm(true: CArm, estimate: CArm, *, radius_mm: float = ERROR_REGION_RADIUS_MM) -> float:
    """Displacement at the iso-center region between two geometries of one view, in mm.

    For the iso-center and points filling a sphere of ``radius_mm`` around it
    (:func:`error_region_points`), the distance on the detector between their projections with
    ``true`` and with ``estimate`` is scaled back to the iso-center plane (divided by the
    nominal magnification SID/SOD); the error is the largest of these distances. It is the
    misregistration a machine-based overlay shows for anatomy near the iso-center.
    """
    if (true.rows, true.cols, true.pixel_mm) != (estimate.rows, estimate.cols, estimate.pixel_mm):
        raise ValueError("true and estimate must share the detector (rows, cols, pixel_mm)")
    pts = error_region_points(radius_mm) + np.asarray(true.isocenter_mm)
    diff_px = true.project(pts) - estimate.project(pts)
    diff_mm = diff_px * np.array([true.pixel_mm[1], true.pixel_mm[0]])
    return float(np.max(np.linalg.norm(diff_mm, axis=1)) / true.magnification)


def calibration_study(*, samples: int = 50, seed: int = 0, table: CalibrationTable | None = None) -> dict[str, Any]:
    """Machine-based registration error at random nominal angles (uniform over the table's
    range) against the true geometry of the default system's bending."""
    if samples < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    table = table or load_calibration_table()
    bending = BendingModel(int(table.meta.get("bending_seed", SYSTEM_BENDING_SEED)))
    rng = np.random.default_rng(seed)
    records = []
    for _ in range(samples):
        a = float(rng.uniform(table.primary_deg[0], table.primary_deg[-1]))
        b = float(rng.uniform(table.secondary_deg[0], table.secondary_deg[-1]))
        nominal = CArm.for_format(27.0, primary_deg=a, secondary_deg=b)
        true = bending.true_geometry(nominal)
        uncorrected = machine_based_error_mm(true, nominal)
        error = machine_based_error_mm(true, table.geometry(nominal))
        records.append({"primary_deg": a, "secondary_deg": b, "error_mm": error, "uncorrected_mm": uncorrected})
    errors = [r["error_mm"] for r in records]
    return {
        "errors_mm": errors,
        "median_mm": float(np.median(errors)),
        "max_mm": float(np.max(errors)),
        "uncorrected_median_mm": float(np.median([r["uncorrected_mm"] for r in records])),
        "records": records,
        "region_radius_mm": ERROR_REGION_RADIUS_MM,
        "target_mm": 0.2,
    }


