"""An XA/RF image's stored values as attenuation line integrals (CONVENTIONS §5): LOG or LIN, either
sign, rescaled; DISP or a missing relationship read as LOG with a warning."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydicom.dataset import Dataset

from registration.io.dicom._common import (
    LOG_UNITS_PER_ATTENUATION,
    LOG_ZERO_VALUE,
    DicomError,
    _float,
    _max_stored,
    _text,
    lookup,
    tag_name,
)


def _intensity_sign(path: Path, sign_value: Any, inferred_sign: int | None) -> tuple[int, str]:
    """PixelIntensityRelationshipSign (+1 or -1) and where it came from: the tag, the collimated
    outside (``inferred_sign``) when the tag is missing, else +1 assumed (with a warning)."""
    sign_from = "PixelIntensityRelationshipSign"
    if (sign_value is None or sign_value == "") and inferred_sign is not None:
        sign = inferred_sign
        sign_from = "no PixelIntensityRelationshipSign: read from the collimated outside (no X-rays)"
        warnings.warn(
            f"{path}: missing {tag_name('PixelIntensityRelationshipSign')}; the collimated outside says {sign:+d}",
            stacklevel=4,
        )
    elif sign_value is None or sign_value == "":
        sign = 1
        sign_from = "assumed (no PixelIntensityRelationshipSign)"
        warnings.warn(f"{path}: missing {tag_name('PixelIntensityRelationshipSign')}; assuming +1", stacklevel=4)
    else:
        try:
            sign = int(sign_value)
        except (TypeError, ValueError):
            raise DicomError(
                path,
                f"{tag_name('PixelIntensityRelationshipSign')} must be +1 or -1, got {str(sign_value)[:20]!r}",
            ) from None
        if sign not in (1, -1):
            raise DicomError(path, f"{tag_name('PixelIntensityRelationshipSign')} must be +1 or -1, got {sign}")
    return sign, sign_from


def _intensity_to_attenuation(
    path: Path,
    ds: Dataset,
    stored: NDArray[Any],
    frame: int,
    field: NDArray[np.bool_],
    inferred_sign: int | None = None,
) -> tuple[NDArray[np.float32], dict]:
    """Attenuation line integrals from the stored values (see the module docstring).

    ``inferred_sign``: the sign the collimated outside shows, used when the file states none.
    """
    relationship = _text(ds, "PixelIntensityRelationship").upper()
    if not relationship:
        found = lookup(ds, "PixelIntensityRelationship", frame)
        relationship = str(found).upper() if found else ""
    sign_value = lookup(ds, "PixelIntensityRelationshipSign", frame)
    info: dict[str, Any] = {}
    if relationship not in ("LOG", "LIN"):
        warnings.warn(
            f"{path}: {tag_name('PixelIntensityRelationship')} is {relationship or 'missing'}; reading the "
            "pixels as LOG (approximate attenuation)",
            stacklevel=3,
        )
        info["intensity_note"] = f"{relationship or 'missing'} read as LOG"
        relationship = "LOG"
    sign, sign_from = _intensity_sign(path, sign_value, inferred_sign)
    slope = _float(path, ds, "RescaleSlope", frame, default=1.0)
    intercept = _float(path, ds, "RescaleIntercept", frame, default=0.0)
    m = stored.astype(np.float64) * slope + intercept
    m_max = _max_stored(ds) * slope + intercept
    upward = m if sign == -1 else m_max - m  # grows with attenuation
    if relationship == "LOG":
        att = (upward - LOG_ZERO_VALUE) / LOG_UNITS_PER_ATTENUATION
    else:
        intensity = m_max - upward
        inside = intensity[field] if field.any() else intensity
        ref = float(np.max(inside)) if inside.size else 1.0
        att = np.log(max(ref, 1.0) / np.maximum(intensity, 1.0))
    info.update(
        pixel_intensity_relationship=relationship,
        pixel_intensity_relationship_sign=sign,
        sign_from=sign_from,
        rescale_slope=slope,
        rescale_intercept=intercept,
        bits_stored=int(ds.get("BitsStored") or ds.get("BitsAllocated") or 0),
    )
    return att.astype(np.float32), info
