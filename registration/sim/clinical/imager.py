"""Clinical-looking X-ray images of a volume: every effect of :class:`ClinicalEffects` composed.

Order of formation (each step optional): the anatomy (the CT without its couch, bone contrast,
the neck bent for this motion), line integrals through it moved by the patient motion
(:class:`registration.sim.volume_xray.VolumeAttenuator`: trilinear samples at half a voxel,
not the DRR renderer that scores) plus the static table's exact line integrals and the
catheter; at the detector the blades, scatter and heel effect, then quantum noise and blur
(:func:`registration.sim.xray.simulate_xray`); the display chain; burned-in text and ruler;
an overlay plane. :meth:`ClinicalImage.write_dicom` writes the file a system would send.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core.geometry import CArm
from registration.core.images import XRayImage
from registration.core.volume import Volume
from registration.sim.clinical.anatomy import bent_volume, patient_only, table_phantom, with_bone_contrast
from registration.sim.clinical.detector import DetectorEffects
from registration.sim.clinical.display import display_pixels, jpeg_bytes, overlay_mask, text_mask
from registration.sim.clinical.effects import ClinicalEffects, Display
from registration.sim.volume_xray import VolumeAttenuator, catheter_devices, default_catheter_path
from registration.sim.xray import simulate_xray

#: Said wherever results on these images are reported.
CLINICAL_IMAGES_FROM_VOLUME = (
    "clinical-looking X-ray images formed from the same volume (trilinear line integrals, not the scoring "
    "renderer) with the effects named: a harder case than clean images, still not a real X-ray"
)


class _StaticPlus:
    """Line integrals of the (moving) patient plus a static object that ignores the motion."""

    def __init__(self, patient: Any, static: Any) -> None:
        self.patient, self.static = patient, static
        self.key = {"patient": patient.key, "static": static.key}
        self.source_label = getattr(patient, "source_label", "") + " + a static table"

    def line_integrals(self, sources_mm: ArrayLike, targets_mm: ArrayLike, motion: ArrayLike | None = None) -> NDArray:
        return self.patient.line_integrals(sources_mm, targets_mm, motion) + self.static.line_integrals(
            sources_mm, targets_mm, None
        )


def _display_tags(ds: Any, d: Display | None) -> None:
    """The display chain's tags: the intensity relationship (DISP, LOG, or none) and its sign (or none)."""
    if d is None:
        ds.PixelIntensityRelationship = "LOG"
        return
    if d.relationship is None:
        del ds.PixelIntensityRelationship
    else:
        ds.PixelIntensityRelationship = d.relationship
    if d.sign_tag:
        ds.PixelIntensityRelationshipSign = 1 if d.polarity == "bone_dark" else -1
    else:
        del ds.PixelIntensityRelationshipSign
    ds.ImageComments = "display-processed fluoroscopy (clinical simulation)"


