"""A start from picked landmarks: corresponding points on the X-ray image(s) and in the volume.

Four or more pairs (a pixel ``(col, row)`` on a view's image, CONVENTIONS §3, and the same
anatomy's position in the volume's world frame, mm, §1-2) give the patient motion ``M`` (§4)
under which the volume's points project onto the picked pixels: a perspective-n-point problem,
solved per view by OpenCV (``solvePnP``; ``solvePnPRansac`` from six pairs on, so a mistaken
pick is left out), then refined over every view's pairs together by least squares on the
reprojection error (biplane: both planes' points constrain all six parameters). Points picked on
a skull's outline lie near a plane, where one view's solution can be a mirror of the right pose
that fits its own picks as well; so the refinement also starts from every three-point solution
(``solveP3P``) of each view's picks and keeps the pose that fits all views' picks best.

The result is a start for the image-based registration, not a registration: its reprojection
error says how well the picks agree with one rigid motion.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import rq
from scipy.optimize import least_squares

from registration.core.geometry import CArm, rigid, rotation_matrix, rotation_vector

Array = NDArray[np.float64]

#: Fewest pairs a view's perspective-n-point solution takes.
MIN_PAIRS = 4
#: From this many pairs in a view on, its solution leaves out picks that disagree (RANSAC).
RANSAC_PAIRS = 6
#: A pair whose reprojection error exceeds this (pixels) is an outlier for RANSAC.
RANSAC_THRESHOLD_PX = 12.0
#: The refinement's further starts: the three-point solutions of at most this many triples of a
#: view's picks (the first ones; four picks have four triples).
P3P_TRIPLES = 20
#: A registration from a landmark start that moves the kept landmarks' projections more than
#: this (mm at the iso-center, root mean square) from where the start put them is not applied
#: automatically: two or more views, and one view, whose start is looser
#: (docs/decisions/2026-12-04-landmark-check.md).
LANDMARK_MOVE_MM = 3.5
LANDMARK_MOVE_MM_ONE_VIEW = 5.0
#: One view's estimate from a landmark start this far (mm at the iso-center) or further from the
#: machine-based pose is not applied automatically: one view sees the depth only through
#: magnification (the same limit as a one-view start from the image shift).
ONE_VIEW_MAX_START_MM = 25.0


@dataclass(frozen=True)
class Landmark:
    """One picked pair: ``image_px`` (col, row) on plane ``plane``'s image (0 = A, 1 = B) and
    ``volume_mm`` (x, y, z) in the volume's world frame."""

    image_px: tuple[float, float]
    volume_mm: tuple[float, float, float]
    plane: int = 0


