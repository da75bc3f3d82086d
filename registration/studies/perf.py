"""Timing of the DRR renderer and of gradient difference (used by ``roadmap3d bench``).

The benchmark volume is a synthetic head-like volume in HU (an ellipsoidal skull shell around
soft tissue with a few dense and air-filled blobs, in air) on the 3DRA grid of the 27 cm volume
format, so that timings do not depend on the phantom module; like a real head in that format it
overfills the cube in two directions. Images use the 27 cm image format with its circular
field mask, at an oblique view (LAO 30, CRAN 15).

Times are wall-clock medians in milliseconds (``time.perf_counter``) on however many threads
numba uses; ``cpu_ms_median`` adds the process CPU time per call, which shows how much of a
slow wall time is the machine being shared.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import numba
import numpy as np
from scipy import ndimage

from registration.core.blas import one_blas_thread
from registration.core.drr import DRRRenderer, render_reference
from registration.core.geometry import CArm
from registration.core.similarity import GradientDifference
from registration.core.volume import Volume, format_grid

#: (image pixels, volume voxels) pairs of the benchmark: 64^2 from 64^3, and so on.
DEFAULT_SIZES: tuple[tuple[int, int], ...] = ((64, 64), (128, 128), (256, 256))

#: Volume and image format of the benchmark (cm).
BENCH_FORMAT_CM = 27.0

#: View of the benchmark (degrees).
BENCH_PRIMARY_DEG = 30.0
BENCH_SECONDARY_DEG = 15.0


def bench_volume(voxels: int, *, seed: int = 0) -> Volume:
    """A head-like HU volume of ``voxels``^3 on the 27 cm 3DRA grid (deterministic).

    An ellipsoidal head (radii 75 mm left-right, 95 mm antero-posterior, 115 mm
    cranio-caudal) with a 7 mm skull, soft tissue, dense and air-filled blobs and mild noise,
    smoothed like a reconstruction. Like a real head in the 27 cm format (182 mm field of view
    at the iso-center) it overfills the cube in two directions, so the renderer's clipping to
    the non-air box gains little.
    """
    if int(voxels) != voxels or voxels < 8:
        raise ValueError(f"voxels must be an integer >= 8, got {voxels}")
    spacing, axis = format_grid(BENCH_FORMAT_CM, voxels=int(voxels))
    z, y, x = np.meshgrid(axis, axis, axis, indexing="ij", sparse=True)
    radii = np.array([75.0, 95.0, 115.0])
    rho = np.sqrt((x / radii[0]) ** 2 + (y / radii[1]) ** 2 + ((z + 15.0) / radii[2]) ** 2)
    hu = np.full(rho.shape, -1000.0, dtype=np.float32)
    hu[rho < 1.0] = 1300.0  # skull
    hu[rho < 1.0 - 7.0 / radii[0]] = 35.0  # brain and soft tissue
    rng = np.random.default_rng(seed)
    for _ in range(16):  # dense (petrous-like) and air (sinus-like) blobs
        c = rng.uniform(-50.0, 50.0, 3)
        r = rng.uniform(5.0, 14.0)
        inside = (x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2 < r * r
        hu[inside] = rng.choice([900.0, -900.0])
    hu += rng.normal(0.0, 20.0, hu.shape).astype(np.float32)
    hu = ndimage.gaussian_filter(hu, 0.7)
    return Volume.from_grid(hu, spacing, label="synthetic head-like benchmark volume")


def bench_geometry(pixels: int) -> CArm:
    """The benchmark view: 27 cm format, ``pixels``^2, LAO 30 CRAN 15."""
    return CArm.for_format(
        BENCH_FORMAT_CM, pixels=pixels, primary_deg=BENCH_PRIMARY_DEG, secondary_deg=BENCH_SECONDARY_DEG
    )


def median_ms(fn: Callable[[], object], repeats: int, *, warmup: int = 1) -> float:
    """Median wall time of ``fn()`` in milliseconds over ``repeats`` calls after ``warmup``."""
    for _ in range(warmup):
        fn()
    wall = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        fn()
        wall.append(time.perf_counter() - t0)
    return float(np.median(wall) * 1e3)


def round_ratios(reference_ms: Sequence[float], fast_ms: Sequence[Sequence[float]]) -> dict:
    """Speed-ups of rounds, each one reference call against the median of the fast calls beside it.

    ``speedup`` is the median over rounds, ``speedup_min`` the least (the round the load hurt the
    most), ``speedup_of_minima`` the reference's fastest call over the fast renderer's fastest
    (both closest to an unloaded machine) and ``speedup_rounds`` every round's ratio.
    """
    if not reference_ms or len(reference_ms) != len(fast_ms) or any(len(f) == 0 for f in fast_ms):
        raise ValueError("every round needs one reference time and at least one fast time")
    ratios = [float(r) / float(np.median(f)) for r, f in zip(reference_ms, fast_ms, strict=True)]
    return {
        "speedup": round(float(np.median(ratios)), 1),
        "speedup_min": round(min(ratios), 1),
        "speedup_of_minima": round(float(min(reference_ms)) / float(min(min(f) for f in fast_ms)), 1),
        "speedup_rounds": [round(r, 1) for r in ratios],
    }


def _bench_one(image_px: int, volume_px: int, repeats: int, rounds: int, masked: bool) -> dict:
    volume = bench_volume(volume_px)
    geometry = bench_geometry(image_px)
    renderer = DRRRenderer(volume, levels=1)
    mask = geometry.field_mask() if masked else None
    out = np.empty((geometry.rows, geometry.cols), dtype=np.float32)
    render = lambda: renderer.render(geometry, mask=mask, out=out)  # noqa: E731
    for _ in range(3):  # warm-up: compiled code, caches
        render()
    render_reference(volume, geometry)  # its first call is up to 3x slower: untimed, like ours
    # rounds interleave the two renderers, so that a burst of load on the shared machine slows
    # both within a round instead of one of them; each round's fast calls follow two untimed ones
    per_round = max(1, repeats // max(1, rounds))
    ref_ms: list[float] = []
    fast_rounds: list[list[float]] = []
    cpu_ms: list[float] = []
    reference = None
    for _ in range(max(1, rounds)):
        t0 = time.perf_counter()
        reference = render_reference(volume, geometry)
        ref_ms.append((time.perf_counter() - t0) * 1e3)
        render()  # the first calls after the reference run on cold caches and sleeping threads
        render()
        walls = []
        for _ in range(per_round):
            c0 = time.process_time()
            t0 = time.perf_counter()
            render()
            walls.append((time.perf_counter() - t0) * 1e3)
            cpu_ms.append((time.process_time() - c0) * 1e3)
        fast_rounds.append(walls)
    fast_all = [w for walls in fast_rounds for w in walls]
    fast_ms = float(np.median(fast_all))
    before = renderer.samples_per_level[0]
    renderer.render(geometry, mask=mask, out=out)
    samples = renderer.samples_per_level[0] - before
    fast = renderer.render(geometry)
    scale = float(reference.max()) or 1.0
    return {
        "image_px": int(image_px),
        "volume_px": int(volume_px),
        "ms_median": round(fast_ms, 4),
        "ms_min": round(min(fast_all), 4),
        "cpu_ms_median": round(float(np.median(cpu_ms)), 4),
        "threads": numba.get_num_threads(),
        # the work of one DRR, whatever the machine's load: its bilinear samples
        "samples_per_drr": int(samples),
        "ns_per_sample": round(fast_ms * 1e6 / samples, 3) if samples else None,
        "reference_ms_median": round(float(np.median(ref_ms)), 2),
        "reference_ms_min": round(min(ref_ms), 2),
        "rounds": len(ref_ms),
        **round_ratios(ref_ms, fast_rounds),
        "max_rel_error": round(float(np.abs(fast - reference).max()) / scale, 5),
    }


def bench_drr(
    sizes: Sequence[tuple[int, int]] = DEFAULT_SIZES,
    repeats: int = 50,
    *,
    rounds: int = 5,
    masked: bool = True,
) -> list[dict]:
    """DRR times of the fast renderer and of the reference, per (image, volume) size, in rounds.

    After an untimed warm-up of both, each round renders the reference once
    (:func:`registration.core.drr.render_reference` at its default step of half a voxel, whole
    image) and then, after two untimed calls, the fast
    renderer ``repeats // rounds`` times into a reused buffer (with the circular field mask when
    ``masked``). Each record: ``image_px`` and ``volume_px`` (edge lengths); ``ms_median`` and ``ms_min`` of the fast
    renderer over all its calls (the minimum is close to the unloaded machine when others share
    it); ``cpu_ms_median`` (its process CPU time per call); ``threads`` (numba threads);
    ``samples_per_drr`` (bilinear samples of one masked DRR: the load-free work) and
    ``ns_per_sample`` (``ms_median`` over them); ``reference_ms_median`` and ``reference_ms_min``;
    ``rounds``; the speed-ups of :func:`round_ratios`; ``max_rel_error`` (max |fast - reference|
    over the reference's maximum, whole image).

    Both run with BLAS on one thread, as the engine registers
    (:func:`registration.core.blas.one_blas_thread`): the reference's matrix products would
    otherwise leave BLAS threads spinning on the cores the fast renderer's next calls need.
    """
    with one_blas_thread():
        return [_bench_one(int(image_px), int(volume_px), repeats, rounds, masked) for image_px, volume_px in sizes]


def bench_gradient_difference(image_px: int = 128, repeats: int = 200) -> float:
    """Median milliseconds of one prepared gradient-difference evaluation at ``image_px``^2."""
    volume = bench_volume(64)
    geometry = bench_geometry(image_px)
    renderer = DRRRenderer(volume, levels=1)
    mask = geometry.field_mask()
    xray = renderer.render(geometry)
    rng = np.random.default_rng(0)
    xray = xray + rng.normal(0.0, 0.01 * float(xray.max()), xray.shape).astype(np.float32)
    shifted = np.roll(renderer.render(geometry), 2, axis=1)
    measure = GradientDifference(xray, mask)
    return median_ms(lambda: measure(shifted), repeats, warmup=2)
