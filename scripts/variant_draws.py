"""The same draws registered once per variant of the options, one JSON line per draw with each
variant's record (``keys`` of it): the study scripts' shared loop.

``write_runs``: the rotational-run study (``roadmap3d validate clinical --quick``, ``cases``
registrations per patient), a line as each draw ends; ``write_volume``: the shared real CT's
clinical-looking images (``roadmap3d validate volume --realism clinical``, single plane, at
``strength``), written when every variant has run; ``write_capture``: the capture-range study's
phantom moments at ``mm`` and ``deg`` (both planes and plane A alone), written when every variant
has run; ``write_biplane``: the biplane study's quick moments, a line as each draw ends.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import replace
from typing import IO

from registration.core.register import RegistrationOptions

Variants = dict[str, RegistrationOptions | None]


def write_runs(fh: IO[str], seed: int, cases: int, variants: Variants, keys: Sequence[str]) -> None:
    from registration.studies import runs

    config = replace(runs.ClinicalConfig.quick_config(seed), registrations_per_patient=cases)
    for task in runs.clinical_tasks(config):
        line = {"case_id": task.case_id, "study": "runs", "seed": seed}
        for name, options in variants.items():
            record = runs.run_clinical_case(task.case, options=options)
            line[name] = {k: record.get(k) for k in keys}
        fh.write(json.dumps(line) + "\n")
        fh.flush()


def write_volume(fh: IO[str], seed: int, cases: int, strength: float, variants: Variants, keys: Sequence[str]) -> None:
    import registration.studies.volume as study
    from registration.io import dicom

    volume = dicom.read_volume(study.find_real_ct())
    iso = study.head_isocenter_mm(volume)
    config = study.VolumeStudyConfig(cases=cases, seed=seed, realism="clinical", strengths=(strength,))
    passes = {name: study.run_volume_study(volume, iso, config, options=o)[0] for name, o in variants.items()}
    for n in range(cases):
        line = {"study": f"volume:{strength:g}", "seed": seed, "case": n}
        for name, records in passes.items():
            line[name] = {k: records[n].get(k) for k in keys}
        fh.write(json.dumps(line) + "\n")


def write_capture(fh: IO[str], seed: int, cases: int, mm: float, deg: float, variants: Variants,
                  keys: Sequence[str]) -> None:  # fmt: skip
    from registration.studies.capture import CaptureConfig, capture_tasks
    from registration.studies.execution import execute

    sweep = "combined" if mm and deg else "rotation" if deg else "translation"
    config = replace(CaptureConfig.quick_config(seed=seed), sweeps=(sweep,), translations_mm=(mm,),
                     rotations_deg=(deg,), registrations_per_level=cases)  # fmt: skip
    lines: dict[str, dict] = {}
    for name, options in variants.items():
        for task in capture_tasks(config, options):
            record = execute(task)
            first = {"case_id": task.case_id, "study": "capture", "seed": seed}
            lines.setdefault(task.case_id, first)[name] = {k: record.get(k) for k in keys}
    for line in lines.values():
        fh.write(json.dumps(line) + "\n")


def write_biplane(fh: IO[str], seed: int, cases: int, variants: Variants, keys: Sequence[str]) -> None:
    from registration.studies.biplane import BiplaneConfig, biplane_tasks

    config = replace(BiplaneConfig.quick_config(seed=seed), registrations_per_patient=cases)
    for task in biplane_tasks(config):
        line = {"case_id": task.case_id, "study": "biplane", "seed": seed}
        for name, options in variants.items():
            record = task.case.run(options=options)
            line[name] = {k: record.get(k) for k in keys}
        fh.write(json.dumps(line) + "\n")
        fh.flush()


def shared_real_ct() -> tuple[object, tuple[float, float, float]] | None:
    """The shared real CT and its head's iso-center; None (said on stderr) when it is not here."""
    import sys

    import registration.studies.volume as study
    from registration.io import dicom

    path = study.find_real_ct()
    if path is None:
        print("the shared real CT is not here (ROADMAP3D_REAL_CT)", file=sys.stderr)
        return None
    volume = dicom.read_volume(path)
    return volume, study.head_isocenter_mm(volume)


def clinical_draws(volume, iso, seed: int, cases: int, strength: float, *, biplane: bool = False) -> tuple:  # noqa: ANN001
    """`validate volume --realism clinical`'s draws on ``volume``: its config and the clinical
    views (every effect at ``strength``, written as XA files and read back)."""
    import registration.studies.volume as study
    from registration.sim.clinical import EFFECT_NAMES
    from registration.sim.clinical.anatomy import patient_only

    config = study.VolumeStudyConfig(cases=cases, seed=seed, realism="clinical", strengths=(strength,),
                                     biplane=biplane)  # fmt: skip
    views = study.ClinicalViews(volume, iso, EFFECT_NAMES, strength, catheter=config.catheter,
                                base=patient_only(volume)[0])  # fmt: skip
    return config, views
