"""The head phantom's anatomy (world mm; +x left, +y posterior, +z superior), painted in order:
the soft-tissue envelope, the skull vault and brain, the skull base, the frontal sinus, the
cervical spine and airway, the facial skeleton and the arteries with an aneurysm; each seed
varies sizes, positions and vessel paths slightly (seed 0: the canonical head).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from registration.sim.phantom_kernels import (
    HU_AIR,
)
from registration.sim.phantom_shapes import Float, HeadPhantom, PhantomBuilder, _euler, _resample_polyline, _rot_to

#: Length of the straight pieces that make up an artery (mm). Neighbouring pieces meet on
#: their bisecting plane (a mitre joint), which joins tubes of one radius without gap or
#: overlap; the arteries bend by at most ~45 degrees per joint.
VESSEL_STEP_MM = 4.0


# Tissue values (HU) of the phantom (air, HU_AIR, is the kernels' background).
HU_SOFT = 40.0  # scalp, muscle, neck


HU_FAT = -80.0  # orbital fat


HU_EYE = 10.0


HU_BRAIN = 35.0


HU_CSF = 5.0


HU_CORTICAL = 1700.0  # inner and outer tables


HU_DIPLOE = 600.0


HU_PETROUS = 2000.0


HU_FACIAL_BONE = 1100.0


HU_ENAMEL = 2800.0


HU_BLOOD = 40.0


HU_CONTRAST = 540.0  # iodine-filled lumen (~ +500 HU over blood)


# --------------------------------------------------------------------------------------
# The anatomy
# --------------------------------------------------------------------------------------
def _catmull_rom(ctrl: Float, step_mm: float = 2.5) -> Float:
    """A smooth curve through the control points, sampled about ``step_mm`` apart."""
    ctrl = np.asarray(ctrl, dtype=np.float64)
    if len(ctrl) == 2:
        return _resample_polyline(ctrl, step_mm)
    p = np.vstack([2 * ctrl[0] - ctrl[1], ctrl, 2 * ctrl[-1] - ctrl[-2]])
    out = [ctrl[:1]]
    for i in range(1, len(p) - 2):
        p0, p1, p2, p3 = p[i - 1], p[i], p[i + 1], p[i + 2]
        n = max(1, int(math.ceil(np.linalg.norm(p2 - p1) / step_mm)))
        t = (np.arange(1, n + 1) / n)[:, None]
        seg = 0.5 * (
            2 * p1 + (-p0 + p2) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t**2 + (-p0 + 3 * p1 - 3 * p2 + p3) * t**3
        )
        out.append(seg)
    return np.vstack(out)


class _Variation:
    """Seeded anatomical variation; seed 0 is the canonical phantom (no variation)."""

    def __init__(self, seed: int) -> None:
        self.on = seed != 0
        rng = np.random.default_rng(seed)
        self.rng = rng
        self.scale = 1.0 + (rng.normal(0.0, 0.03, 3) if self.on else np.zeros(3))
        # a smooth displacement field for vessel paths (mm): three random plane waves
        self.k = rng.normal(0.0, 2 * math.pi / 70.0, (3, 3))
        self.phase = rng.uniform(0, 2 * math.pi, 3)
        self.amp = rng.normal(0.0, 1.5, (3, 3)) if self.on else np.zeros((3, 3))

    def pos(self, p: ArrayLike) -> Float:
        return np.asarray(p, dtype=np.float64) * self.scale

    def size(self, s: ArrayLike, rel: float = 0.0) -> Float:
        s = np.asarray(s, dtype=np.float64)
        jitter = 1.0 + (self.rng.normal(0.0, rel) if (self.on and rel > 0) else 0.0)
        if s.shape == (3,):
            return s * self.scale * jitter
        return s * float(np.mean(self.scale)) * jitter

    def jitter(self, sigma: float, n: int = 3) -> Float:
        return self.rng.normal(0.0, sigma, n) if self.on else np.zeros(n)

    def vessel(self, pts: ArrayLike) -> Float:
        p = self.pos(pts)
        disp = np.zeros_like(p)
        for w in range(3):
            disp += np.sin(p @ self.k[w] + self.phase[w])[:, None] * self.amp[w]
        return p + disp


def _mirror(p: ArrayLike, side: float) -> Float:
    q = np.array(p, dtype=np.float64)
    q[..., 0] *= side
    return q


def _envelope(b: PhantomBuilder, var: _Variation) -> tuple[Float, Float]:
    """The soft-tissue envelope: cranium, face, neck and nose; returns the cranium's center and semi-axes."""
    E, C = b.ellipsoid, b.cylinder
    P, S = var.pos, var.size
    # ----- envelope: cranium, face, neck (soft tissue) --------------------------------
    cran_c = P([0.0, 5.0, 18.0])
    cran_s = S([75.0, 96.0, 90.0])
    b.paint(E(cran_c, cran_s), HU_SOFT, "head", "soft")
    b.paint(E(P([0.0, -38.0, -52.0]), S([63.0, 58.0, 62.0])), HU_SOFT, "head", "soft")
    b.paint(C(P([0.0, 12.0, -300.0]), P([0.0, 12.0, -40.0]), S([56.0, 58.0])), HU_SOFT, "neck", "soft")
    b.paint(E(P([0.0, -99.0, -45.0]), S([9.0, 12.0, 19.0]), _euler(rx=-15)), HU_SOFT, "face", "soft")  # nose
    return cran_c, cran_s


