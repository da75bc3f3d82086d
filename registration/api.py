"""The public face of roadmap3d: what ``import registration`` offers (loaded lazily, see ``__init__``).

Frames, angles and units follow CONVENTIONS.md (docs/conventions.md): the world is DICOM patient
coordinates (LPS, mm), a volume is ``data[k, j, i]`` plus ``index_to_world``, an X-ray image holds
attenuation line integrals, and a registration estimates the patient motion ``M``: anatomy the
volume shows at X is at ``M @ X`` when the X-ray image is taken.

Examples
--------
>>> import registration
>>> ex = registration.load_example("T1")
>>> ex.volume.shape, ex.image.shape, ex.truth_motion[:3, 3].round(3).tolist()
((128, 128, 128), (256, 256), [10.0, 0.0, 0.0])
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core import images as _images
from registration.core import volume as _volume
from registration.core.geometry import CArm
from registration.core.intrinsics import GeometryRefinement
from registration.core.metrics import residuals
from registration.core.preparation import Preparation
from registration.core.register import RegistrationResult
from registration.core.register import register as _register
from registration.core.tracking import TrackingRun, track_run

__all__ = [
    "CArm",
    "Volume",
    "XRayImage",
    "Example",
    "Assessment",
    "Preparation",
    "register",
    "assess",
    "follow_cranium",
    "estimate_geometry",
    "track",
    "render_drr",
    "residuals",
    "load_example",
]

#: NIfTI/nibabel order and frame -> the project's: x and y change sign (CONVENTIONS §8).
_LPS_FROM_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])


class Volume(_volume.Volume):
    """A CT or 3DRA volume: ``data[k, j, i]`` in Hounsfield units and ``index_to_world`` (LPS mm).

    Examples
    --------
    >>> import numpy as np
    >>> v = Volume.from_array(np.zeros((4, 5, 6)), np.diag([0.5, 0.5, 2.0, 1.0]), frame="RAS")
    >>> v.shape  # NIfTI's data[i, j, k] became data[k, j, i]
    (6, 5, 4)
    >>> v.index_to_world.diagonal().tolist()  # RAS became LPS
    [-0.5, -0.5, 2.0, 1.0]
    """

    @classmethod
    def _of(cls, volume: _volume.Volume) -> Volume:
        return cls(data=volume.data, index_to_world=volume.index_to_world, label=volume.label, meta=volume.meta)

    @classmethod
    def from_dicom(cls, path: str | os.PathLike[str]) -> Volume:
        """A DICOM slice series folder or an enhanced multi-frame file."""
        from registration.io import dicom

        return cls._of(dicom.read_volume(path))

    @classmethod
    def from_file(cls, path: str | os.PathLike[str]) -> Volume:
        """A NIfTI (``.nii``, ``.nii.gz``), NRRD (``.nrrd``, ``.nhdr``), MetaImage (``.mha``, ``.mhd``),
        the project's ``.npz``, a DICOM file or folder: read in the project's frame (CONVENTIONS §8)."""
        from registration.io import dicom

        return cls._of(dicom.read_volume(path))

    @classmethod
    def from_array(
        cls,
        data: ArrayLike,
        affine: ArrayLike,
        *,
        frame: str = "LPS",
        order: str | None = None,
        label: str = "",
    ) -> Volume:
        """A volume from an array and a 4x4 affine mapping voxel indices (i, j, k) to world mm.

        ``frame="RAS"`` (nibabel, NIfTI, MONAI) or ``"LPS"`` (DICOM, ITK, the project).
        ``order``: the array's axes, ``"ijk"`` (``data[i, j, k]``, as nibabel gives it) or
        ``"kji"`` (``data[k, j, i]``, as DICOM stacks and SimpleITK give it); by default
        ``"ijk"`` for RAS and ``"kji"`` for LPS.
        """
        if frame not in ("LPS", "RAS"):
            raise ValueError(f"frame must be 'LPS' or 'RAS', got {frame!r}")
        order = order or ("ijk" if frame == "RAS" else "kji")
        if order not in ("ijk", "kji"):
            raise ValueError(f"order must be 'ijk' or 'kji', got {order!r}")
        array = np.asarray(data)
        if array.ndim != 3:
            raise ValueError(f"data must be 3-D, got shape {array.shape}")
        matrix = np.asarray(affine, dtype=np.float64)
        if matrix.shape != (4, 4):
            raise ValueError(f"affine must be 4x4, got shape {matrix.shape}")
        if order == "ijk":
            array = array.transpose(2, 1, 0)
        if frame == "RAS":
            matrix = _LPS_FROM_RAS @ matrix
        return cls(data=array, index_to_world=matrix, label=label, meta={"source": f"array ({frame}, {order})"})

    def to_file(self, path: str | os.PathLike[str]) -> Path:
        """Write as NIfTI (RAS affine), NRRD or MetaImage (LPS), by the file name's ending."""
        from registration.io.volume_files import write_volume_file

        return write_volume_file(self, path)