@dataclass(frozen=True)
class ClinicalImage:
    """One clinical-looking image: the stored pixels as a system keeps them and how to read them.

    ``stored``: (rows, cols) uint16, 0 outside the image format's circle; ``bits`` stored bits;
    ``attenuation``: the log image before the display chain (what the detector measured);
    ``field``: the pixels with anatomy behind them (inside the circle, no blade or wedge, no
    burned-in graphics), the truth a field detector is judged by; ``graphics``: the burned-in
    text and ruler; ``overlay``: the overlay plane's graphics (None: no overlay).
    """

    stored: NDArray[np.uint16]
    bits: int
    geometry: CArm
    kind: str
    attenuation: NDArray[np.float32]
    field: NDArray[np.bool_]
    graphics: NDArray[np.bool_]
    overlay: NDArray[np.bool_] | None
    effects: ClinicalEffects
    meta: dict = field(default_factory=dict, compare=False)

    @property
    def circle(self) -> NDArray[np.bool_]:
        return self.geometry.field_mask()

    def clean_xray(self) -> XRayImage:
        """The detector's log image as the engine would see it without any display chain or
        graphics (for comparisons; a system sends :meth:`write_dicom`'s file)."""
        return XRayImage(self.attenuation, self.circle, self.geometry, self.kind, dict(self.meta))

    def _shutter_tags(self, ds: Any) -> None:
        """The rectangular blades in the shutter module, when the effect says the system writes them
        (and they are not rotated)."""
        b = self.effects.blades
        rect = (self.meta.get("blade_edges") or {}).get("rectangle")
        if b is None or not b.shutter_tags or rect is None or abs(rect["rotation_deg"]) >= 1e-9:
            return
        g = self.geometry
        cr, cc = (g.rows - 1) / 2.0, (g.cols - 1) / 2.0
        ds.ShutterShape = "CIRCULAR\\RECTANGULAR"
        ds.ShutterLeftVerticalEdge = int(np.ceil(cc + rect["left"])) + 1
        ds.ShutterRightVerticalEdge = int(np.floor(cc + rect["right"])) + 1
        ds.ShutterUpperHorizontalEdge = int(np.ceil(cr + rect["top"])) + 1
        ds.ShutterLowerHorizontalEdge = int(np.floor(cr + rect["bottom"])) + 1

    def _overlay_plane(self, ds: Any, stored: np.ndarray, embedded: bool) -> np.ndarray:
        """Overlay plane 6000: in the pixels' unused high bits (``embedded``) or as OverlayData;
        returns the stored pixels (with the overlay bits when embedded)."""
        import pydicom

        assert self.overlay is not None
        ds.add_new(0x60000010, "US", self.geometry.rows)
        ds.add_new(0x60000011, "US", self.geometry.cols)
        ds.add_new(0x60000040, "CS", "G")
        ds.add_new(0x60000050, "SS", [1, 1])
        ds.add_new(0x60000022, "LO", "annotations")
        if embedded:
            ds.add_new(0x60000100, "US", 16)
            ds.add_new(0x60000102, "US", self.bits)
            return stored | (self.overlay.astype(np.uint16) << self.bits)
        ds.add_new(0x60000100, "US", 1)
        ds.add_new(0x60000102, "US", 0)
        ds.add_new(0x60003000, "OW", pydicom.pixels.pack_bits(self.overlay.ravel(), pad=True))
        return stored

    def write_dicom(self, path: str | os.PathLike[str], *, acquired_at: Any = None, plane: str | None = None) -> Path:
        """The XA file a system would send: geometry tags as :func:`registration.io.dicom.write_xray`
        writes them, the stored pixels, the display chain's tags (DISP or no relationship, the
        sign or none), the blades in the shutter module only when they say so, an overlay plane,
        JPEG Baseline for lossy 8-bit pixels."""
        import pydicom
        from pydicom.encaps import encapsulate
        from pydicom.uid import JPEGBaseline8Bit

        from registration.io import dicom

        path = Path(path)
        tmp = path.with_name(f".{path.name}.base")
        dicom.write_xray(self.clean_xray(), tmp, description=f"clinical simulation: {'+'.join(self.effects.names)}",
                         acquired_at=acquired_at, plane=plane, uid_seed=str(self.meta.get("seed", 0)))  # fmt: skip
        ds = pydicom.dcmread(tmp)
        tmp.unlink()
        d = self.effects.display
        bits = self.bits
        stored = self.stored.copy()
        ov = self.effects.overlay
        embedded = ov is not None and ov.embedded and self.overlay is not None and bits < 16
        allocated = 8 if bits <= 8 and not embedded else 16
        ds.BitsAllocated, ds.BitsStored, ds.HighBit = allocated, bits, bits - 1
        ds.PixelRepresentation = 0
        _display_tags(ds, d)
        ds.WindowCenter = (1 << bits) // 2
        ds.WindowWidth = 1 << bits
        if self.effects.text is not None:
            ds.BurnedInAnnotation = "YES"
        self._shutter_tags(ds)
        if self.overlay is not None:
            stored = self._overlay_plane(ds, stored, embedded)
        jpeg = d is not None and d.jpeg_quality is not None
        if jpeg:
            ds.LossyImageCompression = "01"
            ds.LossyImageCompressionMethod = "ISO_10918_1"
            ds.LossyImageCompressionRatio = f"{self.meta.get('jpeg_ratio', 10.0):.2f}"
        if jpeg and allocated == 8 and d is not None and d.jpeg_quality is not None:
            frame = jpeg_bytes(stored, d.jpeg_quality)
            ds.PixelData = encapsulate([frame])
            ds["PixelData"].VR = "OB"
            ds["PixelData"].is_undefined_length = True
            ds.PhotometricInterpretation = "MONOCHROME2"
            ds.file_meta.TransferSyntaxUID = JPEGBaseline8Bit
        else:
            ds.PixelData = stored.astype(np.uint8 if allocated == 8 else np.uint16).tobytes()
            ds["PixelData"].VR = "OB" if allocated == 8 else "OW"
        path.parent.mkdir(parents=True, exist_ok=True)
        part = path.with_name(f".{path.name}.part")
        ds.save_as(part, enforce_file_format=True)
        part.replace(path)
        return path


