"""The effects that make a simulated X-ray image look clinical, each a small frozen option type.

Every effect has its strength as parameters (not constants) and ``at_strength(s)``: the effect
scaled from absent (``s = 0``) through typical (``s = 1``, the defaults) to severe (``s = 2``),
so that a study can sweep it. :class:`ClinicalEffects` composes any subset; :func:`parse_realism`
reads the command line's ``--realism`` words (``clean``, ``clinical`` = all, or effect names
joined by ``+``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

#: Blade shapes :class:`Blades` knows.
BLADE_SHAPES = ("rectangular", "wedge", "circular")
#: Polarities of the stored pixels: bone (more attenuation) dark or bright.
POLARITIES = ("bone_dark", "bone_bright")
#: PixelIntensityRelationship (0028,1040) values the display chain may write (None: no tag).
RELATIONSHIPS = ("DISP", "LOG", None)


def _check(name: str, value: float, lo: float, hi: float) -> None:
    if not (isinstance(value, (int, float)) and math.isfinite(value) and lo <= value <= hi):
        raise ValueError(f"{name} must lie in [{lo:g}, {hi:g}], got {value!r}")


def _strength(s: float) -> float:
    _check("strength", s, 0.0, 3.0)
    return float(s)


@dataclass(frozen=True)
class Blades:
    """Collimator blades: X-rays blocked at the tube side, a sharp straight (or circular) edge.

    ``closed`` is the fraction of the field's half-width closed from the (left, right, top,
    bottom) side; ``rotation_deg`` turns the rectangular blades about the field center;
    ``transmission`` is what passes a blade (with the veiling glare: behind it a weak, noisy
    signal, never a constant); a wedge filter closes ``wedge_closed`` of the field from its
    ``wedge_side`` with ``wedge_transmission``; a circular iris keeps ``iris_fraction`` of the
    field's radius. ``shutter_tags``: the DICOM file states the rectangular blades in its
    shutter module (most clinical files do not).
    """

    shapes: tuple[str, ...] = ("rectangular", "wedge")
    closed: tuple[float, float, float, float] = (0.35, 0.25, 0.2, 0.3)
    rotation_deg: float = 6.0
    transmission: float = 0.08
    wedge_closed: float = 0.3
    wedge_side_deg: float = 35.0
    wedge_transmission: float = 0.35
    iris_fraction: float = 0.85
    penumbra_px: float = 0.7
    shutter_tags: bool = False

    def __post_init__(self) -> None:
        for shape in self.shapes:
            if shape not in BLADE_SHAPES:
                raise ValueError(f"blade shape must be one of {BLADE_SHAPES}, got {shape!r}")
        if len(self.closed) != 4:
            raise ValueError("closed holds four fractions (left, right, top, bottom)")
        for c in self.closed:
            _check("closed", c, 0.0, 0.9)
        _check("rotation_deg", self.rotation_deg, -45.0, 45.0)
        _check("transmission", self.transmission, 0.0, 0.9)
        _check("wedge_closed", self.wedge_closed, 0.0, 0.9)
        _check("wedge_transmission", self.wedge_transmission, 0.0, 1.0)
        _check("iris_fraction", self.iris_fraction, 0.2, 1.0)
        _check("penumbra_px", self.penumbra_px, 0.0, 5.0)

    def at_strength(self, s: float) -> Blades:
        """Closed fractions scaled by ``sqrt(s)`` (strength 2: 1.4 x as far in, the field about
        half as large), none at 0."""
        f = math.sqrt(_strength(s))
        return replace(
            self,
            closed=tuple(min(0.9, c * f) for c in self.closed),  # type: ignore[arg-type]
            wedge_closed=min(0.9, self.wedge_closed * f),
            iris_fraction=max(0.2, 1.0 - (1.0 - self.iris_fraction) * f),
        )


@dataclass(frozen=True)
class BurnedInText:
    """Text (patient, date, angles, frame rate) and a ruler burned into the pixels at full white.

    ``font_scale`` is the text height as a multiple of 1/40 of the image height; ``lines`` per
    corner block (two blocks outside the anatomy's center, one line of angles inside the
    field when ``inside_field``); ``ruler`` a 10 mm-tick scale along the right edge.
    """

    font_scale: float = 1.0
    lines: int = 3
    inside_field: bool = True
    ruler: bool = True

    def __post_init__(self) -> None:
        _check("font_scale", self.font_scale, 0.2, 4.0)
        if int(self.lines) != self.lines or not 0 <= self.lines <= 8:
            raise ValueError(f"lines must be an integer in [0, 8], got {self.lines}")

    def at_strength(self, s: float) -> BurnedInText:
        """More lines (``lines x s``) and larger text (``1 + (s - 1) / 2`` times), none at 0."""
        s = _strength(s)
        scale = max(0.2, self.font_scale * (1.0 + (s - 1.0) / 2.0))
        return replace(self, font_scale=scale, lines=min(8, round(self.lines * s)), ruler=self.ruler and s > 0,
                       inside_field=self.inside_field and s > 0)  # fmt: skip


@dataclass(frozen=True)
class Overlay:
    """A DICOM overlay plane (60xx) with graphics (text, a ruler, a marker) that a viewer draws
    over the image; ``embedded``: in the unused high bits of the pixel data (the retired form,
    16-bit pixels with fewer bits stored) instead of OverlayData."""

    font_scale: float = 1.0
    embedded: bool = False

    def __post_init__(self) -> None:
        _check("font_scale", self.font_scale, 0.2, 4.0)

    def at_strength(self, s: float) -> Overlay:
        return replace(self, font_scale=max(0.2, self.font_scale * max(_strength(s), 0.2)))


@dataclass(frozen=True)
class Display:
    """The vendor's display chain on the log image: unsharp-mask edge enhancement
    (``edge_amount`` x (image - Gaussian of ``edge_sigma_mm`` at the detector)), a window from the
    field's percentiles, a monotone S-shaped look-up table of steepness ``s_curve`` and a gamma,
    the polarity, ``bits`` stored bits, lossy JPEG at ``jpeg_quality`` (None: none), and the tags
    (``relationship`` "DISP", "LOG" or None for no tag; ``sign_tag`` whether the sign is written).
    """

    bits: int = 8
    polarity: str = "bone_dark"
    relationship: str | None = "DISP"
    sign_tag: bool = True
    window_percentiles: tuple[float, float] = (0.5, 99.5)
    gamma: float = 0.75
    s_curve: float = 4.0
    edge_amount: float = 0.8
    edge_sigma_mm: float = 2.5
    jpeg_quality: int | None = 85

    def __post_init__(self) -> None:
        if int(self.bits) != self.bits or not 8 <= self.bits <= 16:
            raise ValueError(f"bits must be an integer in [8, 16], got {self.bits}")
        if self.polarity not in POLARITIES:
            raise ValueError(f"polarity must be one of {POLARITIES}, got {self.polarity!r}")
        if self.relationship not in RELATIONSHIPS:
            raise ValueError(f"relationship must be one of {RELATIONSHIPS}, got {self.relationship!r}")
        lo, hi = self.window_percentiles
        if not 0 <= lo < hi <= 100:
            raise ValueError(f"window_percentiles must satisfy 0 <= lo < hi <= 100, got {self.window_percentiles}")
        _check("gamma", self.gamma, 0.2, 5.0)
        _check("s_curve", self.s_curve, 0.0, 20.0)
        _check("edge_amount", self.edge_amount, 0.0, 5.0)
        _check("edge_sigma_mm", self.edge_sigma_mm, 0.1, 20.0)
        if self.jpeg_quality is not None and not (int(self.jpeg_quality) == self.jpeg_quality
                                                   and 5 <= self.jpeg_quality <= 100):  # fmt: skip
            raise ValueError(f"jpeg_quality must be an integer in [5, 100] or None, got {self.jpeg_quality}")

    def at_strength(self, s: float) -> Display:
        s = _strength(s)
        quality = None if s == 0 or self.jpeg_quality is None else max(5, round(100 - (100 - self.jpeg_quality) * s))
        return replace(
            self,
            gamma=float(self.gamma**s),
            s_curve=self.s_curve * s,
            edge_amount=min(5.0, self.edge_amount * s),
            jpeg_quality=quality,
        )


@dataclass(frozen=True)
class BoneContrast:
    """Fluoroscopy's lower effective energy: bone attenuates relatively more than the CT says.
    Above ``threshold_hu`` the HU above it are multiplied by ``ratio`` (1.0: as the CT)."""

    ratio: float = 1.3
    threshold_hu: float = 100.0

    def __post_init__(self) -> None:
        _check("ratio", self.ratio, 0.5, 3.0)
        _check("threshold_hu", self.threshold_hu, -200.0, 1000.0)

    def at_strength(self, s: float) -> BoneContrast:
        return replace(self, ratio=1.0 + (self.ratio - 1.0) * _strength(s))


@dataclass(frozen=True)
class Scatter:
    """Scattered radiation behind an anti-scatter grid: a smooth background, the collimated
    primary blurred by a Gaussian of ``kernel_mm`` (at the detector), scaled so that scatter /
    primary over the central field is ``spr``."""

    spr: float = 0.4
    kernel_mm: float = 40.0

    def __post_init__(self) -> None:
        _check("spr", self.spr, 0.0, 5.0)
        _check("kernel_mm", self.kernel_mm, 1.0, 500.0)

    def at_strength(self, s: float) -> Scatter:
        return replace(self, spr=self.spr * _strength(s))


@dataclass(frozen=True)
class Heel:
    """The anode heel effect: intensity tilted linearly across the field, ``tilt`` the relative
    difference from one edge of the field to the other, along ``direction_deg`` (0: along the
    image columns, 90: along the rows)."""

    tilt: float = 0.2
    direction_deg: float = 90.0

    def __post_init__(self) -> None:
        _check("tilt", self.tilt, 0.0, 1.5)
        _check("direction_deg", self.direction_deg, -360.0, 360.0)

    def at_strength(self, s: float) -> Heel:
        return replace(self, tilt=min(1.5, self.tilt * _strength(s)))


@dataclass(frozen=True)
class Table:
    """The angiography table and headrest, in the image and not in the volume, static (they do
    not move with the patient); the CT's own couch and head holder removed from the anatomy the
    images are formed from. ``skin_mm``: the carbon-fibre table top's two skins; ``shell_mm``: the
    headrest's shell; ``attenuation_scale`` scales both materials."""

    skin_mm: float = 1.5
    shell_mm: float = 4.0
    attenuation_scale: float = 1.0
    headrest: bool = True

    def __post_init__(self) -> None:
        _check("skin_mm", self.skin_mm, 0.1, 10.0)
        _check("shell_mm", self.shell_mm, 0.5, 20.0)
        _check("attenuation_scale", self.attenuation_scale, 0.0, 5.0)

    def at_strength(self, s: float) -> Table:
        return replace(self, attenuation_scale=self.attenuation_scale * _strength(s))