def _vault(b: PhantomBuilder, var: _Variation, cran_c: Float, cran_s: Float) -> None:
    """The skull vault (outer table, diploe, inner table) above the cranial floor, the brain and the
    ventricles."""
    E = b.ellipsoid
    P, S = var.pos, var.size
    # ----- skull vault: nested ellipsoids above the cranial floor -----------------------
    # The cranial floor is the bowl of a large ellipsoid: high in front (anterior fossa,
    # orbital roofs), low at the back (posterior fossa), curving down laterally (middle fossa).
    bowl_c = P([0.0, 40.0, 75.0]) + var.jitter(1.0)
    bowl_s = S([125.0, 160.0, 120.0])

    def vault(semi_minus: float, floor_minus: float) -> dict:
        region = E(cran_c, cran_s - semi_minus)
        bowl = E(bowl_c, bowl_s - floor_minus)
        return {"quads": region["quads"] + bowl["quads"], "planes": [], "sphere": region["sphere"]}

    b.paint(vault(5.0, 0.0), HU_CORTICAL, "skull", "bone")  # outer table
    b.paint(vault(7.0, 1.5), HU_DIPLOE, "skull", "bone")  # diploe
    b.paint(vault(10.5, 3.5), HU_CORTICAL, "skull", "bone")  # inner table
    b.paint(vault(12.5, 5.0), HU_BRAIN, "skull", "brain")  # brain

    # ventricles (CSF)
    for side in (-1.0, 1.0):
        b.paint(
            E(P(_mirror([9.0, 2.0, 24.0], side)), S([5.0, 26.0, 8.0], 0.1), _euler(rz=side * 8)),
            HU_CSF,
            "brain",
            "brain",
        )
    b.paint(E(P([0.0, 4.0, 4.0]), S([1.8, 11.0, 8.0])), HU_CSF, "brain", "brain")
    b.paint(E(P([0.0, 40.0, -28.0]), S([6.0, 4.0, 5.0])), HU_CSF, "brain", "brain")


