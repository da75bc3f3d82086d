"""The polish's local search against a derivative-free trust-region method, on the same cost.

Each case: the phantom (Table I's four offsets, single plane, the phantom resampled to a 128^3
3DRA grid, exposure images) and the shared real CT (clinical draws, biplane and single plane), the polish
level's problem (128 px, volume level 1) set up at the truth; the search starts at the truth
moved by a random offset of 1.5 mm and 1 degree per parameter (what a polish starts from after
the annealing), and runs with a budget of evaluations. For every method and budget the record
holds the cost reached, the residual at the iso-center from the truth, and the evaluations spent.

Methods: ``powell`` (the project's polish: bounded line searches, ``registration.core.anneal.polish``),
``cobyqa`` (scipy's COBYQA, quadratic models in a trust region, in parameters scaled by the
polish's first steps), ``nelder-mead`` (scipy, the same scaling).

python scripts/local_search_study.py --seed 0 --starts 4 --out local-search.jsonl
python scripts/local_search_study.py --summarize local-search.jsonl --figure local-search.png
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy import optimize

from registration.core.anneal import polish
from registration.core.geometry import CArm, offsets_to_matrix, rigid
from registration.core.metrics import residuals
from registration.core.problem import LevelProblem
from registration.core.register import RegistrationOptions
from registration.core.register.inputs import prepared_renderer
from registration.core.search import SearchSpace

BUDGETS = (10, 20, 30, 40, 60, 80)
START_MM, START_DEG = 1.5, 1.0
STEP_MM, STEP_DEG = 0.5, 0.3  # the polish's first steps (PolishOptions)


def phantom_cases() -> list[tuple[str, object, list, np.ndarray]]:
    from registration.sim.phantom import make_head_phantom, registration_volume
    from registration.sim.xray import simulate_xray

    volume = registration_volume(make_head_phantom(seed=0, contrast=True), 27.0, voxels=128)
    g = CArm.for_format(27.0, pixels=256, primary_deg=20.0)
    phantom = make_head_phantom(seed=0, contrast=False)
    out = []
    for name, t in (("T1", (4, 4, 0, 0, 0, 0)), ("T2", (10, 0, 0, 0, 0, 0)), ("T3", (2, 2, 0, 2, 2, 2)),
                    ("T4", (4, 4, 0, 2, 3, 4))):  # fmt: skip
        truth = offsets_to_matrix(np.asarray(t, dtype=float), g)
        out.append(
            (f"phantom {name}", volume, [simulate_xray(phantom, g, motion=truth, kind="exposure", seed=1)], truth)
        )
    return out


def ct_cases(n: int, seed: int) -> list[tuple[str, object, list, np.ndarray]]:
    from registration.io import dicom
    from registration.studies.volume import VolumeImager, find_real_ct

    path = find_real_ct()
    if path is None:
        return []
    volume = dicom.read_volume(path)
    iso = (247.5, -276.0, -90.0)
    imager = VolumeImager(volume, iso)
    rng = np.random.default_rng([seed, 7])
    out = []
    for k in range(n):
        a = replace(CArm.for_format(27.0, pixels=384, primary_deg=float(rng.uniform(-45, 45)),
                                    secondary_deg=float(rng.uniform(-25, 25))), isocenter_mm=iso)  # fmt: skip
        b = replace(a, primary_deg=a.primary_deg + 90.0, secondary_deg=0.0)
        truth = rigid(None, rng.uniform(-10, 10, 3))
        views = [imager.image(v, truth, kind="fluoro", seed=seed + k) for v in (a, b)]
        out.append((f"real CT {k} single", volume, views[:1], truth))
        out.append((f"real CT {k} biplane", volume, views, truth))
    return out


def run_method(method: str, cost, x0: np.ndarray, bounds: np.ndarray, step: np.ndarray, budget: int):
    """(best x, best cost, evaluations) of ``method`` from ``x0`` within ``budget`` evaluations."""
    if method == "powell":
        r = polish(cost, x0, bounds, step=step, max_evaluations=budget, xtol=0.1)
        return r.x, r.fun, r.nfev
    seen = {"n": 0, "best": (np.inf, x0)}

    def scaled(z: np.ndarray) -> float:
        x = np.clip(x0 + z * step, bounds[:, 0], bounds[:, 1])
        if seen["n"] >= budget:
            return seen["best"][0]
        seen["n"] += 1
        f = cost(x)
        if f < seen["best"][0]:
            seen["best"] = (f, x)
        return f

    zb = np.stack([(bounds[:, 0] - x0) / step, (bounds[:, 1] - x0) / step], axis=1)
    if method == "cobyqa":
        optimize.minimize(scaled, np.zeros_like(x0), method="COBYQA", bounds=zb,
                          options={"maxfev": budget, "initial_tr_radius": 1.0, "final_tr_radius": 0.05})  # fmt: skip
    else:
        optimize.minimize(scaled, np.zeros_like(x0), method="Nelder-Mead", bounds=zb,
                          options={"maxfev": budget, "xatol": 0.05, "fatol": 1e-6})  # fmt: skip
    f, x = seen["best"]
    if not np.isfinite(f):
        f, x = cost(x0), x0
    return x, f, seen["n"]


def summarize(records: list[dict], figure: Path | None) -> str:
    """A markdown table (median over cases and starts) and, given ``figure``, its plot: the
    relative gap to the best measure any run found from that start, against the budget."""
    best: dict[tuple, float] = {}
    for r in records:
        key = (r["case"], r["start"])
        best[key] = min(best.get(key, np.inf), r["cost"])
    kinds = {"phantom": "phantom, one view", "single": "real CT, one view", "biplane": "real CT, two views"}

    def kind(case: str) -> str:
        return "phantom" if case.startswith("phantom") else ("biplane" if case.endswith("biplane") else "single")

    rows, curves = [], {}
    for k in kinds:
        for method in ("powell", "cobyqa", "nelder-mead"):
            for budget in BUDGETS:
                g = [r for r in records if kind(r["case"]) == k and r["method"] == method and r["budget"] == budget]
                if not g:
                    continue
                gap = [(r["cost"] - best[(r["case"], r["start"])]) / abs(best[(r["case"], r["start"])]) for r in g]
                row = (kinds[k], method, budget, len(g), float(np.median([r["evaluations"] for r in g])),
                       float(np.median(gap)), float(np.median([r["criterion_mm"] for r in g])),
                       float(np.median([r["rotation_deg"] for r in g])))  # fmt: skip
                rows.append(row)
                curves.setdefault((k, method), []).append((budget, row[5]))
    lines = ["| images | method | budget | runs | evaluations | measure's gap to the best | mm (criterion) | deg |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |"]  # fmt: skip
    lines += [f"| {a} | {m} | {b} | {n} | {e:.0f} | {g:.4f} | {mm:.3f} | {d:.2f} |" for a, m, b, n, e, g, mm, d in rows]
    if figure is not None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, len(kinds), figsize=(13, 3.8), sharey=True)
        for ax, k in zip(axes, kinds, strict=True):
            for method, color in (("powell", "#4c72b0"), ("cobyqa", "#dd8452"), ("nelder-mead", "#999999")):
                pts = curves.get((k, method))
                if pts:
                    ax.plot([p[0] for p in pts], [max(p[1], 1e-5) for p in pts], "o-", color=color, label=method)
            ax.set_yscale("log")
            ax.set_title(kinds[k])
            ax.set_xlabel("evaluations allowed")
            ax.grid(alpha=0.3)
        axes[0].set_ylabel("median relative gap of the measure\nto the best found from that start")
        axes[0].legend()
        fig.suptitle("The polish's local search: how close each method gets within a budget")
        fig.tight_layout()
        fig.savefig(figure, dpi=110)
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--summarize", type=Path, help="print the table of a records file (and --figure) and stop")
    ap.add_argument("--figure", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--starts", type=int, default=4, help="random starts per case")
    ap.add_argument("--ct-cases", type=int, default=3)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    if args.summarize is not None:
        print(summarize([json.loads(line) for line in args.summarize.open()], args.figure))
        return 0
    if args.out is None:
        ap.error("--out is required (or --summarize)")
    options = RegistrationOptions()
    rng = np.random.default_rng(args.seed)
    with args.out.open("w") as fh:
        for name, volume, views, truth in phantom_cases() + ct_cases(args.ct_cases, args.seed):
            six = len(views) > 1
            space = SearchSpace.for_views(views[0].geometry, truth, optimize_tz=six, bound_mm=30.0, bound_deg=15.0)
            renderer = prepared_renderer(volume, tuple(views), truth, options)
            problem = LevelProblem.prepare(renderer, tuple(views), image_px=128, volume_level=1, motion=truth,
                                           margin_mm=options.margin_mm(len(options.levels)))  # fmt: skip
            evaluator = problem.evaluator()

            def cost(x: np.ndarray, space=space, evaluator=evaluator) -> float:
                return -evaluator.similarity(space.motion(x))

            trans = space.is_translation()
            step = np.where(trans, STEP_MM, STEP_DEG)
            for s in range(args.starts):
                x0 = (
                    np.where(trans, START_MM, START_DEG)
                    * rng.choice([-1.0, 1.0], trans.size)
                    * rng.uniform(0.5, 1, trans.size)
                )
                half = np.where(trans, 2.0, 1.5)  # the polish's reach
                bounds = np.stack([x0 - half, x0 + half], axis=1)
                for method in ("powell", "cobyqa", "nelder-mead"):
                    for budget in BUDGETS:
                        began = time.perf_counter()
                        x, f, n = run_method(method, cost, x0, bounds, step, budget)
                        res = residuals(space.motion(x), truth, views[0].geometry, optimizes_tz=six)
                        rec = {
                            "case": name, "start": s, "method": method, "budget": budget, "evaluations": int(n),
                            "cost": float(f), "criterion_mm": float(res.translation_mm if six else res.inplane_mm),
                            "rotation_deg": float(res.rotation_deg), "seconds": time.perf_counter() - began,
                        }  # fmt: skip
                        fh.write(json.dumps(rec) + "\n")
                        fh.flush()
                print(name, "start", s, file=sys.stderr, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
