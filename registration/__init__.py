"""roadmap3d: automatic 2D-3D registration for the neurovascular 3D roadmap.

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