@dataclass(frozen=True)
class Neck:
    """A neck that bends: the skull moves rigidly with the patient motion, what lies below the
    skull-base plane (``plane_below_iso_mm`` under the iso-center) and behind the pharynx
    (``anterior_cut_mm`` in front of the cervical spine) follows only ``follow`` of it, bent at
    C1/C2 by ``flexion_deg`` (about the left-right axis) and ``rotation_deg`` (about the
    cranio-caudal axis); blended over ``blend_mm``."""

    flexion_deg: float = 5.0
    rotation_deg: float = 3.0
    follow: float = 0.4
    plane_below_iso_mm: float = 38.0
    anterior_cut_mm: float = 20.0
    blend_mm: float = 8.0

    def __post_init__(self) -> None:
        _check("flexion_deg", self.flexion_deg, -30.0, 30.0)
        _check("rotation_deg", self.rotation_deg, -30.0, 30.0)
        _check("follow", self.follow, 0.0, 1.0)
        _check("plane_below_iso_mm", self.plane_below_iso_mm, 0.0, 200.0)
        _check("anterior_cut_mm", self.anterior_cut_mm, 0.0, 200.0)
        _check("blend_mm", self.blend_mm, 0.5, 50.0)

    def at_strength(self, s: float) -> Neck:
        s = _strength(s)
        return replace(
            self,
            flexion_deg=max(-30.0, min(30.0, self.flexion_deg * s)),
            rotation_deg=max(-30.0, min(30.0, self.rotation_deg * s)),
            follow=max(0.0, 1.0 - (1.0 - self.follow) * s),
        )