def _skull_base(b: PhantomBuilder, var: _Variation, texture: np.random.Generator) -> None:
    """The skull base: sphenoid, sella, clivus, foramen magnum, petrous bones and mastoids."""
    E, C = b.ellipsoid, b.cylinder
    P, S = var.pos, var.size
    # ----- skull base: sphenoid, sella, clivus, foramen magnum, petrous, mastoid --------
    b.paint(E(P([0.0, -6.0, -40.0]), S([18.0, 19.0, 13.0])), 800.0, "sphenoid", "bone")  # sphenoid body
    b.paint(E(P([0.0, -14.0, -41.0]), S([12.5, 9.5, 8.5], 0.1)), HU_AIR, "sphenoid", "air")  # sphenoid sinus
    b.paint(E(P([0.0, 3.0, -27.0]), S([7.0, 6.0, 5.5])), HU_SOFT, "sphenoid", "soft")  # pituitary fossa (sella)
    b.paint(E(P([0.0, 10.5, -22.0]), S([7.0, 2.2, 7.0]), _euler(rx=15)), 1500.0, "sphenoid", "bone")  # dorsum
    for side in (-1.0, 1.0):  # anterior clinoid processes
        b.paint(E(P(_mirror([9.0, -8.0, -21.0], side)), S([4.0, 7.0, 2.5])), 1500.0, "sphenoid", "bone")
    b.paint(C(P([0.0, 9.0, -30.0]), P([0.0, 30.0, -60.0]), S([10.0, 5.0])), 1300.0, "clivus", "bone")
    for side in (-1.0, 1.0):
        # greater wings of the sphenoid: oblique plates from the sphenoid body to the temple
        # (the innominate lines of a frontal view)
        wing = E(P(_mirror([30.0, -30.0, -27.0], side)), S([2.5, 21.0, 14.0]), _euler(rz=side * 40.0))
        b.paint(wing, 1200.0, "sphenoid", "bone")
        # styloid processes, pointing down and forward from under the petrous bones
        b.paint(
            C(P(_mirror([40.0, 16.0, -50.0], side)), P(_mirror([34.0, 2.0, -82.0], side)), 1.6),
            1300.0,
            "clivus",
            "bone",
        )
    b.paint(E(P([0.0, 85.0, -20.0]), S([10.0, 5.0, 7.0])), 1500.0, "skull", "bone")  # occipital protuberance
    fm = C(P([0.0, 46.0, -55.0]), P([0.0, 46.0, -38.0]), S([15.0, 18.0]))
    b.paint(fm, HU_BRAIN, "clivus", "brain")  # foramen magnum: medulla through the floor plate
    for side in (-1.0, 1.0):
        g = f"petrous_{'l' if side > 0 else 'r'}"
        apex = P(_mirror([13.0, 3.0, -31.0], side))
        base = P(_mirror([55.0, 28.0, -40.0], side))
        axis = base - apex
        center = (apex + base) / 2
        half = float(np.linalg.norm(axis)) / 2 + 3.0
        b.paint(E(center, [10.0, 7.0, half], _rot_to(axis)), HU_PETROUS, g, "bone")
        b.paint(E(P(_mirror([36.0, 15.0, -35.0], side)), 2.6), HU_CSF, g, "soft")  # cochlea/vestibule
        b.paint(
            C(P(_mirror([20.0, 8.0, -32.0], side)), P(_mirror([33.0, 13.0, -34.5], side)), 2.2),
            HU_CSF,
            g,
            "soft",
        )  # internal auditory canal
        # mastoid process with air cells
        mc = P(_mirror([53.0, 30.0, -50.0], side))
        b.paint(E(mc, S([10.0, 13.0, 16.0])), 1000.0, g, "bone")
        _air_cells(b, mc, S([8.0, 11.0, 14.0]), 26, (1.6, 3.4), texture, g)
        ear = P(_mirror([48.0, 17.0, -40.0], side))
        b.paint(C(ear, P(_mirror([80.0, 17.0, -41.0], side)), 3.5), HU_AIR, g, "air")  # ear canal
        b.paint(E(ear, S([3.0, 4.0, 5.0])), HU_AIR, g, "air")  # middle ear


