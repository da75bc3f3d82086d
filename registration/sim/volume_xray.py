"""X-ray images formed from a voxel volume (a user's CT or 3DRA) by the honest image model.

When the only anatomy at hand is a volume (a real CT, a 3DRA), its simulated X-ray views are
made by the same detector model as the phantom's (:func:`registration.sim.xray.simulate_xray`:
sub-pixel rays averaged in intensity, Beer-Lambert, Poisson quantum noise, electronic noise,
detector blur, collimation), with line integrals taken through the volume's own grid by
:class:`VolumeAttenuator`: trilinear samples every ``step_mm`` (default half the finest voxel
spacing) along the exact segment from the source to each sub-pixel, in world millimetres.

This is not the DRR renderer that scores the images (registration.core.drr renders
pyramid levels resampled to the registration's own grids, with Joseph's method one sample per
slice); but the images still come from the same anatomy the registration volume holds, so
results on them are a **best case**: a real X-ray of that patient differs from any CT of
them (other energy, scatter, a table instead of the CT's couch). Outputs say so
(``IMAGES_FROM_VOLUME``).

:func:`catheter_devices` adds a guide catheter and guidewire the volume lacks, along a path
given in world millimetres.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core.geometry import check_rigid, invert_rigid
from registration.core.volume import Volume, hu_to_mu_per_mm
from registration.sim.phantom_shapes import HeadPhantom, PhantomBuilder
from registration.sim.xray import (
    CATHETER_INNER_RADIUS_MM,
    CATHETER_MU_PER_MM,
    CATHETER_OUTER_RADIUS_MM,
    GUIDEWIRE_MU_PER_MM,
    GUIDEWIRE_RADIUS_MM,
    GUIDEWIRE_TIP_MM,
    GUIDEWIRE_TIP_MU_PER_MM,
    _hu_for_mu,
)

#: Said wherever results on such images are reported.
IMAGES_FROM_VOLUME = (
    "X-ray images formed from the same volume (trilinear line integrals, Beer-Lambert, Poisson noise, blur, "
    "collimation, a catheter the volume lacks): a best case, not a real X-ray"
)
#: Sampling step along each ray as a fraction of the finest voxel spacing.
STEP_FRACTION = 0.5


@numba.njit(parallel=True, cache=True, fastmath=True, nogil=True)
def _integrate(mu, src, dst, step_mm, spacing_ijk, out) -> None:  # noqa: ANN001
    """Midpoint-rule integral of the trilinear interpolant of ``mu`` (k, j, i) along each
    segment src -> dst[n] (voxel indices (i, j, k)), ``step_mm`` apart, zero outside."""
    nk, nj, ni = mu.shape
    for n in numba.prange(dst.shape[0]):
        s0, s1, s2 = src[0], src[1], src[2]
        d0, d1, d2 = dst[n, 0] - s0, dst[n, 1] - s1, dst[n, 2] - s2
        # clip to the box of voxel centers [0, n - 1]
        t_lo, t_hi = 0.0, 1.0
        for s, d, m in ((s0, d0, ni), (s1, d1, nj), (s2, d2, nk)):
            if abs(d) < 1e-12:
                if s < 0.0 or s > m - 1:
                    t_hi = -1.0
            else:
                ta = (0.0 - s) / d
                tb = (m - 1 - s) / d
                if ta > tb:
                    ta, tb = tb, ta
                t_lo = max(t_lo, ta)
                t_hi = min(t_hi, tb)
        out[n] = 0.0
        if not t_lo < t_hi:
            continue
        length_mm = math.sqrt((d0 * spacing_ijk[0]) ** 2 + (d1 * spacing_ijk[1]) ** 2 + (d2 * spacing_ijk[2]) ** 2) * (
            t_hi - t_lo
        )
        steps = max(1, int(math.ceil(length_mm / step_mm)))
        dt = (t_hi - t_lo) / steps
        acc = 0.0
        for q in range(steps):
            t = t_lo + (q + 0.5) * dt
            x = s0 + t * d0
            y = s1 + t * d1
            z = s2 + t * d2
            i = min(max(int(math.floor(x)), 0), ni - 2)
            j = min(max(int(math.floor(y)), 0), nj - 2)
            k = min(max(int(math.floor(z)), 0), nk - 2)
            fx, fy, fz = x - i, y - j, z - k
            c00 = mu[k, j, i] + fx * (mu[k, j, i + 1] - mu[k, j, i])
            c01 = mu[k, j + 1, i] + fx * (mu[k, j + 1, i + 1] - mu[k, j + 1, i])
            c10 = mu[k + 1, j, i] + fx * (mu[k + 1, j, i + 1] - mu[k + 1, j, i])
            c11 = mu[k + 1, j + 1, i] + fx * (mu[k + 1, j + 1, i + 1] - mu[k + 1, j + 1, i])
            c0 = c00 + fy * (c01 - c00)
            c1 = c10 + fy * (c11 - c10)
            acc += c0 + fz * (c1 - c0)
        out[n] = acc * (length_mm / steps)


class VolumeAttenuator:
    """Line integrals of attenuation (1/mm) through a volume, for :func:`simulate_xray`.

    Parameters
    ----------
    volume
        The anatomy in HU (converted with :func:`registration.core.volume.hu_to_mu_per_mm`).
    step_mm
        Sampling step along the rays (default ``STEP_FRACTION`` of the finest voxel spacing).
    """

    def __init__(self, volume: Volume, *, step_mm: float | None = None) -> None:
        if not isinstance(volume, Volume):
            raise ValueError(f"volume must be a Volume, got {type(volume).__name__}")
        spacing = volume.spacing_mm
        step = STEP_FRACTION * float(spacing.min()) if step_mm is None else float(step_mm)
        if not math.isfinite(step) or step <= 0:
            raise ValueError(f"step_mm must be positive, got {step_mm}")
        self.volume = volume
        self.step_mm = step
        self._mu = np.ascontiguousarray(hu_to_mu_per_mm(volume.data))
        self._spacing = np.ascontiguousarray(spacing, dtype=np.float64)
        self.key = {"volume": volume.label, "shape": list(volume.shape), "step_mm": step}
        self.source_label = f"trilinear line integrals through the volume every {step:.2f} mm"

    def line_integrals(self, sources_mm: ArrayLike, targets_mm: ArrayLike, motion: ArrayLike | None = None) -> NDArray:
        """Integral of attenuation along each segment from the (one) source to the targets,
        through the volume moved by ``motion`` (CONVENTIONS §4)."""
        src = np.asarray(sources_mm, dtype=np.float64).reshape(-1, 3)
        dst = np.asarray(targets_mm, dtype=np.float64).reshape(-1, 3)
        if len(src) != 1 and not np.all(src == src[0]):
            raise ValueError("VolumeAttenuator traces rays from one source")
        to_index = self.volume.index_from_world
        if motion is not None:
            to_index = to_index @ invert_rigid(check_rigid(motion, name="motion"))
        s = to_index[:3, :3] @ src[0] + to_index[:3, 3]
        d = dst @ to_index[:3, :3].T + to_index[:3, 3]
        out = np.empty(len(d), dtype=np.float64)
        _integrate(self._mu, np.ascontiguousarray(s), np.ascontiguousarray(d), self.step_mm, self._spacing, out)
        return out


def catheter_devices(path_mm: ArrayLike, *, seed: int = 0) -> HeadPhantom:
    """A 6 F guide catheter along ``path_mm`` (N, 3) and a guidewire running on past its tip.

    The catheter covers the path but its last ``GUIDEWIRE_TIP_MM``, the guidewire the whole
    path (radiopaque tip included): exact analytic tubes, as the phantom's devices.
    """
    pts = np.asarray(path_mm, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2 or not np.all(np.isfinite(pts)):
        raise ValueError("a device path needs at least two finite points (N, 3) in mm")
    # resample the polyline every 2 mm so the tubes follow it closely
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.linspace(0.0, arc[-1], max(2, int(arc[-1] / 2.0) + 1))
    path = np.stack([np.interp(s, arc, pts[:, a]) for a in range(3)], axis=1)
    tip = int(np.argmax(s >= arc[-1] - GUIDEWIRE_TIP_MM))
    b = PhantomBuilder()
    cath = path[: max(tip, 2)]
    b.tube(cath, CATHETER_OUTER_RADIUS_MM, _hu_for_mu(CATHETER_MU_PER_MM), "catheter", "device")
    b.tube(cath, CATHETER_INNER_RADIUS_MM, -1000.0, "catheter", "air")
    b.tube(path[: tip + 1], GUIDEWIRE_RADIUS_MM, _hu_for_mu(GUIDEWIRE_MU_PER_MM), "wire", "device")
    b.tube(path[tip:], GUIDEWIRE_RADIUS_MM, _hu_for_mu(GUIDEWIRE_TIP_MU_PER_MM), "wire_tip", "device")
    return b.build(seed=seed, contrast=False, facial=False, params={"device": "catheter+guidewire", "path": "given"})


def default_catheter_path(isocenter_mm: ArrayLike) -> NDArray[np.float64]:
    """A catheter path up the left side of the neck to the skull base, about the iso-center:
    from 150 mm below it, 20 mm to the patient's left, curving toward the midline (world mm)."""
    c = np.asarray(isocenter_mm, dtype=np.float64)
    offsets = np.array([[22.0, 8.0, -150.0], [21.0, 6.0, -110.0], [20.0, 4.0, -70.0], [16.0, 0.0, -45.0],
                        [12.0, -6.0, -30.0], [8.0, -10.0, -20.0]])  # fmt: skip
    return c + offsets