class XRayImage(_images.XRayImage):
    """An X-ray image as attenuation line integrals, its field mask and its C-arm view (:class:`CArm`).

    Examples
    --------
    >>> import numpy as np
    >>> carm = CArm(rows=2, cols=2)
    >>> image = XRayImage.from_array(intensity=np.array([[100.0, 50.0], [25.0, 100.0]]), carm=carm)
    >>> image.image.astype(float).round(3).tolist()  # -log(I / I0), I0 the brightest pixel
    [[0.0, 0.693], [1.386, 0.0]]
    """

    @classmethod
    def _of(cls, xray: _images.XRayImage) -> XRayImage:
        return cls(image=xray.image, mask=xray.mask, geometry=xray.geometry, kind=xray.kind, meta=xray.meta)

    @classmethod
    def from_dicom(
        cls,
        path: str | os.PathLike[str],
        *,
        frame: int | None = None,
        isocenter_mm: ArrayLike = (0.0, 0.0, 0.0),
        sid_mm: float | None = None,
        sod_mm: float | None = None,
        pixel_mm: float | None = None,
    ) -> XRayImage:
        """An XA/RF DICOM image (``frame`` of a multi-frame run, 0-based). ``sid_mm``, ``sod_mm``,
        ``pixel_mm``: the source-detector and source-iso-center distances and the detector's pixel
        size, for files that lack them; given for a file that has them, they replace its values."""
        from registration.io import dicom

        return cls._of(dicom.read_xray(path, frame=frame, isocenter_mm=isocenter_mm, sid_mm=sid_mm, sod_mm=sod_mm,
                                       pixel_mm=pixel_mm))  # fmt: skip

    @classmethod
    def from_file(
        cls,
        path: str | os.PathLike[str],
        geometry: str | os.PathLike[str] | dict | None = None,
        *,
        isocenter_mm: ArrayLike = (0.0, 0.0, 0.0),
        sid_mm: float | None = None,
        sod_mm: float | None = None,
        pixel_mm: float | None = None,
    ) -> XRayImage:
        """A TIFF or PNG image with its geometry (a JSON side file or a dict; default ``<image>.json``),
        see :mod:`registration.io.image_files` for the keys; a DICOM file is read as :meth:`from_dicom`.
        ``sid_mm``, ``sod_mm``: as for :meth:`from_dicom`; ``pixel_mm``: for a DICOM file only (an
        image file's pixel size is in its geometry)."""
        from registration.io.image_files import is_image_file, read_image_file

        if not is_image_file(path):
            return cls.from_dicom(path, isocenter_mm=isocenter_mm, sid_mm=sid_mm, sod_mm=sod_mm, pixel_mm=pixel_mm)
        if pixel_mm is not None:
            raise ValueError(f"{path}: pixel_mm is for DICOM files; an image file's pixel size is in its geometry")
        image = read_image_file(path, geometry=geometry, isocenter_mm=isocenter_mm, sid_mm=sid_mm, sod_mm=sod_mm)
        return cls._of(image)

    @classmethod
    def from_array(
        cls,
        *,
        carm: CArm,
        intensity: ArrayLike | None = None,
        line_integrals: ArrayLike | None = None,
        mask: ArrayLike | None = None,
        i0: float | None = None,
    ) -> XRayImage:
        """An image from detector ``intensity`` (linear, air bright: ``-log(I / I0)`` is taken) or from
        attenuation ``line_integrals`` (larger = more attenuation), seen through ``carm``.

        ``mask``: True inside the collimated field (default: every pixel); ``i0``: the
        unattenuated intensity (default: the brightest pixel inside the field).
        """
        if (intensity is None) == (line_integrals is None):
            raise ValueError("give exactly one of intensity= or line_integrals=")
        given = np.asarray(intensity if intensity is not None else line_integrals)
        name = "intensity" if intensity is not None else "line_integrals"
        if np.iscomplexobj(given) or not (np.issubdtype(given.dtype, np.number) or given.dtype == bool):
            raise ValueError(f"{name} must hold real numbers, got dtype {given.dtype}")
        values = given.astype(np.float64)
        if intensity is not None and (values < 0).any():
            raise ValueError("intensity must be >= 0 (detector counts, air bright); line_integrals= takes attenuation")
        if i0 is not None and not (np.isfinite(i0) and i0 > 0):
            raise ValueError(f"i0 (the unattenuated intensity) must be a positive number, got {i0}")
        field = np.ones(values.shape, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
        if field.shape != values.shape:
            raise ValueError(f"mask has shape {field.shape}, the image {values.shape}: one flag per pixel is needed")
        if intensity is not None:
            values = _images.line_integrals(values, mask=field, i0=i0)
        image = np.where(field, values, 0.0).astype(np.float32)
        return cls(image=image, mask=field, geometry=carm, kind="dicom", meta={"source": "array"})


def register(
    volume: _volume.Volume,
    images: _images.XRayImage | Sequence[_images.XRayImage],
    *,
    preparation: Preparation | None = None,
    **options: Any,
) -> RegistrationResult:
    """Estimate the patient motion between ``volume`` and one X-ray image (or a biplane pair).

    ``images``: one :class:`XRayImage`, or plane A and plane B of one moment. ``preparation``:
    a :class:`Preparation` of the volume for these views, built once and held by the caller
    (``Preparation.of(volume, images)``), to register several images with it or to
    :func:`assess` the result on the same levels; without it the volume is prepared for this
    call. Other keyword options are those of :func:`registration.core.register.register`
    (``initial_motion``, ``options``, ``seed``, ``callback``, ``truth``, ...). The result's
    ``patient_motion`` is ``M`` (CONVENTIONS §4); ``.to_dict()`` gives its JSON form.

    What it cannot take is refused before any work, naming the argument (``TypeError`` or
    ``ValueError``): views registered together must look along beams at least 2° apart, and a
    start that puts the volume where no ray of a detector meets it, even moved by the search's
    range, raises :class:`~registration.core.checks.NoInformationError`, as a volume or an image
    without edges does.
    """
    if preparation is not None:
        if not isinstance(preparation, Preparation):
            raise TypeError(f"preparation must be a Preparation (Preparation.of(volume, images)), "
                            f"got {type(preparation).__name__}")  # fmt: skip
        options.setdefault("renderer", preparation.renderer)
    return _register(volume, images, **options)


def follow_cranium(
    volume: _volume.Volume,
    images: _images.XRayImage | Sequence[_images.XRayImage],
    *,
    initial_motion: ArrayLike | None = None,
) -> list[_images.XRayImage]:
    """The images as ``roadmap3d register`` registers them by default: each field without the
    pixels that see mostly the neck below the skull base found in ``volume`` (with the volume at
    ``initial_motion``, the start; identity by default), which follows a head's motion only
    partly. The images unchanged when the volume has no neck. Register on the result; assess
    (:func:`assess`) on the original images, as the command line does: the confidence rule was
    calibrated on whole fields (docs/clinical-images.md)."""
    from registration.core.roi import followed_region, region_views

    motion = None if initial_motion is None else np.asarray(initial_motion, dtype=np.float64)
    return region_views(volume, followed_region(volume, "cranium"), images, motion)[0]


@dataclass(frozen=True)
class Assessment:
    """Whether to trust a registration: ``confidence`` in 0..1, ``applied`` (the roadmap uses the
    estimate) or withheld with a ``reason``, and the ``evidence`` the rule weighed."""

    confidence: float
    applied: bool
    reason: str
    evidence: dict

    def __repr__(self) -> str:
        """A line a notebook shows: the decision, its confidence, why, and the evidence that was
        measured (the entries that are None were not)."""
        decision = "applied" if self.applied else "withheld"
        why = f": {self.reason}" if self.reason else ""
        shown = ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}"
                          for k, v in self.evidence.items() if v is not None)  # fmt: skip
        return f"Assessment({decision}, confidence {self.confidence:.2f}{why}; evidence: {shown or 'none'})"


