"""C-arm geometry, rigid transforms and the view-frame offset parameterisation.

Every convention here is the one written in ``shared/CONVENTIONS.md`` (restated in the
README): world = patient LPS millimetres, iso-center at the origin unless stated, angles in
degrees. Rigid transforms are plain 4x4 ``float64`` arrays named by the frames they map
between (``world_from_view``); compose with ``@`` and invert with :func:`invert_rigid`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

ASSETS = Path(__file__).resolve().parents[2] / "assets"

#: The offset parameter names of Table I, in order: translations (mm), rotations (deg).
OFFSET_NAMES = ("tx", "ty", "tz", "rx", "ry", "rz")

#: Image formats of the default system (field diameter at the detector, cm), as
#: assets/carm_system.txt states them; Table II of the paper uses the same eight.
IMAGE_FORMATS_CM: tuple[float, ...] = (15.0, 19.0, 22.0, 27.0, 31.0, 37.0, 42.0, 48.0)
#: Source-to-image and source-to-iso-center distances of the default system (mm), as
#: assets/carm_system.txt states them: the defaults of every geometry.
DEFAULT_SID_MM = 1200.0
DEFAULT_SOD_MM = 810.0
#: Formats the commercial product does not register (paper section II.C): too few landmarks.
SMALL_FORMATS_CM: tuple[float, ...] = (15.0, 19.0)


def clinically_relevant(volume_format_cm: float, image_format_cm: float) -> bool:
    """The paper's clinically relevant subset (II.C, IV): neither format is 15 or 19 cm, and
    the volume format is not smaller than the image format."""
    small = volume_format_cm in SMALL_FORMATS_CM or image_format_cm in SMALL_FORMATS_CM
    return not small and volume_format_cm >= image_format_cm


# --------------------------------------------------------------------------------------
# Rotations and rigid transforms
# --------------------------------------------------------------------------------------
def rotation_x(angle_deg: float) -> Array:
    """Right-handed rotation about the x axis (3x3)."""
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rotation_y(angle_deg: float) -> Array:
    """Right-handed rotation about the y axis (3x3)."""
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rotation_z(angle_deg: float) -> Array:
    """Right-handed rotation about the z axis (3x3)."""
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rigid(rotation: ArrayLike | None = None, translation_mm: ArrayLike | None = None) -> Array:
    """A 4x4 rigid transform from a 3x3 rotation and a translation in millimetres."""
    out = np.eye(4)
    if rotation is not None:
        out[:3, :3] = np.asarray(rotation, dtype=np.float64)
    if translation_mm is not None:
        out[:3, 3] = np.asarray(translation_mm, dtype=np.float64)
    return out


def invert_rigid(transform: ArrayLike) -> Array:
    """Exact inverse of a rigid 4x4 transform (transpose of the rotation)."""
    t = np.asarray(transform, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = t[:3, :3].T
    out[:3, 3] = -t[:3, :3].T @ t[:3, 3]
    return out


def rotation_angle_deg(transform_or_rotation: ArrayLike) -> float:
    """The rotation angle (degrees, 0..180) of a 3x3 rotation or of a 4x4 transform's block.

    ``atan2(2 sin, 2 cos)`` from the skew part and the trace: every digit at any angle (the
    arccosine of the trace alone reads angles below 1.2e-6 degrees as 0)."""
    r = np.asarray(transform_or_rotation, dtype=np.float64)[:3, :3]
    two_sin = math.hypot(r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1])
    return math.degrees(math.atan2(two_sin, float(np.trace(r)) - 1.0))


def _skew(a: Array) -> Array:
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


#: Below this angle (radians) a rotation vector maps to and from its matrix by series.
SMALL_ANGLE_RAD = 1e-6
#: Between this and pi - NEAR_PI_RAD (radians) the angle comes from the matrix's trace.
MID_ANGLE_RAD = 1e-2
#: Within this of pi (radians) the rotation vector's axis comes from the matrix's symmetric part.
NEAR_PI_RAD = 1e-3


def axis_rotation(axis: ArrayLike, angle_rad: float) -> Array:
    """The 3x3 rotation by ``angle_rad`` about ``axis`` (any length > 0; Rodrigues' formula)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    k = _skew(a)
    return np.eye(3) + math.sin(angle_rad) * k + (1.0 - math.cos(angle_rad)) * (k @ k)


def rotation_matrix(rotation_vector_rad: ArrayLike) -> Array:
    """The 3x3 rotation of a rotation vector (axis times angle, radians); a series below
    :data:`SMALL_ANGLE_RAD` (exact to rounding there), Rodrigues' formula above."""
    v = np.asarray(rotation_vector_rad, dtype=np.float64).reshape(3)
    angle = float(np.linalg.norm(v))
    if angle < SMALL_ANGLE_RAD:
        k = _skew(v)
        return np.eye(3) + k + 0.5 * (k @ k)
    return axis_rotation(v, angle)


def rotation_vector(rotation: ArrayLike) -> Array:
    """Axis times angle (radians, angle in [0, pi]) of a 3x3 rotation (or a 4x4 transform's
    block); the inverse of :func:`rotation_matrix`. Accurate near 0 (the angle from the skew
    part, not from an arccos near 1) and near pi (the axis from the symmetric part, where the
    skew part vanishes)."""
    r = np.asarray(rotation, dtype=np.float64)[:3, :3]
    w = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    cos = (np.trace(r) - 1.0) / 2.0
    sin = float(np.linalg.norm(w)) / 2.0
    angle = math.atan2(sin, cos)
    if angle < SMALL_ANGLE_RAD:
        return 0.5 * w * (1.0 + angle * angle / 6.0)  # angle / sin(angle) to second order
    if angle < math.pi - NEAR_PI_RAD:
        if angle > MID_ANGLE_RAD:  # the arccos is well conditioned here
            angle = math.acos(max(-1.0, min(1.0, cos)))
            return w / (2.0 * math.sin(angle)) * angle
        return w * (angle / (2.0 * sin))
    # near pi: a a^T = (sym(R) - cos I) / (1 - cos); its largest diagonal's column is best conditioned
    outer = ((r + r.T) / 2.0 - cos * np.eye(3)) / (1.0 - cos)
    i = int(np.argmax(np.diag(outer)))
    axis = outer[:, i] / math.sqrt(max(outer[i, i], 1e-300))
    if axis @ w < 0.0:
        axis = -axis
    return axis * angle


def apply(transform: ArrayLike, points_mm: ArrayLike) -> Array:
    """Apply a 4x4 transform to points of shape (..., 3)."""
    t = np.asarray(transform, dtype=np.float64)
    p = np.asarray(points_mm, dtype=np.float64)
    return p @ t[:3, :3].T + t[:3, 3]


def check_rigid(transform: ArrayLike, *, name: str = "transform") -> Array:
    """Return ``transform`` as a 4x4 array or raise ValueError saying why it is not rigid."""
    t = np.asarray(transform, dtype=np.float64)
    if t.shape != (4, 4):
        raise ValueError(f"{name} must be a 4x4 matrix, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError(f"{name} contains NaN or infinite values")
    if not np.allclose(t[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise ValueError(f"{name} must have last row (0, 0, 0, 1), got {t[3].tolist()}")
    r = t[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
        raise ValueError(f"{name} is not a rigid transform (its 3x3 block is not a rotation)")
    return t


def _finite(name: str, value: float) -> float:
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value}")
    return value


# --------------------------------------------------------------------------------------
# The C-arm
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CArm:
    """One X-ray view of a C-arm, as the DICOM XA/RF positioner module describes it.

    Angles and axes follow CONVENTIONS.md §3: the detector direction from the iso-center is
    ``d = R @ (0, -1, 0)`` with ``R = Rz(primary) @ Rx(-secondary)``; image columns run along
    ``u = R @ (1, 0, 0)``, rows along ``v = R @ (0, 0, -1)``; the central ray meets the
    detector at pixel ``((cols - 1) / 2, (rows - 1) / 2)``.

    The ``*_shift_mm`` and ``detector_tilt_deg`` fields describe a *true* geometry that
    deviates from the nominal one (gravitational bending, calibration results); they are
    zero for the nominal geometry that the angle sensors report. The view frame used for
    offsets and residuals is always the nominal one.
    """

    primary_deg: float = 0.0
    secondary_deg: float = 0.0
    sid_mm: float = DEFAULT_SID_MM
    sod_mm: float = DEFAULT_SOD_MM
    rows: int = 512
    cols: int = 512
    #: (row spacing, column spacing) at the detector plane, as ImagerPixelSpacing.
    pixel_mm: tuple[float, float] = (480.0 / 512, 480.0 / 512)
    isocenter_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    source_shift_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    detector_shift_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: small rotations (x, y, z in the view frame) of the detector about its own center.
    detector_tilt_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False, hash=False)

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        for name in ("primary_deg", "secondary_deg", "sid_mm", "sod_mm"):
            set_(self, name, _finite(name, getattr(self, name)))
        if self.sid_mm <= 0 or self.sod_mm <= 0:
            raise ValueError(f"sid_mm and sod_mm must be positive, got {self.sid_mm}, {self.sod_mm}")
        if self.sid_mm <= self.sod_mm:
            raise ValueError(
                f"sid_mm ({self.sid_mm}) must exceed sod_mm ({self.sod_mm}): the iso-center lies "
                "between the source and the detector"
            )
        if abs(self.primary_deg) > 360 or abs(self.secondary_deg) > 360:
            raise ValueError(
                f"angles must lie within +-360 degrees, got primary {self.primary_deg}, secondary {self.secondary_deg}"
            )
        if int(self.rows) != self.rows or int(self.cols) != self.cols or self.rows < 2 or self.cols < 2:
            raise ValueError(f"rows and cols must be integers >= 2, got {self.rows}x{self.cols}")
        set_(self, "rows", int(self.rows))
        set_(self, "cols", int(self.cols))
        pix = np.broadcast_to(np.asarray(self.pixel_mm, dtype=np.float64), (2,))
        if not np.all(np.isfinite(pix)) or np.any(pix <= 0):
            raise ValueError(f"pixel_mm must be positive and finite, got {self.pixel_mm}")
        set_(self, "pixel_mm", (float(pix[0]), float(pix[1])))
        for name in ("isocenter_mm", "source_shift_mm", "detector_shift_mm", "detector_tilt_deg"):
            vec = np.asarray(getattr(self, name), dtype=np.float64).reshape(-1)
            if vec.shape != (3,) or not np.all(np.isfinite(vec)):
                raise ValueError(f"{name} must be three finite numbers, got {getattr(self, name)}")
            set_(self, name, (float(vec[0]), float(vec[1]), float(vec[2])))

    # ----- construction helpers -----------------------------------------------------
    @classmethod
    def for_format(
        cls,
        image_format_cm: float,
        *,
        pixels: int = 512,
        primary_deg: float = 0.0,
        secondary_deg: float = 0.0,
        system: SystemSpec | None = None,
    ) -> CArm:
        """A nominal view whose ``pixels`` x ``pixels`` image spans ``image_format_cm``."""
        system = system or default_system()
        image_format_cm = _finite("image_format_cm", image_format_cm)
        if image_format_cm <= 0:
            raise ValueError(f"image_format_cm must be positive, got {image_format_cm}")
        pixel = image_format_cm * 10.0 / pixels
        return cls(
            primary_deg=primary_deg,
            secondary_deg=secondary_deg,
            sid_mm=system.sid_mm,
            sod_mm=system.sod_mm,
            rows=pixels,
            cols=pixels,
            pixel_mm=(pixel, pixel),
        )

    def with_angles(self, primary_deg: float, secondary_deg: float) -> CArm:
        return replace(self, primary_deg=primary_deg, secondary_deg=secondary_deg)

    def resized(self, rows: int, cols: int) -> CArm:
        """The same view with a detector of ``rows`` x ``cols`` pixels over the same area."""
        return replace(
            self,
            rows=rows,
            cols=cols,
            pixel_mm=(self.pixel_mm[0] * self.rows / rows, self.pixel_mm[1] * self.cols / cols),
        )

    def nominal(self) -> CArm:
        """The geometry the angle sensors report (no bending)."""
        return replace(
            self,
            source_shift_mm=(0.0, 0.0, 0.0),
            detector_shift_mm=(0.0, 0.0, 0.0),
            detector_tilt_deg=(0.0, 0.0, 0.0),
        )

    # ----- frames -----------------------------------------------------------------
    @property
    def rotation(self) -> Array:
        """R = Rz(primary) @ Rx(-secondary): maps the frontal C-arm frame to this one."""
        return rotation_z(self.primary_deg) @ rotation_x(-self.secondary_deg)

    @property
    def direction(self) -> Array:
        """d: unit vector from the iso-center toward the detector center."""
        return self.rotation @ np.array([0.0, -1.0, 0.0])

    @property
    def u(self) -> Array:
        """Nominal unit vector along increasing column index."""
        return self.rotation @ np.array([1.0, 0.0, 0.0])

    @property
    def v(self) -> Array:
        """Nominal unit vector along increasing row index."""
        return self.rotation @ np.array([0.0, 0.0, -1.0])

    @property
    def world_from_view(self) -> Array:
        """The view frame (x = u, y = v, z = u x v = -d, origin at the iso-center)."""
        cached = self._cache.get("world_from_view")
        if cached is None:
            rot = np.column_stack([self.u, self.v, -self.direction])
            cached = self._cache["world_from_view"] = rigid(rot, self.isocenter_mm)
        return cached.copy()

    @property
    def view_from_world(self) -> Array:
        cached = self._cache.get("view_from_world")
        if cached is None:
            cached = self._cache["view_from_world"] = invert_rigid(self.world_from_view)
        return cached.copy()

    def detector_axes(self) -> tuple[Array, Array, Array]:
        """True (u, v, n) of the detector, n = unit normal pointing away from the source."""
        tilt = rotation_z(self.detector_tilt_deg[2]) @ rotation_y(self.detector_tilt_deg[1])
        tilt = tilt @ rotation_x(self.detector_tilt_deg[0])
        frame = self.world_from_view[:3, :3] @ tilt
        return frame[:, 0], frame[:, 1], -frame[:, 2]

    @property
    def source_mm(self) -> Array:
        iso = np.asarray(self.isocenter_mm)
        return iso - self.sod_mm * self.direction + np.asarray(self.source_shift_mm)

    @property
    def detector_center_mm(self) -> Array:
        iso = np.asarray(self.isocenter_mm)
        return iso + (self.sid_mm - self.sod_mm) * self.direction + np.asarray(self.detector_shift_mm)

    @property
    def detector_corners_mm(self) -> Array:
        """World positions of the outer corners of the detector, shape (4, 3).

        Order: (row 0, col 0), (row 0, col last), (row last, col last), (row last, col 0),
        taken at the pixel edges (half a pixel beyond the pixel centers).
        """
        u, v, _ = self.detector_axes()
        hw = self.cols * self.pixel_mm[1] / 2.0
        hh = self.rows * self.pixel_mm[0] / 2.0
        c = self.detector_center_mm
        return np.stack([c - hw * u - hh * v, c + hw * u - hh * v, c + hw * u + hh * v, c - hw * u + hh * v])

    @property
    def magnification(self) -> float:
        """Nominal magnification of an object at the iso-center: SID / SOD."""
        return self.sid_mm / self.sod_mm

    @property
    def field_diameter_mm(self) -> float:
        """Diameter of the circular field (the image format) at the detector."""
        return min(self.rows * self.pixel_mm[0], self.cols * self.pixel_mm[1])

    @property
    def projection_matrix(self) -> Array:
        """3x4 P with (col*w, row*w, w) = P @ (x, y, z, 1) for world points, w > 0 in front.

        P = M @ [I | -S]; the rows are built from the true detector frame so shifted and
        tilted (calibrated) geometries are exact.
        """
        cached = self._cache.get("P")
        if cached is not None:
            return cached.copy()
        u, v, n = self.detector_axes()
        s = self.source_mm
        focal = float(n @ (self.detector_center_mm - s))  # source to detector plane
        a = float(u @ (s - self.detector_center_mm))
        b = float(v @ (s - self.detector_center_mm))
        cx, cy = (self.cols - 1) / 2.0, (self.rows - 1) / 2.0
        pr, pc = self.pixel_mm
        m = np.stack(
            [
                (focal / pc) * u + (cx + a / pc) * n,
                (focal / pr) * v + (cy + b / pr) * n,
                n,
            ]
        )
        p = np.concatenate([m, (-m @ s)[:, None]], axis=1)
        self._cache["P"] = p
        return p.copy()

    def project(self, points_mm: ArrayLike) -> Array:
        """Pixel coordinates (col, row) of world points, shape (..., 2)."""
        p = self.projection_matrix
        pts = np.asarray(points_mm, dtype=np.float64)
        h = pts @ p[:, :3].T + p[:, 3]
        return h[..., :2] / h[..., 2:3]

    def pixel_to_world(self, cols: ArrayLike, rows: ArrayLike) -> Array:
        """World position of detector pixel centers (on the detector plane), shape (..., 3)."""
        u, v, _ = self.detector_axes()
        c = np.asarray(cols, dtype=np.float64)[..., None]
        r = np.asarray(rows, dtype=np.float64)[..., None]
        cx, cy = (self.cols - 1) / 2.0, (self.rows - 1) / 2.0
        return self.detector_center_mm + (c - cx) * self.pixel_mm[1] * u + (r - cy) * self.pixel_mm[0] * v

    def field_mask(self, *, margin_px: float = 0.0) -> NDArray[np.bool_]:
        """The circular collimated field (the image format) as a boolean (rows, cols) mask."""
        rr, cc = np.mgrid[0 : self.rows, 0 : self.cols]
        y = (rr - (self.rows - 1) / 2.0) * self.pixel_mm[0]
        x = (cc - (self.cols - 1) / 2.0) * self.pixel_mm[1]
        radius = self.field_diameter_mm / 2.0 - margin_px * max(self.pixel_mm)
        return (x * x + y * y) <= radius * radius

    def to_dict(self) -> dict:
        return {
            "primary_deg": self.primary_deg,
            "secondary_deg": self.secondary_deg,
            "sid_mm": self.sid_mm,
            "sod_mm": self.sod_mm,
            "rows": self.rows,
            "cols": self.cols,
            "pixel_mm": list(self.pixel_mm),
            "isocenter_mm": list(self.isocenter_mm),
            "source_shift_mm": list(self.source_shift_mm),
            "detector_shift_mm": list(self.detector_shift_mm),
            "detector_tilt_deg": list(self.detector_tilt_deg),
        }

    @classmethod
    def from_dict(cls, data: dict) -> CArm:
        known = {k: v for k, v in data.items() if k in cls.__dataclass_fields__ and k != "_cache"}
        for key in ("pixel_mm", "isocenter_mm", "source_shift_mm", "detector_shift_mm", "detector_tilt_deg"):
            if key in known:
                known[key] = tuple(known[key])
        return cls(**known)


# --------------------------------------------------------------------------------------
# Offsets in the view frame (Table I)
# --------------------------------------------------------------------------------------
def offsets_to_matrix(offsets: ArrayLike, geometry: CArm) -> Array:
    """Patient motion M from (tx, ty, tz mm, rx, ry, rz deg) in ``geometry``'s view frame.

    M = world_from_view @ T(t) @ Rz(rz) @ Ry(ry) @ Rx(rx) @ view_from_world (CONVENTIONS §4).
    """
    o = np.asarray(offsets, dtype=np.float64).reshape(-1)
    if o.shape != (6,) or not np.all(np.isfinite(o)):
        raise ValueError(f"offsets must be six finite numbers (tx, ty, tz, rx, ry, rz), got {offsets}")
    rot = rotation_z(o[5]) @ rotation_y(o[4]) @ rotation_x(o[3])
    in_view = rigid(rot, o[:3])
    return geometry.world_from_view @ in_view @ geometry.view_from_world


def matrix_to_offsets(motion: ArrayLike, geometry: CArm) -> Array:
    """Inverse of :func:`offsets_to_matrix`: (tx, ty, tz, rx, ry, rz), rotations in (-180, 180]."""
    m = check_rigid(motion, name="patient motion")
    in_view = geometry.view_from_world @ m @ geometry.world_from_view
    r = in_view[:3, :3]
    # R = Rz(c) Ry(b) Rx(a): r20 = -sin b, r21 = cos b sin a, r22 = cos b cos a, r10 = sin c cos b
    b = math.asin(max(-1.0, min(1.0, -r[2, 0])))
    if abs(r[2, 0]) < 1.0 - 1e-12:
        a = math.atan2(r[2, 1], r[2, 2])
        c = math.atan2(r[1, 0], r[0, 0])
    else:  # gimbal lock: fold everything into rx
        a = math.atan2(-r[1, 2], r[1, 1])
        c = 0.0
    return np.array([*in_view[:3, 3], math.degrees(a), math.degrees(b), math.degrees(c)])


#: Table I of the paper: the four initial offsets (tx, ty, tz mm, rx, ry, rz deg).
TABLE_I: dict[str, tuple[float, float, float, float, float, float]] = {
    "T1": (10.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    "T2": (-8.0, 6.0, 0.0, 0.0, 0.0, 0.0),
    "T3": (0.0, 0.0, 0.0, 5.0, 0.0, 0.0),
    "T4": (4.0, 4.0, 0.0, 2.0, 3.0, 4.0),
}


# --------------------------------------------------------------------------------------
# The system description (assets/carm_system.txt)
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SystemSpec:
    """A C-arm system: distances, image formats and the default grids."""

    name: str = "neuro flat-detector C-arm"
    sid_mm: float = DEFAULT_SID_MM
    sod_mm: float = DEFAULT_SOD_MM
    image_formats_cm: tuple[float, ...] = IMAGE_FORMATS_CM
    image_pixels: int = 512
    volume_voxels: int = 256

    def volume_fov_mm(self, volume_format_cm: float) -> float:
        """Field of view at the iso-center of a 3DRA of ``volume_format_cm``: f x SOD / SID."""
        return volume_format_cm * 10.0 * self.sod_mm / self.sid_mm


def load_system(path: Path | str) -> SystemSpec:
    """Read a ``key = value`` system description (``#`` comments)."""
    path = Path(path)
    values: dict[str, str] = {}
    for lineno, raw in enumerate(path.read_text().splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        if "=" not in line:
            raise ValueError(f"{path}:{lineno}: expected 'key = value', got {raw!r}")
        key, value = (s.strip() for s in line.split("=", 1))
        values[key] = value
    try:
        spec = SystemSpec(
            name=values.get("name", SystemSpec.name),
            sid_mm=float(values["sid_mm"]),
            sod_mm=float(values["sod_mm"]),
            image_formats_cm=tuple(float(x) for x in values["image_formats_cm"].split(",")),
            image_pixels=int(values.get("image_pixels", 512)),
            volume_voxels=int(values.get("volume_voxels", 256)),
        )
    except KeyError as exc:
        raise ValueError(f"{path}: missing key {exc.args[0]!r}") from None
    CArm(sid_mm=spec.sid_mm, sod_mm=spec.sod_mm)  # validates the distances
    return spec


_DEFAULT_SYSTEM: SystemSpec | None = None


def default_system() -> SystemSpec:
    """The default system of ``assets/carm_system.txt``."""
    global _DEFAULT_SYSTEM
    if _DEFAULT_SYSTEM is None:
        _DEFAULT_SYSTEM = load_system(ASSETS / "carm_system.txt")
    return _DEFAULT_SYSTEM
