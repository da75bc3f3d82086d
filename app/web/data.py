"""What the app shows, prepared once: phantom, registration volumes, renderers, surface meshes.

Everything expensive is built on first use, reported through a ``progress(message, fraction)``
callback, and cached on disk by :mod:`registration.io.cache` (under the user's cache dir), keyed by
its parameters, so a warm start only loads arrays.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np
import trimesh

from registration.core.drr import DRRRenderer
from registration.core.images import XRayImage
from registration.core.roi import followed_region
from registration.core.volume import Volume
from registration.io.meshes import cached_surface_meshes, surface_meshes
from registration.sim.phantom import HeadPhantom, make_head_phantom
from registration.sim.threedra import FDK, VOLUME_SOURCES, VolumeRecipe
from registration.sim.xray import simulate_xray

if TYPE_CHECKING:
    from registration.core.prepare import PreparedVolume
    from registration.core.roi import RegionOfInterest

__all__ = ["AppConfig", "DataSource", "FileData", "PhantomData", "XRayImage", "simulate_xray", "ProgressFn"]

ProgressFn = Callable[[str, float], None]

#: How long the first FDK 3DRA of a volume format takes here (2 cores, 256^3): the progress bar's pace.
FDK_EXPECTED_S = 75.0
#: While waiting for it, the progress line is refreshed this often (seconds).
TICK_S = 1.0


def _quiet(_message: str, _fraction: float) -> None:
    pass


@dataclass(frozen=True)
class AppConfig:
    """Sizes of what the app computes; smaller values start faster (tests use them)."""

    voxels: int = 256
    """Registration volume grid (voxels per axis)."""
    pixels: int = 256
    """X-ray image size (pixels per side); the registration's finest stage works at 256."""
    display_px: int = 384
    """Size of each 2-D tile in the panel."""
    skull_detail: int = 64
    """Marching-cubes cells across the skull (the browser draws it, in software on some machines)."""
    volume_source: str = FDK
    """The phantom's 3DRA, one of registration.sim.threedra.VOLUME_SOURCES: "fdk" (reconstructed from a
    simulated rotational run, as a real 3DRA; about a minute the first time per volume format, then cached)
    or "resampled" (the phantom resampled on the 3DRA grid, a quick stand-in; ``ROADMAP3D_APP_VOLUME=resampled``)."""
    run_pixels: int = 128
    """Image size of the rotational run shown in the calibration view (simulated on demand)."""
    run_projections: int = 120
    """Projections of that run (the reconstruction's protocol)."""
    seed: int = 0

    @classmethod
    def from_env(cls) -> AppConfig:
        """Overrides from ROADMAP3D_APP_VOXELS / _PIXELS (tests, slow machines) and ROADMAP3D_APP_VOLUME
        (``fdk``, the default, or ``resampled``)."""
        voxels = int(os.environ.get("ROADMAP3D_APP_VOXELS", cls.voxels))
        pixels = int(os.environ.get("ROADMAP3D_APP_PIXELS", cls.pixels))
        source = os.environ.get("ROADMAP3D_APP_VOLUME", cls.volume_source)
        if source not in VOLUME_SOURCES:
            raise ValueError(f"ROADMAP3D_APP_VOLUME must be one of {', '.join(VOLUME_SOURCES)}, got {source!r}")
        if not 32 <= voxels <= 512 or not 64 <= pixels <= 2048:
            raise ValueError(
                f"ROADMAP3D_APP_VOXELS must lie in 32..512 and _PIXELS in 64..2048, got {voxels}, {pixels}"
            )
        return cls(voxels=voxels, pixels=pixels, volume_source=source)


@runtime_checkable
class DataSource(Protocol):
    """What the app shows and registers: the built-in phantom (:class:`PhantomData`) or the
    user's files (:class:`FileData`). Methods take the volume format (cm) the C-arm panel
    selects; a source with one fixed volume ignores it."""

    config: AppConfig
    #: Where the data came from (the Data tab shows it).
    source: str
    #: Whether the true patient motion is known (the phantom: yes; the user's data: no).
    has_truth: bool
    #: The user's X-ray image (its geometry fixes the C-arm); None: images are simulated.
    fixed_xray: XRayImage | None

    def volume(self, volume_format_cm: float) -> Volume:
        """The registration volume (3DRA)."""
        ...

    def renderer(
        self,
        volume_format_cm: float,
        views: Sequence[XRayImage] | None = None,
        initial_motion: np.ndarray | None = None,
    ) -> DRRRenderer:
        """The DRR renderer of :meth:`volume`, prepared once; ``views`` / ``initial_motion``: what a
        registration or a run compares with and where it starts (a source may prepare for them)."""
        ...

    def evidence_renderer(
        self,
        volume_format_cm: float,
        views: Sequence[XRayImage],
        initial_motion: np.ndarray | None = None,
    ) -> DRRRenderer:
        """The renderer a registration's confidence is assessed with (the levels its rule reads)."""
        ...

    def meshes(self, volume_format_cm: float) -> dict[str, trimesh.Trimesh]:
        """Vessel and bone surfaces of :meth:`volume` in world mm."""
        ...

    def mesh_spacing_mm(self, volume_format_cm: float) -> float:
        """Typical distance between neighbouring mesh vertices."""
        ...

    def vessel_points_mm(self) -> np.ndarray | None:
        """Vessel centerline points for the mTRE (None without ground truth)."""
        ...


