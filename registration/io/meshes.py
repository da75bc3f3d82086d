"""Vessel and bone surfaces of a volume (marching cubes), in world millimetres.

Surfaces are extracted from the HU values (sub-voxel, scikit-image's marching cubes) and
mapped through the volume's ``index_to_world`` (CONVENTIONS.md §2), so they overlay the
volume and the DRRs exactly. Face winding is fixed so normals point out of the structure.
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np
import trimesh
from numpy.typing import NDArray
from scipy import ndimage
from skimage.measure import marching_cubes

from registration.core.volume import Volume

#: Iodinated contrast in vessels is ~ +300..+700 HU (CONVENTIONS §2); soft tissue stays below.
VESSEL_HU = 250.0
#: Cortical bone is ~ +1000..+2000 HU; its partial-volume rim is excluded from the vessels.
BONE_HU = 700.0
#: Voxels within this distance (voxels) of bone are not vessel (the bone's partial-volume rim).
BONE_MARGIN_VOXELS = 2
#: Vessel components smaller than this many voxels are dropped (noise, isolated bone specks).
MIN_VESSEL_VOXELS = 40
#: A light morphological opening (this many erosions then dilations with the 6-neighbour
#: cross) finds the candidates' cores; only components holding a core are kept (an opening
#: by reconstruction): specks and thin streaks of reconstruction noise have none, while thin
#: arteries keep their full shape as long as they join a thicker part of the tree.
OPENING_ITERATIONS = 1
#: Components within this many voxels of the volume's border, or of the edge of the
#: reconstructable region (voxels at UNRECONSTRUCTED_HU or below, what FDK sets outside its
#: cylinder), are dropped when more than MAX_EDGE_FRACTION of their voxels lie there: bone
#: cut by the border and cone-beam artefacts at the cylinder's edge form flat rings there, while
#: arteries entering the volume (the carotids at its bottom) only pass through.
EDGE_MARGIN_VOXELS = 3
MAX_EDGE_FRACTION = 0.25
UNRECONSTRUCTED_HU = -1000.0
#: Arteries run in brain and soft tissue; thin facial bones and sinus walls whose partial-volume
#: values fall between the thresholds border air. A component whose SHELL_VOXELS shell holds more
#: than this fraction of air (< AIR_HU) is not a vessel. (On the phantom the vessel components'
#: shells hold no air at all and every other component's at least 7 %; on its FDK
#: reconstruction, whose air edges are smoothed, the ethmoid's 4-voxel shell holds 9 %.)
MAX_SHELL_AIR_FRACTION = 0.02
#: Thickness (voxels) of that shell.
SHELL_VOXELS = 4
AIR_HU = -300.0
#: Iodine is not the only thing between the thresholds: bone's partial-volume voxels are too (the
#: rims of thin facial bones, sinus walls and the skull base in thick CT slices, cancellous bone
#: behind thin cortex: ~+250..+700 HU like contrast). They lie against bone and among more such
#: values, while a contrast-filled artery runs through brain and soft tissue. Three rules, in mm
#: whatever the grid, keep a component as a vessel only when it is like that:
#: (1) at least half its voxels lie MIN_VESSEL_BONE_DISTANCE_MM or more from bone (>= bone_hu);
#: (2) at least MIN_SOFT_SURROUND_FRACTION of the voxels within SURROUND_MM of it are soft tissue
#:     (< SOFT_TISSUE_MAX_HU: brain, blood, muscle, fat; bone and its partial volume are above);
#: (3) it runs at least MIN_VESSEL_LENGTH_MM (the largest side of its bounding box): a
#:     calcification (a plaque, a calcified node) or a bone speck is a blob, not a vessel.
#: Measured on the components that pass the rules above. The shared head CT (no contrast; 24
#: components, bone partial volume and one calcification): 21 have under half their voxels 6 mm
#: from bone (at most 0.44), two more a surround of at most 0.60 soft tissue, and the
#: calcification (0.94, 0.83) is 15 mm long. The phantom's contrast-filled arteries (FDK 3DRA
#: 128^3 and 256^3, stand-ins 128^3 and 256^3: 13 components) have >= 0.64 of their voxels 6 mm
#: from bone, a surround >= 0.74 soft tissue and are >= 29.9 mm long. What is lost: artery
#: pieces cut off against bone by the bone margin above (a 9 mm piece of a vertebral artery in
#: the FDK 256^3 phantom, a 6 mm one by the dens in the 256^3 stand-in); gone from the FDK 256^3
#: phantom's vessels are five bone partial-volume pieces (18 % of its vertices).
MIN_VESSEL_BONE_DISTANCE_MM = 6.0
SOFT_TISSUE_MAX_HU = 150.0
SURROUND_MM = 3.0
MIN_SOFT_SURROUND_FRACTION = 2.0 / 3.0
MIN_VESSEL_LENGTH_MM = 20.0
#: What the app and the mesh command say when no vessel surface is found.
NO_VESSELS_NOTE = (
    "no contrast-filled vessels found in this volume (nothing brighter than soft tissue and away from bone "
    "that runs like a vessel): no vessel surface, no roadmap outline"
)

#: Bone components smaller than this (mm^3, 26-connected voxels at or above the bone threshold)
#: are left out of the display surface of :func:`bone_surface`: CT noise specks and calcifications
#: of a few voxels, which at a display cell of ~5 mm float free as blobs of a few faces. The
#: smallest bones drawn (nasal bones, hyoid: ~0.5-2 mL) stay.
MIN_BONE_COMPONENT_MM3 = 200.0
#: :func:`bone_surface` smooths each cell's bone fraction with a Gaussian of this many cells
#: (sigma) and takes the surface at BONE_FRACTION_LEVEL of it. Without the smoothing a plate about
#: a cell thick (the skull in ~5 mm cells) lies in cells that touch only at edges and corners where
#: it steps from one layer of cells to the next, and the surface is perforated there; with it, and
#: the low level, plates down to ~1 mm stay closed (a 3 mm shell in 6 mm cells: two closed
#: spheres, inside and out), at the price of a surface up to about a cell outside thick bone.
BONE_SMOOTHING_CELLS = 0.5
BONE_FRACTION_LEVEL = 0.1

COLORS = {"vessels": (200, 40, 40, 255), "bone": (228, 218, 196, 255)}
MESH_SUFFIXES = (".stl", ".ply", ".glb")


def _surface(
    field: NDArray[np.float32], level: float, index_to_world: NDArray[np.float64], step: int
) -> trimesh.Trimesh | None:
    if not (field.min() < level < field.max()):
        return None
    verts_kji, faces, _normals, _values = marching_cubes(field, level=level, step_size=step)
    ijk = verts_kji[:, ::-1]
    world = ijk @ index_to_world[:3, :3].T + index_to_world[:3, 3]
    # After reordering (k, j, i) -> (i, j, k), scikit-image's winding gives outward normals
    # for a positive-determinant affine; a mirroring affine reverses it.
    if np.linalg.det(index_to_world[:3, :3]) < 0:
        faces = faces[:, ::-1]
    return trimesh.Trimesh(vertices=world, faces=faces, process=False)


def _edge_region(hu: NDArray[np.float32]) -> NDArray[np.bool_]:
    """Voxels within EDGE_MARGIN_VOXELS of the border or of the unreconstructed region."""
    outside = hu <= UNRECONSTRUCTED_HU
    m = EDGE_MARGIN_VOXELS
    border = np.ones(hu.shape, dtype=bool)
    border[m:-m, m:-m, m:-m] = False
    return border | ndimage.binary_dilation(outside, iterations=m)


def _vessel_components(
    hu: NDArray[np.float32], candidate: NDArray[np.bool_], bone: NDArray[np.bool_], spacing_kji_mm: NDArray[np.float64]
) -> NDArray[np.bool_]:
    """Keep the candidate components that are big enough, clear of the volume's edges, surrounded
    by tissue, not air, and like a contrast-filled vessel: mostly MIN_VESSEL_BONE_DISTANCE_MM from
    ``bone``, in soft tissue (MIN_SOFT_SURROUND_FRACTION) and MIN_VESSEL_LENGTH_MM long."""
    labels, count = ndimage.label(candidate)
    if not count:
        return candidate
    sizes = np.bincount(labels.ravel())
    cored = np.zeros(count + 1, dtype=bool)
    if OPENING_ITERATIONS:
        cross = ndimage.generate_binary_structure(3, 1)
        core = ndimage.binary_opening(candidate, structure=cross, iterations=OPENING_ITERATIONS)
        cored[np.unique(labels[core])] = True
    else:
        cored[:] = True
    at_edge = np.bincount(labels[_edge_region(hu)], minlength=count + 1)
    touching = at_edge > MAX_EDGE_FRACTION * sizes
    keep = np.zeros(count + 1, dtype=bool)
    margin = SHELL_VOXELS
    # Distances are needed up to MIN_VESSEL_BONE_DISTANCE_MM (from bone) and SURROUND_MM (from the
    # component): what lies further than that from a component, outside its box grown by as much,
    # changes no decision.
    reach_mm = max(MIN_VESSEL_BONE_DISTANCE_MM, SURROUND_MM)
    reach = np.ceil(reach_mm / spacing_kji_mm).astype(int) + 1
    for index, box in enumerate(ndimage.find_objects(labels), start=1):
        if box is None or sizes[index] < MIN_VESSEL_VOXELS or touching[index] or not cored[index]:
            continue
        length_mm = max((b.stop - b.start) * float(d) for b, d in zip(box, spacing_kji_mm, strict=True))
        if length_mm < MIN_VESSEL_LENGTH_MM:
            continue
        grown = tuple(slice(max(0, b.start - margin), b.stop + margin) for b in box)
        inside = labels[grown] == index
        shell = ndimage.binary_dilation(inside, iterations=margin) & ~inside
        air = float(np.mean(hu[grown][shell] < AIR_HU)) if shell.any() else 0.0
        if air > MAX_SHELL_AIR_FRACTION:
            continue
        near = tuple(slice(max(0, b.start - r), b.stop + r) for b, r in zip(box, reach, strict=True))
        inside = labels[near] == index
        bone_near = bone[near]
        if bone_near.any():
            from_bone_mm = ndimage.distance_transform_edt(~bone_near, sampling=spacing_kji_mm)[inside]
            if np.mean(from_bone_mm >= MIN_VESSEL_BONE_DISTANCE_MM) < 0.5:
                continue
        from_vessel_mm = ndimage.distance_transform_edt(~inside, sampling=spacing_kji_mm)
        surround = hu[near][(from_vessel_mm > 0) & (from_vessel_mm <= SURROUND_MM)]
        keep[index] = surround.size == 0 or np.mean(surround < SOFT_TISSUE_MAX_HU) >= MIN_SOFT_SURROUND_FRACTION
    return keep[labels]


def bone_surface(
    volume: Volume,
    *,
    cells_across: int,
    bone_hu: float = BONE_HU,
    min_component_mm3: float = MIN_BONE_COMPONENT_MM3,
) -> trimesh.Trimesh | None:
    """The bone's surface for display: about ``cells_across`` marching-cubes cells across the
    bone's largest extent, near-cubic in mm whatever the volume's grid; None without bone.

    Striding the voxel grid (``surface_meshes(bone_step=...)``) cannot do this for a CT: with
    1 x 1 x 3 mm voxels and a field of view two to three times the head, the step that keeps
    the face count down samples every 8 x 8 x 24 mm, the skull (2-7 mm thick) falls between
    samples and breaks into floating plates. Here the bone is the voxels at or above
    ``bone_hu`` in 26-connected components of at least ``min_component_mm3``
    (MIN_BONE_COMPONENT_MM3); each cell spans a whole number of voxels along each axis (the
    cell size in mm divided by that axis's spacing, at least one) and holds the fraction of
    them that is bone (a box filter: thin bone is not missed between samples), smoothed over
    BONE_SMOOTHING_CELLS, and the surface is its iso-surface at BONE_FRACTION_LEVEL, in world mm.
    ``mesh.metadata["cell_mm"]`` holds the cell's size (x, y, z).
    """
    from skimage.measure import block_reduce

    if int(cells_across) != cells_across or cells_across < 1:
        raise ValueError(f"cells_across must be a positive integer, got {cells_across}")
    if not min_component_mm3 >= 0:
        raise ValueError(f"min_component_mm3 must be >= 0, got {min_component_mm3}")
    bone = volume.data >= bone_hu
    if not bone.any():
        return None
    labels, count = ndimage.label(bone, structure=ndimage.generate_binary_structure(3, 3))
    voxel_mm3 = abs(float(np.linalg.det(volume.index_to_world[:3, :3])))
    sizes = np.bincount(labels.ravel(), minlength=count + 1)
    keep = sizes * voxel_mm3 >= min_component_mm3
    keep[0] = False
    bone = keep[labels]
    if not bone.any():
        return None
    # The kept bone's bounding box (k, j, i) and its extent in mm.
    lo = np.array([np.flatnonzero(bone.any(axis=axes))[0] for axes in ((1, 2), (0, 2), (0, 1))])
    hi = np.array([np.flatnonzero(bone.any(axis=axes))[-1] + 1 for axes in ((1, 2), (0, 2), (0, 1))])
    spacing_kji = np.asarray(volume.spacing_mm, np.float64)[::-1]
    cell_mm = float(np.max((hi - lo) * spacing_kji)) / int(cells_across)
    factors = np.maximum(1, np.rint(cell_mm / spacing_kji)).astype(int)
    box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))
    fraction = block_reduce(bone[box].astype(np.float32), tuple(int(f) for f in factors), np.mean, cval=0.0)
    fraction = ndimage.gaussian_filter(fraction, BONE_SMOOTHING_CELLS, mode="constant")
    # One cell of "no bone" around closes the surface where bone reaches the box's edge. Cell c of
    # the padded grid covers voxels lo + (c - 1) f .. lo + c f - 1 (per axis): its center is voxel
    # lo + (c - 1) f + (f - 1) / 2.
    padded = np.pad(fraction, 1, mode="constant", constant_values=0.0)
    f_ijk, lo_ijk = factors[::-1].astype(np.float64), lo[::-1].astype(np.float64)
    voxel_from_cell = np.diag([*f_ijk, 1.0])
    voxel_from_cell[:3, 3] = lo_ijk - f_ijk + (f_ijk - 1.0) / 2.0
    mesh = _surface(padded, BONE_FRACTION_LEVEL, volume.index_to_world @ voxel_from_cell, 1)
    if mesh is None or not len(mesh.faces):
        return None
    mesh.metadata["cell_mm"] = tuple(float(v) for v in factors[::-1] * spacing_kji[::-1])
    return mesh


def surface_meshes(
    volume: Volume,
    *,
    vessel_hu: float = VESSEL_HU,
    bone_hu: float = BONE_HU,
    step: int = 1,
    bone_step: int | None = None,
    bone_cells_across: int | None = None,
) -> dict[str, trimesh.Trimesh]:
    """The ``"vessels"`` and ``"bone"`` surfaces of ``volume`` (absent keys: nothing found).

    Vessels are the iso-surface at ``vessel_hu`` of the voxels that lie more than
    BONE_MARGIN_VOXELS from bone, in components of at least MIN_VESSEL_VOXELS that hold a core
    surviving a light opening (OPENING_ITERATIONS), lie mostly clear of the volume's border and
    of the reconstructable region's edge (EDGE_MARGIN_VOXELS, MAX_EDGE_FRACTION), are
    surrounded by tissue rather than air (MAX_SHELL_AIR_FRACTION), lie mostly away from bone
    (MIN_VESSEL_BONE_DISTANCE_MM) in soft tissue (MIN_SOFT_SURROUND_FRACTION) and run like a
    vessel (MIN_VESSEL_LENGTH_MM): iodine-filled
    arteries of a contrast 3DRA or CTA. A volume without contrast (a plain CT) has none, and no
    ``"vessels"`` key (NO_VESSELS_NOTE says why). Bone is the iso-surface at ``bone_hu``.
    ``step`` > 1 trades detail for speed; ``bone_step`` (default ``step``) sets it for the
    bone alone, whose surface is by far the larger. ``bone_cells_across`` instead makes the
    bone :func:`bone_surface`'s (that many near-cubic cells across the bone, small components
    dropped): for volumes whose grid is anisotropic or much larger than the bone (a CT).
    """
    if not vessel_hu < bone_hu:
        raise ValueError(f"vessel_hu ({vessel_hu}) must be below bone_hu ({bone_hu})")
    bone_step = step if bone_step is None else bone_step
    for name, value in (("step", step), ("bone_step", bone_step)):
        if int(value) != value or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value}")
    hu = volume.data
    floor = np.float32(min(float(hu.min()), -1000.0))
    bone = hu >= bone_hu
    near_bone = ndimage.binary_dilation(bone, iterations=BONE_MARGIN_VOXELS) if bone.any() else bone
    candidate = (hu > vessel_hu) & ~near_bone
    spacing_kji_mm = np.asarray(volume.spacing_mm, np.float64)[::-1]
    candidate = _vessel_components(hu, candidate, bone, spacing_kji_mm)
    vessel_field = np.where(ndimage.binary_dilation(candidate, iterations=1) & ~near_bone, hu, floor)
    # Padding by one voxel of "nothing" closes surfaces that touch the volume's border; the
    # padded grid's index 0 is the volume's index -1.
    padded_to_world = volume.index_to_world.copy()
    padded_to_world[:3, 3] -= volume.index_to_world[:3, :3].sum(axis=1)
    out: dict[str, trimesh.Trimesh] = {}
    parts = [("vessels", vessel_field, vessel_hu, step)]
    if bone_cells_across is None:
        parts.append(("bone", hu, bone_hu, bone_step))
    for name, field, level, part_step in parts:
        padded = np.pad(field.astype(np.float32), 1, mode="constant", constant_values=floor)
        mesh = _surface(padded, level, padded_to_world, int(part_step))
        if mesh is not None and len(mesh.faces):
            mesh.visual.face_colors = np.tile(COLORS[name], (len(mesh.faces), 1))
            mesh.metadata["name"] = name
            out[name] = mesh
    if bone_cells_across is not None:
        mesh = bone_surface(volume, cells_across=bone_cells_across, bone_hu=bone_hu)
        if mesh is not None:
            mesh.visual.face_colors = np.tile(COLORS["bone"], (len(mesh.faces), 1))
            mesh.metadata["name"] = "bone"
            out["bone"] = mesh
    return out


def surface_params(
    *, vessel_hu: float = VESSEL_HU, bone_hu: float = BONE_HU, step: int = 1, bone_step: int | None = None
) -> dict:
    """Everything besides the volume that defines :func:`surface_meshes`' output (cache keys)."""
    return {
        "vessel_hu": float(vessel_hu),
        "bone_hu": float(bone_hu),
        "steps": [int(step), int(step if bone_step is None else bone_step)],
        "segmentation": [
            BONE_MARGIN_VOXELS, MIN_VESSEL_VOXELS, OPENING_ITERATIONS, EDGE_MARGIN_VOXELS, MAX_EDGE_FRACTION,
            UNRECONSTRUCTED_HU, SHELL_VOXELS, MAX_SHELL_AIR_FRACTION, AIR_HU, MIN_VESSEL_BONE_DISTANCE_MM,
            SOFT_TISSUE_MAX_HU, SURROUND_MM, MIN_SOFT_SURROUND_FRACTION, MIN_VESSEL_LENGTH_MM,
        ],
    }  # fmt: skip