def assess(
    result: RegistrationResult,
    images: _images.XRayImage | Sequence[_images.XRayImage],
    preparation: Preparation | _volume.Volume,
) -> Assessment:
    """Whether to trust ``result``: the apply/withhold decision the command line and the web app
    make. ``images``: those ``result`` was registered on (``ValueError`` for others);
    ``preparation``: the one the registration used (its probe levels render the evidence), or the
    volume (then prepared here for ``images``)."""
    from registration.studies.cases import confidence_fields

    if not isinstance(result, RegistrationResult):
        raise TypeError(f"result must be a RegistrationResult (what register returns), got {type(result).__name__}")
    views = tuple(images) if isinstance(images, Sequence) else (images,)
    if not views or not all(isinstance(v, _images.XRayImage) for v in views):
        raise TypeError("images must be the XRayImage (or the sequence of them) the result was registered on")
    if result.views and (len(views) != len(result.views)
                         or any(v.geometry != g for v, g in zip(views, result.views, strict=False))):  # fmt: skip
        raise ValueError(f"images: {len(views)} view(s) that are not the {len(result.views)} the result was "
                         "registered on (each image's C-arm must be the one registered)")  # fmt: skip
    if not isinstance(preparation, Preparation | _volume.Volume):
        raise TypeError(f"preparation must be the registration's Preparation or the Volume, "
                        f"got {type(preparation).__name__}")  # fmt: skip
    if isinstance(preparation, _volume.Volume):
        preparation = Preparation.of(preparation, images)
    fields = confidence_fields(preparation.volume, images, result, preparation.probe_renderer())
    return Assessment(
        confidence=float(fields["confidence"]),
        applied=bool(fields["applied"]),
        reason=str(fields.get("withheld_reason") or ""),
        evidence=dict(fields.get("confidence_evidence") or {}),
    )


