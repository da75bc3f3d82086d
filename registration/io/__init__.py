"""Files and data at rest: DICOM in and out, vessel and bone meshes, the on-disk cache.

Owns: every format detail (DICOM tags, axis flips, transfer syntaxes, atomic writes), so the
core never sees one. May import: ``registration.core`` and third-party readers/writers.
Not ``sim``, ``studies`` or ``app``.
"""
