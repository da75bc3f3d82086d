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
point = np.array([10.0, -20.0, 15.0])  # a point of the anatomy (LPS mm)
where_now = result.patient_motion @ np.append(point, 1.0)
value_then = volume.EvaluateAtPhysicalPoint(point.tolist(), sitk.sitkLinear)
value_now = moved.EvaluateAtPhysicalPoint(where_now[:3].tolist(), sitk.sitkLinear)
print(f"HU at the point in the 3DRA: {value_then:.1f}; at M @ point after resampling: {value_now:.1f}")
assert abs(value_then - value_now) < 1.0
