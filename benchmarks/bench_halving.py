"""Replay paired successive halving offline: on synthetic studies and on finished studies.

    .venv/bin/python benchmarks/bench_halving.py [--studies 500] [--storage URL --study NAME]

Synthetic studies: ``--methods`` methods x ``--configs`` configurations x ``--seeds``
seeds, each configuration a success curve ``level * (1 - exp(-t / speed))`` plus noise,
evaluated every 1,000 of 20,000 steps. ``level`` is the method's skill plus the SAC
configuration's effect (shared by every method, as the paired design shares it) plus a
(method, config) part; ``speed`` is drawn under three worlds: fast configurations are the
good ones (``aligned``), speed and level independent (``independent``), and the best
configurations start slowly (``late_bloomers``), the case that early stopping gets wrong.

For each world, schedule (the default: keep 1/3 at 1/9 and 1/3 of the budget; and two
gentler ones) and rule (``per_method``, ``mean_rank``), it prints how often each method's
best full-budget configuration survives, the mean and worst AUC lost (best full AUC minus
the chosen configuration's), and the fraction of env steps spent against the full study.

With ``--storage``/``--study`` it also replays a study's recorded curves, on the SAC
configurations every method has finished (all of them once the study is), e.g. the
FetchReach CPU study:

    .venv/bin/python benchmarks/bench_halving.py --storage \
        sqlite:///docs/studies/fetch_reach_cpu/study.db --study fetch_reach_cpu
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from sweeper.plan import _halving as halving  # noqa: E402
from sweeper.spec import DEFAULT_KEEP, default_rungs, rungs_at  # noqa: E402

BUDGET, EVAL_EVERY = 20_000, 1_000
WORLDS = ("aligned", "independent", "late_bloomers")


def synthetic_curves(
    rng: np.random.Generator, world: str, methods: int, configs: int, seeds: int
) -> halving.Curves:
    """One synthetic finished study (see the module docstring)."""
    steps = np.arange(0, BUDGET + 1, EVAL_EVERY)
    shared = rng.normal(0, 0.1, configs)  # a SAC configuration's effect, the same for all
    curves = {}
    for m in range(methods):
        skill = 0.3 + 0.5 * m / max(1, methods - 1)  # later methods are better on average
        level = np.clip(skill + shared + rng.normal(0, 0.1, configs), 0.05, 1.0)
        # the step at which a configuration reaches 63% of its level
        quantile = rng.uniform(0, 1, configs)
        if world == "aligned":
            quantile = 1 - (np.argsort(np.argsort(level)) + rng.uniform(0, 1, configs)) / configs
        elif world == "late_bloomers":
            quantile = (np.argsort(np.argsort(level)) + rng.uniform(0, 1, configs)) / configs
        speed = 1_000 + 9_000 * quantile
        for c in range(configs):
            for s in range(seeds):
                mean = level[c] * (1 - np.exp(-steps / speed[c]))
                noisy = np.clip(mean + rng.normal(0, 0.1, steps.size), 0, 1)
                noisy[0] = 0.0
                curves[(f"m{m}", c, s)] = (steps.tolist(), noisy.tolist())
    return curves


def summarize(results: list[dict[str, halving.MethodReplay]]) -> tuple[float, float, float, float]:
    """(best survives, mean AUC lost, worst AUC lost, compute fraction) over all methods of
    all replays."""
    rows = [r for result in results for r in result.values()]
    lost = np.array([r.auc_lost for r in rows])
    survived = np.mean([r.survived for r in rows])
    return float(survived), float(lost.mean()), float(lost.max()), rows[0].compute_fraction


def study_curves(storage: str, study: str) -> tuple[halving.Curves, list[int], int, int]:
    """The search curves of a study's configurations that every method has finished (every
    seed; a study still running has done some, as its keys run round by round), those
    configurations, how many the plan has, and the spec's seed steps."""
    from sweeper.results._frame import load_study_frame, scored, stage_frame, study_info

    frame = load_study_frame(storage, study)
    attrs = study_info(frame).attrs
    plan = attrs.get("plan", [])
    seed_steps = int(attrs.get("spec", {}).get("budget", {}).get("seed_steps", 0))
    planned_configs = sorted({int(k.split("/")[1]) for k in plan})
    done = scored(stage_frame(frame, "search"))
    finished = set(done["key"])
    complete = [
        c for c in planned_configs if all(k in finished for k in plan if int(k.split("/")[1]) == c)
    ]
    curves = {}
    rows = done[done["config_id"].astype(int).isin(complete)]
    for (method, config, seed), trial in rows.groupby(["method", "config_id", "seed"]):
        curves[(method, int(config), int(seed))] = (
            trial["step"].astype(int).tolist(),
            trial["success_rate"].astype(float).tolist(),
        )
    return curves, complete, len(planned_configs), seed_steps