def cached_surface_meshes(
    volume: Volume, volume_key: dict, *, step: int = 1, bone_step: int | None = None
) -> dict[str, trimesh.Trimesh]:
    """:func:`surface_meshes` through the on-disk cache (:mod:`registration.io.cache`).

    ``volume_key`` must identify the volume's contents (e.g. a recipe's cache parameters, or
    the volume's ``meta`` and label); the surface parameters are added here
    (:func:`surface_params`).
    """
    from registration.io.cache import cached_arrays

    def build() -> dict[str, np.ndarray]:
        out: dict[str, np.ndarray] = {}
        for name, mesh in surface_meshes(volume, step=step, bone_step=bone_step).items():
            out[f"{name}.vertices"] = np.asarray(mesh.vertices, dtype=np.float32)
            out[f"{name}.faces"] = np.asarray(mesh.faces, dtype=np.int32)
        return out

    params = {"volume": volume_key, **surface_params(step=step, bone_step=bone_step)}
    arrays = cached_arrays("meshes", params, build)
    names = sorted({key.rsplit(".", 1)[0] for key in arrays})
    return {name: trimesh.Trimesh(arrays[f"{name}.vertices"], arrays[f"{name}.faces"], process=False) for name in names}


def write_meshes(meshes: dict[str, trimesh.Trimesh], path: str | os.PathLike[str]) -> Path:
    """Write the surfaces to STL or PLY (one combined mesh) or GLB (one node per surface).

    The file is written through a temporary file and renamed, so no partial file is left.
    """
    from registration.io.dicom import write_bytes_atomic

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise ValueError(f"{path}: mesh format must be one of {', '.join(MESH_SUFFIXES)}, got {suffix or 'none'}")
    if not meshes:
        raise ValueError("no surface to write")
    if suffix == ".glb":
        scene = trimesh.Scene()
        for name, mesh in meshes.items():
            scene.add_geometry(mesh, node_name=name, geom_name=name)
        data = scene.export(file_type="glb")
    else:
        combined = trimesh.util.concatenate(list(meshes.values()))
        buffer = io.BytesIO()
        combined.export(buffer, file_type=suffix[1:])
        data = buffer.getvalue()
    write_bytes_atomic(path, data)
    return path