def _frontal_sinus(b: PhantomBuilder, var: _Variation) -> None:
    """The frontal sinus (walls first, then air so the two lobes join)."""
    E = b.ellipsoid
    P, S = var.pos, var.size
    # ----- frontal sinus (walls first, then air so the two lobes join) -----------------
    fs = [(P(_mirror([7.0, -80.0, 8.0], side)), S([8.0, 6.0, 11.0], 0.1)) for side in (-1.0, 1.0)]
    for c, s in fs:
        b.paint(E(c, s + 2.0), 1400.0, "frontal", "bone")
    for c, s in fs:
        b.paint(E(c, s), HU_AIR, "frontal", "air")


def _spine_and_airway(b: PhantomBuilder, var: _Variation) -> None:
    """The cervical spine, the cord, the airway, the occipital condyles and the hyoid."""
    E, C = b.ellipsoid, b.cylinder
    P, S = var.pos, var.size
    # ----- cervical spine and airway --------------------------------------------------
    b.paint(C(P([0.0, 28.0, -67.0]), P([0.0, 28.0, -58.0]), S([22.0, 19.0])), 1000.0, "spine", "bone")  # C1
    b.paint(C(P([0.0, 14.0, -90.0]), P([0.0, 14.0, -56.0]), S(5.0)), 1100.0, "spine", "bone")  # dens
    for level in range(6):
        z = -90.0 - 18.0 * level
        b.paint(C(P([0.0, 14.0, z - 7.0]), P([0.0, 14.0, z + 7.0]), S([10.0, 8.5])), 900.0, "spine", "bone")
        b.paint(E(P([0.0, 40.0, z + 2.0]), S([17.0, 15.0, 5.0])), 900.0, "spine", "bone")  # arch
    b.paint(C(P([0.0, 34.0, -300.0]), P([0.0, 34.0, -56.0]), S([8.0, 7.0])), HU_BRAIN, "spine", "brain")  # cord
    airway = _catmull_rom(P([[0.0, -26.0, -50.0], [0.0, -12.0, -72.0], [0.0, -9.0, -130.0], [0.0, -14.0, -300.0]]))
    b.tube(airway, float(S(7.0)), HU_AIR, "airway", "air")
    for side in (-1.0, 1.0):  # occipital condyles, resting on the atlas
        b.paint(E(P(_mirror([13.0, 36.0, -58.0], side)), S([6.0, 10.0, 5.0])), 1300.0, "spine", "bone")
    hyoid = np.stack([20.0 * (u := np.linspace(-1.0, 1.0, 9)), -38.0 + 26.0 * u**2, np.full_like(u, -125.0)], axis=1)
    b.tube(P(hyoid), float(S(2.2)), 1000.0, "spine", "bone")


def _build_phantom(seed: int, contrast: bool, facial: bool) -> HeadPhantom:
    var = _Variation(seed)
    # texture: irregular small structure (air cells), fixed for a seed, canonical for seed 0
    texture = np.random.default_rng(1000 + seed)
    b = PhantomBuilder()
    cran_c, cran_s = _envelope(b, var)
    _vault(b, var, cran_c, cran_s)
    _skull_base(b, var, texture)
    _frontal_sinus(b, var)
    _spine_and_airway(b, var)

    if facial:
        _facial_skeleton(b, var, texture)

    aneurysm_c, aneurysm_r, paths = _arteries(b, var, contrast)
    return b.build(
        paths=tuple(paths),
        seed=seed,
        contrast=contrast,
        facial=facial,
        params={"aneurysm_center_mm": aneurysm_c.tolist(), "aneurysm_radius_mm": aneurysm_r},
    )


def _air_cells(
    b: PhantomBuilder, center: Float, semi: Float, count: int, radii: tuple[float, float], rng, group: str
) -> None:
    """``count`` air cells of random radius at random places inside an ellipsoid."""
    placed = 0
    while placed < count:
        off = rng.uniform(-1.0, 1.0, 3)
        if off @ off > 1.0:
            continue
        radius = rng.uniform(*radii)
        b.paint(b.ellipsoid(center + off * semi, radius), HU_AIR, group, "air")
        placed += 1


