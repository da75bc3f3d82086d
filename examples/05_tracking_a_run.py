# %% [markdown]
# # Tracking a fluoroscopy run, with the confidence
#
# During a run the patient may move. The tracker checks every frame against the last applied
# pose, refines small motion, captures large motion again, and says for each frame whether the
# roadmap uses the estimate (`applied`), keeps the last pose because the estimate is not trusted
# (`withheld`), or saw no motion (`unchanged`), with a confidence (CONVENTIONS §7).

# %%
import matplotlib.pyplot as plt
import numpy as np

import registration
from registration.sim.fluoro import RunScript, simulate_run
from registration.sim.phantom import make_head_phantom

ex = registration.load_example("T1", pixels=128)
script = RunScript(duration_s=2.0, fps=4.0, seed=3, still_start_s=0.6, sudden_moves=1, max_move_mm=6.0,
                   max_move_deg=2.0, drift=False, catheter=False)  # fmt: skip
run = simulate_run(make_head_phantom(seed=0, contrast=True), ex.image.geometry, script, cache=False)
tracked = registration.track(ex.volume, list(run), run.times_s, realtime=False)
for f in tracked.frames:
    error = registration.residuals(f.patient_motion, run.truth[f.frame], run.geometry)  # of the pose shown
    confidence = "-" if f.confidence is None else f"{f.confidence:.2f}"
    print(
        f"t={f.t_s:4.2f} s  {f.status:9s} {f.path:8s} confidence {confidence:4s}  "
        f"in-plane error {error.inplane_mm:.2f} mm, {error.rotation_deg:.2f} deg"
    )

# %%
t = [f.t_s for f in tracked.frames]
moved = [np.linalg.norm(run.truth[f.frame][:3, 3]) for f in tracked.frames]
conf = [np.nan if f.confidence is None else f.confidence for f in tracked.frames]
fig, ax = plt.subplots(figsize=(6, 3))
ax.plot(t, moved, "k-", label="true motion (mm)")
ax2 = ax.twinx()
ax2.plot(t, conf, "o", color="tab:blue", label="confidence")
ax2.set_ylim(0, 1.05)
ax.set_xlabel("time (s)")
ax.legend(loc="upper left")
ax2.legend(loc="lower right")
plt.show()
assert len(tracked.frames) == len(run)
