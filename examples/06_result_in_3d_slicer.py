# %% [markdown]
# # Reading a result in 3D Slicer
#
# 3D Slicer (and ITK-SNAP, SimpleITK) read the volume as NIfTI and the registration as an ITK
# transform file. roadmap3d writes the transform as ITK expects it: from the fixed space (the
# patient as imaged) to the moving space (the volume), in LPS, which is the inverse of the
# patient motion `M`. In Slicer: *Add Data* the `.nii.gz` and the `.tfm`, then in *Data* drag
# the volume under the transform: it moves as the patient moved (Slicer shows RAS and converts).
# On the command line: `roadmap3d register ... --out-transform result.tfm`.
#
# Here SimpleITK plays Slicer's part: resampling the volume with the file must put the anatomy
# where the motion says.

# %%
import tempfile
from pathlib import Path

import numpy as np
import SimpleITK as sitk

import registration
from registration.io.transforms import write_itk_transform

folder = Path(tempfile.mkdtemp())
ex = registration.load_example("T3", pixels=128)
result = registration.register(ex.volume, ex.image)
ex.volume.to_file(folder / "3dra.nii.gz")
write_itk_transform(result.patient_motion, folder / "result.tfm")
print((folder / "result.tfm").read_text())

# %%
volume = sitk.ReadImage(str(folder / "3dra.nii.gz"))
moved = sitk.Resample(volume, volume, sitk.ReadTransform(str(folder / "result.tfm")), sitk.sitkLinear, -1000.0)
# points of the anatomy (LPS mm, a 5 x 5 x 5 grid about the iso-center)
axis = np.linspace(-40.0, 40.0, 5)
points = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)


def hu(image: sitk.Image, p: np.ndarray) -> float:
    return image.EvaluateAtPhysicalPoint(p.tolist(), sitk.sitkLinear)


then = np.array([hu(volume, p) for p in points])
now = np.array([hu(moved, (result.patient_motion @ np.append(p, 1.0))[:3]) for p in points])
# the other convention, for comparison: the anatomy looked up where the inverse motion puts it
other = np.array([hu(moved, (np.linalg.inv(result.patient_motion) @ np.append(p, 1.0))[:3]) for p in points])
right, wrong = np.median(np.abs(now - then)), np.median(np.abs(other - then))
print(f"median HU difference at M @ point: {right:.1f}; at the inverse motion's point: {wrong:.1f}")
# resampling interpolates once more, so the right convention agrees up to that smoothing only
assert right < 0.25 * wrong
