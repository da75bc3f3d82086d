"""Honest X-ray image formation from the analytic phantom (DESIGN.md, "honest simulation").

:func:`simulate_xray` never touches a voxel volume or the DRR renderer: every pixel is the
exact line integral of attenuation through :class:`registration.sim.phantom.HeadPhantom` from the
(true, possibly bent) source to the pixel, averaged over sub-pixel rays in intensity,
attenuated by Beer-Lambert, counted with Poisson quantum noise at a fluoroscopy or exposure dose,
blurred by the detector, log-transformed back to an attenuation line integral (CONVENTIONS §5:
larger = more attenuation) and collimated to the circular image format. A catheter and guidewire
that the 3DRA does not contain can be added.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike
from scipy import ndimage

from registration.core.geometry import CArm, check_rigid
from registration.core.images import XRayImage
from registration.core.volume import MU_WATER_PER_MM
from registration.sim.phantom_shapes import HeadPhantom, PhantomBuilder

#: Photons per pixel reaching the detector behind the head (the automatic exposure control's
#: target, measured over the central part of the field) for a fluoroscopy frame.
FLUORO_PHOTONS_PER_PIXEL = 600.0
#: The same for a single exposure (acquisition) frame: 20x the fluoroscopy dose.
EXPOSURE_PHOTONS_PER_PIXEL = 12000.0
#: Dose per image kind.
PHOTONS_PER_PIXEL = {"fluoro": FLUORO_PHOTONS_PER_PIXEL, "exposure": EXPOSURE_PHOTONS_PER_PIXEL}
#: Fraction of the field diameter (centered) over which the exposure control measures.
AEC_FIELD_FRACTION = 0.5
#: Detector point spread function: Gaussian sigma in pixels (scintillator light spread).
DETECTOR_BLUR_PX = 0.8
#: Sub-pixel rays per pixel along each axis (the detector integrates over the pixel area).
SUPERSAMPLE = 2
#: Electronic (read-out) noise, standard deviation in photon equivalents.
ELECTRONIC_NOISE_PHOTONS = 1.5
#: Fewest photons a pixel may hold before the log transform (keeps the logarithm finite).
MIN_PHOTONS = 1.0

# Interventional devices (attenuation at the effective energy of the phantom, 1/mm).
#: Guide catheter (braided polymer, 6 F): outer and inner radius (mm) and attenuation.
CATHETER_OUTER_RADIUS_MM = 1.0
CATHETER_INNER_RADIUS_MM = 0.7
CATHETER_MU_PER_MM = 0.06
#: Guidewire (0.014 inch): radius, shaft (steel/nitinol) and radiopaque platinum tip.
GUIDEWIRE_RADIUS_MM = 0.18
GUIDEWIRE_MU_PER_MM = 1.0
GUIDEWIRE_TIP_MU_PER_MM = 7.0
GUIDEWIRE_TIP_MM = 30.0


class Attenuator(Protocol):
    """Anything whose attenuation line integrals an image can be formed from."""

    key: dict

    def line_integrals(
        self, sources_mm: ArrayLike, targets_mm: ArrayLike, motion: ArrayLike | None = None
    ) -> np.ndarray:
        """Integral of attenuation (1/mm) along each segment, through the anatomy moved by ``motion``."""
        ...


# --------------------------------------------------------------------------------------
# Devices
# --------------------------------------------------------------------------------------
def _hu_for_mu(mu_per_mm: float) -> float:
    return (mu_per_mm / MU_WATER_PER_MM - 1.0) * 1000.0


def _truncate_polyline(points: np.ndarray, length_mm: float) -> np.ndarray:
    """The first ``length_mm`` of a polyline (at least its first segment's start)."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    along = np.concatenate([[0.0], np.cumsum(seg)])
    if length_mm >= along[-1]:
        return points
    k = int(np.searchsorted(along, length_mm, side="right"))  # points[:k] lie within length_mm
    frac = (length_mm - along[k - 1]) / max(seg[k - 1], 1e-12)
    end = points[k - 1] + frac * (points[k] - points[k - 1])
    return np.vstack([points[:k], end[None, :]])


def device_phantom(phantom: HeadPhantom, *, wire_length_mm: float | None = None) -> HeadPhantom:
    """A guide catheter up the left internal carotid and a guidewire on to the aneurysm.

    ``wire_length_mm``: how far the guidewire has been advanced along its path (from the
    neck; None: all the way, ending short of the aneurysm), e.g. to show it advancing over a
    fluoroscopy run. Returned as a phantom of its own (air elsewhere) whose line integrals add
    to the anatomy's.
    """
    ica, _ = phantom.path("ica_l")
    m1, _ = phantom.path("m1_l")
    b = PhantomBuilder()
    # guide catheter: from the neck to the petrous segment (where the ICA enters the skull)
    stop = int(np.argmax(ica[:, 2] > -60.0))
    cath = ica[: max(stop, 2)]
    b.tube(cath, CATHETER_OUTER_RADIUS_MM, _hu_for_mu(CATHETER_MU_PER_MM), "catheter", "device")
    b.tube(cath, CATHETER_INNER_RADIUS_MM, -1000.0, "catheter", "air")  # the lumen
    # guidewire: through the catheter, the siphon and M1, ending short of the aneurysm
    wire = np.vstack([ica, m1[1:-1]])
    seg = np.linalg.norm(np.diff(wire, axis=0), axis=1)
    from_end = np.concatenate([np.cumsum(seg[::-1])[::-1], [0.0]])
    if wire_length_mm is not None:
        if not math.isfinite(wire_length_mm) or wire_length_mm <= 2 * GUIDEWIRE_RADIUS_MM:
            raise ValueError(f"wire_length_mm must be a positive length, got {wire_length_mm}")
        wire = _truncate_polyline(wire, float(wire_length_mm))
        seg = np.linalg.norm(np.diff(wire, axis=0), axis=1)
        from_end = np.concatenate([np.cumsum(seg[::-1])[::-1], [0.0]])
    tip = int(np.argmax(from_end <= GUIDEWIRE_TIP_MM))
    tip = min(tip, len(wire) - 2)  # the tip keeps at least one segment
    if tip == 0:  # a wire shorter than its tip: all tip
        b.tube(wire, GUIDEWIRE_RADIUS_MM, _hu_for_mu(GUIDEWIRE_TIP_MU_PER_MM), "wire_tip", "device")
        return b.build(seed=phantom.seed, contrast=False, facial=False, params={"device": "catheter+guidewire"})
    b.tube(wire[: tip + 1], GUIDEWIRE_RADIUS_MM, _hu_for_mu(GUIDEWIRE_MU_PER_MM), "wire", "device")
    b.tube(wire[tip:], GUIDEWIRE_RADIUS_MM, _hu_for_mu(GUIDEWIRE_TIP_MU_PER_MM), "wire_tip", "device")
    return b.build(seed=phantom.seed, contrast=False, facial=False, params={"device": "catheter+guidewire"})


# --------------------------------------------------------------------------------------
# Image formation
# --------------------------------------------------------------------------------------
def _checked(
    phantom: HeadPhantom | Attenuator, geometry: CArm, motion: ArrayLike | None, kind: str, catheter: bool,
    devices: HeadPhantom | None, blur_px: float, supersample: int, photons_per_pixel: float | None,
) -> tuple[np.ndarray | None, float, int, float]:  # fmt: skip
    """:func:`simulate_xray`'s inputs checked: the motion, the blur, the supersampling and the dose."""
    if not callable(getattr(phantom, "line_integrals", None)):
        raise ValueError(f"phantom must be a HeadPhantom or an Attenuator, got {type(phantom).__name__}")
    if catheter and devices is None and not isinstance(phantom, HeadPhantom):
        raise ValueError("catheter=True follows the phantom's vessels; pass devices= for another anatomy")
    if not isinstance(geometry, CArm):
        raise ValueError(f"geometry must be a CArm, got {type(geometry).__name__}")
    if kind not in PHOTONS_PER_PIXEL:
        raise ValueError(f"kind must be one of {tuple(PHOTONS_PER_PIXEL)}, got {kind!r}")
    if motion is not None:
        motion = check_rigid(motion, name="motion")
    blur_px = float(blur_px)
    if not math.isfinite(blur_px) or blur_px < 0:
        raise ValueError(f"blur_px must be finite and >= 0, got {blur_px}")
    if int(supersample) != supersample or supersample < 1:
        raise ValueError(f"supersample must be a positive integer, got {supersample}")
    photons = PHOTONS_PER_PIXEL[kind] if photons_per_pixel is None else float(photons_per_pixel)
    if not math.isfinite(photons) or photons <= 0:
        raise ValueError(f"photons_per_pixel must be positive, got {photons_per_pixel}")
    return motion, blur_px, int(supersample), photons


def _transmission(
    phantom: HeadPhantom | Attenuator, geometry: CArm, field_mask: np.ndarray, motion: np.ndarray | None,
    supersample: int, devices: HeadPhantom | None, catheter: bool,
) -> np.ndarray:  # fmt: skip
    """The mean transmission over each field pixel's sub-pixel rays (the detector integrates
    intensity), all traced in one call; zero outside the field."""
    rr, cc = np.nonzero(field_mask)
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    dr, dc = np.meshgrid(offsets, offsets, indexing="ij")
    targets = geometry.pixel_to_world(cc[None, :] + dc.reshape(-1, 1), rr[None, :] + dr.reshape(-1, 1))
    targets = targets.reshape(-1, 3)
    source = geometry.source_mm
    integral = phantom.line_integrals(source, targets, motion)
    if catheter:
        dev = devices if devices is not None else device_phantom(phantom)
        integral += dev.line_integrals(source, targets, motion)
    transmission = np.exp(-integral).reshape(supersample * supersample, len(rr)).mean(axis=0)
    frame = np.zeros((geometry.rows, geometry.cols))
    frame[rr, cc] = transmission
    return frame


def _exposure_control(frame: np.ndarray, geometry: CArm, field_mask: np.ndarray, photons: float) -> float:
    """Automatic exposure control: the unattenuated count I0 at which the central field receives
    ``photons`` per pixel."""
    y = (np.arange(geometry.rows) - (geometry.rows - 1) / 2.0)[:, None] * geometry.pixel_mm[0]
    x = (np.arange(geometry.cols) - (geometry.cols - 1) / 2.0)[None, :] * geometry.pixel_mm[1]
    aec_radius = AEC_FIELD_FRACTION * geometry.field_diameter_mm / 2.0
    central = field_mask & (x * x + y * y <= aec_radius * aec_radius)
    return photons / max(float(np.median(frame[central])), 1e-6)


def _detected(frame: np.ndarray, field_mask: np.ndarray, i0: float, seed: int, blur_px: float) -> np.ndarray:
    """Quantum noise, detector blur and electronic noise, as attenuation line integrals -log(I / I0)
    (zero outside the field)."""
    rng = np.random.default_rng(seed)
    counts = rng.poisson(i0 * frame).astype(np.float64)
    if blur_px > 0:  # normalised blur: the dark collimator does not leak into the field
        weight = ndimage.gaussian_filter(field_mask.astype(np.float64), blur_px, mode="constant")
        counts = ndimage.gaussian_filter(counts, blur_px, mode="constant") / np.maximum(weight, 1e-12)
    counts += rng.normal(0.0, ELECTRONIC_NOISE_PHOTONS, counts.shape)
    image = -np.log(np.maximum(counts, MIN_PHOTONS) / i0)
    return np.where(field_mask, image, 0.0).astype(np.float32)


def simulate_xray(
    phantom: HeadPhantom | Attenuator,
    geometry: CArm,
    *,
    motion: ArrayLike | None = None,
    kind: str = "fluoro",
    catheter: bool = False,
    seed: int = 0,
    blur_px: float = DETECTOR_BLUR_PX,
    supersample: int = SUPERSAMPLE,
    photons_per_pixel: float | None = None,
    devices: HeadPhantom | None = None,
    detector_effects: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
) -> XRayImage:
    """Simulate a fluoroscopy or exposure image of the phantom (the honest image model).

    Parameters
    ----------
    phantom
        The analytic head, or any :class:`Attenuator` (e.g. the line integrals through a
        user's volume, :class:`registration.sim.volume_xray.VolumeAttenuator`).
    geometry
        The view; may be a true (bent, calibrated) geometry: rays run from
        ``geometry.source_mm`` to ``geometry.pixel_to_world(col, row)``.
    motion
        Rigid 4x4 patient motion ``M`` (CONVENTIONS §4): the image shows the phantom moved by M.
    kind
        "fluoro" (low dose, ``FLUORO_PHOTONS_PER_PIXEL``) or "exposure" (``EXPOSURE_...``).
    catheter
        Add a guide catheter and guidewire (:func:`device_phantom`), absent from any 3DRA
        (along the phantom's vessels; for another anatomy pass ``devices``).
    seed
        Seed of the quantum and electronic noise.
    blur_px
        Detector blur, Gaussian sigma in pixels (0 for none).
    supersample
        Sub-pixel rays per pixel along each axis.
    photons_per_pixel
        Override the dose of ``kind`` (photons per pixel behind the head).
    devices
        Interventional devices as a phantom of their own (e.g. :func:`device_phantom` with the
        guidewire partly advanced, or :func:`registration.sim.volume_xray.catheter_devices`
        for a volume's anatomy); used instead of the default devices when ``catheter``.
    detector_effects
        ``f(transmission, field_mask) -> transmission``: what reaches the detector besides the
        primary beam (collimator blades, scatter, the heel effect), applied to the mean
        transmission frame (zero outside the field) before the exposure control and the
        quantum noise (:mod:`registration.sim.clinical`); None for the primary beam alone.

    Returns
    -------
    XRayImage
        Attenuation line integrals ``-log(I / I0)`` (float32), zero outside the circular field,
        with the field mask.
    """
    motion, blur_px, supersample, photons = _checked(
        phantom, geometry, motion, kind, catheter, devices, blur_px, supersample, photons_per_pixel
    )
    field_mask = geometry.field_mask()
    frame = _transmission(phantom, geometry, field_mask, motion, supersample, devices if catheter else None,
                          catheter)  # fmt: skip
    if detector_effects is not None:
        frame = np.where(field_mask, np.asarray(detector_effects(frame, field_mask), dtype=np.float64), 0.0)
        if not np.all(np.isfinite(frame)) or frame.min() < 0:
            raise ValueError("detector_effects must return a finite, non-negative transmission frame")
    i0 = _exposure_control(frame, geometry, field_mask, photons)
    image = _detected(frame, field_mask, i0, seed, blur_px)
    meta = {
        "kind": kind,
        "photons_per_pixel": photons,
        "i0_photons": i0,
        "seed": int(seed),
        "catheter": bool(catheter),
        "blur_px": blur_px,
        "supersample": supersample,
        "motion": None if motion is None else motion.tolist(),
        "phantom": phantom.key,
        "source": getattr(phantom, "source_label", "analytic phantom line integrals (honest simulation)"),
    }
    return XRayImage(image, field_mask, geometry, kind, meta)
