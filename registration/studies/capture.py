"""``roadmap3d validate capture``: how success falls with the initial offset.

The paper's Fig. 6 stops at its clinical offsets (25 mm, 10 degrees). This study sweeps the
patient's offset from the machine-based pose further: translation alone (0-80 mm in a random
3-D direction), rotation alone (0-40 degrees about a random axis) and both together, each moment
seen by two planes (plane A near frontal, plane B near lateral) and registered biplane and, on
plane A alone, single plane, exactly as :mod:`registration.studies.biplane` does.

The capture radius of a sweep is the largest offset below which at least 95 % of the
registrations at every level succeed (biplane: the 3-D criterion; single plane: the paper's
in-plane criterion). Beyond it the engine must withhold or refuse, never apply: the applied
precision says whether it does.
"""

from __future__ import annotations

import re
import textwrap
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from registration import __version__
from registration.core.register import RegistrationOptions
from registration.studies.biplane import (
    PLANE_A_PRIMARY_DEG,
    PLANE_B_PRIMARY_DEG,
    SECONDARY_DEG,
    BiplaneCase,
)
from registration.studies.runs import StudyTask, _stable_seed, random_unit_vector

#: The sweeps: which offset grows along each (the other stays zero, or both grow together).
SWEEPS = ("translation", "rotation", "combined")
#: Share of successes a level needs to count as captured.
CAPTURE_SHARE = 0.95


@dataclass(frozen=True)
class CaptureConfig:
    """What the capture-range study registers."""

    #: Offset levels of the translation sweep (mm); the combined sweep pairs them with the rotations.
    translations_mm: tuple[float, ...] = (0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0)
    #: Offset levels of the rotation sweep (degrees), as many as the translations.
    rotations_deg: tuple[float, ...] = (0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 35.0, 40.0)
    sweeps: tuple[str, ...] = SWEEPS
    registrations_per_level: int = 10
    phantom_seed: int = 0
    volume_format_cm: float = 27.0
    plane_a_pixels: int = 512
    plane_b_pixels: int = 384
    volume_voxels: int = 256
    kind: str = "fluoro"
    #: A DICOM CT folder instead of the phantom's 3DRA (images formed from the CT itself).
    ct_path: str | None = None
    seed: int = 0
    quick: bool = False
    #: Register each moment from this many landmarks per plane picked with error instead of from
    #: the machine-based pose (:mod:`registration.studies.landmark_starts`; None: from the
    #: machine-based pose), and their picking error (mm).
    landmark_pairs: int | None = None
    landmark_noise_mm: float = 3.0
    #: Both C-arms aimed at the moved head (:attr:`registration.studies.biplane.BiplaneCase.aimed`):
    #: the head stays in both fields, the machine-based pose is off by the offset.
    aimed: bool = False

    def __post_init__(self) -> None:
        if self.landmark_pairs is not None and not 4 <= self.landmark_pairs <= 8:
            raise ValueError(f"landmark pairs must lie in 4..8 (four fix a pose), got {self.landmark_pairs}")
        if not (np.isfinite(self.landmark_noise_mm) and self.landmark_noise_mm >= 0):
            raise ValueError(f"the landmarks' picking error must be >= 0 mm, got {self.landmark_noise_mm}")
        if len(self.translations_mm) != len(self.rotations_deg):
            raise ValueError("the translation and rotation sweeps need the same number of levels")
        unknown = set(self.sweeps) - set(SWEEPS)
        if unknown:
            raise ValueError(f"unknown sweep(s) {sorted(unknown)}; choose from {', '.join(SWEEPS)}")
        if self.registrations_per_level < 1:
            raise ValueError(f"registrations per level must be >= 1, got {self.registrations_per_level}")

    @classmethod
    def quick_config(cls, seed: int = 0, ct_path: str | None = None) -> CaptureConfig:
        """Minutes on 2 cores: five levels per sweep, three moments each, 256/192 px, 128^3."""
        return cls(
            translations_mm=(0.0, 20.0, 40.0, 60.0, 80.0),
            rotations_deg=(0.0, 10.0, 20.0, 30.0, 40.0),
            registrations_per_level=3,
            plane_a_pixels=256,
            plane_b_pixels=192,
            volume_voxels=128,
            ct_path=ct_path,
            seed=seed,
            quick=True,
        )

    def level_offset(self, sweep: str, level: int) -> tuple[float, float]:
        """(translation mm, rotation deg) of one level of one sweep."""
        t, r = self.translations_mm[level], self.rotations_deg[level]
        return {"translation": (t, 0.0), "rotation": (0.0, r), "combined": (t, r)}[sweep]


