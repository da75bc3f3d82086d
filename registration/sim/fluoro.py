"""Simulated fluoroscopy runs: the phantom imaged at 15 frames/s while the patient moves.

A run (CONVENTIONS §7) is a sequence of fluoro frames at times ``t_n`` with the true patient
motion of every frame. :func:`motion_trajectory` writes the patient's script: still periods,
slow drift (at most ``drift_mm_per_s``), sudden moves (up to ``max_move_mm`` / ``max_move_deg``
within ``move_s``), a small breathing-like oscillation, while a guidewire advances.
:func:`simulate_run` forms every frame with the honest image model
(:func:`registration.sim.xray.simulate_xray`: exact line integrals through the analytic
phantom, Poisson noise at fluoroscopy dose, detector blur, collimation; never the DRR
renderer) and caches the run on disk. :func:`simulate_biplane_run` images the same motion
through two planes at the same moments, each with its own noise.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np
from numpy.typing import NDArray

from registration.core.geometry import CArm, axis_rotation, rigid
from registration.core.images import XRayImage
from registration.sim.phantom import HeadPhantom

Array = NDArray[np.float64]

#: Phases of the patient's script, as each frame's truth names them.
PHASES = ("still", "drift", "move", "settled", "glitch")


@dataclass(frozen=True)
class RunScript:
    """What happens during a simulated run (times in s, lengths in mm, angles in degrees)."""

    duration_s: float = 20.0
    fps: float = 15.0
    seed: int = 0
    #: The patient lies still for this long at the start of the run.
    still_start_s: float = 2.0
    #: Sudden moves over the run (each followed by a still period).
    sudden_moves: int = 2
    max_move_mm: float = 25.0
    max_move_deg: float = 10.0
    #: Smallest sudden move drawn (translation length, rotation angle).
    min_move_mm: float = 3.0
    min_move_deg: float = 1.0
    #: A sudden move lasts this long (smooth start and stop).
    move_s: float = 0.5
    #: Drift periods: speed at most this (translation), rotation at most ``drift_deg_per_s``.
    drift: bool = True
    drift_mm_per_s: float = 1.0
    drift_deg_per_s: float = 0.3
    #: Breathing-like oscillation along the body axis (amplitude mm, period s); 0 for none.
    breathing_mm: float = 0.15
    breathing_period_s: float = 4.0
    #: A guide catheter with a guidewire advancing from ``wire_start_mm`` to ``wire_end_mm``.
    catheter: bool = True
    wire_start_mm: float = 120.0
    wire_end_mm: float = 200.0
    #: Frames that show no anatomy (a detector read-out glitch: a flat field with its noise),
    #: at these times (s): frames the engine cannot register, whose estimates must be withheld.
    glitch_times_s: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        for name in ("duration_s", "fps", "move_s", "max_move_mm", "max_move_deg", "breathing_period_s"):
            value = float(getattr(self, name))
            if not math.isfinite(value) or value <= 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        for name in (
            "still_start_s",
            "drift_mm_per_s",
            "drift_deg_per_s",
            "breathing_mm",
            "min_move_mm",
            "min_move_deg",
        ):
            value = float(getattr(self, name))
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.sudden_moves < 0:
            raise ValueError(f"sudden_moves must be >= 0, got {self.sudden_moves}")
        if self.duration_s * self.fps > 5000:
            raise ValueError(f"a run of {self.duration_s * self.fps:.0f} frames is too long (5000 at most)")
        if self.min_move_mm > self.max_move_mm or self.min_move_deg > self.max_move_deg:
            raise ValueError("min_move_mm/deg must not exceed max_move_mm/deg")

    @classmethod
    def still(cls, duration_s: float = 4.0, *, seed: int = 0, fps: float = 15.0) -> RunScript:
        """A patient who never moves (no drift, no breathing, no sudden move)."""
        return cls(duration_s=duration_s, fps=fps, seed=seed, sudden_moves=0, drift=False, breathing_mm=0.0)

    @property
    def frames(self) -> int:
        return int(math.floor(self.duration_s * self.fps + 1e-9))

    def to_dict(self) -> dict:
        return asdict(self)


def _axis_angle(rotvec_deg: Array) -> Array:
    angle = float(np.linalg.norm(rotvec_deg))
    return np.eye(3) if angle < 1e-12 else axis_rotation(rotvec_deg, math.radians(angle))


def _motion(translation_mm: Array, rotvec_deg: Array) -> Array:
    """T(t) @ R(rotvec) about the iso-center (the world origin)."""
    return rigid(_axis_angle(np.asarray(rotvec_deg, dtype=np.float64)), np.asarray(translation_mm, dtype=np.float64))


def _unit(rng: np.random.Generator) -> Array:
    v = rng.normal(size=3)
    return v / max(float(np.linalg.norm(v)), 1e-12)


def _smoothstep(x: float) -> float:
    x = min(max(x, 0.0), 1.0)
    return x * x * (3.0 - 2.0 * x)


@dataclass(frozen=True)
class _Segment:
    kind: str  # "still", "drift", "move"
    start_s: float
    end_s: float
    translation_mm: Array  # total over the segment (drift: velocity x duration)
    rotvec_deg: Array


def _segments(script: RunScript, rng: np.random.Generator) -> list[_Segment]:
    """Still / drift / sudden-move periods filling the run."""
    total = script.duration_s
    zero = np.zeros(3)
    segs: list[_Segment] = [_Segment("still", 0.0, min(script.still_start_s, total), zero, zero)]
    t = segs[0].end_s
    moves_left = script.sudden_moves
    # Spread the sudden moves over the run: one per slot, the rest drift and still periods.
    slots = max(1, moves_left + (1 if script.drift else 0))
    slot_s = max((total - t) / slots, 1e-3)
    # the pose so far (to keep the patient within the moves' range of the start)
    pose_t, pose_r = np.zeros(3), np.zeros(3)
    while t < total - 1e-9:
        slot_end = min(total, t + slot_s)
        if script.drift and t < slot_end:
            length = min(slot_end - t, rng.uniform(0.35, 0.55) * slot_s)
            v = rng.uniform(0.3, 1.0) * script.drift_mm_per_s * _unit(rng)
            w = rng.uniform(0.0, 1.0) * script.drift_deg_per_s * _unit(rng)
            segs.append(_Segment("drift", t, t + length, v * length, w * length))
            pose_t, pose_r = pose_t + v * length, pose_r + w * length
            t += length
            if t < slot_end:
                still = min(slot_end - t, rng.uniform(0.3, 0.5) * slot_s)
                segs.append(_Segment("still", t, t + still, zero, zero))
                t += still
        if moves_left and t + script.move_s <= total:
            length = rng.uniform(script.min_move_mm, script.max_move_mm)
            angle = rng.uniform(script.min_move_deg, script.max_move_deg)
            d, a = length * _unit(rng), angle * _unit(rng)
            # Keep the patient within max_move of the start: a move that would leave it goes back.
            if np.linalg.norm(pose_t + d) > script.max_move_mm:
                d = -d
            if np.linalg.norm(pose_r + a) > script.max_move_deg:
                a = -a
            segs.append(_Segment("move", t, t + script.move_s, d, a))
            pose_t, pose_r = pose_t + d, pose_r + a
            t += script.move_s
            moves_left -= 1
        still_end = slot_end if slot_end > t else min(total, t + slot_s / 2)
        if still_end > t:
            segs.append(_Segment("still", t, still_end, zero, zero))
            t = still_end
    return segs


def motion_trajectory(script: RunScript) -> tuple[Array, Array, tuple[str, ...]]:
    """Times (s), true patient motions (frames, 4, 4) and the phase of every frame.

    Motion composes as ``M(t) = B(t) @ S(t)``: ``S`` the body pose (each drift or sudden move
    applied on the left of the pose before it, rotations about the iso-center), ``B`` the
    breathing oscillation (a translation along the body axis, +z). Frames that follow a
    sudden move within one second are "settled", other still frames "still".
    """
    rng = np.random.default_rng([int(script.seed), 1303])
    segs = _segments(script, rng)
    n = script.frames
    times = np.arange(n, dtype=np.float64) / script.fps
    motions = np.empty((n, 4, 4))
    phases: list[str] = []
    phase_breath = rng.uniform(0.0, 2.0 * math.pi)
    base = np.eye(4)
    seg_index = 0
    last_move_end = -math.inf
    for i, t in enumerate(times):
        while seg_index < len(segs) - 1 and t >= segs[seg_index].end_s - 1e-12:
            s = segs[seg_index]
            base = _motion(s.translation_mm, s.rotvec_deg) @ base
            if s.kind == "move":
                last_move_end = s.end_s
            seg_index += 1
        s = segs[seg_index]
        frac = (t - s.start_s) / max(s.end_s - s.start_s, 1e-12)
        if s.kind == "move":
            frac = _smoothstep(frac)
        elif s.kind != "drift":
            frac = 0.0
        body = _motion(frac * s.translation_mm, frac * s.rotvec_deg) @ base
        breath = script.breathing_mm * math.sin(2.0 * math.pi * t / script.breathing_period_s + phase_breath)
        motions[i] = rigid(None, (0.0, 0.0, breath)) @ body
        kind = s.kind
        if kind == "still" and t - last_move_end < 1.0:
            kind = "settled"
        phases.append(kind)
    return times, motions, tuple(phases)


def wire_lengths_mm(script: RunScript) -> Array:
    """The guidewire's advanced length at every frame (linear over the run)."""
    n = script.frames
    return np.linspace(script.wire_start_mm, script.wire_end_mm, n) if n > 1 else np.array([script.wire_start_mm])