class PhantomData:
    """The built-in head phantom and what is derived from it, built lazily and cached."""

    has_truth = True
    fixed_xray: XRayImage | None = None
    source = "built-in head phantom"

    def __init__(self, config: AppConfig, progress: ProgressFn = _quiet) -> None:
        self.config = config
        self.progress = progress
        self._lock = threading.RLock()
        self._phantoms: dict[bool, HeadPhantom] = {}
        self._volumes: dict[float, Volume] = {}
        self._renderers: dict[float, DRRRenderer] = {}
        self._meshes: dict[float, dict[str, trimesh.Trimesh]] = {}
        self._vessel_points: np.ndarray | None = None

    def phantom(self, contrast: bool = True) -> HeadPhantom:
        with self._lock:
            if contrast not in self._phantoms:
                self.progress(f"Building the head phantom ({'with' if contrast else 'without'} contrast)", 0.05)
                self._phantoms[contrast] = make_head_phantom(seed=self.config.seed, contrast=contrast)
            return self._phantoms[contrast]

    def recipe(self, volume_format_cm: float) -> VolumeRecipe:
        """Which 3DRA of the phantom the app registers to at this volume format."""
        config = self.config
        return VolumeRecipe(
            phantom_seed=config.seed,
            volume_format_cm=volume_format_cm,
            source=config.volume_source,
            voxels=config.voxels,
            noise_seed=config.seed,
        )

    def volume(self, volume_format_cm: float) -> Volume:
        """The registration volume (3DRA) of one volume format (cached on disk by the engine)."""
        with self._lock:
            if volume_format_cm not in self._volumes:
                self._volumes[volume_format_cm] = self._build(self.recipe(volume_format_cm))
            return self._volumes[volume_format_cm]

    def _build(self, recipe: VolumeRecipe) -> Volume:
        """Load or build the volume, reporting elapsed time while it is built."""
        fmt = f"{recipe.volume_format_cm:g} cm"
        if not recipe.reconstructed:
            self.progress(f"Loading or voxelizing the {fmt} volume ({recipe.voxels}³ voxels)", 0.2)
            return recipe.build()
        what = f"3DRA {fmt}: {recipe.describe()}"
        self.progress(f"Loading the {fmt} 3DRA (FDK reconstruction) from the cache…", 0.15)
        done = threading.Event()
        start = time.monotonic()

        def tick() -> None:
            while not done.wait(TICK_S):
                elapsed = time.monotonic() - start
                fraction = 0.15 + 0.4 * min(1.0, elapsed / FDK_EXPECTED_S)
                message = f"{what}: {elapsed:.0f} s (about {FDK_EXPECTED_S:.0f} s the first time; cached afterwards)"
                self.progress(message, fraction)

        ticker = threading.Thread(target=tick, name="fdk-progress", daemon=True)
        ticker.start()
        try:
            return recipe.build()
        finally:
            done.set()
            ticker.join()

    def renderer(
        self,
        volume_format_cm: float,
        views: Sequence[XRayImage] | None = None,
        initial_motion: np.ndarray | None = None,
    ) -> DRRRenderer:
        """The index pyramid of the whole 3DRA, levels 0-3 (``views`` and ``initial_motion`` are not
        needed: the phantom's 3DRA is the field's size; the confidence rule was calibrated with this
        pyramid, and level 3 is where ``register`` captures)."""
        with self._lock:
            if volume_format_cm not in self._renderers:
                volume = self.volume(volume_format_cm)
                self.progress("Preparing the DRR renderer", 0.6)
                self._renderers[volume_format_cm] = DRRRenderer(volume, levels=4)
            return self._renderers[volume_format_cm]

    def evidence_renderer(
        self,
        volume_format_cm: float,
        views: Sequence[XRayImage],
        initial_motion: np.ndarray | None = None,
    ) -> DRRRenderer:
        """The whole 3DRA's index pyramid: the one the confidence rule was calibrated with."""
        return self.renderer(volume_format_cm)

    def meshes(self, volume_format_cm: float) -> dict[str, trimesh.Trimesh]:
        with self._lock:
            if volume_format_cm not in self._meshes:
                volume = self.volume(volume_format_cm)
                self.progress("Loading or extracting skull and vessel surfaces (marching cubes)", 0.35)
                vessel_step, bone_step = self.mesh_steps
                # Keyed by what defines the volume (its meta holds the phantom model version).
                key = {"meta": volume.meta, "label": volume.label}
                self._meshes[volume_format_cm] = cached_surface_meshes(
                    volume, key, step=vessel_step, bone_step=bone_step
                )
            return self._meshes[volume_format_cm]

    @property
    def mesh_steps(self) -> tuple[int, int]:
        """Marching-cubes steps (vessels, bone): the skull is kept to ~120k faces for the browser."""
        voxels = self.config.voxels
        return max(1, round(voxels / 200)), max(1, math.ceil(voxels / self.config.skull_detail))

    def mesh_spacing_mm(self, volume_format_cm: float) -> float:
        """Typical distance between neighbouring mesh vertices."""
        return float(np.mean(self.volume(volume_format_cm).spacing_mm)) * self.mesh_steps[0]

    def vessel_points_mm(self) -> np.ndarray:
        with self._lock:
            if self._vessel_points is None:
                self._vessel_points = np.asarray(self.phantom(True).vessel_centerline_mm(), dtype=np.float64)
            return self._vessel_points


