"""The Landmarks tab: pick corresponding points in the 3-D scene and start the registration there.

With picking on, a click on the X-ray image (shown on the detector in the scene) marks a pixel,
and the next click on the skull or the vessels marks the same anatomy in the volume: one pair.
From four pairs on one plane, "Start from landmarks" puts the roadmap at the pose the pairs give
(:func:`registration.core.landmarks.landmark_start`: perspective-n-point and a least-squares
refinement), says how well the picks agree (reprojection error in pixels), and Register refines
it. Biplane: pairs on plane B's image count as well.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import trimesh
import viser

from app.web.panels import BasePanel, PanelContext
from app.web.scene import M_PER_MM
from registration.core.geometry import CArm, apply, invert_rigid
from registration.core.landmarks import MIN_PAIRS, Landmark, LandmarkStart, landmark_start

PLANES = ("A", "B")


def image_hit(
    geometries: Sequence[CArm], origin_mm: np.ndarray, direction: np.ndarray
) -> tuple[int, float, float, float] | None:
    """Where a ray (world mm) meets a view's image on its detector: (plane, col, row, distance
    along the ray, mm) of the nearest image it crosses within its pixels, or None."""
    best = None
    d = direction / np.linalg.norm(direction)
    for plane, g in enumerate(geometries):
        _, _, n = g.detector_axes()
        denom = float(d @ n)
        if abs(denom) < 1e-9:
            continue
        t = float((g.detector_center_mm - origin_mm) @ n) / denom
        if t <= 0:
            continue
        col, row = g.project(origin_mm + t * d)
        if -0.5 <= col <= g.cols - 0.5 and -0.5 <= row <= g.rows - 0.5 and (best is None or t < best[3]):
            best = (plane, float(col), float(row), t)
    return best


def volume_hit(
    meshes: Sequence[trimesh.Trimesh], pose: np.ndarray, origin_mm: np.ndarray, direction: np.ndarray
) -> tuple[np.ndarray, float] | None:
    """Where a ray (world mm) first meets the surfaces of the volume shown at ``pose`` (its patient
    motion): the point in the volume's own frame (mm) and the distance along the ray, or None."""
    inverse = invert_rigid(pose)
    o = apply(inverse, origin_mm)
    d = inverse[:3, :3] @ (direction / np.linalg.norm(direction))
    best = None
    for mesh in meshes:
        t = _first_hit(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces), o, d)
        if t is not None and (best is None or t < best[1]):
            best = (o + t * d, t)
    return best


