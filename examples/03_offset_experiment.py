# %% [markdown]
# # An offset experiment
#
# How far from the truth does a registration end, by starting offset? Each image shows the
# phantom moved by one offset of Table I; each registration starts from no motion. The residual
# is taken at the iso-center (CONVENTIONS §4); success is < 1 mm and < 3 degrees (in-plane for a
# single view).

# %%
import matplotlib.pyplot as plt

import registration

offsets = ["T1", "T2", "T3"]
rows = []
for name in offsets:
    ex = registration.load_example(name, pixels=128)  # small images keep the example quick
    result = registration.register(ex.volume, ex.image, seed=0)
    error = registration.residuals(result.patient_motion, ex.truth_motion, ex.image.geometry)
    rows.append((name, error.inplane_mm, error.rotation_deg, error.success))
    print(f"{name}: in-plane {error.inplane_mm:.2f} mm, rotation {error.rotation_deg:.2f} deg, success {error.success}")

# %%
fig, ax = plt.subplots(figsize=(5, 3))
ax.bar([r[0] for r in rows], [r[1] for r in rows], color=["tab:green" if r[3] else "tab:red" for r in rows])
ax.axhline(1.0, color="k", ls="--", lw=1, label="success: 1 mm")
ax.set_ylabel("in-plane residual at the iso-center (mm)")
ax.legend()
plt.show()
assert all(r[3] for r in rows)