def capture_tasks(config: CaptureConfig, options: RegistrationOptions | None = None) -> list[StudyTask]:
    """Every registration of the study; each draw depends only on the seed, sweep, level and number."""
    source = "ct" if config.ct_path else "fdk"
    tag = f"a{config.plane_a_pixels}-b{config.plane_b_pixels}-v{config.volume_voxels}-{source}-{config.kind}"
    tag += "-aimed" if config.aimed else ""
    tasks = []
    for sweep in config.sweeps:
        for level in range(len(config.translations_mm)):
            t_mm, r_deg = config.level_offset(sweep, level)
            for number in range(config.registrations_per_level):
                rng = np.random.default_rng([config.seed, 0xCA, SWEEPS.index(sweep), level, number])
                angles = (
                    (float(rng.uniform(*PLANE_A_PRIMARY_DEG)), float(rng.uniform(*SECONDARY_DEG))),
                    (float(rng.uniform(*PLANE_B_PRIMARY_DEG)), float(rng.uniform(*SECONDARY_DEG))),
                )
                translation = t_mm * random_unit_vector(rng)
                axis = random_unit_vector(rng)
                ident = f"capture/{source}/{sweep}/{t_mm:g}mm-{r_deg:g}deg/r{number}"
                case = BiplaneCase(
                    phantom_seed=config.phantom_seed,
                    volume_format_cm=config.volume_format_cm,
                    volume_voxels=config.volume_voxels,
                    angles_deg=angles,
                    translation_mm=(float(translation[0]), float(translation[1]), float(translation[2])),
                    rotation_axis=(float(axis[0]), float(axis[1]), float(axis[2])),
                    rotation_deg=r_deg,
                    pixels=(config.plane_a_pixels, config.plane_b_pixels),
                    kind=config.kind,
                    seed=_stable_seed(config.seed, ident),
                    ct_path=config.ct_path,
                    aimed=config.aimed,
                )
                extra = {
                    "study_seed": config.seed,
                    "sweep": sweep,
                    "level": level,
                    "level_translation_mm": t_mm,
                    "level_rotation_deg": r_deg,
                    "registration": number,
                    "aimed": config.aimed,
                }
                case_id = f"{ident}/{tag}/s{config.seed}"
                if config.landmark_pairs is not None:
                    from registration.studies.landmark_starts import LandmarkCase

                    case_id += f"/landmarks-{config.landmark_pairs}x{config.landmark_noise_mm:g}mm-in-field"
                    pick_seed = _stable_seed(config.seed, case_id)
                    case = LandmarkCase(case, config.landmark_pairs, config.landmark_noise_mm, pick_seed)
                tasks.append(StudyTask(case_id, case, extra, options))
    return tasks


# --------------------------------------------------------------------------------------
# Summary
# --------------------------------------------------------------------------------------
def _plane_keys(plane: str) -> tuple[str, str]:
    """(success key, applied key) of a record for ``plane`` ("biplane" or "single_plane")."""
    return ("success", "applied") if plane == "biplane" else ("single_success_inplane", "single_applied")


def success_interval(successes: int, runs: int) -> tuple[float, float]:
    """The 95 % interval of a success rate of ``successes`` in ``runs`` (Wilson's score interval)."""
    from scipy.stats import binomtest

    ci = binomtest(successes, runs).proportion_ci(confidence_level=0.95, method="wilson")
    return float(ci.low), float(ci.high)


