# %% [markdown]
# # Register in ten lines
#
# The head phantom's 3DRA and a fluoroscopy image of the phantom moved by offset T4 of Table I
# (4 mm, 4 mm, 0 mm; 2, 3, 4 degrees). `register` estimates the patient motion `M`: anatomy the
# volume shows at X is at `M @ X` when the image was taken (docs/conventions.md).

# %%
import matplotlib.pyplot as plt
import numpy as np

import registration

ex = registration.load_example("T4")  # the 3DRA (cached after the first call) and a moved image
result = registration.register(ex.volume, ex.image)
error = registration.residuals(result.patient_motion, ex.truth_motion, ex.image.geometry)
print(
    f"{result.drr_count} DRRs in {result.seconds:.1f} s; residual {error.translation_mm:.2f} mm, "
    f"{error.rotation_deg:.2f} deg; success: {error.success}"
)
assert error.success

# %% [markdown]
# The image, and the DRR of the volume at the estimated pose beside it.

# %%
drr = registration.render_drr(ex.volume, ex.image.geometry, result.patient_motion)
fig, axes = plt.subplots(1, 2, figsize=(8, 4))
for ax, picture, title in zip(axes, [ex.image.image, drr.image], ["X-ray image", "DRR at the estimate"], strict=True):
    ax.imshow(picture, cmap="gray_r")
    ax.set_title(title)
    ax.axis("off")
plt.show()
print("patient motion (LPS mm):\n", np.round(result.patient_motion, 3))