def _first_hit(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, direction: np.ndarray) -> float | None:
    """Distance along a ray to its first triangle (Moller-Trumbore over all faces at once), or None."""
    if len(faces) == 0:
        return None
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    e1, e2 = b - a, c - a
    p = np.cross(direction, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = origin - a
    u = np.einsum("ij,ij->i", s, p) * inv
    q = np.cross(s, e1)
    v = (q @ direction) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    return float(t[hit].min()) if hit.any() else None


@dataclass
class LandmarkPicks:
    """The pairs picked so far and an image point waiting for its volume point."""

    pairs: list[Landmark] = field(default_factory=list)
    pending: tuple[int, float, float] | None = None

    def click(
        self, geometries: Sequence[CArm], meshes: Sequence[trimesh.Trimesh], pose: np.ndarray,
        origin_mm: np.ndarray, direction: np.ndarray,
    ) -> str:  # fmt: skip
        """Take a click's ray (world mm): an image point first, then its volume point. Returns what
        happened, for the status line."""
        on_image = image_hit(geometries, origin_mm, direction)
        on_volume = volume_hit(meshes, pose, origin_mm, direction)
        if self.pending is None or on_volume is None:
            if on_image is None:
                if on_volume is not None:
                    return "Landmarks: click a point on the X-ray image (on the detector) first"
                return "Landmarks: the click met neither the X-ray image nor the volume's surfaces"
            plane, col, row, _ = on_image
            self.pending = (plane, col, row)
            return (f"Landmarks: image point ({col:.1f}, {row:.1f}) px on plane {PLANES[plane]}; now click the same "
                    "anatomy on the skull or the vessels")  # fmt: skip
        point, _ = on_volume
        plane, col, row = self.pending
        self.pairs.append(Landmark((col, row), (float(point[0]), float(point[1]), float(point[2])), plane))
        self.pending = None
        return (f"Landmarks: pair {len(self.pairs)}: ({col:.1f}, {row:.1f}) px on plane {PLANES[plane]} ↔ "
                f"({point[0]:.1f}, {point[1]:.1f}, {point[2]:.1f}) mm")  # fmt: skip

    def undo(self) -> None:
        if self.pending is not None:
            self.pending = None
        elif self.pairs:
            self.pairs.pop()

    def table_markdown(self, start: LandmarkStart | None = None) -> str:
        if not self.pairs and self.pending is None:
            return f"No pairs yet. Pick at least {MIN_PAIRS} on one image."
        lines = ["| # | plane | image px | volume mm | error px |", "| ---: | --- | --- | --- | ---: |"]
        for i, p in enumerate(self.pairs):
            error = "" if start is None or i >= len(start.errors_px) else f"{start.errors_px[i]:.1f}"
            if start is not None and i < len(start.inliers) and not start.inliers[i]:
                error += " (left out)"
            lines.append(f"| {i + 1} | {PLANES[p.plane]} | {p.image_px[0]:.1f}, {p.image_px[1]:.1f} | "
                         f"{p.volume_mm[0]:.1f}, {p.volume_mm[1]:.1f}, {p.volume_mm[2]:.1f} | {error} |")  # fmt: skip
        if self.pending is not None:
            plane, col, row = self.pending
            lines.append(f"| {len(self.pairs) + 1} | {PLANES[plane]} | {col:.1f}, {row:.1f} | (pick it) | |")
        return "\n".join(lines)


class LandmarksPanel(BasePanel):
    """The Landmarks tab (see the module)."""

    def __init__(self, ctx: PanelContext) -> None:
        self.ctx = ctx
        self.picks = LandmarkPicks()
        self.start: LandmarkStart | None = None
        self._lock = threading.Lock()
        gui = ctx.server.gui
        with ctx.layout.control_tab("Landmarks", viser.Icon.MAP_PIN):
            gui.add_markdown(
                "<small>Far from the machine-based pose? Pick pairs: a click on the X-ray image on the "
                "detector, then one on the same anatomy on the skull or the vessels (orbit rims, ear canals, "
                f"the dens). {MIN_PAIRS} or more spread over the head.</small>"
            )
            self.picking = gui.add_checkbox("Pick landmarks", initial_value=False)
            self.table = gui.add_markdown(self.picks.table_markdown())
            self.undo_button = gui.add_button("Undo last pick", disabled=True)
            self.clear_button = gui.add_button("Clear", disabled=True)
            self.start_button = gui.add_button("Start from landmarks", icon=viser.Icon.TARGET, disabled=True)
        self.picking.on_update(ctx.guarded(lambda _e: self._picking_changed()))
        self.undo_button.on_click(ctx.guarded(lambda _e: self._edit(self.picks.undo)))
        self.clear_button.on_click(ctx.guarded(lambda _e: self._edit(self.clear)))
        self.start_button.on_click(ctx.guarded(lambda _e: self.start_from_landmarks()))
        self._clicks = None

    # ----- picking ------------------------------------------------------------------------
    def _picking_changed(self) -> None:
        scene = self.ctx.server.scene
        if self.picking.value and self._clicks is None:
            self._clicks = scene.on_click()(self.ctx.guarded(self._on_click))
        elif not self.picking.value and self._clicks is not None:
            scene.remove_click_callback(self._clicks)
            self._clicks = None

    def _on_click(self, event: viser.SceneClickEvent) -> None:
        self.click(np.asarray(event.ray_origin) / M_PER_MM, np.asarray(event.ray_direction))

    def click(self, origin_mm: np.ndarray, direction: np.ndarray) -> str:
        """A click's ray in world mm (the scene's metres converted): an image or a volume point."""
        s = self.ctx.session
        geometries = [v.geometry for v in s.views()]
        with s.lock:
            pose = s.estimate.copy()
            volume_format = s.settings.volume_format_cm
        meshes = list(s.data.meshes(volume_format).values())
        with self._lock:
            ray = np.asarray(origin_mm, dtype=np.float64), np.asarray(direction, dtype=np.float64)
            said = self.picks.click(geometries, meshes, pose, *ray)
            self.start = None
            self.table.content = self.picks.table_markdown()
            self._update_buttons()
        self.ctx.message(said)
        return said

    def _edit(self, change) -> None:  # noqa: ANN001
        with self._lock:
            change()
            self.start = None
            self.table.content = self.picks.table_markdown()
            self._update_buttons()

    def clear(self) -> None:
        self.picks = LandmarkPicks()

    def _update_buttons(self) -> None:
        """Undo and Clear once something is picked; the start once some plane has enough pairs."""
        nothing = not self.picks.pairs and self.picks.pending is None
        self.undo_button.disabled = self.clear_button.disabled = nothing
        counts = [sum(p.plane == n for p in self.picks.pairs) for n in range(2)]
        self.start_button.disabled = max(counts) < MIN_PAIRS

    # ----- the start ------------------------------------------------------------------------
    def start_from_landmarks(self) -> LandmarkStart:
        """Put the roadmap at the pose the pairs give (refused with the reason: too few pairs,
        a registration running); Register refines it."""
        s = self.ctx.session
        geometries = [v.geometry for v in s.views()]
        with self._lock:
            pairs = [p for p in self.picks.pairs if p.plane < len(geometries)]
            start = landmark_start(geometries, pairs)  # ValueError (too few, degenerate): a message
            self.start = start
            self.table.content = self.picks.table_markdown(start)
        s.start_from(start.patient_motion, start)
        self.ctx.refresh()
        kept = int(start.inliers.sum())
        self.ctx.message(f"Landmarks: the roadmap starts at the pose of {kept} pairs (reprojection error "
                         f"{start.rms_px:.1f} px rms); press Register to refine it")  # fmt: skip
        return start

    def settings_changed(self) -> None:
        with self._lock:  # another image or C-arm: the picked pixels belong to the old one
            if self.picks.pairs or self.picks.pending is not None:
                self.picks = LandmarkPicks()
                self.start = None
                self.table.content = self.picks.table_markdown()
                self._update_buttons()

    def close(self) -> None:
        if self._clicks is not None:
            self.ctx.server.scene.remove_click_callback(self._clicks)
            self._clicks = None