def level_rates(records: list[dict], sweep: str, plane: str) -> list[dict]:
    """Per level of one sweep: offset, runs, successes, success rate with its 95 % interval
    (Wilson's score interval: how well a level of this many runs pins the rate down), applied
    and wrongly applied counts."""
    success, applied = _plane_keys(plane)
    rows = []
    for level in sorted({r["level"] for r in records if r["sweep"] == sweep}):
        at = [r for r in records if r["sweep"] == sweep and r["level"] == level]
        k = sum(bool(r[success]) for r in at)
        low, high = success_interval(k, len(at))
        rows.append(
            {
                "translation_mm": at[0]["level_translation_mm"],
                "rotation_deg": at[0]["level_rotation_deg"],
                "runs": len(at),
                "successes": k,
                "success_rate": k / len(at),
                "success_interval_95": [round(low, 4), round(high, 4)],
                "applied": sum(bool(r.get(applied)) for r in at),
                "applied_wrong": sum(bool(r.get(applied)) and not r[success] for r in at),
            }
        )
    return rows


def capture_radius(rows: list[dict], key: str) -> float | None:
    """The largest offset (``key`` of the rows) up to which every level succeeds >= 95 %;
    None when even the smallest level does not."""
    radius = None
    for row in sorted(rows, key=lambda r: r[key]):
        if row["success_rate"] < CAPTURE_SHARE:
            break
        radius = float(row[key])
    return radius


def _plane_summary(records: list[dict], plane: str) -> dict:
    success, applied = _plane_keys(plane)
    present = [sweep for sweep in SWEEPS if any(r["sweep"] == sweep for r in records)]
    sweeps = {sweep: level_rates(records, sweep, plane) for sweep in present}
    radius = lambda sweep, key: capture_radius(sweeps[sweep], key) if sweep in sweeps else None  # noqa: E731
    combined = None
    if radius("combined", "translation_mm") is not None:
        combined = {
            "translation_mm": radius("combined", "translation_mm"),
            "rotation_deg": radius("combined", "rotation_deg"),
        }
    taken = [r for r in records if r.get(applied)]
    right = [r for r in taken if r[success]]
    start_key = "landmark_start" if plane == "biplane" else "single_landmark_start"
    from_landmarks = [r for r in records if r.get(start_key)]
    landmarks = {}
    if any(start_key in r for r in records):  # a landmark run: the moments whose fields showed the picks
        landmarks = {
            "landmark_starts": len(from_landmarks),
            "landmark_start_success_rate": (
                sum(bool(r[success]) for r in from_landmarks) / len(from_landmarks) if from_landmarks else None
            ),
        }
    return {
        "capture_radius_mm_95": radius("translation", "translation_mm"),
        "capture_radius_deg_95": radius("rotation", "rotation_deg"),
        "capture_radius_combined_95": combined,
        "applied_precision": len(right) / len(taken) if taken else None,
        "applied": len(taken),
        "applied_wrong": [r["case_id"] for r in taken if not r[success]],
        "success_rate": sum(bool(r[success]) for r in records) / len(records) if records else None,
        "runs": len(records),
        "sweeps": sweeps,
        **landmarks,
    }


#: What a moment's record must share with every other pooled one: the study's design.
_POOL_DESIGN = ("pixels", "volume_format_cm", "volume_label", "image_source", "aimed")


def _landmark_picks(record: dict) -> re.Match | None:
    """A landmark run's picks in a moment's case id ("landmarks-4x3mm": pairs, error), None otherwise."""
    return re.search(r"/landmarks-(\d+)x([0-9.]+)mm", str(record.get("case_id", "")))


def _design(record: dict) -> dict:
    picks = _landmark_picks(record)
    return {k: record.get(k) for k in _POOL_DESIGN} | {"landmarks": picks.group(0)[1:] if picks else None}


def pooled_config(records: list[dict], paths: Sequence[Path]) -> dict:
    """The summary's configuration of pooled moments (:func:`pooled_records`): the runs, their
    seeds and revisions, and the design's start (aimed C-arms, landmarks)."""
    picks = _landmark_picks(records[0]) if records else None
    return {
        "pooled": [str(p) for p in paths],
        "seeds": sorted({r["study_seed"] for r in records if r.get("study_seed") is not None}),
        "revisions": sorted({r["revision"] for r in records if r.get("revision")}),
        "aimed": bool(records and records[0].get("aimed")),
        "landmark_pairs": int(picks.group(1)) if picks else None,
        "landmark_noise_mm": float(picks.group(2)) if picks else None,
    }


