"""Write registration/data/example-t4.npz: the default case of ``registration.load_example()``.

The phantom's 3DRA (128³, 27 cm, whole HU, int16) and the T4 fluoroscopy image (256 px), made by
``registration.api.simulate_example``; ``tests/test_public_api.py`` checks the shipped copy
against a fresh simulation.

    python scripts/make_example.py
"""

from __future__ import annotations

import json

import numpy as np

from registration.api import SHIPPED_EXAMPLE, simulate_example


def main() -> None:
    ex = simulate_example("T4", pixels=256, seed=0)
    SHIPPED_EXAMPLE.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        SHIPPED_EXAMPLE,
        volume=ex.volume.data.astype(np.int16),
        index_to_world=ex.volume.index_to_world,
        label=np.array(ex.volume.label),
        image=ex.image.image,
        mask=ex.image.mask,
        geometry=np.array(json.dumps(ex.image.geometry.to_dict())),
        truth_motion=ex.truth_motion,
    )
    print(SHIPPED_EXAMPLE, f"{SHIPPED_EXAMPLE.stat().st_size / 1e6:.1f} MB")


if __name__ == "__main__":
    main()
