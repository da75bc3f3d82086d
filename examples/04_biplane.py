# %% [markdown]
# # Biplane
#
# A neuro suite images the patient through two planes at the same moment (CONVENTIONS §6):
# plane A frontal, plane B lateral, each with its own distances and detector. Given both,
# `register` estimates all six offsets, the one along plane A's beam too.

# %%
import registration
from registration.sim.biplane import plane_b_spec
from registration.sim.phantom import make_head_phantom
from registration.sim.xray import simulate_xray

ex = registration.load_example("T4", pixels=128)
plane_b = plane_b_spec().nominal(90.0, 0.0, pixels=96)  # lateral: the detector at the patient's left
phantom = make_head_phantom(seed=0, contrast=True)
image_b = registration.XRayImage._of(
    simulate_xray(phantom, plane_b, motion=ex.truth_motion, kind="fluoro", seed=1)
)  # the same moment: the same motion, its own noise
result = registration.register(ex.volume, [ex.image, image_b])
error = registration.residuals(result.patient_motion, ex.truth_motion, ex.image.geometry)
print(
    f"3-D residual {error.translation_mm:.2f} mm (along plane A's beam {error.outofplane_mm:.2f} mm), "
    f"{error.rotation_deg:.2f} deg; success: {error.success_total}"
)
assert error.success_total