def pooled_records(paths: Sequence[Path]) -> list[dict]:
    """The moments of earlier runs (``results.jsonl`` files or the folders holding them), pooled
    for one summary: every moment's own seed and draws, levels pooled by offset. ValueError,
    naming the file, when one holds no capture moments, holds moments another already gave (the
    same run pooled twice), or comes from another design (image size, volume, image source,
    aimed C-arms, landmark starts) or another ladder of levels."""
    from registration.studies.execution import ResultsLog

    if not paths:
        raise ValueError("--pool needs at least one results.jsonl (or its folder)")
    records: list[dict] = []
    seen: dict[str, Path] = {}
    first: tuple[Path, dict] | None = None
    levels: dict[tuple[str, int], tuple[float, float]] = {}
    for given in paths:
        path = Path(given) / "results.jsonl" if Path(given).is_dir() else Path(given)
        if not path.is_file():
            raise ValueError(f"{path}: no such results file")
        found = [r for r in ResultsLog(path).read() if {"sweep", "level", "level_translation_mm"} <= r.keys()]
        if not found:
            raise ValueError(f"{path}: holds no moments of the capture study")
        for r in found:
            if r["case_id"] in seen:
                raise ValueError(f"{path}: moment {r['case_id']} was already pooled from {seen[r['case_id']]}")
            seen[r["case_id"]] = path
            design = _design(r)
            if first is None:
                first = (path, design)
            elif design != first[1]:
                k = next(k for k in design if design[k] != first[1][k])
                raise ValueError(f"{path}: cannot pool with {first[0]}: {k} {design[k]!r} against {first[1][k]!r}")
            offset = (float(r["level_translation_mm"]), float(r["level_rotation_deg"]))
            if levels.setdefault((r["sweep"], int(r["level"])), offset) != offset:
                raise ValueError(f"{path}: its {r['sweep']} level {r['level']} lies at another offset than the others'")
        records += found
    return records


def capture_summary(records: list[dict], *, config: dict, wall_seconds: float) -> dict:
    """The study's numbers (the ``--json`` object): one block per plane count."""
    return {
        "study": "capture",
        "single_plane": {**_plane_summary(records, "single_plane"), "criterion": "in-plane < 1 mm and < 3 deg"},
        "biplane": {**_plane_summary(records, "biplane"), "criterion": "3-D < 1 mm and < 3 deg"},
        "capture_share": CAPTURE_SHARE,
        "image_source": records[0]["image_source"] if records else "",
        "volume_labels": sorted({r["volume_label"] for r in records}),
        "wall_seconds": wall_seconds,
        "config": config,
        "version": __version__,
    }


# --------------------------------------------------------------------------------------
# Figure and report
# --------------------------------------------------------------------------------------
_SWEEP_AXES = {
    "translation": ("translation_mm", "initial translation offset (mm), no rotation"),
    "rotation": ("rotation_deg", "initial rotation offset (deg), no translation"),
    "combined": ("translation_mm", "initial offset: translation (mm), rotation = half of it (deg)"),
}


