"""The 3-D scene: the patient's skull and vessels, their true position as a ghost, the C-arm.

World coordinates are patient LPS millimetres (CONVENTIONS §1) shown in metres (viser's
lights and camera controls are tuned for metre-sized scenes); anterior (-y) is up, as for a
supine patient on the table.
"""

from __future__ import annotations

import math

import numpy as np
import trimesh
import viser
import viser.transforms as vtf

from registration.core.geometry import CArm

M_PER_MM = 1e-3

BONE_RGB = (226, 216, 196)
VESSEL_RGB = (214, 38, 38)
GHOST_RGB = (90, 200, 255)
CARM_RGB = (120, 128, 140)
SOURCE_RGB = (255, 190, 60)
#: Plane B's beam and source (biplane mode): its own colour beside plane A's amber.
PLANE_B_RGB = (190, 120, 255)


def pose_of(motion: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(wxyz, position in metres) of a node placed by a 4x4 patient motion in mm."""
    wxyz = vtf.SO3.from_matrix(np.asarray(motion)[:3, :3]).wxyz
    return wxyz, np.asarray(motion)[:3, 3] * M_PER_MM


#: A mesh over the scene's face budget is simplified (quadric edge collapse, fast_simplification
#: through trimesh) to the budget; when the result of a closed mesh is not closed (the collapse
#: leaves an occasional degenerate fold: 2 open edges of 12,000 faces on a marching-cubes shell),
#: it is simplified again to this fraction of the previous target, up to DECIMATION_TRIES times.
DECIMATION_RETRY_FRACTION = 0.9
DECIMATION_TRIES = 5


def _cleaned(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """``mesh`` without zero-area and repeated faces (edge collapse leaves some) or unused vertices."""
    out = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    out.update_faces(out.nondegenerate_faces())
    out.update_faces(out.unique_faces())
    out.remove_unreferenced_vertices()
    return out


def _decimated(mesh: trimesh.Trimesh, max_faces: int) -> trimesh.Trimesh:
    """``mesh`` itself when it has at most ``max_faces`` faces, else simplified to at most that many
    (quadric decimation, the ``fast-simplification`` dependency), closed if ``mesh`` is closed
    (retried at DECIMATION_RETRY_FRACTION of the target when a collapse opened it; after
    DECIMATION_TRIES the last, under-budget result is drawn)."""
    if len(mesh.faces) <= max_faces:
        return mesh
    closed = mesh.is_watertight
    target = int(max_faces)
    shown = mesh
    for _ in range(DECIMATION_TRIES):
        shown = _cleaned(mesh.simplify_quadric_decimation(face_count=target))
        if len(shown.faces) <= max_faces and (shown.is_watertight or not closed):
            return shown
        target = max(4, int(target * DECIMATION_RETRY_FRACTION))
    if len(shown.faces) > max_faces:  # not seen: fast_simplification reaches its target at its default aggression
        raise RuntimeError(f"could not simplify a {len(mesh.faces)}-face mesh to {max_faces} faces")
    return shown


class Scene:
    """Owns the scene nodes; every method may be called from any thread."""

    def __init__(self, server: viser.ViserServer) -> None:
        self.server = server
        self.scene = server.scene
        self.scene.set_up_direction("-y")
        self.scene.add_grid(
            "/floor",
            width=4.0,
            height=4.0,
            plane="xz",
            position=(0.0, 1.0, 0.0),  # the floor, below the X-ray tube
            cell_color=(60, 64, 72),
            section_color=(80, 86, 96),
        )
        self.isocenter = self.scene.add_icosphere(
            "/isocenter", radius=0.004, color=(255, 255, 255), position=(0.0, 0.0, 0.0)
        )  # moved to the C-arm's iso-center by set_carm (a CT's is rarely the world origin)
        self.scene.add_label("/isocenter/label", "iso-center", position=(0.0, 0.0, -0.1), font_screen_scale=0.8)
        self.patient: list = []
        self.ghost: list = []
        self.frustum: viser.CameraFrustumHandle | None = None
        self.frustum_b: viser.CameraFrustumHandle | None = None
        self.plane_b_nodes: list = []

    # ----- the patient ------------------------------------------------------------------
    def set_anatomy(self, meshes: dict[str, trimesh.Trimesh], *, max_faces: int = 120_000) -> None:
        """(Re)create skull and vessel nodes from meshes in world mm at the volume's pose."""
        for handle in self.patient + self.ghost:
            handle.remove()
        self.patient, self.ghost = [], []
        for name, mesh in meshes.items():
            is_vessel = "vessel" in name
            shown = _decimated(mesh, max_faces if is_vessel else max_faces)
            verts = np.asarray(shown.vertices, np.float32) * M_PER_MM
            faces = np.asarray(shown.faces, np.uint32)
            self.patient.append(
                self.scene.add_mesh_simple(
                    f"/patient/{name}",
                    verts,
                    faces,
                    color=VESSEL_RGB if is_vessel else BONE_RGB,
                    opacity=1.0 if is_vessel else 0.22,
                    side="double" if not is_vessel else "front",
                    flat_shading=False,
                )
            )
            if is_vessel:
                self.ghost.append(
                    self.scene.add_mesh_simple(
                        f"/truth/{name}", verts, faces, color=GHOST_RGB, opacity=0.35, visible=False
                    )
                )

    def place(self, estimate: np.ndarray, truth: np.ndarray | None, *, show_ghost: bool) -> None:
        wxyz, pos = pose_of(estimate)
        for handle in self.patient:
            handle.wxyz, handle.position = wxyz, pos
        if truth is not None:
            wxyz_t, pos_t = pose_of(truth)
        for handle in self.ghost:
            handle.visible = show_ghost and truth is not None
            if truth is not None:
                handle.wxyz, handle.position = wxyz_t, pos_t

    # ----- the C-arm --------------------------------------------------------------------
    def set_carm(self, geometry: CArm, image: np.ndarray | None = None, *, plane_b: bool = False) -> None:
        """Source, detector, frustum (with ``image`` on the detector) and the C arc; ``plane_b``:
        the biplane system's second C-arm (its nodes under ``/carm_b``, its beam in PLANE_B_RGB)."""
        root, beam_rgb = ("/carm_b", PLANE_B_RGB) if plane_b else ("/carm", SOURCE_RGB)
        sid = geometry.sid_mm * M_PER_MM
        d = geometry.direction
        u, v = geometry.u, geometry.v
        # OpenCV camera frame at the source: +z along the beam, +y along image rows; +x = -u keeps
        # it right-handed (u x v = -d), so the picture is mirrored left-right to sit where it formed.
        rot = np.column_stack([-u, v, d])
        wxyz = vtf.SO3.from_matrix(rot).wxyz
        half_h = geometry.rows * geometry.pixel_mm[0] / 2.0
        half_w = geometry.cols * geometry.pixel_mm[1] / 2.0
        fov = 2.0 * math.atan(half_h / geometry.sid_mm)
        aspect = half_w / half_h
        tan = math.tan(fov / 2.0)
        scale = sid * (tan * tan * aspect / 3.0) ** (1.0 / 3.0)  # viser normalises the frustum volume
        source = geometry.source_mm * M_PER_MM
        kwargs: dict = {}
        if image is not None:
            kwargs = {"image": np.ascontiguousarray(image[:, ::-1]), "format": "jpeg", "jpeg_quality": 85}
        frustum = self.scene.add_camera_frustum(
            f"{root}/beam",
            fov=fov,
            aspect=aspect,
            scale=scale,
            color=beam_rgb,
            thickness=0.0015,
            wxyz=wxyz,
            position=source,
            **kwargs,
        )
        source_node = self.scene.add_icosphere(f"{root}/source", radius=0.03, color=beam_rgb, position=source)
        center = geometry.detector_center_mm * M_PER_MM
        detector = self.scene.add_box(
            f"{root}/detector",
            dimensions=(2 * half_w * M_PER_MM + 0.06, 2 * half_h * M_PER_MM + 0.06, 0.05),
            color=(70, 74, 82),
            opacity=0.45,  # the image on the detector shows through its housing
            wxyz=wxyz,
            position=center + d * 0.026,
        )
        # The C: a half circle from the source housing round to the detector housing.
        mid = (source + center) / 2.0
        radius = sid / 2.0 + 0.08
        t = np.linspace(0.0, math.pi, 48)
        side = np.cross(d, np.array([0.0, 0.0, 1.0]))
        side = side / np.linalg.norm(side) if np.linalg.norm(side) > 1e-6 else u
        arc = mid - np.cos(t)[:, None] * d * radius + np.sin(t)[:, None] * side * radius * 0.9
        arc_node = self.scene.add_spline_catmull_rom(f"{root}/arc", arc, thickness=0.03, color=CARM_RGB)
        if not plane_b:
            self.isocenter.position = tuple(float(x) for x in np.asarray(geometry.isocenter_mm) * M_PER_MM)
        if plane_b:
            self.frustum_b = frustum
            self.plane_b_nodes = [frustum, source_node, detector, arc_node]
        else:
            self.frustum = frustum

    def remove_plane_b(self) -> None:
        """Back to one plane: plane B's C-arm leaves the scene."""
        for node in self.plane_b_nodes:
            node.remove()
        self.plane_b_nodes, self.frustum_b = [], None

    def set_detector_image(self, image: np.ndarray, *, plane_b: bool = False) -> None:
        frustum = self.frustum_b if plane_b else self.frustum
        if frustum is not None:
            frustum.image = np.ascontiguousarray(image[:, ::-1])