@dataclass(frozen=True)
class LandmarkStart:
    """The motion the landmarks give, and how well they agree with it.

    ``patient_motion``: 4x4 (CONVENTIONS §4); ``errors_px``: each pair's reprojection error at
    it, in the order given; ``rms_px``: their root mean square over the pairs kept;
    ``inliers``: which pairs were kept (False: left out by RANSAC)."""

    patient_motion: Array
    errors_px: Array
    rms_px: float
    inliers: NDArray[np.bool_]
    #: The pairs and the views' C-arms the start was computed from (for :meth:`moved_mm`).
    landmarks: tuple[Landmark, ...] = ()
    geometries: tuple[CArm, ...] = ()

    def moved_mm(self, motion: ArrayLike) -> float:
        """How far ``motion`` moves the kept landmarks' projections from where the start put
        them: the root mean square over the kept pairs of the shift on their view's image, in
        mm at the iso-center. 0.0 without the pairs."""
        planes = self._kept_by_plane
        if not planes:
            return 0.0
        m = np.asarray(motion, dtype=np.float64)
        total, count = 0.0, 0
        for g, points, at_start, mm_per_px in planes:
            shift = np.linalg.norm(g.project(points @ m[:3, :3].T + m[:3, 3]) - at_start, axis=1) * mm_per_px
            total += float(np.sum(shift * shift))
            count += len(points)
        return float(np.sqrt(total / count))

    @cached_property
    def _kept_by_plane(self) -> tuple[tuple[CArm, Array, Array, float], ...]:
        """Per view with kept pairs: its C-arm, their volume points, where the start projects
        them and the view's mm at the iso-center per pixel."""
        kept = [lm for lm, keep in zip(self.landmarks, self.inliers, strict=False) if keep]
        if not kept or not self.geometries:
            return ()
        s = self.patient_motion
        out = []
        for plane, g in enumerate(self.geometries):
            points = np.array([lm.volume_mm for lm in kept if lm.plane == plane], dtype=np.float64).reshape(-1, 3)
            if len(points):
                at_start = g.project(points @ s[:3, :3].T + s[:3, 3])
                out.append((g, points, at_start, float(np.mean(g.pixel_mm)) / g.magnification))
        return tuple(out)

    def limit_mm(self) -> float:
        """How far an estimate may move the landmarks before :meth:`veto` holds it back (mm at
        the iso-center, root mean square): :data:`LANDMARK_MOVE_MM`, one view
        :data:`LANDMARK_MOVE_MM_ONE_VIEW`."""
        return LANDMARK_MOVE_MM if len(self.geometries) > 1 else LANDMARK_MOVE_MM_ONE_VIEW

    def wall(self, weight: float) -> Callable[[Array], float]:
        """The search's soft wall around the poses these landmarks allow: a motion that moves
        them no further than :meth:`limit_mm` costs nothing, one that moves them ``d`` mm further
        costs ``weight * d**2`` (added to the registration's cost, -similarity)."""
        if not (np.isfinite(weight) and weight > 0):
            raise ValueError(f"the landmarks' wall weight must be positive, got {weight}")
        limit = self.limit_mm()

        def cost(motion: Array) -> float:
            over = self.moved_mm(motion) - limit
            return weight * over * over if over > 0 else 0.0

        return cost

    def start_offset_mm(self) -> float:
        """How far the start puts the patient from the machine-based pose (no motion) at the first
        view's iso-center, mm. 0.0 without the views."""
        if not self.geometries:
            return 0.0
        iso = np.asarray(self.geometries[0].isocenter_mm, dtype=np.float64)
        return float(np.linalg.norm(self.patient_motion[:3, :3] @ iso + self.patient_motion[:3, 3] - iso))

    def veto(self, motion: ArrayLike) -> str | None:
        """Why an estimate registered from this start is not applied automatically: it moves the
        landmarks' projections more than :data:`LANDMARK_MOVE_MM` (one view:
        :data:`LANDMARK_MOVE_MM_ONE_VIEW`) from where the picks put them (the image-based search
        settled away from what the landmarks say), or, with one view, the start lies
        :data:`ONE_VIEW_MAX_START_MM` or more from the machine-based pose. None: it agrees."""
        moved = self.moved_mm(motion)
        limit = self.limit_mm()
        if moved > limit:
            shown = f"{moved:.1f}" if round(moved, 1) > limit else f"{moved:.2f}"  # never "3.5 mm, more than 3.5"
            return (
                f"the estimate moves the landmarks {shown} mm (rms, at the iso-center) from where their picks "
                f"put them, more than {limit:g} mm: check the landmarks and the estimate by eye before applying it"
            )
        far = self.start_offset_mm()
        if len(self.geometries) == 1 and far >= ONE_VIEW_MAX_START_MM:
            return (
                f"the landmarks put the patient {far:.0f} mm from the machine-based pose, where one view cannot "
                "confirm the depth: check the estimate by eye before applying it"
            )
        return None

    def to_dict(self) -> dict:
        return {
            "patient_motion": self.patient_motion.tolist(),
            "reprojection_rms_px": self.rms_px,
            "reprojection_errors_px": [round(float(e), 3) for e in self.errors_px],
            "inliers": [bool(i) for i in self.inliers],
        }

    def report(self, motion: ArrayLike) -> dict:
        """:meth:`to_dict` with how far ``motion`` (the registration's estimate) moves the
        landmarks (``estimate_moved_mm``) and how far the start lies from the machine-based pose
        (``start_offset_mm``)."""
        return {**self.to_dict(), "estimate_moved_mm": round(self.moved_mm(motion), 3),
                "start_offset_mm": round(self.start_offset_mm(), 3)}  # fmt: skip


