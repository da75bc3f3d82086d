"""Experiments on the engine: Table I cases, the phantom and clinical studies, reports, benchmarks.

Owns: study configurations (frozen dataclasses), records, resumable result logs, summaries,
figures and speed measurements. Returns data; printing belongs to the command line (``app.cli``).
May import: ``registration.core``, ``registration.io``, ``registration.sim``. Not ``app``.
"""