def capture_curves(records: list[dict], summary: dict, path: Path) -> Path:
    """Success and wrongly applied share against the offset, one panel per sweep."""
    from registration.studies.report_kit import pyplot, stamp

    plt = pyplot()
    sweeps = [s for s in SWEEPS if s in summary["biplane"]["sweeps"]]
    fig, axes = plt.subplots(1, len(sweeps), figsize=(4.6 * len(sweeps), 4.0), squeeze=False)
    for ax, sweep in zip(axes[0], sweeps, strict=True):
        key, label = _SWEEP_AXES[sweep]
        # biplane drawn wider beneath single plane, so both show where their curves coincide
        for plane, colour, name, width in (("biplane", "#4a7ab5", "biplane", 4.0),
                                           ("single_plane", "#f0ad4e", "single plane A", 1.5)):  # fmt: skip
            rows = summary[plane]["sweeps"][sweep]
            x = [r[key] for r in rows]
            ax.plot(x, [100 * r["success_rate"] for r in rows], "o-", color=colour, lw=width, ms=2 * width + 1,
                    label=f"{name}: success")  # fmt: skip
            band = [r.get("success_interval_95") for r in rows]
            if all(band):
                ax.fill_between(x, [100 * b[0] for b in band], [100 * b[1] for b in band], color=colour, alpha=0.15,
                                lw=0, label=f"{name}: 95 % interval")  # fmt: skip
            wrong = [100 * r["applied_wrong"] / r["runs"] for r in rows]
            ax.plot(x, wrong, "x--", color=colour, alpha=0.8, label=f"{name}: applied and wrong")
        ax.axhline(100 * CAPTURE_SHARE, color="#d9534f", ls=":", lw=1)
        ax.set_ylim(-3, 103)
        ax.set_xlabel(label, fontsize=8)
        ax.set_ylabel("% of registrations", fontsize=8)
        ax.set_title(f"{sweep} sweep (n = {rows[0]['runs']} per level)", fontsize=9)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7, loc="lower left", bbox_to_anchor=(0.0, 0.06))
    picks = summary.get("config", {}).get("landmark_pairs")
    start = f", from {picks} landmarks per plane" if picks else ""
    start += ", C-arms aimed at the head" if summary.get("config", {}).get("aimed") else ""
    title = f"Capture range{start}: success against the initial offset (dotted: 95 %)"
    fig.suptitle(textwrap.fill(title, width=60 * len(sweeps)), fontsize=10)  # one panel: two lines
    fig.tight_layout()
    stamp(fig, records)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def radius_words(x: float | None, unit: str, ran: bool = True) -> str:
    """A capture radius in words: its value, "below the smallest level" or, for a sweep the run
    does not hold, "not run"."""
    if not ran:
        return "not run"
    return "below the smallest level" if x is None else f"{x:g} {unit}"


def _level_size_words(summary: dict) -> str:
    """What a level of the run's size can tell: how many misses it allows and the least rate
    that all of them right is consistent with."""
    rows = [r for plane in ("biplane", "single_plane") for v in summary[plane]["sweeps"].values() for r in v]
    sizes = sorted({r["runs"] for r in rows})
    if len(sizes) != 1 or not rows:
        return ""
    n = sizes[0]
    allowed = int(np.floor((1.0 - CAPTURE_SHARE) * n + 1e-9))
    low = success_interval(n, n)[0]
    misses = "none missed" if allowed == 0 else f"at most {allowed} missed"
    return (
        f": with {n} registrations a level passes with {misses}, and {n} of {n} right is consistent with a "
        f"rate as low as {100 * low:.0f} % (the 95 % interval beside each level's success, Wilson's)"
    )


def interval_words(lo: float | None, hi: float | None) -> str:
    """A success rate's 95 % interval as the report shows it ("72-100 %")."""
    if lo is None or hi is None:
        return "-"
    return f"{100 * lo:.0f}-{100 * hi:.0f} %"


