"""The roadmap picture a PACS keeps: the X-ray image with the volume's contrast-filled vessels
projected over it in red (a secondary capture)."""

from __future__ import annotations

from typing import Any

#: Vessel voxels drawn in the overlay: the mesh module's contrast threshold (HU).
OVERLAY_VESSEL_HU = 250.0
#: Bone (HU) and the margin (voxels) around it left out of the vessels.
OVERLAY_BONE_HU = 700.0
OVERLAY_BONE_MARGIN_VOXELS = 2
#: Colour of the overlaid vessels (RGB) and their largest opacity.
OVERLAY_RGB = (255, 60, 40)
OVERLAY_ALPHA = 0.8


def overlay_rgb(volume: Any, xray: Any, patient_motion: Any) -> Any:
    """The X-ray image (radiological display: attenuation dark) with the volume's contrast-filled
    vessels projected at ``patient_motion`` drawn over it in red; rows x cols x 3 uint8."""
    import numpy as np
    from scipy.ndimage import binary_dilation

    from registration.core.drr import DRRRenderer

    data = np.asarray(volume.data, dtype=np.float32)
    # contrast (250..700 HU) away from bone: bone edges pass through the same values
    bone = binary_dilation(data >= OVERLAY_BONE_HU, iterations=OVERLAY_BONE_MARGIN_VOXELS)
    keep = (data >= OVERLAY_VESSEL_HU) & (data < OVERLAY_BONE_HU) & ~bone
    vessels = volume.with_data(np.where(keep, data, -1000.0).astype(np.float32))
    drr = DRRRenderer(vessels, levels=1).render(xray.geometry, np.asarray(patient_motion, dtype=np.float64))
    image = np.asarray(xray.image, dtype=np.float64)
    mask = np.asarray(xray.mask, dtype=bool)
    inside = image[mask] if mask.any() else image.ravel()
    low, high = np.percentile(inside, [1.0, 99.0])
    gray = 1.0 - np.clip((image - low) / max(high - low, 1e-9), 0.0, 1.0)
    gray[~mask] = 0.0
    top = float(np.percentile(drr[drr > 0], 99.0)) if np.any(drr > 0) else 1.0
    alpha = OVERLAY_ALPHA * np.clip(drr / max(top, 1e-9), 0.0, 1.0) * mask
    rgb = gray[..., None] * (1.0 - alpha[..., None]) + (np.array(OVERLAY_RGB) / 255.0) * alpha[..., None]
    return np.round(255.0 * np.clip(rgb, 0.0, 1.0)).astype(np.uint8)