@dataclass(frozen=True, eq=False)
class FluoroRun(Sequence[XRayImage]):
    """A simulated run of one plane: frames, their times and the truth of every frame.

    ``run[n]`` is frame ``n`` as an :class:`XRayImage` (``meta`` holds ``frame``, ``t_s`` and
    the true motion); ``truth[n]`` the true patient motion (4x4, CONVENTIONS §4).
    """

    images: NDArray[np.float32]
    mask: NDArray[np.bool_]
    geometry: CArm
    times_s: Array
    truth: Array
    phases: tuple[str, ...]
    plane: str = "MONOPLANE"
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.images.shape[0])

    def __getitem__(self, index: int) -> XRayImage:  # type: ignore[override]
        n = int(index)
        if n < 0:
            n += len(self)
        if not 0 <= n < len(self):
            raise IndexError(f"frame {index} out of range: the run has {len(self)} frames")
        meta = {**self.meta, "frame": n, "t_s": float(self.times_s[n]), "plane": self.plane}
        return XRayImage(self.images[n], self.mask, self.geometry, "fluoro", meta)

    def __iter__(self) -> Iterator[XRayImage]:
        for n in range(len(self)):
            yield self[n]

    @property
    def geometries(self) -> tuple[CArm, ...]:
        return (self.geometry,) * len(self)


