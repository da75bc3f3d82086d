"""roadmap3d: automatic 2D-3D registration for the neurovascular 3D roadmap.

The numerical engine: numpy in, numpy and dataclasses out; no printing, no GUI.
See shared/CONVENTIONS.md (restated in README.md) for frames, angles and units.
"""

__version__ = "0.1.0"