def _orbits_and_sinuses(b: PhantomBuilder, var: _Variation, texture: np.random.Generator) -> None:
    """The orbits (bony cone, fat, globe), the maxillary sinuses, the ethmoid labyrinth and the nasal bones."""
    E, C = b.ellipsoid, b.cylinder
    P, S = var.pos, var.size
    # orbits: bony cone (walls) behind the rim, fat, globe
    for side in (-1.0, 1.0):
        g = f"orbit_{'l' if side > 0 else 'r'}"
        axis = np.array([side * math.sin(math.radians(20)), -math.cos(math.radians(20)), -0.05])
        c = P(_mirror([33.0, -62.0, -30.0], side))
        rot = _rot_to(axis)
        semi = S([16.5, 16.5, 24.0], 0.05)
        rim = c + axis * 17.0  # the orbital opening
        b.paint(b.clip(E(c, semi + 2.5, rot), axis, rim), HU_FACIAL_BONE, g, "bone")
        b.paint(E(c, semi, rot), HU_FAT, g, "fat")
        b.paint(E(c + axis * 15.0, S(12.0)), HU_EYE, g, "soft")
        # zygoma and zygomatic arch
        b.paint(E(P(_mirror([48.0, -60.0, -44.0], side)), S([8.0, 9.0, 13.0])), HU_FACIAL_BONE, g, "bone")
        b.paint(
            C(P(_mirror([50.0, -55.0, -44.0], side)), P(_mirror([60.0, -2.0, -40.0], side)), [4.0, 3.0]),
            1200.0,
            g,
            "bone",
        )
    # maxillary sinuses (walls first)
    ms = [(P(_mirror([29.0, -57.0, -50.0], side)), S([13.0, 17.0, 15.0], 0.08)) for side in (-1.0, 1.0)]
    for i, (c, s) in enumerate(ms):
        b.paint(E(c, s + 2.0), HU_FACIAL_BONE, f"maxilla_{i}", "bone")
    for i, (c, s) in enumerate(ms):
        b.paint(E(c, s), HU_AIR, f"maxilla_{i}", "air")
    # ethmoid labyrinth: a block of thin septa with air cells
    ec = P([0.0, -52.0, -29.0])
    b.paint(E(ec, S([11.0, 22.0, 10.0])), 300.0, "ethmoid", "bone")
    _air_cells(b, ec, S([8.5, 19.0, 7.5]), 30, (1.8, 3.2), texture, "ethmoid")
    for side in (-1.0, 1.0):  # nasal bones at the bridge of the nose
        b.paint(
            E(P(_mirror([4.0, -92.0, -30.0], side)), S([2.5, 2.0, 10.0]), _euler(rx=-20.0)),
            1100.0,
            "nasal",
            "bone",
        )


def _nasal_cavity(b: PhantomBuilder, var: _Variation) -> None:
    """The nasal cavity, its septum and turbinates, and the hard palate."""
    E = b.ellipsoid
    P, S = var.pos, var.size
    # nasal cavity, septum, turbinates, hard palate
    b.paint(E(P([0.0, -58.0, -55.0]), S([12.0, 31.0, 14.0])), HU_AIR, "nasal", "air")
    b.paint(E(P([0.0, -58.0, -53.0]), S([1.2, 28.0, 13.0])), 600.0, "nasal", "bone")
    for side in (-1.0, 1.0):
        b.paint(E(P(_mirror([9.0, -55.0, -60.0], side)), S([2.5, 22.0, 4.0])), 300.0, "nasal", "soft")
        b.paint(E(P(_mirror([9.5, -52.0, -50.0], side)), S([2.0, 17.0, 3.0])), 300.0, "nasal", "soft")
    b.paint(E(P([0.0, -52.0, -71.0]), S([21.0, 30.0, 3.0])), 1300.0, "nasal", "bone")