def _frame_seed(seed: int, plane: int, frame: int) -> int:
    return int((int(seed) * 1_000_003 + plane * 7919 + frame * 104_729 + 17) % (2**31 - 1))


def _plane_frames(
    phantom: HeadPhantom, geometry: CArm, script: RunScript, times: np.ndarray, truth: np.ndarray,
    wires: np.ndarray, plane: int, progress: object, total: int,
) -> dict[str, np.ndarray]:  # fmt: skip
    """One plane's frames at the script's moments (its own noise per frame; the guidewire advanced
    in 0.5 mm steps) and the field mask."""
    from registration.sim.xray import device_phantom, simulate_xray

    frames = np.empty((len(times), geometry.rows, geometry.cols), np.float32)
    mask = geometry.field_mask()
    devices: dict[float, HeadPhantom] = {}
    for i in range(len(times)):
        dev = None
        if script.catheter:
            length = round(float(wires[i]) * 2.0) / 2.0  # the wire advances in 0.5 mm steps
            dev = devices.get(length)
            if dev is None:
                dev = devices[length] = device_phantom(phantom, wire_length_mm=length)
        img = simulate_xray(phantom, geometry, motion=truth[i], kind="fluoro", catheter=script.catheter, devices=dev,
                            seed=_frame_seed(script.seed, plane, i))  # fmt: skip
        frames[i] = img.image
        mask = img.mask
        if callable(progress):
            progress(plane * len(times) + i + 1, total)
    return {"images": frames, "mask": mask}


