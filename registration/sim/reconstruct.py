"""FDK cone-beam reconstruction of a rotational run: the 3DRA (paper section II.A).

The run (:mod:`registration.sim.rotational_run`) forms its images with the *true* (bent)
geometry of each view; the reconstruction sees only the images and the geometry *calibrated*
from a dodecahedron run with the same angles, as on a real system.

:func:`fdk` back-projects filtered projections with each view's general 3x4 projection matrix
(Feldkamp-Davis-Kress: cosine weights, Parker short-scan weights, ramp filter with a Hann
window, voxel-driven numba back-projection with bilinear detector interpolation) into the 3DRA
grid of a volume format (field of view f x SOD / SID at the iso-center,
:func:`registration.core.volume.format_grid`) and returns Hounsfield units
(HU = 1000 (mu / mu_water - 1), mu_water = :data:`registration.core.volume.MU_WATER_PER_MM`, as
:func:`registration.core.volume.hu_to_mu_per_mm`). Voxels that leave the collimated field in
any view lie outside the reconstructable cylinder and are set to air (-1000 HU).

Conventions (frames, angles, units) are those of ``shared/CONVENTIONS.md``.

References
----------
L. A. Feldkamp, L. C. Davis, J. W. Kress, "Practical cone-beam algorithm", JOSA A 1(6), 1984.
D. L. Parker, "Optimal short scan convolution reconstruction for fan beam CT", Med. Phys. 9(2),
1982. A. C. Kak, M. Slaney, "Principles of Computerized Tomographic Imaging", ch. 3 (the
band-limited ramp kernel).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import fft as sfft

from registration.core.geometry import CArm
from registration.core.volume import MU_WATER_PER_MM, Volume, format_grid
from registration.sim.bending import default_bending
from registration.sim.rotational_run import (
    RUN_ARC_DEG,
    RUN_PROJECTIONS,
    Imager,
    RotationalRun,
    rotational_run,
    run_angles,
)

Array = NDArray[np.float64]

#: Label of reconstructed volumes (outputs repeat it).
RECONSTRUCTION_LABEL = "FDK reconstruction of a simulated rotational run ({n} projections)"

#: Longest extension (detector mm) of a projection row beyond the collimated field by water
#: cylinder extrapolation before filtering (reduces truncation artefacts of heads wider than
#: the field of view; the extension itself is never back-projected).
TRUNCATION_MAX_MM = 200.0
#: Attenuation (1/mm) of the extrapolating cylinders: twice water, because the periphery of a
#: head (scalp over skull) attenuates more than water; water itself over-extends the rows.
TRUNCATION_MU_PER_MM = 2.0 * MU_WATER_PER_MM
#: Pixels over which the slope at the field edge is measured for the extrapolation.
TRUNCATION_FIT_PX = 4


# --------------------------------------------------------------------------------------
# FDK
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _ViewFrame:
    """What FDK needs of one view: detector distance, principal point, source-iso distance."""

    focal_mm: float  # source to detector plane, along the detector normal
    principal_px: tuple[float, float]  # (col, row) of the foot of the normal from the source
    source_iso_mm: float  # source to iso-center, along the detector normal


def _view_frame(geometry: CArm) -> _ViewFrame:
    p00 = geometry.pixel_to_world(0.0, 0.0)
    u = geometry.pixel_to_world(1.0, 0.0) - p00
    v = geometry.pixel_to_world(0.0, 1.0) - p00
    n = np.cross(u, v)
    n /= np.linalg.norm(n)
    s = geometry.source_mm
    focal = float(n @ (geometry.detector_center_mm - s))
    if focal < 0:
        n, focal = -n, -focal
    foot = s + focal * n
    col, row = geometry.project(foot)
    return _ViewFrame(focal, (float(col), float(row)), float(n @ (np.asarray(geometry.isocenter_mm) - s)))


def ramp_kernel_spectrum(size: int, *, window: str = "hann") -> NDArray[np.float64]:
    """Real spectrum (rfft, length size // 2 + 1) of the band-limited ramp kernel for unit
    pixel spacing (Kak-Slaney: h(0) = 1/4, h(odd n) = -1/(pi n)^2), times the window."""
    if window not in ("hann", "ram-lak"):
        raise ValueError(f"window must be 'hann' or 'ram-lak', got {window!r}")
    n = np.arange(size)
    n = np.where(n <= size // 2, n, n - size)
    h = np.zeros(size)
    h[0] = 0.25
    odd = (n % 2) == 1
    h[odd] = -1.0 / (math.pi * n[odd]) ** 2
    spectrum = np.real(np.fft.rfft(h))
    if window == "hann":
        f = np.arange(spectrum.size) / (size / 2.0)  # 0 .. 1 (Nyquist)
        spectrum *= 0.5 * (1.0 + np.cos(math.pi * f))
    return spectrum


def parker_weights(beta_rad: float, gamma_rad: NDArray[np.float64], half_fan_rad: float) -> NDArray[np.float64]:
    """Parker short-scan weights for view angle ``beta_rad`` in [0, pi + 2 half_fan] and fan
    angles ``gamma_rad`` (toward +u). The conjugate of ray (beta, gamma) is
    (beta + pi + 2 gamma, -gamma) for this rotation sense; weights of conjugate rays sum to 1.
    Fan angles beyond ``half_fan_rad`` are clipped to it (the arc is then shorter than a full
    short scan for those rays)."""
    big = half_fan_rad
    g = np.clip(gamma_rad, -big + 1e-9, big - 1e-9)
    w = np.ones_like(g)
    b = beta_rad
    start = b < 2 * big - 2 * g
    w = np.where(start, np.sin(math.pi / 4 * b / (big - g)) ** 2, w)
    end = b > math.pi - 2 * g
    w = np.where(end, np.sin(math.pi / 4 * (math.pi + 2 * big - b) / (big + g)) ** 2, w)
    return np.clip(w, 0.0, 1.0)


def _extend_truncated(
    image: NDArray[np.float64], mask: NDArray[np.bool_], *, pixel_mm: float, magnification: float
) -> tuple[NDArray[np.float64], int]:
    """Water-cylinder extrapolation of each row beyond the collimated field (Hsieh et al. 2004).

    At each end of a row's field, the line integral p and its outward slope s (over
    :data:`TRUNCATION_FIT_PX` pixels) fix a cylinder of :data:`TRUNCATION_MU_PER_MM` (per
    detector mm: divided by the magnification) whose projection continues the row: center
    a = -s p / (4 mu^2) inside the edge (a >= 0), radius sqrt((p / 2 mu)^2 + a^2), at most
    :data:`TRUNCATION_MAX_MM` long. Returns the rows padded on both sides so the extension can
    reach past the detector edge, and the pad (pixels).
    """
    rows, cols = image.shape
    mu = TRUNCATION_MU_PER_MM / magnification
    inside = np.where(mask, image, 0.0)
    has = mask.any(axis=1)
    if not has.any():
        return inside, 0
    r = np.flatnonzero(has)
    m = mask[r]
    lo = np.argmax(m, axis=1)
    hi = cols - 1 - np.argmax(m[:, ::-1], axis=1)
    sides = []
    longest_mm = 0.0
    for edge, sign in ((lo, -1), (hi, 1)):
        inner = np.clip(edge - sign * TRUNCATION_FIT_PX, lo, hi)
        p_edge = np.maximum(0.5 * (image[r, edge] + image[r, np.clip(edge - sign, lo, hi)]), 0.0)
        run_mm = np.maximum(np.abs(edge - inner), 1) * pixel_mm
        slope = (p_edge - image[r, inner]) / run_mm  # outward derivative
        a = np.maximum(-slope * p_edge / (4.0 * mu * mu), 0.0)
        radius = np.sqrt((p_edge / (2.0 * mu)) ** 2 + a * a)
        longest_mm = max(longest_mm, float(np.max(radius - a)))
        sides.append((edge, sign, a, radius))
    pad = int(math.ceil(min(longest_mm, TRUNCATION_MAX_MM) / pixel_mm)) + 1
    out = np.zeros((rows, cols + 2 * pad))
    out[:, pad : pad + cols] = inside
    idx = np.arange(cols + 2 * pad)[None, :] - pad
    for edge, sign, a, radius in sides:
        t = sign * (idx - edge[:, None]) * pixel_mm  # outward distance from the edge (mm)
        ext = 2.0 * mu * np.sqrt(np.maximum(radius[:, None] ** 2 - (a[:, None] + t) ** 2, 0.0))
        ext[t > TRUNCATION_MAX_MM] = 0.0
        out[r] = np.where(t > 0, ext, out[r])
    return out, pad


def filter_projections(
    images: ArrayLike,
    geometries: Sequence[CArm],
    primary_deg: ArrayLike,
    *,
    masks: ArrayLike | None = None,
    window: str = "hann",
) -> NDArray[np.float32]:
    """Weighted, ramp-filtered projections ready for back-projection (FDK steps 1-2).

    Each view is extended beyond its collimated field when ``masks`` are given (water-cylinder
    extrapolation, :func:`_extend_truncated`), multiplied by the cosine weight
    D / sqrt(D^2 + x^2 + y^2) (D: source to detector, x, y: detector mm from the principal
    point) and the Parker weight of its angle, ramp-filtered along rows with the Hann window
    (:func:`ramp_kernel_spectrum`), and scaled by dbeta R^2 / tau (tau the pixel spacing at
    the iso-center, R the source-iso distance) so that :func:`backproject` with weight 1/w^2 gives attenuation in 1/mm.
    The run must be a propeller rotation (secondary 0): the Parker weights assume rotation
    about the world z axis, increasing with ``primary_deg``.
    """
    imgs = np.asarray(images, dtype=np.float32)
    if imgs.ndim != 3 or imgs.shape[0] != len(geometries):
        raise ValueError(f"images must be (views, rows, cols) with one geometry per view, got {imgs.shape}")
    angles = np.radians(np.asarray(primary_deg, dtype=np.float64).reshape(-1))
    if angles.size != imgs.shape[0]:
        raise ValueError(f"{angles.size} angles for {imgs.shape[0]} views")
    order = np.argsort(angles)
    if np.any(np.diff(angles[order]) <= 0):
        raise ValueError("view angles must be distinct")
    arc = float(angles[order[-1]] - angles[order[0]])
    if arc <= math.pi:
        raise ValueError(f"the run covers {math.degrees(arc):.1f} deg; FDK needs more than 180")
    half_fan = (arc - math.pi) / 2.0
    dbeta = arc / (angles.size - 1)
    if any(abs(g.secondary_deg) > 1e-9 for g in geometries):
        raise ValueError("FDK here expects a propeller run (secondary angle 0 in every view)")
    nv, rows, cols = imgs.shape
    msk = None if masks is None else np.asarray(masks, dtype=bool)
    out = np.empty((nv, rows, cols), dtype=np.float32)
    for i in range(nv):
        g = geometries[i]
        if (g.rows, g.cols) != (rows, cols):
            raise ValueError(f"geometry {i} has {g.rows}x{g.cols} pixels, images {rows}x{cols}")
        frame = _view_frame(g)
        proj = imgs[i].astype(np.float64)
        pad = 0
        if msk is not None:
            proj, pad = _extend_truncated(proj, msk[i], pixel_mm=g.pixel_mm[1], magnification=g.magnification)
        width = proj.shape[1]
        c0, r0 = frame.principal_px
        x = (np.arange(width) - pad - c0) * g.pixel_mm[1]
        y = (np.arange(rows) - r0) * g.pixel_mm[0]
        d = frame.focal_mm
        cosine = d / np.sqrt(d * d + x[None, :] ** 2 + y[:, None] ** 2)
        gamma = np.arctan(x / d)
        parker = parker_weights(float(angles[i] - angles[order[0]]), gamma, half_fan)
        proj *= cosine * parker[None, :]
        size = 1 << int(math.ceil(math.log2(2 * width)))
        spectrum = ramp_kernel_spectrum(size, window=window)
        filtered = sfft.irfft(sfft.rfft(proj, n=size, axis=1, workers=2) * spectrum, n=size, axis=1, workers=2)
        tau = g.pixel_mm[1] * frame.source_iso_mm / d
        out[i] = (filtered[:, pad : pad + cols] * (dbeta * frame.source_iso_mm**2 / tau)).astype(np.float32)
    return out


@numba.njit(parallel=True, fastmath=True, cache=True)
def _backproject_kernel(
    q: np.ndarray,
    pmats: np.ndarray,
    index_to_world: np.ndarray,
    field_radius2: np.ndarray,
    out: np.ndarray,
    outside: np.ndarray,
) -> None:  # pragma: no cover - compiled
    nk, nj, ni = out.shape
    nv, rows, cols = q.shape
    cx = (cols - 1) / 2.0
    cy = (rows - 1) / 2.0
    a = index_to_world
    for k in numba.prange(nk):
        # view-major inside a slice: a slice projects onto a narrow band of detector rows, so
        # the image lines it needs stay in cache while the slice's voxels are visited
        for v in range(nv):
            p = pmats[v]
            rad2 = field_radius2[v]
            img = q[v]
            d0 = p[0, 0] * a[0, 0] + p[0, 1] * a[1, 0] + p[0, 2] * a[2, 0]
            d1 = p[1, 0] * a[0, 0] + p[1, 1] * a[1, 0] + p[1, 2] * a[2, 0]
            d2 = p[2, 0] * a[0, 0] + p[2, 1] * a[1, 0] + p[2, 2] * a[2, 0]
            for j in range(nj):
                x0 = a[0, 1] * j + a[0, 2] * k + a[0, 3]
                y0 = a[1, 1] * j + a[1, 2] * k + a[1, 3]
                z0 = a[2, 1] * j + a[2, 2] * k + a[2, 3]
                h0 = p[0, 0] * x0 + p[0, 1] * y0 + p[0, 2] * z0 + p[0, 3]
                h1 = p[1, 0] * x0 + p[1, 1] * y0 + p[1, 2] * z0 + p[1, 3]
                h2 = p[2, 0] * x0 + p[2, 1] * y0 + p[2, 2] * z0 + p[2, 3]
                for i in range(ni):
                    w = h2 + d2 * i
                    inv = 1.0 / w
                    c = (h0 + d0 * i) * inv
                    r = (h1 + d1 * i) * inv
                    dc = c - cx
                    dr = r - cy
                    if dc * dc + dr * dr > rad2 or c < 0.0 or r < 0.0 or c > cols - 1.0 or r > rows - 1.0:
                        outside[k, j, i] = True
                        continue
                    c0 = min(int(c), cols - 2)
                    r0 = min(int(r), rows - 2)
                    fc = np.float32(c - c0)
                    fr = np.float32(r - r0)
                    top = img[r0, c0] + fc * (img[r0, c0 + 1] - img[r0, c0])
                    bottom = img[r0 + 1, c0] + fc * (img[r0 + 1, c0 + 1] - img[r0 + 1, c0])
                    out[k, j, i] += (top + fr * (bottom - top)) * np.float32(inv * inv)


def backproject(
    filtered: ArrayLike,
    geometries: Sequence[CArm],
    shape: tuple[int, int, int],
    index_to_world: ArrayLike,
) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """Voxel-driven back-projection with each view's 3x4 projection matrix (FDK step 3).

    Returns attenuation (1/mm, with :func:`filter_projections`' scaling) on the grid
    ``shape`` = (k, j, i) and a mask of voxels that left the circular field in some view.
    """
    q = np.ascontiguousarray(filtered, dtype=np.float32)
    pm = np.ascontiguousarray(np.stack([g.projection_matrix for g in geometries]), dtype=np.float64)
    rad = np.array([(g.field_diameter_mm / 2.0 / max(g.pixel_mm)) ** 2 for g in geometries], dtype=np.float64)
    out = np.zeros(shape, dtype=np.float32)
    outside = np.zeros(shape, dtype=np.bool_)
    _backproject_kernel(q, pm, np.ascontiguousarray(index_to_world, dtype=np.float64), rad, out, outside)
    return out, outside


def fdk(
    images: ArrayLike,
    geometries: Sequence[CArm],
    primary_deg: ArrayLike,
    *,
    volume_format_cm: float,
    voxels: int = 256,
    masks: ArrayLike | None = None,
    window: str = "hann",
    label: str | None = None,
) -> Volume:
    """FDK reconstruction (HU) into the 3DRA grid of ``volume_format_cm``.

    ``geometries`` are the (calibrated) geometries the reconstruction trusts, ``primary_deg``
    the nominal view angles (Parker weights, angular step). The grid is axis-aligned (LPS),
    centered at the iso-center, ``voxels``^3 over f x SOD / SID
    (:func:`registration.core.volume.format_grid`).
    """
    if voxels < 2:
        raise ValueError(f"voxels must be >= 2, got {voxels}")
    spacing, axis = format_grid(volume_format_cm, voxels=voxels)
    probe = Volume.from_grid(np.zeros((2, 2, 2), np.float32), spacing)
    index_to_world = probe.index_to_world.copy()
    index_to_world[:3, 3] = axis[0]
    q = filter_projections(images, geometries, primary_deg, masks=masks, window=window)
    mu, outside = backproject(q, geometries, (voxels, voxels, voxels), index_to_world)
    hu = 1000.0 * (mu / MU_WATER_PER_MM - 1.0)
    hu[outside] = -1000.0
    n = len(geometries)
    return Volume(
        hu.astype(np.float32),
        index_to_world,
        label=label or RECONSTRUCTION_LABEL.format(n=n),
        meta={"projections": n, "volume_format_cm": float(volume_format_cm), "voxels": voxels},
    )


def reconstruct_run(run: RotationalRun, *, volume_format_cm: float, voxels: int = 256) -> Volume:
    """FDK of a rotational run with its calibrated geometries (never the true ones)."""
    return fdk(
        run.images,
        run.calibrated_geometries,
        run.primary_deg,
        volume_format_cm=volume_format_cm,
        voxels=voxels,
        masks=run.masks,
    )


def _3dra_params(
    phantom_seed: int,
    *,
    volume_format_cm: float,
    contrast: bool,
    pixels: int,
    projections: int,
    arc_deg: float,
    kind: str,
    seed: int,
) -> dict:
    from registration.sim.phantom import PHANTOM_MODEL_VERSION

    return {
        "phantom_seed": int(phantom_seed),
        "volume_format_cm": float(volume_format_cm),
        "contrast": bool(contrast),
        "pixels": int(pixels),
        "projections": int(projections),
        "arc_deg": float(arc_deg),
        "kind": kind,
        "seed": int(seed),
        "bending_seed": default_bending().seed,
        "phantom_model": PHANTOM_MODEL_VERSION,
    }


def fdk_3dra_params(
    phantom_seed: int,
    *,
    volume_format_cm: float,
    contrast: bool = True,
    voxels: int = 256,
    pixels: int = 256,
    projections: int = RUN_PROJECTIONS,
    arc_deg: float = RUN_ARC_DEG,
    kind: str = "exposure",
    seed: int = 0,
) -> dict:
    """The cache parameters of :func:`reconstruct_3dra` (kind ``"fdk-3dra"``)."""
    params = _3dra_params(
        phantom_seed, volume_format_cm=volume_format_cm, contrast=contrast, pixels=pixels,
        projections=projections, arc_deg=arc_deg, kind=kind, seed=seed,
    )  # fmt: skip
    return {**params, "voxels": int(voxels)}


def rotational_run_3dra(
    phantom_seed: int,
    *,
    volume_format_cm: float,
    contrast: bool = True,
    pixels: int = 256,
    projections: int = RUN_PROJECTIONS,
    arc_deg: float = RUN_ARC_DEG,
    kind: str = "exposure",
    seed: int = 0,
    cache: bool = True,
) -> RotationalRun:
    """The rotational run that :func:`reconstruct_3dra` reconstructs (same parameters, same
    images), cached under the user's cache directory; the geometries are recomputed (cheap:
    the calibration run is cached too)."""
    from registration.io.cache import cached_arrays

    params = _3dra_params(
        phantom_seed, volume_format_cm=volume_format_cm, contrast=contrast, pixels=pixels,
        projections=projections, arc_deg=arc_deg, kind=kind, seed=seed,
    )  # fmt: skip

    def run_with(imager: Imager | None = None) -> RotationalRun:
        from registration.sim.phantom import make_head_phantom

        return rotational_run(
            make_head_phantom(seed=phantom_seed, contrast=contrast),
            image_format_cm=volume_format_cm,
            projections=projections,
            arc_deg=arc_deg,
            kind=kind,
            pixels=pixels,
            seed=seed,
            imager=imager,
        )

    def build() -> dict[str, np.ndarray]:
        run = run_with()
        return {"images": run.images, "masks": run.masks}

    arrays = cached_arrays("3dra-run", params, build, enabled=cache)

    def blank(ph: object, geom: CArm, index: int) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        return np.zeros((geom.rows, geom.cols), np.float32), np.ones((geom.rows, geom.cols), bool)

    geometries = run_with(blank)
    return replace(geometries, images=arrays["images"], masks=arrays["masks"].astype(bool))


def reconstruct_3dra(
    phantom_seed: int,
    *,
    volume_format_cm: float,
    contrast: bool = True,
    voxels: int = 256,
    pixels: int = 256,
    projections: int = RUN_PROJECTIONS,
    arc_deg: float = RUN_ARC_DEG,
    kind: str = "exposure",
    seed: int = 0,
    cache: bool = True,
) -> Volume:
    """The 3DRA of a head phantom: rotational run at image format = ``volume_format_cm``,
    calibrated geometry, FDK; cached under the user's cache directory by its parameters.

    ``pixels`` defaults to 256: rotational runs use a 2x2-binned detector mode, whose pixel
    (at the iso-center) matches the 256^3 voxel; each simulated pixel still integrates 2x2
    sub-pixel rays. The first call simulates the whole run with the honest image model
    (minutes; the run is cached too, :func:`rotational_run_3dra`); later calls load the cached volume.
    """
    from registration.io.cache import cached_arrays

    run_params = dict(
        volume_format_cm=volume_format_cm, contrast=contrast, pixels=pixels, projections=projections,
        arc_deg=arc_deg, kind=kind, seed=seed,
    )  # fmt: skip
    params = fdk_3dra_params(phantom_seed, voxels=voxels, **run_params)  # type: ignore[arg-type]

    def build() -> dict[str, np.ndarray]:
        run = rotational_run_3dra(phantom_seed, cache=cache, **run_params)  # type: ignore[arg-type]
        vol = reconstruct_run(run, volume_format_cm=volume_format_cm, voxels=voxels)
        return {"data": vol.data, "index_to_world": vol.index_to_world}

    arrays = cached_arrays("fdk-3dra", params, build, enabled=cache)
    return Volume(
        arrays["data"],
        arrays["index_to_world"],
        label=RECONSTRUCTION_LABEL.format(n=projections),
        meta=dict(params),
    )


def bench_reconstruction(*, projections: int = 120, pixels: int = 512, voxels: int = 256) -> dict:
    """Time FDK (filtering + back-projection) of ``projections`` views of ``pixels``^2 into
    ``voxels``^3 (analytic sphere projections; the numba kernel is compiled beforehand).

    Returns ``{"seconds", "cpu_seconds", "projections", "volume_px", "pixels", "threads"}``.
    """
    from registration.sim.dodecahedron import SpherePhantom, simulate_sphere_image

    spheres = SpherePhantom(
        np.array([[0.0, 0.0, 0.0], [20.0, -10.0, 5.0]]), np.array([60.0, 5.0]), [MU_WATER_PER_MM, 0.01]
    )
    angles = run_angles(projections, 200.0)
    geoms = [CArm.for_format(27.0, pixels=pixels, primary_deg=float(a)) for a in angles]
    images = np.stack([simulate_sphere_image(spheres, g, supersample=1, full_frame=True) for g in geoms])
    backproject(np.zeros((1, 4, 4), np.float32), [geoms[0].resized(4, 4)], (2, 2, 2), np.eye(4))  # compile
    masks = np.stack([g.field_mask() for g in geoms])
    start, cpu = time.perf_counter(), time.process_time()
    fdk(images, geoms, angles, volume_format_cm=27.0, voxels=voxels, masks=masks)
    seconds, cpu = time.perf_counter() - start, time.process_time() - cpu
    return {
        "seconds": round(seconds, 3),
        "cpu_seconds": round(cpu, 3),  # all threads; on a shared machine, wall time / load
        "projections": projections,
        "volume_px": voxels,
        "pixels": pixels,
        "threads": numba.get_num_threads(),
    }