def study_schedules(
    budget: int, grid: int, seed_steps: int = 0
) -> list[tuple[tuple[int, ...], float]]:
    """The schedules compared: the default (keep 1/3 at 1/9 and 1/3 of the budget), one rung
    at 1/4, and keep 1/2 at 1/10 and 1/4; rungs rounded down to the evaluation grid, none
    inside the seed phase."""

    def on_grid(*fractions: float) -> tuple[int, ...]:
        return rungs_at(fractions, budget, grid, seed_steps)

    return [
        (default_rungs(budget, grid, seed_steps), DEFAULT_KEEP),
        (on_grid(1 / 4), DEFAULT_KEEP),
        (on_grid(1 / 10, 1 / 4), 0.5),
    ]


def print_replay(name: str, result: dict[str, halving.MethodReplay]) -> None:
    print(f"  {name}")
    for method, r in result.items():
        alive = " -> ".join(str(len(a)) for a in r.alive)
        print(
            f"    {method:<18} configs {alive}  best {r.best_full} ({r.best_auc:.3f})  "
            f"chosen {r.chosen} ({r.chosen_auc:.3f})  survived {'yes' if r.survived else 'no'}"
            f"  AUC lost {r.auc_lost:.3f}  compute {r.compute_fraction:.0%}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--studies", type=int, default=500, help="synthetic studies per world (0: none)"
    )
    parser.add_argument("--methods", type=int, default=6)
    parser.add_argument("--configs", type=int, default=20)
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--storage", help="replay this finished study too")
    parser.add_argument("--study", help="its name")
    args = parser.parse_args()

    schedules = study_schedules(BUDGET, EVAL_EVERY)
    if args.studies:  # 0: the study only
        print(
            f"synthetic: {args.studies} studies per world, {args.methods} methods x "
            f"{args.configs} configs x {args.seeds} seeds, {BUDGET} env steps"
        )
        print(
            f"{'world':<14} {'rungs':<14} {'keep':>5} {'rule':<11} {'best kept':>9} "
            f"{'AUC lost':>8} {'worst':>6} {'compute':>8}"
        )
        for world in WORLDS:
            rng = np.random.default_rng(0)
            studies = [
                synthetic_curves(rng, world, args.methods, args.configs, args.seeds)
                for _ in range(args.studies)
            ]
            for rungs, keep in schedules:
                for rule in halving.RULES:
                    results = [halving.replay(c, rungs, keep, rule) for c in studies]
                    survived, lost, worst, fraction = summarize(results)
                    print(
                        f"{world:<14} {list(rungs)!s:<14} {keep:>5.2f} {rule:<11} "
                        f"{survived:>9.0%} {lost:>8.3f} {worst:>6.3f} {fraction:>8.0%}"
                    )

    if args.storage:
        curves, complete, planned, seed_steps = study_curves(args.storage, args.study)
        print(f"\nstudy {args.study!r} in {args.storage}")
        print(f"  configurations every method has finished: {complete} of {planned}")
        if len(complete) < 2:
            print("  fewer than 2: nothing to choose between, nothing to replay")
            return
        budget = max(steps[-1] for steps, _ in curves.values())
        grid = int(np.diff(next(iter(curves.values()))[0]).min())
        for rungs, keep in study_schedules(budget, grid, seed_steps):
            sizes = halving.rung_sizes(len(complete), len(rungs) + 1, keep)
            for rule in halving.RULES:
                name = f"rungs {list(rungs)} keep {keep:.2f} ({sizes}) rule {rule}"
                print_replay(name, halving.replay(curves, rungs, keep, rule))


if __name__ == "__main__":
    main()
