"""Where a user's data is imaged about: the iso-center of ``--isocenter``, the volume's
IsocenterPosition (300A,012C), or the world origin (CONVENTIONS §1). Shared by the command line
and the web app."""

from __future__ import annotations

import math

from registration.core.volume import Volume

#: ``--isocenter`` keyword: the center of the volume's voxel grid.
VOLUME_CENTER = "volume-center"


def resolve_isocenter(text: str | None, volume: Volume | None = None) -> tuple[tuple[float, float, float], str]:
    """The iso-center (mm, world frame) for ``--isocenter`` and where it came from.

    * ``"x,y,z"``: as given;
    * ``"volume-center"``: the center of the volume's voxel grid (``Volume.center_mm``);
    * absent: IsocenterPosition (300A,012C) when the volume's files carry it (read into
      ``volume.meta["isocenter_mm"]``), else the world origin (CONVENTIONS §1).
    """
    if text is None or text.strip() == "":
        if volume is not None and volume.meta.get("isocenter_mm") is not None:
            iso = tuple(float(v) for v in volume.meta["isocenter_mm"])
            return (iso[0], iso[1], iso[2]), str(volume.meta.get("isocenter_from", "the volume's files"))
        return (0.0, 0.0, 0.0), "the world origin (default)"
    if text.strip().lower() == VOLUME_CENTER:
        if volume is None:
            raise ValueError(f"--isocenter {VOLUME_CENTER} needs the volume (--volume)")
        center = [float(v) for v in volume.center_mm]
        return (center[0], center[1], center[2]), "the center of the volume's grid (--isocenter volume-center)"
    parts = text.replace(" ", "").split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise ValueError(
            f"--isocenter must be three numbers 'x,y,z' in mm or '{VOLUME_CENTER}', got {text!r}"
        ) from None
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise ValueError(f"--isocenter must be three finite numbers 'x,y,z' in mm or '{VOLUME_CENTER}', got {text!r}")
    return (values[0], values[1], values[2]), "--isocenter"
