"""The same draws registered once per variant of the options, one JSON line per draw with each
variant's record (``keys`` of it): the study scripts' shared loop.

``write_runs``: the rotational-run study (``roadmap3d validate clinical --quick``, ``cases``
registrations per patient), a line as each draw ends; ``write_volume``: the shared real CT's
clinical-looking images (``roadmap3d validate volume --realism clinical``, single plane, at
``strength``), written when every variant has run.
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
