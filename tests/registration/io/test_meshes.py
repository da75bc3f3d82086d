"""Vessel segmentation of registration/meshes.py on volumes with known structures.

A reconstructed (FDK) 3DRA has reconstruction noise, bone cut by the volume's border and a
reconstructable cylinder outside which every voxel is air; the vessel surface must keep the
arteries (also where they enter the volume) and drop the rest.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from registration.core.volume import Volume
from registration.io.meshes import MIN_VESSEL_VOXELS, surface_meshes

N = 64
SPACING_MM = 1.0


def _fdk_like_volume() -> tuple[Volume, dict[str, np.ndarray]]:
    """Brain tissue in the reconstructable cylinder (air outside), an artery, noise and rings."""
    k, j, i = np.mgrid[0:N, 0:N, 0:N].astype(np.float64)
    c = (N - 1) / 2.0
    radial = np.hypot(j - c, i - c)
    hu = np.full((N, N, N), 40.0, np.float32)
    hu[radial > 28.0] = -1000.0  # outside the reconstructable cylinder (exactly the fill value)
    parts = {
        # An artery 5 voxels across entering at the bottom border, running up to mid-volume.
        "artery": (np.hypot(j - c, i - (c - 8)) < 2.6) & (k < 40),
        # Reconstruction noise: a single bright voxel and a one-voxel-thick streak (no core).
        "speck": (k == 30) & (j == 20) & (i == 40),
        "streak": (k == 20) & (np.abs(j - 44) < 1) & (np.abs(i - 30) < 30) & (radial < 27),
        # Bone cut by the top of the volume: a flat ring in the last two slices.
        "top_ring": (k >= N - 2) & (np.abs(radial - 14.0) < 2.0),
        # A cone-beam artefact hugging the cylinder's edge.
        "edge_ring": (k >= 45) & (k < 49) & (radial > 25.0) & (radial < 27.5),
    }
    for mask in parts.values():
        hu[mask] = 500.0
    return Volume.from_grid(hu, SPACING_MM), parts


def _inside(mesh_vertices_mm: np.ndarray, part: np.ndarray, volume: Volume) -> int:
    """How many mesh vertices lie within 1.5 voxels of ``part``."""
    near = ndimage.binary_dilation(part, iterations=2)
    ijk = (mesh_vertices_mm - volume.index_to_world[:3, 3]) @ np.linalg.inv(volume.index_to_world[:3, :3]).T
    kji = np.clip(np.rint(ijk[:, ::-1]).astype(int), 0, N - 1)
    return int(near[tuple(kji.T)].sum())


def test_vessels_keep_the_artery_and_drop_noise_and_rings() -> None:
    volume, parts = _fdk_like_volume()
    assert parts["streak"].sum() >= MIN_VESSEL_VOXELS  # dropped for its shape, not its size
    vessels = surface_meshes(volume)["vessels"]
    verts = np.asarray(vessels.vertices)
    assert _inside(verts, parts["artery"], volume) == len(verts)  # nothing but the artery...
    # ...and all of it, down to the border where it enters (the surface is closed there).
    assert verts[:, 2].min() < volume.index_to_world[2, 3] + 1.0
    assert vessels.is_watertight
    for name in ("speck", "streak", "top_ring", "edge_ring"):
        assert _inside(verts, parts[name], volume) == 0, name