def _with_glitches(images: np.ndarray, mask: np.ndarray, glitches: set[int], seed: int, plane: int) -> np.ndarray:
    """The frames with the glitched ones replaced by flat noise (a copy when there are any)."""
    if not glitches:
        return images
    images = images.copy()
    for i in sorted(glitches):
        rng = np.random.default_rng(_frame_seed(seed, plane, i) + 1)
        flat = float(np.median(images[i][mask]))
        images[i] = np.where(mask, flat + 0.04 * rng.standard_normal(mask.shape), 0.0).astype(np.float32)
    return images


def simulate_biplane_run(
    phantom: HeadPhantom,
    geometries: Sequence[CArm],
    script: RunScript,
    *,
    planes: Sequence[str] | None = None,
    cache: bool = True,
    progress: object = None,
) -> list[FluoroRun]:
    """Image the script's motion through every geometry at the same moments (one run each).

    Frames of each plane have their own noise (seeds from the script's seed, the plane and the
    frame). ``phantom`` should be the anatomy without contrast (fluoro shows none). Runs are
    cached on disk (:func:`registration.io.cache.cached_arrays`) by everything that makes them.
    ``progress``: called as ``progress(done, total)`` while frames are formed.
    """
    from registration.io.cache import cached_arrays

    geometries = list(geometries)
    if not geometries:
        raise ValueError("at least one geometry is needed")
    if planes is None:
        planes = ["MONOPLANE"] if len(geometries) == 1 else ["PLANE A", "PLANE B"][: len(geometries)]
    if len(planes) != len(geometries):
        raise ValueError(f"{len(planes)} plane names for {len(geometries)} geometries")
    times, truth, phases = motion_trajectory(script)
    wires = wire_lengths_mm(script)
    glitches = {int(np.argmin(np.abs(times - t))) for t in script.glitch_times_s}
    runs = []
    total = len(times) * len(geometries)
    for p, geometry in enumerate(geometries):
        params = {
            "phantom": phantom.key,
            "geometry": geometry.to_dict(),
            # glitches are applied to the cached frames (the anatomy's frames do not depend on them)
            "script": {k: v for k, v in script.to_dict().items() if k != "glitch_times_s"},
            "plane": p,
            "model": "fluoro-run-1",
        }

        def build(geometry: CArm = geometry, p: int = p) -> dict[str, np.ndarray]:
            return _plane_frames(phantom, geometry, script, times, truth, wires, p, progress, total)

        arrays = cached_arrays("fluoro-run", params, build, enabled=cache)
        images = _with_glitches(arrays["images"], arrays["mask"].astype(bool), glitches, script.seed, p)
        meta = {
            "source": "simulated fluoroscopy run of the analytic phantom (honest image model)",
            "script": script.to_dict(),
            "phantom": phantom.key,
        }
        runs.append(
            FluoroRun(
                images=images,
                mask=arrays["mask"].astype(bool),
                geometry=geometry,
                times_s=times,
                truth=truth,
                phases=tuple("glitch" if i in glitches else ph for i, ph in enumerate(phases)),
                plane=planes[p],
                meta=meta,
            )
        )
    return runs


def simulate_run(
    phantom: HeadPhantom, geometry: CArm, script: RunScript, *, cache: bool = True, progress: object = None
) -> FluoroRun:
    """One plane's run of the script (see :func:`simulate_biplane_run`)."""
    return simulate_biplane_run(phantom, [geometry], script, cache=cache, progress=progress)[0]