#: The effects by their command-line names, in the order the image is formed.
EFFECT_TYPES = {
    "contrast": BoneContrast,
    "neck": Neck,
    "table": Table,
    "blades": Blades,
    "scatter": Scatter,
    "heel": Heel,
    "display": Display,
    "text": BurnedInText,
    "overlay": Overlay,
}
EFFECT_NAMES = tuple(EFFECT_TYPES)


@dataclass(frozen=True)
class ClinicalEffects:
    """Which effects an image carries (None: absent), each with its own parameters."""

    contrast: BoneContrast | None = None
    neck: Neck | None = None
    table: Table | None = None
    blades: Blades | None = None
    scatter: Scatter | None = None
    heel: Heel | None = None
    display: Display | None = None
    text: BurnedInText | None = None
    overlay: Overlay | None = None

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if value is not None and not isinstance(value, EFFECT_TYPES[f.name]):
                raise ValueError(f"{f.name} must be a {EFFECT_TYPES[f.name].__name__} or None")

    @classmethod
    def all(cls) -> ClinicalEffects:
        """Every effect at its typical strength."""
        return cls(**{name: t() for name, t in EFFECT_TYPES.items()})

    @classmethod
    def of(cls, names: tuple[str, ...] | list[str], strength: float = 1.0) -> ClinicalEffects:
        """The named effects (``EFFECT_NAMES``) at ``strength`` (0: none of them, a clean image)."""
        unknown = [n for n in names if n not in EFFECT_TYPES]
        if unknown:
            raise ValueError(f"unknown effect {unknown[0]!r}; known: {', '.join(EFFECT_NAMES)}")
        if _strength(strength) == 0:
            return cls()
        return cls(**{n: EFFECT_TYPES[n]().at_strength(strength) for n in names})

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(n for n in EFFECT_NAMES if getattr(self, n) is not None)

    @property
    def is_clean(self) -> bool:
        return not self.names

    def describe(self) -> dict:
        """The effects and their parameters (JSON-ready)."""
        from dataclasses import asdict

        return {n: asdict(getattr(self, n)) for n in self.names}


