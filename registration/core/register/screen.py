"""The out-of-plane rotation screen of a single-plane estimate: how sharply the measure peaks in
rx and ry there. A wrong rx / ry optimum sits on a flat ridge (its margin small or negative), as
the confidence's ``rotation_margin`` finds; the depth correction's first polish and the rotation
check skip an estimate whose margin reaches their threshold."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from registration.core.search import SearchSpace

Array = NDArray[np.float64]

#: The turn of rx and ry (deg) at which the screen measures the estimate's margin.
SCREEN_TURN_DEG = 3.0


def rotation_margin(cost: Callable[[Array], float], space: SearchSpace, x: Array, f_est: float) -> float:
    """The estimate's relative margin over its out-of-plane rotations: the measure at ``x`` less
    the best of rx and ry turned by +- :data:`SCREEN_TURN_DEG` (four evaluations of ``cost``,
    the negated measure), relative to the measure; not finite when the run was stopped."""
    worst = min(cost(turned) for turned in turned_starts(x, space, SCREEN_TURN_DEG))
    margin = float((worst - f_est) / max(abs(f_est), 1e-12))
    return margin if math.isfinite(margin) else math.nan


def turned_starts(x: Array, space: SearchSpace, turn_deg: float) -> list[Array]:
    """``x`` with rx, then ry (of the five parameters) turned by +``turn_deg`` and -``turn_deg``,
    each clipped to the space's bounds."""
    out = []
    for slot in (2, 3):
        for sign in (1.0, -1.0):
            turned = np.array(x, dtype=np.float64)
            turned[slot] += sign * turn_deg
            out.append(np.clip(turned, space.bounds[:, 0], space.bounds[:, 1]))
    return out