class ClinicalImager:
    """Forms clinical-looking images of one volume (the anatomy's fixed parts built once).

    Parameters
    ----------
    volume
        The CT or 3DRA (HU); the images are formed from it, so results on them are still a best
        case for that anatomy (``CLINICAL_IMAGES_FROM_VOLUME``).
    isocenter_mm
        Where the C-arm looks (the neck's skull-base plane, the headrest and the catheter are
        placed from it).
    effects
        Which effects, with their parameters.
    catheter
        A guide catheter and guidewire the volume lacks.
    """

    def __init__(self, volume: Volume, isocenter_mm: ArrayLike, effects: ClinicalEffects, *,
                 catheter: bool = True, base: Volume | None = None) -> None:  # fmt: skip
        if not isinstance(effects, ClinicalEffects):
            raise ValueError(f"effects must be ClinicalEffects, got {type(effects).__name__}")
        self.isocenter_mm = tuple(float(c) for c in np.asarray(isocenter_mm, dtype=np.float64).reshape(3))
        self.effects = effects
        anatomy = base if base is not None else (patient_only(volume)[0] if effects.table is not None else volume)
        if effects.contrast is not None:
            anatomy = with_bone_contrast(anatomy, effects.contrast)
        self.anatomy = _tissue_box(anatomy)
        self._attenuator = VolumeAttenuator(self.anatomy) if effects.neck is None else None
        self._bent: tuple[NDArray[np.float64], Any] | None = None
        self.table = None
        self.table_placement: dict = {}
        if effects.table is not None:
            self.table, self.table_placement = table_phantom(self.anatomy, self.isocenter_mm, effects.table)
        self.devices = catheter_devices(default_catheter_path(self.isocenter_mm)) if catheter else None

    def attenuator(self, motion: NDArray[np.float64]) -> Any:
        """The line integrals for this motion (the neck bent for it when asked; the last one kept,
        so that both planes of a biplane pair share it)."""
        if self.effects.neck is None:
            patient: Any = self._attenuator
        elif self._bent is not None and np.array_equal(self._bent[0], motion):
            patient = self._bent[1]
        else:
            patient = VolumeAttenuator(bent_volume(self.anatomy, motion, self.isocenter_mm, self.effects.neck))
            self._bent = (np.array(motion, dtype=np.float64), patient)
        return patient if self.table is None else _StaticPlus(patient, self.table)

    def image(
        self, geometry: CArm, motion: ArrayLike | None = None, *, kind: str = "fluoro", seed: int = 0
    ) -> ClinicalImage:
        """The clinical-looking image of the volume moved by ``motion`` (CONVENTIONS §4) in ``geometry``."""
        m = np.eye(4) if motion is None else np.asarray(motion, dtype=np.float64)
        e = self.effects
        detector = DetectorEffects(geometry, blades=e.blades, scatter=e.scatter, heel=e.heel)
        use_detector = any(x is not None for x in (e.blades, e.scatter, e.heel))
        xray = simulate_xray(
            self.attenuator(m), geometry, motion=m, kind=kind, seed=seed,
            catheter=self.devices is not None, devices=self.devices,
            detector_effects=detector if use_detector else None,
        )  # fmt: skip
        circle = xray.mask
        field = circle & detector.open_field
        meta: dict = {"seed": int(seed), "effects": e.describe(), "kind": kind}
        if detector.edges:
            meta["blade_edges"] = detector.edges
        if detector.spr_measured is not None:
            meta["spr_measured"] = detector.spr_measured
        if self.table_placement:
            meta["table"] = self.table_placement
        if e.display is not None:
            stored, info = display_pixels(xray.image, circle, detector.open_field, geometry, e.display)
            bits = e.display.bits
            meta.update({f"display_{k}" if k != "jpeg_ratio" else k: v for k, v in info.items()})
        else:  # the project's own LOG encoding (as registration.io.dicom.write_xray stores it)
            from registration.io.dicom.xray_write import _encode_attenuation

            stored, bits = _encode_attenuation(xray.image, circle), 16
        graphics = np.zeros(circle.shape, dtype=bool)
        if e.text is not None:
            graphics = text_mask(geometry, e.text, seed=seed)
            stored = np.where(graphics, (1 << bits) - 1, stored).astype(np.uint16)
            field &= ~graphics
        overlay = overlay_mask(geometry, e.overlay, seed=seed) if e.overlay is not None else None
        return ClinicalImage(stored=stored, bits=bits, geometry=geometry, kind=kind, attenuation=xray.image,
                             field=field, graphics=graphics, overlay=overlay, effects=e, meta=meta)  # fmt: skip


def _tissue_box(volume: Volume, tissue_hu: float = -900.0, margin_voxels: int = 3) -> Volume:
    """The volume cut to the box of its non-air voxels (plus a margin)."""
    inside = volume.data > tissue_hu
    spans = [np.flatnonzero(inside.any(axis=tuple(a for a in range(3) if a != axis))) for axis in range(3)]
    if any(s.size == 0 for s in spans):
        return volume
    lo = [max(int(s[0]) - margin_voxels, 0) for s in spans]
    hi = [min(int(s[-1]) + margin_voxels, n - 1) for s, n in zip(spans, volume.shape, strict=True)]
    data = volume.data[lo[0] : hi[0] + 1, lo[1] : hi[1] + 1, lo[2] : hi[2] + 1]
    affine = volume.index_to_world.copy()
    affine[:3, 3] = volume.index_to_world[:3, :3] @ np.array([lo[2], lo[1], lo[0]]) + volume.index_to_world[:3, 3]
    return Volume(np.ascontiguousarray(data), affine, label=volume.label, meta=volume.meta)


def with_strength(effects: ClinicalEffects, strength: float) -> ClinicalEffects:
    """Every present effect at ``strength`` (its ``at_strength``)."""
    return replace(effects, **{n: getattr(effects, n).at_strength(strength) for n in effects.names})