def parse_realism(text: str) -> list[tuple[str, tuple[str, ...]]]:
    """The study's arms from ``--realism``: comma-separated; each ``clean``, ``clinical`` (every
    effect), ``each`` (every effect alone, one arm each) or effect names joined by ``+``.
    Returns (arm name, effect names) pairs, in order, without repeats."""
    arms: list[tuple[str, tuple[str, ...]]] = []
    words = [w.strip().lower() for w in str(text).split(",")]
    if not any(words):
        raise ValueError(
            "--realism is empty; give clean, clinical, each or effect names (" + ", ".join(EFFECT_NAMES) + ")"
        )
    for word in words:
        if not word:
            continue
        if word == "clean":
            arms.append(("clean", ()))
        elif word == "clinical":
            arms.append(("clinical", EFFECT_NAMES))
        elif word == "each":
            arms.extend((n, (n,)) for n in EFFECT_NAMES)
        else:
            names = tuple(p.strip() for p in word.split("+"))
            unknown = [n for n in names if n not in EFFECT_TYPES]
            if unknown:
                raise ValueError(
                    f"--realism: unknown effect {unknown[0]!r}; use clean, clinical, each or "
                    f"{', '.join(EFFECT_NAMES)} (joined by + to combine)"
                )
            ordered = tuple(n for n in EFFECT_NAMES if n in names)
            arms.append(("+".join(ordered), ordered))
    seen: dict[str, tuple[str, ...]] = {}
    for name, effects in arms:
        seen.setdefault(name, effects)
    return list(seen.items())