def camera_of(geometry: CArm) -> tuple[Array, Array]:
    """The pinhole camera of a view: intrinsics ``K`` (3x3, pixels) and ``camera_from_world``
    (4x4 rigid, depth positive in front of the source) with ``P = K @ camera_from_world[:3]`` up to
    a positive scale (the view's projection matrix). The image's rows and columns with the beam
    form a left-handed frame (CONVENTIONS §3), so ``K[1, 1]`` is negative."""
    p = geometry.projection_matrix  # w > 0 in front of the source
    k, r = rq(p[:, :3])
    signs = np.diag(np.sign(np.diag(k)))
    k, r = k @ signs, signs @ r  # K with a positive diagonal, w = K[2, 2] * depth
    if np.linalg.det(r) < 0:  # the image axes (u, v) and the beam are left-handed: rows run negative
        flip = np.diag([1.0, -1.0, 1.0])
        k, r = k @ flip, flip @ r
    t = np.linalg.solve(k, p[:, 3])
    scale = k[2, 2]
    return k / scale, rigid(r, t)


def read_landmarks(path: str | Path) -> list[Landmark]:
    """Landmarks from a JSON file: ``{"landmarks": [{"image_px": [col, row], "volume_mm": [x, y,
    z], "plane": "A"}, ...]}`` (``plane`` optional, ``"A"`` or ``"B"``). Raises ``ValueError``
    naming the file and the entry that is wrong."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not a landmarks JSON file ({exc})") from None
    entries = data.get("landmarks") if isinstance(data, dict) else None
    if not isinstance(entries, list):
        raise ValueError(f'{path}: expected {{"landmarks": [{{"image_px": [col, row], "volume_mm": [x, y, z]}}, ...]}}')
    out = []
    for n, entry in enumerate(entries):
        try:
            image = [float(v) for v in entry["image_px"]]
            point = [float(v) for v in entry["volume_mm"]]
            plane = {"A": 0, "B": 1}[str(entry.get("plane", "A")).strip().upper()]
        except (KeyError, TypeError, ValueError, AttributeError):
            raise ValueError(
                f'{path}: landmark {n}: needs "image_px" [col, row], "volume_mm" [x, y, z] and an optional '
                '"plane" "A" or "B"'
            ) from None
        if len(image) != 2 or len(point) != 3 or not np.all(np.isfinite(image + point)):
            raise ValueError(f"{path}: landmark {n}: image_px must be 2 and volume_mm 3 finite numbers")
        out.append(Landmark((image[0], image[1]), (point[0], point[1], point[2]), plane))
    return out


def _reprojection(motion: Array, geometries: Sequence[CArm], landmarks: Sequence[Landmark]) -> Array:
    errors = np.empty(len(landmarks))
    for n, lm in enumerate(landmarks):
        moved = motion[:3, :3] @ np.asarray(lm.volume_mm) + motion[:3, 3]
        errors[n] = float(np.linalg.norm(geometries[lm.plane].project(moved) - np.asarray(lm.image_px)))
    return errors


def _pnp(geometry: CArm, landmarks: Sequence[Landmark]) -> tuple[Array, NDArray[np.bool_]]:
    import cv2

    k, camera_from_world = camera_of(geometry)
    objects = np.asarray([lm.volume_mm for lm in landmarks], dtype=np.float64)
    pixels = np.asarray([lm.image_px for lm in landmarks], dtype=np.float64)
    mirror = np.diag([1.0, -1.0, 1.0])  # OpenCV's camera wants positive focal lengths: rows mirrored
    k, pixels = mirror @ k, pixels * np.array([1.0, -1.0])
    inliers = np.ones(len(landmarks), dtype=bool)
    if len(landmarks) >= RANSAC_PAIRS:
        ok, rvec, tvec, kept = cv2.solvePnPRansac(
            objects, pixels, k, None, reprojectionError=RANSAC_THRESHOLD_PX, flags=cv2.SOLVEPNP_SQPNP
        )
        if ok and kept is not None and len(kept) >= MIN_PAIRS:
            inliers[:] = False
            inliers[np.asarray(kept).ravel()] = True
    else:
        ok = False
    if not ok:
        ok, rvec, tvec = cv2.solvePnP(objects, pixels, k, None, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        raise ValueError("the landmarks admit no pose (are the picked points collinear or repeated?)")
    camera_from_volume = rigid(rotation_matrix(np.ravel(rvec)), np.ravel(tvec))
    return np.linalg.inv(camera_from_world) @ camera_from_volume, inliers


def _p3p_starts(geometries: Sequence[CArm], landmarks: Sequence[Landmark]) -> list[Array]:
    """The patient motions of the three-point solutions (OpenCV's ``solveP3P``, AP3P) of the
    first :data:`P3P_TRIPLES` triples of each view's ``landmarks``."""
    import itertools

    import cv2

    starts = []
    for plane, geometry in enumerate(geometries):
        mine = [lm for lm in landmarks if lm.plane == plane]
        if len(mine) < 3:
            continue
        k, camera_from_world = camera_of(geometry)
        k = np.diag([1.0, -1.0, 1.0]) @ k  # OpenCV's camera wants positive focal lengths: rows mirrored
        world_from_camera = np.linalg.inv(camera_from_world)
        for triple in itertools.islice(itertools.combinations(mine, 3), P3P_TRIPLES):
            objects = np.asarray([lm.volume_mm for lm in triple], dtype=np.float64)
            pixels = np.asarray([lm.image_px for lm in triple], dtype=np.float64) * np.array([1.0, -1.0])
            try:
                _, rvecs, tvecs = cv2.solveP3P(objects, pixels, k, None, flags=cv2.SOLVEPNP_AP3P)
            except cv2.error:  # a degenerate triple (collinear or repeated points)
                continue
            for rvec, tvec in zip(rvecs, tvecs, strict=True):
                camera_from_volume = rigid(rotation_matrix(np.ravel(rvec)), np.ravel(tvec))
                starts.append(world_from_camera @ camera_from_volume)
    return starts


def landmark_start(geometries: CArm | Sequence[CArm], landmarks: Sequence[Landmark]) -> LandmarkStart:
    """The patient motion under which the landmarks' volume points project onto their pixels.

    ``geometries``: the views' C-arms (plane A first); every view with landmarks needs at least
    :data:`MIN_PAIRS` of them, and some view at least that many. Raises ``ValueError`` when the
    landmarks cannot give a pose."""
    geometries = (geometries,) if isinstance(geometries, CArm) else tuple(geometries)
    landmarks = list(landmarks)
    counts = [sum(lm.plane == p for lm in landmarks) for p in range(len(geometries))]
    if any(lm.plane >= len(geometries) for lm in landmarks):
        raise ValueError("a landmark names plane B but only one view was given")
    if max(counts, default=0) < MIN_PAIRS:
        have = ", ".join(f"{n} on plane {'AB'[p] if p < 2 else p + 1}" for p, n in enumerate(counts))
        raise ValueError(f"a landmark start needs at least {MIN_PAIRS} pairs on one view; there are {have}")
    best = int(np.argmax(counts))
    picked = [n for n, lm in enumerate(landmarks) if lm.plane == best]
    motion, kept = _pnp(geometries[best], [landmarks[n] for n in picked])
    inliers = np.ones(len(landmarks), dtype=bool)
    inliers[np.asarray(picked)[~kept]] = False

    used = [lm for lm, keep in zip(landmarks, inliers, strict=True) if keep]

    def residual(x: Array) -> Array:
        m = rigid(rotation_matrix(x[:3]), x[3:])
        out = []
        for lm in used:
            moved = m[:3, :3] @ np.asarray(lm.volume_mm) + m[:3, 3]
            out.extend(geometries[lm.plane].project(moved) - np.asarray(lm.image_px))
        return np.asarray(out)

    best_fit = None
    for start in [motion, *_p3p_starts(geometries, used)]:
        x0 = np.concatenate([rotation_vector(start[:3, :3]), start[:3, 3]])
        fit = least_squares(residual, x0, method="lm" if 2 * len(used) >= 6 else "trf")
        # a further start's pose only where it fits clearly better (the first one's otherwise)
        if best_fit is None or fit.cost < best_fit.cost * (1.0 - 1e-6):
            best_fit = fit
    motion = rigid(rotation_matrix(best_fit.x[:3]), best_fit.x[3:])
    errors = _reprojection(motion, geometries, landmarks)
    rms = float(np.sqrt(np.mean(errors[inliers] ** 2)))
    return LandmarkStart(motion, errors, rms, inliers, tuple(landmarks), geometries)


__all__ = [
    "LANDMARK_MOVE_MM",
    "LANDMARK_MOVE_MM_ONE_VIEW",
    "MIN_PAIRS",
    "ONE_VIEW_MAX_START_MM",
    "Landmark",
    "LandmarkStart",
    "camera_of",
    "landmark_start",
    "read_landmarks",
]