def estimate_geometry(
    volume: _volume.Volume,
    images: Sequence[_images.XRayImage],
    result: RegistrationResult,
    *,
    preparation: Preparation | None = None,
) -> GeometryRefinement:
    """Each plane's source-image distance estimated together with the pose, for files whose
    distances are nominal (an uncalibrated C-arm): what ``register --estimate-geometry`` does.

    ``images``: plane A and plane B of one moment (one view cannot tell its distance from the
    depth: ValueError); ``result``: their registration; ``preparation``: the one it used (else
    prepared here). Two passes, the second on the volume's own grid. The returned
    ``patient_motion`` is the pose with the estimated geometry, ``views`` the images with it,
    ``intrinsics`` each plane's distance (``sid_mm``, ``sid_change`` against the file's).
    """
    from registration.core.intrinsics import estimate_geometry as _estimate

    images = tuple(images)
    if preparation is None:
        preparation = Preparation.of(volume, images)
    return _estimate(volume, preparation.renderer, images, result.patient_motion)


def track(
    volume: _volume.Volume,
    frames: Sequence[_images.XRayImage],
    times_s: ArrayLike,
    **options: Any,
) -> TrackingRun:
    """Follow the patient's motion over a fluoroscopy run (CONVENTIONS §7), frame by frame.

    ``frames``: one plane's frames, or a biplane run as ``[frames_a, frames_b]`` (one frame per
    time each). Each frame gets ``status`` applied/withheld/unchanged, its ``patient_motion`` and
    a ``confidence``; options are those of :func:`registration.core.tracking.track_run`
    (``realtime=False`` processes every frame).
    """
    runs = list(frames)
    if runs and all(isinstance(r, Sequence) and not isinstance(r, str | bytes) for r in runs):
        return track_run(volume, [list(r) for r in runs], times_s, **options)  # planes A and B
    return track_run(volume, [runs], times_s, **options)


