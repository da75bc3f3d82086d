"""Clinical-looking X-ray images formed from a volume: collimator blades, burned-in text and
rulers, an overlay plane, the vendor's display chain, bone contrast, scatter, the heel effect, a
static table and headrest, and a neck that bends; each effect an option with its strength as
parameters, all composable (:class:`ClinicalEffects`, :class:`ClinicalImager`).

The images are formed by :mod:`registration.sim.volume_xray`'s integrator and
:func:`registration.sim.xray.simulate_xray`'s detector model, never by the DRR renderer that
scores them.
"""

from registration.sim.clinical.effects import (
    EFFECT_NAMES,
    Blades,
    BoneContrast,
    BurnedInText,
    ClinicalEffects,
    Display,
    Heel,
    Neck,
    Overlay,
    Scatter,
    Table,
    parse_realism,
)
from registration.sim.clinical.imager import CLINICAL_IMAGES_FROM_VOLUME, ClinicalImage, ClinicalImager, with_strength

__all__ = [
    "CLINICAL_IMAGES_FROM_VOLUME",
    "EFFECT_NAMES",
    "Blades",
    "BoneContrast",
    "BurnedInText",
    "ClinicalEffects",
    "ClinicalImage",
    "ClinicalImager",
    "Display",
    "Heel",
    "Neck",
    "Overlay",
    "Scatter",
    "Table",
    "parse_realism",
    "with_strength",
]