def _jaws_and_teeth(b: PhantomBuilder, var: _Variation) -> None:
    """The upper dental arch, the mandible and the teeth (enamel crowns and roots)."""
    E = b.ellipsoid
    P, S = var.pos, var.size
    # upper dental arch (alveolar bone) and mandible, as tubes along parabolic arches
    s_up = np.linspace(-0.78, 0.78, 25)
    up = np.stack([45.0 * s_up, -79.0 + 70.0 * s_up**2, np.full_like(s_up, -71.0)], axis=1)
    b.tube(P(up), float(S(6.5)), HU_FACIAL_BONE, "jaw", "bone")
    s_lo = np.linspace(-1.0, 1.0, 33)
    for z in (-104.0, -94.0):
        lo = np.stack([47.0 * s_lo, -77.0 + 77.0 * s_lo**2, np.full_like(s_lo, z)], axis=1)
        b.tube(P(lo), float(S(6.0)), 1300.0, "jaw", "bone")
    for side in (-1.0, 1.0):
        ramus = _catmull_rom(P(_mirror([[47.0, 0.0, -100.0], [48.5, 6.0, -72.0], [50.0, 12.0, -48.0]], side)))
        b.tube(ramus, float(S(5.0)), 1300.0, "jaw", "bone")
        coronoid = _catmull_rom(P(_mirror([[46.0, -14.0, -95.0], [45.0, -20.0, -60.0]], side)))
        b.tube(coronoid, float(S(3.5)), 1300.0, "jaw", "bone")
        b.paint(E(P(_mirror([50.0, 12.0, -45.0], side)), S([9.0, 5.0, 5.0])), 1300.0, "jaw", "bone")  # condyle
    # teeth: 7 per side per jaw (incisors to molars); enamel crowns and roots
    s_teeth = [0.05, 0.16, 0.27, 0.38, 0.48, 0.59, 0.7]
    crowns = [
        (3.3, 2.2, 4.5),
        (3.0, 2.2, 4.5),
        (3.0, 3.3, 5.0),
        (3.2, 3.5, 4.0),
        (3.3, 3.6, 4.0),
        (4.8, 5.0, 3.8),
        (4.6, 4.8, 3.6),
    ]
    for side in (-1.0, 1.0):
        for s, crown in zip(s_teeth, crowns, strict=True):
            for jaw_z, root_dz, arch in (
                (-79.0, 8.0, (45.0, -79.0, 70.0)),
                (-88.0, -8.0, (47.0, -77.0, 77.0)),
            ):
                x = side * arch[0] * s * 0.93
                y = arch[1] + arch[2] * s**2 + 3.0
                c = P([x, y, jaw_z])
                b.paint(
                    E(c + [0.0, 0.0, root_dz], S([crown[0] * 0.55, crown[1] * 0.55, 7.0])),
                    1700.0,
                    "teeth",
                    "teeth",
                )
                b.paint(E(c, S(crown)), HU_ENAMEL, "teeth", "teeth")


def _facial_skeleton(b: PhantomBuilder, var: _Variation, texture: np.random.Generator) -> None:
    """The facial skeleton of the 22 cm facial volume."""
    _orbits_and_sinuses(b, var, texture)
    _nasal_cavity(b, var)
    _jaws_and_teeth(b, var)


