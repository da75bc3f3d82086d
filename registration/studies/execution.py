"""Running a study's tasks: each in a worker (joblib processes or a Dask cluster), its record appended
to a resumable results.jsonl as it arrives (a rerun skips what is done), the volumes built first.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

from registration import __version__
from registration.core.blas import with_one_blas_thread
from registration.core.register import RegistrationOptions
from registration.studies.cases import case_volume, run_case
from registration.studies.runs import ClinicalCase, StudyTask, patient_of, patient_params, run_clinical_case

if TYPE_CHECKING:
    pass


@with_one_blas_thread
def execute(task: StudyTask, threads: int | None = None) -> dict:
    """Run one task (in a worker) and return its record (JSON-ready); BLAS on one thread
    throughout, the images' simulation included (:mod:`registration.core.blas`)."""
    if threads:
        import numba

        numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))
    options = task.options
    if threads:
        # The capture runs' threads share this worker's cores too (no oversubscription).
        options = dataclasses.replace(options or RegistrationOptions(), threads=int(threads))
    if isinstance(task.case, ClinicalCase):
        record = run_clinical_case(task.case, options=options)
    elif hasattr(task.case, "run"):  # a case that runs itself (the biplane study)
        record = task.case.run(options=options)
    else:
        record = run_case(task.case, options=options)
    record.update(task.extra)
    record["case_id"] = task.case_id
    record["version"] = __version__
    record["revision"] = _revision()
    return record


@lru_cache(maxsize=1)
def _revision() -> str:
    from registration.studies.report_kit import source_revision

    return source_revision()


def prebuild(tasks: Iterable[StudyTask], log: Callable[[str], None] | None = None) -> None:
    """Build every volume (and rotational run) the tasks need, once, in this process."""
    done: set = set()
    for task in tasks:
        case = task.case
        if hasattr(case, "prepare"):  # a case that prepares its own volume (the biplane study)
            key: tuple = case.prepare_key()
            if key not in done:
                if log:
                    log(f"preparing {key}")
                case.prepare()
        elif isinstance(case, ClinicalCase):
            key = ("patient", *patient_params(case).values())
            if key not in done:
                if log:
                    log(f"preparing patient {case.patient}: rotational run and FDK ({case.volume_format_cm:g} cm)")
                patient_of(case)
        else:
            key = (
                "volume",
                case.phantom_seed,
                case.facial,
                case.volume_format_cm,
                case.volume_voxels,
                case.volume_source,
                case.volume_contrast,
                case.volume_center_mm,
            )
            if key not in done:
                if log:
                    log(f"preparing the {case.volume_format_cm:g} cm volume ({case.volume_source})")
                case_volume(case)
        done.add(key)


# --------------------------------------------------------------------------------------
# Results log (resume, crash safety)
# --------------------------------------------------------------------------------------
class ResultsLog:
    """``results.jsonl``: one record per line, appended, flushed and fsynced per record.

    Reading drops a torn last line (a kill during a write) and any line that is not a JSON
    object with a ``case_id``; before appending, a last line that does not parse is cut off
    and one that only lost its newline gets it back, so no finished record is ever dropped.
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)

    def read(self) -> list[dict]:
        if not self.path.exists():
            return []
        records = []
        for line in self.path.read_text().splitlines():
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(rec, dict) and "case_id" in rec:
                records.append(rec)
        return records

    def _repair_tail(self) -> None:
        """Make the file end with a newline without losing a record.

        A last line that parses (only its newline was lost) is kept and gets its newline; a
        last line that does not parse (torn by a kill during a write) is cut off.
        """
        if not self.path.exists():
            return
        with open(self.path, "rb+") as fh:
            data = fh.read()
            if not data or data.endswith(b"\n"):
                return
            cut = data.rfind(b"\n") + 1
            try:
                json.loads(data[cut:].decode("utf-8"))
            except (UnicodeDecodeError, json.JSONDecodeError):
                fh.truncate(cut)
            else:
                fh.seek(0, os.SEEK_END)
                fh.write(b"\n")
            fh.flush()
            os.fsync(fh.fileno())

    def append(self, record: dict) -> None:
        self._repair_tail()
        line = json.dumps(record, sort_keys=True) + "\n"
        with open(self.path, "a", encoding="utf-8") as fh:
            fh.write(line)
            fh.flush()
            os.fsync(fh.fileno())


# --------------------------------------------------------------------------------------
# Running a study
# --------------------------------------------------------------------------------------
def _results_local(tasks: list[StudyTask], n_jobs: int) -> Iterator[dict]:
    if n_jobs <= 1:
        for task in tasks:
            yield execute(task)
        return
    from joblib import Parallel, delayed

    # one numba thread per process: the processes already fill the cores
    parallel = Parallel(n_jobs=n_jobs, backend="loky", return_as="generator_unordered", batch_size=1)
    yield from parallel(delayed(execute)(task, 1) for task in tasks)


def _results_dask(tasks: list[StudyTask], scheduler: Any) -> Iterator[dict]:
    from distributed import Client, as_completed

    client = scheduler if isinstance(scheduler, Client) else Client(scheduler)
    try:
        futures = client.map(execute, tasks, [1] * len(tasks), pure=False)
        for future in as_completed(futures):
            yield future.result()
    finally:
        if client is not scheduler:
            client.close()


def run_study(
    tasks: list[StudyTask],
    out: Path,
    *,
    n_jobs: int | None = None,
    scheduler: Any = None,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
) -> tuple[list[dict], float]:
    """Run the tasks not yet in ``out/results.jsonl``; return (all records of these tasks, wall
    seconds of every invocation that ran some of them).

    ``scheduler``: a Dask address (``tcp://HOST:PORT``) or a ``distributed.Client``; else
    joblib processes on ``n_jobs`` local cores (default: all).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    results = ResultsLog(out / "results.jsonl")
    wanted = {t.case_id for t in tasks}
    finished = {r["case_id"]: r for r in results.read() if r["case_id"] in wanted}
    todo = [t for t in tasks if t.case_id not in finished]
    started = time.perf_counter()
    if todo:
        prebuild(todo, log)
    jobs = n_jobs or os.cpu_count() or 1
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(tasks), initial=len(finished), file=sys.stderr, unit="reg", dynamic_ncols=True)
    ok = sum(bool(r["success"]) for r in finished.values())
    try:
        stream = _results_dask(todo, scheduler) if scheduler is not None else _results_local(todo, jobs)
        for record in stream:
            results.append(record)
            finished[record["case_id"]] = record
            ok += bool(record["success"])
            if bar is not None:
                bar.set_postfix_str(f"success {ok}/{len(finished)} ({100.0 * ok / len(finished):.0f}%)")
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    order = {t.case_id: i for i, t in enumerate(tasks)}
    records = sorted(finished.values(), key=lambda r: order[r["case_id"]])
    return records, _log_invocation(out, len(todo), time.perf_counter() - started)


def _log_invocation(out: Path, ran: int, wall_seconds: float) -> float:
    """Append this invocation to ``out/invocations.jsonl``; return the wall time of every
    invocation that ran registrations (a killed one is not counted)."""
    path = out / "invocations.jsonl"
    entry = {"ran": ran, "wall_seconds": wall_seconds, "finished_unix": time.time(), "version": __version__}
    if ran:
        with open(path, "a", encoding="utf-8") as fh:
            fh.write(json.dumps(entry) + "\n")
    total = 0.0
    if path.exists():
        for line in path.read_text().splitlines():
            try:
                total += float(json.loads(line)["wall_seconds"])
            except (ValueError, KeyError, TypeError):
                continue
    return total if total else wall_seconds
