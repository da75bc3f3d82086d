"""``--report DIR`` of ``register`` and ``track``: the report folder of
:mod:`registration.studies.qa_report` / :mod:`registration.studies.qa_track`, from what the
command read and computed."""

from __future__ import annotations

import shlex
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from registration.core.drr import DRRRenderer
    from registration.core.images import XRayImage
    from registration.core.volume import Volume
    from registration.studies.qa_report import Anatomy


def check_report_folder(folder: Path | None) -> None:
    """Refuse ``--report`` before any work: the folder must be new or empty, its parent writable."""
    if folder is None:
        return
    folder = Path(folder)
    if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
        raise ValueError(f"{folder}: exists and is not an empty folder (--report writes a new folder)")
    parent = folder.parent if str(folder.parent) else Path(".")
    existing = next((p for p in (parent, *parent.parents) if p.exists()), Path("."))
    if not existing.is_dir():
        raise ValueError(f"{folder}: {existing} is not a folder (--report)")
    import os

    if not os.access(existing, os.W_OK):
        raise ValueError(f"{folder}: cannot write into {existing} (--report)")


def command_line(identify: bool) -> str:
    """The command as typed (``identify``), else its subcommand and flags only: paths and values
    may name the patient."""
    argv = [Path(sys.argv[0]).name, *sys.argv[1:]]
    if identify:
        return shlex.join(argv)
    kept = [argv[0]] + [a for n, a in enumerate(argv[1:]) if a.startswith("-") or n == 0]
    return " ".join(kept)


def vessel_anatomy(volume: Volume) -> Anatomy | None:
    """The volume's vessel surface for the roadmap outline (None: no contrast-filled vessels)."""
    from registration.io.meshes import surface_meshes
    from registration.studies.qa_report import Anatomy

    meshes = surface_meshes(volume)
    if "vessels" not in meshes:
        return None
    return Anatomy(np.asarray(meshes["vessels"].vertices), float(max(volume.spacing_mm)))


def write_register_report(
    folder: Path,
    *,
    document: dict[str, Any],
    assessed: dict[str, Any] | None,
    volume: Volume,
    views: list[XRayImage],
    renderer: DRRRenderer,
    initial_motion: np.ndarray | None,
    identify: bool,
) -> Path:
    """The report of one ``register`` run (its JSON ``document``, the confidence's fields)."""
    from registration.studies.qa_report import write_registration_report

    return write_registration_report(
        folder, document=document, volume=volume, views=views, renderer=renderer, initial_motion=initial_motion,
        anatomy=vessel_anatomy(volume), depth_probe=(assessed or {}).get("depth_probe"),
        depth_scan=(assessed or {}).get("depth_scan"), depth_far=(assessed or {}).get("depth_far"), identify=identify,
        command=command_line(identify),
    )  # fmt: skip


def write_run_report(
    folder: Path,
    *,
    document: dict[str, Any],
    volume: Volume,
    last_views: list[XRayImage],
    renderer: DRRRenderer,
    truth: np.ndarray | None,
    identify: bool,
) -> Path:
    """The report of one ``track`` run (its JSON ``document``)."""
    from registration.studies.qa_track import write_track_report

    return write_track_report(
        folder, document=document, volume=volume, last_views=last_views, renderer=renderer, truth=truth,
        anatomy=vessel_anatomy(volume), identify=identify, command=command_line(identify),
    )  # fmt: skip
