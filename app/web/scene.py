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
#: The vessels at the machine-based (initial) pose, beside the registered roadmap.
INITIAL_RGB = (255, 190, 60)
CARM_RGB = (120, 128, 140)
SOURCE_RGB = (255, 190, 60)
#: Plane B's beam and source (biplane mode): its own colour beside plane A's amber.
PLANE_B_RGB = (190, 120, 255)


#: The default camera: from above the patient's feet (anterior is up),
#: looking at the vessels, which fill this fraction of the view's height (and at most EDGE_FILL
#: of its width: the app's 3-D view is often narrow between its panels).
CAMERA_DIRECTION = (0.0, -0.84, -0.54)
CAMERA_FOV_DEG = 50.0
CAMERA_FILL = 0.6
EDGE_FILL = 0.95
#: The canvas aspect (width / height) assumed before a browser reports its own.
CAMERA_ASPECT = 1.0
#: Vertices of the vessels the camera frames (a regular subsample).
FRAMED_POINTS = 4000


def _camera_basis(direction: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    forward = -direction / np.linalg.norm(direction)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    return forward, right, np.cross(right, forward)


def screen_extent(
    points: np.ndarray, position: np.ndarray, look_at: np.ndarray, up: np.ndarray, fov_rad: float, aspect: float
) -> tuple[float, float]:
    """The fractions of a perspective view's height and width that the screen box of ``points``
    spans (camera at ``position`` looking at ``look_at``, vertical field of view ``fov_rad``,
    canvas width / height ``aspect``)."""
    forward, right, true_up = _camera_basis(np.asarray(position) - np.asarray(look_at), np.asarray(up, float))
    rel = np.asarray(points, float) - np.asarray(position, float)
    depth = np.maximum(rel @ forward, 1e-9)
    t = math.tan(fov_rad / 2.0)
    ndc_y = (rel @ true_up) / (depth * t)
    ndc_x = (rel @ right) / (depth * t * aspect)
    return float(np.ptp(ndc_y) / 2.0), float(np.ptp(ndc_x) / 2.0)


def frame_points(
    points: np.ndarray, *, direction=CAMERA_DIRECTION, up=(0.0, -1.0, 0.0),  # noqa: ANN001
    fov_rad: float = math.radians(CAMERA_FOV_DEG), fill: float = CAMERA_FILL, aspect: float = CAMERA_ASPECT,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(position, look_at) of a camera looking at the center of ``points``' box from
    ``direction``, as near as it may be for their screen box to span at most ``fill`` of the
    view's height and EDGE_FILL of its width."""
    pts = np.asarray(points, float)
    center = (pts.min(axis=0) + pts.max(axis=0)) / 2.0
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    radius = max(float(np.linalg.norm(pts - center, axis=1).max()), 1e-6)
    near, far = radius * 1.01, radius * 1e3

    def fits(dist: float) -> bool:
        h, w = screen_extent(pts, center + dist * d, center, np.asarray(up, float), fov_rad, aspect)
        return h <= fill and w <= EDGE_FILL

    for _ in range(60):  # bisection on the distance: nearer is larger on the screen
        mid = math.sqrt(near * far)
        near, far = (near, mid) if fits(mid) else (mid, far)
    return center + far * d, center


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
        #: The vessels at the machine-based pose (the pose before the last registration).
        self.initial: list = []
        #: The points (world m, at the volume's pose) the default camera frames: the vessels', else the anatomy's.
        self.framed_m: np.ndarray | None = None
        #: The C-arm whose source the cameras look from (None: the default camera on the vessels).
        self.source_view: CArm | None = None
        self._framed_motion: np.ndarray | None = None
        server.on_client_connect(self._on_connect)
        self.frustum: viser.CameraFrustumHandle | None = None
        self.frustum_b: viser.CameraFrustumHandle | None = None
        self.plane_b_nodes: list = []

    # ----- the patient ------------------------------------------------------------------
    def set_anatomy(self, meshes: dict[str, trimesh.Trimesh], *, max_faces: int = 120_000) -> None:
        """(Re)create skull and vessel nodes from meshes in world mm at the volume's pose."""
        for handle in self.patient + self.ghost + self.initial:
            handle.remove()
        self.patient, self.ghost, self.initial = [], [], []
        framed = [np.asarray(m.vertices) for name, m in meshes.items() if "vessel" in name and len(m.vertices)]
        framed = framed or [np.asarray(m.vertices) for m in meshes.values() if len(m.vertices)]
        self.framed_m = None
        if framed:
            pts = np.concatenate(framed)
            self.framed_m = pts[:: max(1, len(pts) // FRAMED_POINTS)] * M_PER_MM
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
                self.initial.append(
                    self.scene.add_mesh_simple(
                        f"/initial/{name}", verts, faces, color=INITIAL_RGB, opacity=0.45, visible=False
                    )
                )

    def place(
        self,
        estimate: np.ndarray,
        truth: np.ndarray | None,
        *,
        show_ghost: bool,
        initial: np.ndarray | None = None,
        show_initial: bool = False,
    ) -> None:
        """The patient at ``estimate``; the ghosts at ``truth`` (blue) and ``initial`` (amber, the
        machine-based pose) when shown."""
        wxyz_i, pos_i = pose_of(np.eye(4) if initial is None else initial)
        for handle in self.initial:
            handle.visible = show_initial and initial is not None
            handle.wxyz, handle.position = wxyz_i, pos_i
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

    # ----- the camera -------------------------------------------------------------------
    def _framed_at(self, motion: np.ndarray | None) -> np.ndarray | None:
        if self.framed_m is None:
            return None
        m = np.eye(4) if motion is None else np.asarray(motion, float)
        return self.framed_m @ m[:3, :3].T + m[:3, 3] * M_PER_MM

    def _aim(self, camera, aspect: float) -> None:  # noqa: ANN001 - a client's camera or the initial one
        """Point ``camera`` as the scene asks: from the source, or on the vessels."""
        if self.source_view is not None:
            g = self.source_view
            half_h = g.rows * g.pixel_mm[0] / 2.0
            fov = 2.0 * math.atan(half_h / g.sid_mm) * 1.15  # a margin around the field
            up, look_at, position = (
                -np.asarray(g.v, float),
                np.asarray(g.isocenter_mm) * M_PER_MM,
                g.source_mm * M_PER_MM,
            )
        else:
            points = self._framed_at(self._framed_motion)
            if points is None:
                return
            fov, up = math.radians(CAMERA_FOV_DEG), np.array([0.0, -1.0, 0.0])
            position, look_at = frame_points(points, aspect=aspect)
        if isinstance(camera, viser.CameraHandle):
            camera.fov = fov
            if self.source_view is not None:
                camera.up_direction = tuple(up)
        else:
            camera.fov = fov
            if self.source_view is not None:
                camera.up = tuple(up)
        camera.position = tuple(position)  # then look_at: a client's position moves its look_at along
        camera.look_at = tuple(look_at)

    def _aim_all(self) -> None:
        self._aim(self.server.initial_camera, CAMERA_ASPECT)
        for client in self.server.get_clients().values():
            self._aim(client.camera, _aspect(client))

    def _on_connect(self, client: viser.ClientHandle) -> None:
        """A new tab: aimed when its canvas reports its size, and again while the canvas changes
        its shape (the page's panels settle) as long as nobody moved the camera since."""
        aimed: dict[str, object] = {}

        def on_update(camera: viser.CameraHandle) -> None:
            aspect = _aspect(client)
            last = aimed.get("aspect")
            untouched = last is None or np.allclose(camera.position, aimed["position"], atol=1e-6)  # type: ignore[arg-type]
            if untouched and (last is None or abs(aspect / float(last) - 1.0) > 0.02):  # type: ignore[arg-type]
                self._aim(camera, aspect)
                aimed.update(aspect=aspect, position=np.array(camera.position))

        client.camera.on_update(on_update)

    def frame_anatomy(self, motion: np.ndarray | None = None) -> None:
        """The default camera and every open tab's on the vessels at ``motion`` (:func:`frame_points`)."""
        self.source_view = None
        self._framed_motion = None if motion is None else np.asarray(motion, float)
        self._aim_all()

    def view_from_source(self, geometry: CArm) -> None:
        """Every tab's camera (and the default one) at the X-ray source, looking at the
        iso-center, image rows downward (as the detector sees the patient), over the beam's field."""
        self.source_view = geometry
        self._aim_all()


def _aspect(client: viser.ClientHandle) -> float:
    """The width / height of a tab's canvas (CAMERA_ASPECT until it has reported it)."""
    try:
        return float(client.camera.aspect)
    except (AssertionError, ZeroDivisionError):
        return CAMERA_ASPECT
