# %% [markdown]
# # Your own NIfTI CT and a TIFF X-ray
#
# A research data set usually holds the CT as NIfTI (RAS, `data[i, j, k]`) and the X-ray as a TIFF
# or PNG with its geometry written down somewhere. roadmap3d reads both in its own frame
# (CONVENTIONS §8): `Volume.from_file` turns RAS into LPS and the array into `data[k, j, i]`;
# `XRayImage.from_file` takes a geometry side file (angles, SID, SOD, pixel spacing, principal
# point, flips, and whether pixels are intensities or line integrals).
#
# To run without your data, this example first writes such files from the phantom.

# %%
import json
import tempfile
from pathlib import Path

import numpy as np
import tifffile

import registration

folder = Path(tempfile.mkdtemp())
ex = registration.load_example("T2")
ex.volume.to_file(folder / "ct.nii.gz")  # NIfTI: RAS affine, data[i, j, k]
g = ex.image.geometry
intensity = np.round(4000.0 * np.exp(-ex.image.image)).astype(np.uint16)  # a detector's raw counts
intensity[~ex.image.mask] = 0  # outside the collimated field: a constant dark border
tifffile.imwrite(folder / "xray.tif", intensity)
geometry = {
    "primary_deg": g.primary_deg,
    "secondary_deg": g.secondary_deg,
    "sid_mm": g.sid_mm,
    "sod_mm": g.sod_mm,
    "pixel_mm": list(g.pixel_mm),
    "pixel_values": "intensity",
    "i0": 4000.0,
}
(folder / "xray.json").write_text(json.dumps(geometry, indent=2))
print(sorted(p.name for p in folder.iterdir()))

# %% [markdown]
# Now read them as you would your own files, and register.

# %%
volume = registration.Volume.from_file(folder / "ct.nii.gz")
image = registration.XRayImage.from_file(folder / "xray.tif", folder / "xray.json")
print(volume.shape, volume.meta["orientation_from"], "| mask from", image.meta["mask_from"])
result = registration.register(volume, image)
error = registration.residuals(result.patient_motion, ex.truth_motion, image.geometry)
print(f"residual {error.translation_mm:.2f} mm, {error.rotation_deg:.2f} deg; success: {error.success}")
assert error.success
