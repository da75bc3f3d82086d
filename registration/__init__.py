"""roadmap3d: automatic 2D-3D registration for the neurovascular 3D roadmap.

Examples
--------
>>> import registration
>>> ex = registration.load_example()                      # the phantom's 3DRA and a moved image
>>> result = registration.register(ex.volume, ex.image)   # estimates the patient motion
>>> error = registration.residuals(result.patient_motion, ex.truth_motion, ex.image.geometry)
>>> bool(error.success)                                   # < 1 mm and < 3 degrees at the iso-center
True

The engine, in layers (docs/ARCHITECTURE.md has the picture; ``tests/test_architecture.py``
keeps it):

- :mod:`registration.core`: the numerical core (geometry, volumes, DRRs, similarity, annealing,
  registration, metrics). Arrays and dataclasses in and out. Imports nothing else of the project.
- :mod:`registration.io`: files and data at rest (DICOM, meshes, the on-disk cache, atomic writes).
  Imports ``core``.
- :mod:`registration.sim`: the simulated world (the head phantom, honest X-ray image formation,
  C-arm bending and calibration, the rotational run and FDK). Imports ``core`` and ``io``.
- :mod:`registration.studies`: experiments (Table I cases, the phantom and clinical studies,
  reports, benchmarks). Imports everything above.

No module of ``registration`` prints or imports the web app or the command line (:mod:`app`);
the engine reports through return values, callbacks and :mod:`logging`.
See shared/CONVENTIONS.md (restated in README.md) for frames, angles and units.
"""

__version__ = "0.1.0"

#: The public API, defined in :mod:`registration.api` and loaded on first use (no numba, no
#: viser at ``import registration``). It is reached by name, not by an import statement, so the
#: version string above stays importable from every layer (docs/ARCHITECTURE.md).
__all__ = [
    "CArm",
    "Volume",
    "XRayImage",
    "Example",
    "Assessment",
    "Preparation",
    "register",
    "assess",
    "follow_cranium",
    "estimate_geometry",
    "track",
    "render_drr",
    "residuals",
    "load_example",
]


def __getattr__(name: str) -> object:
    if name in __all__:
        import importlib

        value = getattr(importlib.import_module("registration.api"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'registration' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
