"""The simulated world: the analytic head phantom, honest X-ray image formation, C-arm bending,
the dodecahedron calibration, the rotational run and its FDK reconstruction.

Owns: everything that makes test data without touching the renderer that scores it
(DESIGN.md, "honest simulation"). May import: ``registration.core`` and ``registration.io``
(the cache). Not ``studies`` or ``app``.
"""