def capture_report_md(summary: dict, image: str) -> str:
    pct = lambda x: "-" if x is None else f"{100 * x:.1f} %"  # noqa: E731
    cfg = summary["config"]
    start = "the machine-based pose"
    if cfg.get("landmark_pairs"):
        start = (f"the pose {cfg['landmark_pairs']} landmarks per plane give, picked on the skull's outline "
                 f"where the plane's field shows it, with {cfg['landmark_noise_mm']:g} mm error (volume and "
                 "image)")  # fmt: skip
    lines = [
        "# Capture range" + (" from landmarks" if cfg.get("landmark_pairs") else ""),
        "",
        "Each moment is seen by plane A (near frontal) and plane B (near lateral) and registered biplane and, on "
        f"plane A alone, single plane, from {start} while the patient is offset by the level's "
        "translation (random 3-D direction) and rotation (random axis)"
        + (
            ", both C-arms aimed at the moved head (their iso-center follows the translation, as when the table is "
            "panned back to the anatomy, missing the head's centre by 15 mm in a random direction: the head stays in "
            "both fields, the machine-based pose is off by the offset)"
            if cfg.get("aimed")
            else ""
        )
        + ". The capture radius is the largest offset "
        f"up to which every level succeeds in at least {100 * CAPTURE_SHARE:g} % of the registrations"
        + _level_size_words(summary)
        + ".",
        "",
        f"Volumes: {', '.join(summary['volume_labels'])}. Images: {summary['image_source']}.",
        "",
        "| | biplane (3-D criterion) | single plane A (in-plane criterion) |",
        "| --- | --- | --- |",
    ]
    bi, sp = summary["biplane"], summary["single_plane"]
    ran = set(bi["sweeps"])  # the sweeps this run holds

    def comb(c: dict | None) -> str:
        if c is None:
            return radius_words(None, "", "combined" in ran)
        return f"{c['translation_mm']:g} mm with {c['rotation_deg']:g} deg"

    lines += [
        f"| capture radius, translation | {radius_words(bi['capture_radius_mm_95'], 'mm', 'translation' in ran)} | "
        f"{radius_words(sp['capture_radius_mm_95'], 'mm', 'translation' in ran)} |",
        f"| capture radius, rotation | {radius_words(bi['capture_radius_deg_95'], 'deg', 'rotation' in ran)} | "
        f"{radius_words(sp['capture_radius_deg_95'], 'deg', 'rotation' in ran)} |",
        f"| capture radius, both together | {comb(bi['capture_radius_combined_95'])} | "
        f"{comb(sp['capture_radius_combined_95'])} |",
        f"| applied precision | {pct(bi['applied_precision'])} ({bi['applied']} applied) | "
        f"{pct(sp['applied_precision'])} ({sp['applied']} applied) |",
        f"| registrations | {bi['runs']} | {sp['runs']} |",
    ]
    if "landmark_starts" in bi:
        lines.append(
            f"| from landmarks (the others: too little of the skull in the fields to pick four on one plane; "
            f"registered from the machine-based pose) | {bi['landmark_starts']}, "
            f"{pct(bi['landmark_start_success_rate'])} right | {sp['landmark_starts']}, "
            f"{pct(sp['landmark_start_success_rate'])} right |"
        )
    lines += [
        "",
        f"![capture curves]({image})",
        "",
    ]
    for plane, name in (("biplane", "Biplane"), ("single_plane", "Single plane A")):
        lines += [f"## {name} per level", "", "| sweep | translation (mm) | rotation (deg) | runs | success | "
                  "95 % interval | applied | applied and wrong |",
                  "| --- | --- | --- | --- | --- | --- | --- | --- |"]  # fmt: skip
        for sweep, rows in summary[plane]["sweeps"].items():
            for r in rows:
                lo, hi = r.get("success_interval_95") or (None, None)
                lines.append(
                    f"| {sweep} | {r['translation_mm']:g} | {r['rotation_deg']:g} | {r['runs']} | "
                    f"{pct(r['success_rate'])} | {interval_words(lo, hi)} | {r['applied']} | {r['applied_wrong']} |"
                )
        wrong = summary[plane]["applied_wrong"]
        lines += ["", "Applied and wrong: " + (", ".join(wrong) if wrong else "none") + ".", ""]
    if cfg.get("pooled"):
        runs = len(cfg["pooled"])
        lines.append(
            f"Pooled from {runs} run{'s' * (runs > 1)}: seeds {', '.join(str(x) for x in cfg['seeds'])}; revisions "
            f"{', '.join(cfg['revisions']) or 'not recorded'}; roadmap3d {summary['version']}."
        )
    else:
        lines.append(f"roadmap3d {summary['version']}, seed {cfg.get('seed')}, wall {summary['wall_seconds']:.0f} s.")
    return "\n".join(lines) + "\n"


def write_capture_report(records: list[dict], summary: dict, out: Path) -> dict[str, str]:
    """``capture_curves.png``, ``report.md`` and ``report.html`` in ``out``."""
    from registration.studies.report_kit import markdown_to_html

    out = Path(out)
    png = capture_curves(records, summary, out / "capture_curves.png")
    md = capture_report_md(summary, png.name)
    (out / "report.md").write_text(md)
    (out / "report.html").write_text(markdown_to_html(md, "Capture range"))
    return {"curves": str(png), "report": str(out / "report.md")}
