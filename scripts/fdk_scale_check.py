"""Is the clinical study's 3DRA at the scale of its frames? (docs/validation/clinical-200/scale_check.md)

For one virtual patient of the clinical study (the cached rotational run and its FDK
reconstruction, ``registration.studies.runs.patient_data``):

1. the magnification of the calibrated geometry (the one the reconstruction and the
   registration use) against the true, bent geometry the frames were formed with;
2. a similarity fit of the reconstruction against the phantom voxelised on the same grid: the
   normalised cross-correlation (HU clipped to [-1000, 2000], inside 80 % of the grid and the
   reconstructable field) of the reconstruction with the phantom (smoothed by one voxel) scaled
   about the iso-center,
   isotropically and per axis (x = y in the rotation plane, z along the rotation axis).

    .venv/bin/python scripts/fdk_scale_check.py 22 1 1   # format (cm), phantom seed, contrast
    .venv/bin/python scripts/fdk_scale_check.py 27 2 0

Slow the first time (the run and its reconstruction are simulated; minutes), then the
voxelisation of the phantom dominates (seconds to minutes).
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy import ndimage

from registration.sim.phantom import make_head_phantom
from registration.sim.reconstruct import _view_frame
from registration.studies.runs import patient_data


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("format_cm", type=float)
    parser.add_argument("phantom_seed", type=int)
    parser.add_argument("contrast", type=int, choices=(0, 1))
    parser.add_argument("--voxels", type=int, default=128)
    args = parser.parse_args()
    data = patient_data(args.phantom_seed, args.format_cm, bool(args.contrast), 120, 200.0, 256, args.voxels)
    pairs = zip(data.true_geometries, data.calibrated_geometries, strict=True)
    frames = [(_view_frame(t), _view_frame(c)) for t, c in pairs]
    mag_true = np.mean([t.focal_mm / t.source_iso_mm for t, _ in frames])
    mag_cal = np.mean([c.focal_mm / c.source_iso_mm for _, c in frames])
    print(f"magnification at the iso-center: true {mag_true:.6f}, calibrated {mag_cal:.6f} "
          f"(ratio {mag_cal / mag_true:.7f})")  # fmt: skip
    vol = data.volume
    phantom = make_head_phantom(seed=args.phantom_seed, contrast=bool(args.contrast))
    # smoothed by a voxel: the reconstruction is blurred, and the linear interpolation of the
    # scaled copies would otherwise smooth every scale but 1 (and favour them)
    ref = ndimage.gaussian_filter(phantom.voxelize(vol.data.shape, vol.index_to_world, supersample=2), 1.0)
    rec = np.clip(vol.data.astype(np.float64), -1000.0, 2000.0)
    iso = np.linalg.solve(vol.index_to_world, [0.0, 0.0, 0.0, 1.0])[:3][::-1]  # (k, j, i)
    n = vol.data.shape[0]
    kk, jj, ii = np.indices(rec.shape)
    inside = (vol.data > -990) & (np.abs(kk - iso[0]) < 0.4 * n) & (np.abs(jj - iso[1]) < 0.4 * n)
    inside &= np.abs(ii - iso[2]) < 0.4 * n
    a = rec[inside] - rec[inside].mean()

    def ncc(s_xy: float, s_z: float) -> float:
        # the phantom scaled by s about the iso-center: value at p = ref(iso + (p - iso) / s)
        mat = np.diag([1.0 / s_z, 1.0 / s_xy, 1.0 / s_xy])
        moved = ndimage.affine_transform(ref, mat, offset=iso - mat @ iso, order=1, mode="nearest")
        b = np.clip(moved, -1000.0, 2000.0)[inside]
        b = b - b.mean()
        return float(a @ b / np.sqrt((a @ a) * (b @ b)))

    scales = np.round(np.arange(0.985, 1.0151, 0.0025), 4)
    iso_fit = [(s, ncc(s, s)) for s in scales]
    for s, v in iso_fit:
        print(f"isotropic scale {s:.4f}: NCC {v:.5f}")
    best = max(iso_fit, key=lambda x: x[1])
    print(f"best isotropic scale {best[0]:.4f} (NCC {best[1]:.5f})")
    grid = [(sxy, sz, ncc(sxy, sz)) for sxy in (0.99, 1.0, 1.01) for sz in (0.99, 1.0, 1.01)]
    sxy, sz, v = max(grid, key=lambda x: x[2])
    print(f"best per-axis scale (1 % steps): x = y {sxy:.2f}, z {sz:.2f} (NCC {v:.5f})")


if __name__ == "__main__":
    main()
