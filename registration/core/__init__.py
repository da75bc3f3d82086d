"""The numerical core: C-arm geometry and poses, volumes, DRRs, similarity, annealing, registration.

Owns: the math of one registration (CONVENTIONS.md §1-§6). Arrays and frozen dataclasses in,
arrays and dataclasses out; options keyword-only and checked with ``ValueError``.
May import: numpy, scipy, numba, and other modules of ``registration.core``. Nothing else of
the project (not ``io``, ``sim``, ``studies`` or ``app``).
"""