#: The arteries of each side (the left's; the right mirrors them): name, control points (mm, the
#: phantom's frame before its variation) and radius (mm), in the order they are drawn.
_SIDE_ARTERIES: tuple[tuple[str, list, float], ...] = (
    (
        "ica",
        [
            [22, 8, -160],
            [23, 9, -110],
            [25, 10, -72],
            [25, 9, -55],
            [22, 2, -46],
            [17, -6, -40],
            [16, -10, -33],
            [15, -18, -27],
            [14, -21, -18],
            [13, -14, -10],
            [13, -8, -4],
            [14, -4, 0],
        ],
        2.0,
    ),
    (
        "vert",
        [
            [26, 22, -170],
            [26, 24, -110],
            [27, 26, -88],
            [36, 30, -78],
            [30, 40, -68],
            [14, 36, -60],
            [4, 26, -56],
            [0.0, 23, -54],
        ],
        1.5,
    ),
    ("a1", [[14, -4, 0], [9, -13, 2], [3.5, -20, 4]], 1.0),
    (
        "a2",
        [[3.5, -20, 4], [3, -30, 12], [3, -40, 25], [4, -45, 40], [4, -36, 55], [4, -12, 64], [4, 18, 64], [5, 40, 56]],
        0.9,
    ),
    ("callosomarginal", [[3, -40, 28], [8, -58, 40], [8, -55, 60], [9, -30, 78]], 0.75),
    ("m1", [[14, -4, 0], [25, -6, 0], [37, -8, 2], [45, -8, 4]], 1.4),
    ("m2_sup", [[45, -8, 4], [50, -12, 15], [55, -6, 30], [58, 6, 45], [55, 20, 58]], 1.0),
    ("m2_inf", [[45, -8, 4], [52, -3, -3], [57, 10, 0], [60, 25, 8], [58, 42, 18]], 1.0),
    ("m3", [[55, -6, 30], [62, -20, 35], [64, -35, 30]], 0.75),
    ("m3b", [[57, 10, 0], [63, 15, 20], [62, 12, 40]], 0.75),
    ("pcom", [[13, -8, -4], [11, 0, -6], [8, 8, -7]], 0.75),
    ("p1", [[0, 10, -9], [8, 8, -7]], 1.1),
    ("p2", [[8, 8, -7], [18, 16, -5], [22, 32, 0], [18, 48, 5], [12, 66, 10], [8, 82, 16]], 1.0),
    ("sca", [[0, 12, -13], [12, 16, -15], [18, 28, -17], [14, 42, -18]], 0.75),
)


def _arteries(b: PhantomBuilder, var: _Variation, contrast: bool) -> tuple[Float, float, list]:
    """Internal carotids, vertebrals, basilar, circle of Willis, ACA/MCA/PCA, aneurysm."""
    lumen_hu = HU_CONTRAST if contrast else HU_BLOOD
    paths: list[tuple[str, Float, float]] = []

    def vessel(name: str, ctrl: list, radius: float) -> Float:
        pts = _catmull_rom(var.vessel(ctrl), VESSEL_STEP_MM)
        r = float(var.size(radius))
        b.tube(pts, r, lumen_hu, "vessels", "vessel")
        paths.append((name, pts, r))
        return pts

    for side, tag in ((-1.0, "r"), (1.0, "l")):
        for name, ctrl, radius in _SIDE_ARTERIES:
            vessel(f"{name}_{tag}", _mirror(ctrl, side), radius)
    vessel("basilar", [[0.0, 23, -54], [0.0, 19, -40], [0.0, 14, -25], [0.0, 10, -9]], 1.5)
    vessel("acom", [[-3.5, -20, 4], [3.5, -20, 4]], 0.75)
    # aneurysm at the left MCA bifurcation, bulging on along the M1 direction
    m1 = var.vessel(_mirror([[37, -8, 2], [45, -8, 4]], 1.0))
    direction = (m1[1] - m1[0]) / np.linalg.norm(m1[1] - m1[0])
    radius = 3.5 + (var.rng.uniform(-0.3, 0.3) if var.on else 0.0)
    center = m1[1] + direction * (radius - 1.0)  # the neck overlaps the bifurcation by 1 mm
    b.paint(b.ellipsoid(center, radius), lumen_hu, "vessels", "vessel")
    return center, radius, paths