class FileData:
    """The user's own volume and X-ray image (from the command line or an upload).

    The image is fixed (its geometry comes from the file) and there is no ground truth: the
    patient-motion controls move the roadmap (the estimate) instead of the patient.
    """

    has_truth = False

    def __init__(
        self, volume: Volume, xray: XRayImage, *, source: str, config: AppConfig,
        isocenter_from: str = "the image's geometry",
    ) -> None:  # fmt: skip
        self.config = config
        self.source = source
        self._volume = volume
        #: The volume as read: the meshes and a new region of interest start from it.
        self._full_volume = volume
        #: The region the registration follows (as ``register --roi cranium``: the image's pixels
        #: that see mostly the neck below the skull base are left out; a user's mask replaces it).
        self.region: RegionOfInterest | None = followed_region(volume, "cranium")
        self.fixed_xray = xray
        #: Where the iso-center came from: "--isocenter", the volume's IsocenterPosition tag, the
        #: center of its grid, the world origin (default), the Data tab.
        self.isocenter_from = isocenter_from
        self._lock = threading.RLock()
        self._meshes: dict[str, trimesh.Trimesh] | None = None

    @property
    def isocenter_mm(self) -> tuple[float, float, float]:
        """The C-arm's iso-center (mm, world): the image is placed about it (CONVENTIONS §1)."""
        return self.fixed_xray.geometry.isocenter_mm

    @property
    def isocenter_text(self) -> str:
        """Where the iso-center is and where it came from (printed at start, shown in the Data tab)."""
        iso = self.isocenter_mm
        return f"({iso[0]:.2f}, {iso[1]:.2f}, {iso[2]:.2f}) mm, from {self.isocenter_from}"

    def set_isocenter(self, isocenter_mm: tuple[float, float, float], source: str) -> None:
        """Place the user's image about another iso-center (mm, world; ``source`` says where it came
        from): the image's geometry changes, so the next preparation and registration use it."""
        with self._lock:
            geometry = replace(self.fixed_xray.geometry, isocenter_mm=tuple(float(v) for v in isocenter_mm))
            self.fixed_xray = replace(self.fixed_xray, geometry=geometry)
            self.isocenter_from = source

    def region_views(self, views: list[XRayImage], initial_motion: np.ndarray | None) -> list[XRayImage]:
        """``views`` with the pixels that see mostly what lies outside the region left out of their
        fields (:func:`registration.core.roi.region_views`)."""
        from registration.core.roi import region_views

        with self._lock:
            region = self.region
        return region_views(self._full_volume, region, views, initial_motion)[0]

    @property
    def whole_volume(self) -> Volume:
        """The volume as read, before any region (the skull-and-spine check searches it)."""
        return self._full_volume

    def set_region(self, path: str | os.PathLike[str], name: str) -> None:
        """Follow only the labelled voxels of a mask file on the volume's grid (``.npz``, NIfTI,
        DICOM SEG; as ``register --roi-mask``): outside them bone becomes soft tissue in the
        registration's volume; the scene keeps the whole volume. ValueError naming the file."""
        from dataclasses import replace as replaced

        from registration.core.roi import roi_volume
        from registration.io.roi_masks import read_roi_mask

        with self._lock:
            region = replaced(read_roi_mask(path, self._full_volume), source=name)
            self._volume = roi_volume(self._full_volume, region)
            self.region = region

    def set_user_mask(self, path: str | os.PathLike[str]) -> None:
        """Narrow the image's field by the user's mask file (PNG or TIFF of the image's stored
        size, nonzero = usable), as ``register --image-mask`` does; ValueError naming the file."""
        from registration.io.dicom.xray import with_user_mask

        with self._lock:
            self.fixed_xray = with_user_mask(self.fixed_xray, path)

    @classmethod
    def from_paths(
        cls, volume_path: str | os.PathLike[str], image_path: str | os.PathLike[str], *, frame: int | None,
        config: AppConfig, sid_mm: float | None = None, sod_mm: float | None = None,
        isocenter: str | None = None,
    ) -> FileData:  # fmt: skip
        """Read with the engine's DICOM readers (their errors name the file and the tag);
        ``sid_mm`` / ``sod_mm`` for an image that lacks the distances; ``isocenter`` as
        ``register --isocenter`` (:func:`registration.io.isocenter.resolve_isocenter`: "x,y,z" mm,
        "head", "volume-center", default the volume's IsocenterPosition, else the world origin)."""
        from registration.io.dicom import read_volume, read_xray
        from registration.io.isocenter import resolve_isocenter

        volume = read_volume(volume_path)
        iso, iso_from = resolve_isocenter(isocenter, volume)
        xray = read_xray(image_path, frame=frame, isocenter_mm=iso, sid_mm=sid_mm, sod_mm=sod_mm)
        return cls(volume, xray, source=f"{volume_path} + {image_path}", config=config, isocenter_from=iso_from)

    @property
    def label(self) -> str:
        return self._volume.label

    def volume(self, _volume_format_cm: float | None = None) -> Volume:
        return self._volume

    def prepared(
        self,
        views: Sequence[XRayImage] | None = None,
        initial_motion: np.ndarray | None = None,
    ) -> PreparedVolume:
        """The volume prepared as ``roadmap3d register`` prepares it
        (:meth:`registration.core.preparation.Preparation.of`, its view-independent part in the disk cache):
        cropped to what ``views``' fields (default: the user's image) reach over a registration's
        search from ``initial_motion`` (default: none), levels resampled in mm. Prepared once per
        views; another start reuses it when the search stays within its reach, else slices the
        cached levels again (fast). The view-independent part is kept on disk for the next session."""
        from registration.core.preparation import Preparation
        from registration.io.cache import PreparationCache

        with self._lock:  # one preparation at a time: a second caller finds the first's in memory
            store = PreparationCache(background=True)  # writes from its own threads; the app goes on
            views = list(views) if views else [self.fixed_xray]
            return Preparation.of(self._volume, views, initial_motion=initial_motion, store=store).prepared

    def renderer(
        self, _volume_format_cm: float | None = None, views: Sequence[XRayImage] | None = None,
        initial_motion: np.ndarray | None = None,
    ) -> DRRRenderer:  # fmt: skip
        """The renderer of :meth:`prepared` (the registration's prepared levels, not a pyramid of
        the whole volume: a CT's scanner-sized field of view is cropped to the anatomy in the field)."""
        return self.prepared(views, initial_motion).renderer

    def evidence_renderer(
        self,
        _volume_format_cm: float | None,
        views: Sequence[XRayImage],
        initial_motion: np.ndarray | None = None,
    ) -> DRRRenderer:
        """As ``register --confidence`` assesses (:func:`registration.core.preparation.probe_renderer`):
        the registration's prepared levels, with level 0 over the prepared box where the rule reads it."""
        from registration.core.preparation import probe_renderer

        return probe_renderer(self.prepared(views, initial_motion), planes=len(views))

    @property
    def vessel_step(self) -> int:
        """The vessels' marching-cubes step (voxels); the bone has its own cells (below)."""
        return max(1, round(max(self._volume.shape) / 200))

    def meshes(self, _volume_format_cm: float | None = None) -> dict[str, trimesh.Trimesh]:
        with self._lock:
            if self._meshes is None:
                # The bone in near-cubic cells across the bone itself (skull_detail of them), small
                # components dropped: a CT's grid is anisotropic and far larger than the head, and a
                # step of its voxels broke the skull into floating plates.
                self._meshes = surface_meshes(
                    self._full_volume, step=self.vessel_step, bone_cells_across=self.config.skull_detail
                )
            return self._meshes

    def mesh_spacing_mm(self, _volume_format_cm: float | None = None) -> float:
        return float(np.mean(self._volume.spacing_mm)) * self.vessel_step

    def vessel_points_mm(self) -> None:
        return None
