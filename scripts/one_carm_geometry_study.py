"""One C-arm at several angulations of a still patient: can the detector's principal point and
source-image distance be estimated with the pose when every view shares them?

The biplane study's moments (the phantom, clinical offsets) are imaged by plane A at its own
angulation and at further ones (``--angles "60,20;-45,-25"``: primary, secondary degrees added),
the analytic phantom's line integrals with the exact geometry. The files then give a detector
shifted by ``--shift-px`` in a random direction and a source-image distance ``--sid-error`` short,
the same for every view. Each moment is registered on the files' geometry, then the pose and
one shared set of intrinsics are refined (``refine_geometry(..., shared=True)`` and the second
pass on the volume's own grid). ``--from-truth`` starts the refinement at the true pose.

    PYTHONPATH=. python scripts/one_carm_geometry_study.py --seed 100 --moments 2 --angles "60,20;-45,-25"
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace

import numpy as np

from registration.core.intrinsics import refine_geometry, refine_on_own_grid, with_intrinsics
from registration.core.metrics import residuals
from registration.core.preparation import Preparation
from registration.core.register import RegistrationOptions, register
from registration.sim.biplane import BiplaneSystem
from registration.sim.xray import simulate_xray
from registration.studies.biplane import BiplaneConfig, _offset_motion, biplane_tasks, study_volume
from registration.studies.cases import _phantom


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=100)
    parser.add_argument("--moments", type=int, default=2)
    parser.add_argument("--shift-px", type=float, default=10.0)
    parser.add_argument("--sid-error", type=float, default=0.05)
    parser.add_argument("--angles", default="60,20;-45,-25")
    parser.add_argument("--from-truth", action="store_true")
    args = parser.parse_args()
    extra = [tuple(float(a) for a in part.split(",")) for part in args.angles.split(";")]
    config = BiplaneConfig(patients=((0, 27.0),), registrations_per_patient=args.moments, seed=args.seed)
    estimate = ("sid", "principal_point")
    for task in biplane_tasks(config):
        moment = task.case
        volume = study_volume(None, moment.phantom_seed, moment.volume_format_cm, moment.volume_voxels)
        truth = _offset_motion(moment)
        anatomy = _phantom(moment.phantom_seed, False, True)
        system = BiplaneSystem()
        plane = system.planes()[0]
        primary, secondary = moment.angles_deg[0]
        exact = []
        for k, (p, s) in enumerate([(primary, secondary)] + [(primary + a, secondary + b) for a, b in extra]):
            geometry = system.calibrated_geometry(plane, plane.nominal(p, s, pixels=moment.pixels[0]))
            exact.append(simulate_xray(anatomy, geometry, motion=truth, kind=moment.kind, seed=moment.seed + k))
        rng = np.random.default_rng([moment.seed, 0x6E0])
        direction = rng.normal(size=2)
        shift = args.shift_px * direction / np.linalg.norm(direction)
        files = [replace(v, geometry=with_intrinsics(v.geometry, 1.0 / (1.0 + args.sid_error), shift)) for v in exact]
        options = RegistrationOptions()
        prepared = Preparation.of(volume, tuple(files), options=options)
        plain = register(volume, list(files), truth=truth, seed=moment.seed, options=options,
                         renderer=prepared.renderer)  # fmt: skip
        began = time.perf_counter()
        start = truth if args.from_truth else plain.patient_motion
        first = refine_geometry(prepared.renderer, files, start, estimate=estimate, shared=True)
        found = refine_on_own_grid(volume, files, first, estimate=estimate, shared=True)
        residual = residuals(found.patient_motion, truth, files[0].geometry, None, optimizes_tz=True)
        detector = found.intrinsics[0]
        print(json.dumps({
            "case": task.case_id, "angles_deg": [list(moment.angles_deg[0]), *map(list, extra)],
            "from_truth": args.from_truth,
            "files_translation_mm": round(float(plain.residual.translation_mm), 3),
            "estimated_translation_mm": round(float(residual.translation_mm), 3),
            "estimated_success": bool(residual.success_total),
            "shift_px": [round(float(s), 2) for s in shift],
            "found_shift_px": [round(float(s), 2) for s in detector.principal_point_shift_px],
            "sid_error_percent": round(100.0 * (detector.sid_mm / exact[0].geometry.sid_mm - 1.0), 3),
            "seconds": round(time.perf_counter() - began, 1),
        }), flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