def render_drr(volume: _volume.Volume, carm: CArm, motion: ArrayLike | None = None) -> XRayImage:
    """The digitally reconstructed radiograph (line integrals) of ``volume`` moved by ``motion``.

    Examples
    --------
    >>> import numpy as np
    >>> water = Volume.from_array(np.zeros((16, 16, 16)), np.eye(4))  # 0 HU, 1 mm voxels
    >>> drr = render_drr(water, CArm(rows=8, cols=8))
    >>> drr.image.shape, round(float(drr.image.max()), 3)  # 15 mm between voxel centres x 0.0206 / mm
    ((8, 8), 0.309)
    """
    from registration.core.drr import DRRRenderer

    image = DRRRenderer(volume, levels=1).render(carm, motion)
    return XRayImage(image=np.asarray(image, dtype=np.float32), mask=np.ones(image.shape, dtype=bool),
                     geometry=carm, kind="drr", meta={"source": "render_drr"})  # fmt: skip


@dataclass(frozen=True)
class Example:
    """The head phantom's 3DRA, an X-ray image of the moved phantom and the motion it moved by."""

    volume: Volume
    image: XRayImage
    truth_motion: NDArray[np.float64]
    offset: str

    def __repr__(self) -> str:
        return f"Example({self.offset}: {self.volume!r}, {self.image!r}, truth_motion 4x4)"


#: The default example (seed 0, T4, 256 px) as :func:`simulate_example` makes it, shipped so a
#: first run compiles only the engine's kernels, not the simulator's (``scripts/make_example.py``).
SHIPPED_EXAMPLE = Path(__file__).resolve().parent / "data" / "example-t4.npz"


def load_example(offset: str = "T4", *, pixels: int = 256, seed: int = 0) -> Example:
    """A runnable case: the phantom's 3DRA (128³ voxels, 27 cm format, whole HU) and a fluoroscopy
    image of the phantom moved by ``offset`` (one of Table I: T1-T4).

    The image is formed from the analytic phantom (not by the DRR renderer that registration
    uses), with the system's noise; ``truth_motion`` is the motion it was moved by. The default
    case is read from a copy shipped with the package; any other is simulated (the volume is
    cached on disk after the first call).
    """
    if (offset, pixels, seed) == ("T4", 256, 0) and SHIPPED_EXAMPLE.is_file():
        with np.load(SHIPPED_EXAMPLE, allow_pickle=False) as f:
            volume = Volume(data=f["volume"], index_to_world=f["index_to_world"], label=str(f["label"]))
            carm = CArm.from_dict(json.loads(str(f["geometry"])))
            image = XRayImage(image=f["image"], mask=f["mask"], geometry=carm, kind="fluoro",
                              meta={"source": "shipped example"})  # fmt: skip
            return Example(volume=volume, image=image, truth_motion=f["truth_motion"], offset=offset)
    return simulate_example(offset, pixels=pixels, seed=seed)


def simulate_example(offset: str = "T4", *, pixels: int = 256, seed: int = 0) -> Example:
    """What :func:`load_example` returns, made from the phantom now (see there)."""
    from registration.core.geometry import TABLE_I, offsets_to_matrix
    from registration.sim.phantom import make_head_phantom
    from registration.sim.threedra import VolumeRecipe
    from registration.sim.xray import simulate_xray

    if offset not in TABLE_I:
        raise ValueError(f"offset must be one of {', '.join(TABLE_I)}, got {offset!r}")
    if isinstance(pixels, bool) or not isinstance(pixels, int | np.integer) or pixels < 16:
        raise ValueError(f"pixels must be an integer >= 16 (the image's size across), got {pixels!r}")
    recipe = VolumeRecipe(
        phantom_seed=seed, volume_format_cm=27.0, source="resampled", voxels=128, contrast=True, noise_seed=seed
    )
    built = recipe.build()
    # whole Hounsfield units, as a 3DRA series stores them
    volume = Volume(data=np.rint(built.data), index_to_world=built.index_to_world, label=built.label)
    carm = CArm.for_format(27.0, pixels=pixels)
    motion = offsets_to_matrix(np.asarray(TABLE_I[offset]), carm)
    image = simulate_xray(make_head_phantom(seed=seed, contrast=True), carm, motion=motion, kind="fluoro", seed=seed)
    return Example(volume=volume, image=XRayImage._of(image), truth_motion=motion, offset=offset)
