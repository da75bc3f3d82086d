"""Two views of the phantom at one moment, registered from the machine-based pose: the scene the
tests of the far-start stages (fine polish, translation-first candidate) start from."""

from __future__ import annotations

from collections.abc import Sequence

from registration.core.geometry import CArm, offsets_to_matrix
from registration.core.register import RegistrationOptions, register


def phantom_pair(offsets: Sequence[float]) -> tuple:
    """(volume, x-rays, truth, options, result): the phantom's 128³ 3DRA over 27 cm, planes at
    LAO 20 (256 px) and RAO 70 (192 px) seeing the patient moved by ``offsets`` (plane A's view
    frame: tx, ty, tz mm, rx, ry, rz deg), and the default registration of both."""
    from registration.sim.phantom import make_head_phantom, registration_volume
    from registration.sim.xray import simulate_xray

    volume = registration_volume(make_head_phantom(seed=0, contrast=True), 27.0, voxels=128)
    views = [CArm.for_format(27.0, pixels=256, primary_deg=20.0), CArm.for_format(27.0, pixels=192, primary_deg=-70.0)]
    truth = offsets_to_matrix(tuple(offsets), views[0])
    phantom = make_head_phantom(seed=0, contrast=False)
    xrays = [simulate_xray(phantom, g, motion=truth, kind="exposure", seed=1 + n) for n, g in enumerate(views)]
    options = RegistrationOptions()
    return volume, xrays, truth, options, register(volume, xrays, truth=truth, seed=0, options=options)
