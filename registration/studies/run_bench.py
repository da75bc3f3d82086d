"""Reading a real X-ray run frame by frame (used by ``roadmap3d bench``).

A run's frames are read as tracking reads them: each frame decoded, its usable field found in
its pixels (the collimation on the first frame and kept for the run, burned-in graphics on every
frame) and its intensities turned into attenuation. The reference in the same run is decoding
the same frames alone, with the decoder the reader uses.
"""

from __future__ import annotations

import os
import time
import warnings
from pathlib import Path

import numpy as np

#: The shared real coronary run beside the project (``ROADMAP3D_REAL_XA_RUN`` overrides it).
REAL_RUN_RELATIVE = Path("..") / "shared" / "data" / "real-xa" / "coronary-xa-96-frames.dcm"
#: The run states no distances or pixel size; these nominal values only let it be read (the
#: field and the intensities do not depend on them).
NOMINAL_GEOMETRY = {"sid_mm": 1200.0, "sod_mm": 800.0, "pixel_mm": 0.3}


def find_real_run() -> Path | None:
    """The shared real XA run (``ROADMAP3D_REAL_XA_RUN`` or ``../shared/data/real-xa/...``
    beside the project), None when absent."""
    env = os.environ.get("ROADMAP3D_REAL_XA_RUN")
    root = Path(__file__).resolve().parents[2]
    for candidate in ([Path(env)] if env else []) + [root / REAL_RUN_RELATIVE]:
        if candidate.is_file():
            return candidate
    return None


def bench_real_run(*, frames: int = 40) -> dict:
    """Milliseconds per frame of reading the shared real run through
    :func:`registration.io.dicom.read_xray_run` (the first frame apart: it finds the
    collimation), against decoding each frame alone, interleaved frame by frame; min and median
    over the frames and the median of the frames' ratios. ``{"skipped": reason}`` when absent."""
    import pydicom

    from registration.io.dicom import pixel_decoder, read_xray_run

    path = find_real_run()
    if path is None:
        return {"skipped": f"no real XA run at {REAL_RUN_RELATIVE} (or ROADMAP3D_REAL_XA_RUN)"}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the file's missing tags: `roadmap3d info` says them
        run = read_xray_run(path, **NOMINAL_GEOMETRY)
        ds = pydicom.dcmread(path)
        plugin, _ = pixel_decoder(ds)
        n = min(frames, len(run))
        pydicom.pixels.pixel_array(ds, index=0, decoding_plugin=plugin)  # the decoder loaded
        t0 = time.perf_counter()
        first = run[0]
        first_ms = (time.perf_counter() - t0) * 1e3
        read_ms, decode_ms = [], []
        for i in range(1, n):
            t0 = time.perf_counter()
            pydicom.pixels.pixel_array(ds, index=i, decoding_plugin=plugin)
            t1 = time.perf_counter()
            run[i]
            t2 = time.perf_counter()
            decode_ms.append((t1 - t0) * 1e3)
            read_ms.append((t2 - t1) * 1e3)
    return {
        "file": path.name,
        "frames": n,
        "pixels": list(first.image.shape),
        "first_frame_ms": first_ms,
        "frame_ms_median": float(np.median(read_ms)),
        "frame_ms_min": float(np.min(read_ms)),
        "decode_ms_median": float(np.median(decode_ms)),
        "decode_ms_min": float(np.min(decode_ms)),
        "frame_to_decode_median": float(np.median(np.divide(read_ms, decode_ms))),
        "field": first.meta.get("mask_from", ""),
        "decoder": plugin or "pydicom",
    }
