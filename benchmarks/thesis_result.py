"""The thesis' FetchReach claims judged on a study the sweep made (the README's table).

    .venv/bin/python benchmarks/thesis_result.py [--storage URL] [--study NAME]

Default: the published study, ``docs/studies/fetch_reach_cpu/study.db``. Prints a Markdown
table, per method: done of planned trials, IQM AUC with its 95 % interval, the IQM of the
final success rate (the last evaluation), how many trials reach success 0.8 at some
evaluation, and the paired probability of improvement over PIXEL with its interval and
number of pairs; the random agent's success rate (the floor); then one verdict per thesis
claim:

- PIXEL solves FetchReach; CONV solves it: "solves" is the IQM final success rate >= 0.8
  (the bar of ``bench_learning.py``; the thesis' Figure 4.1 shows success near 1);
- CONV >= the learned latents (VAE, CVAE); VAE below the learning-free methods (PIXEL,
  LINEAR, CONV): from the paired probabilities of improvement, by ``judge``.

Every statistic comes from ``sweeper aggregate``'s own tables (the same seed), so the
figures match the study's ``auc_table.csv`` and ``improvement.csv``. A claim resting on
fewer than 5 trials or pairs says so.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

#: the final success rate at which a method "solves" the task
SOLVED = 0.8
#: the published study
STORAGE = f"sqlite:///{ROOT / 'docs' / 'studies' / 'fetch_reach_cpu' / 'study.db'}"


def judge(intervals: Sequence[tuple[float, float]]) -> str:
    """The verdict on "A is ahead of each B" from the intervals of P(A > B): ``holds`` when
    every interval lies above 0.5, ``contradicted`` when one lies below it, ``not settled``
    otherwise (the intervals reach 0.5; or there is no pair)."""
    if not intervals or any(low != low for low, _ in intervals):  # NaN: no pair
        return "not settled"
    if any(high < 0.5 for _, high in intervals):
        return "contradicted"
    if all(low > 0.5 for low, _ in intervals):
        return "holds"
    return "not settled"


def main() -> None:
    import numpy as np

    from sweeper import stats
    from sweeper.aggregate.frame import (
        load_study_frame,
        random_success,
        scored,
        stage_frame,
        study_info,
    )
    from sweeper.aggregate.report import MIN_RELIABLE, _fmt
    from sweeper.aggregate.tables import study_tables

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--storage", default=STORAGE)
    parser.add_argument("--study", default="fetch_reach_cpu")
    args = parser.parse_args()

    frame = load_study_frame(args.storage, args.study)
    seed = int((study_info(frame).attrs.get("spec") or {}).get("seed", 0))
    search = stage_frame(frame, "search")
    tables = study_tables(search, driver_alive=False, seed=seed)
    table = tables.table.set_index("method")
    improvement = {(r.method, r.versus): r for r in tables.improvement.itertuples()}
    rows = scored(search)
    last = rows.sort_values("step").groupby("trial").tail(1)
    reached = rows.groupby("trial")["success_rate"].max() >= SOLVED

    def few(n: int) -> str:
        return "*" if 0 < n < MIN_RELIABLE else ""

    def versus(method: str, other: str) -> str:
        r = improvement.get((method, other))
        if r is None or not r.pairs:
            return "–"
        probability = f"{_fmt(r.probability, 2)} [{_fmt(r.low, 2)}, {_fmt(r.high, 2)}]"
        return f"{probability} ({r.pairs}{few(r.pairs)})"

    final = {}
    print(
        "| method | done | IQM AUC [95% CI] | IQM final success | trials reaching "
        f"{SOLVED} | P(method > pixel) [95% CI] (pairs) |"
    )
    print("|---|---:|---:|---:|---:|---:|")
    for method, row in table.iterrows():
        mine = last[last["method"] == method]
        final[method] = float(stats.iqm(mine["success_rate"])) if len(mine) else float("nan")
        hits = int(reached[mine["trial"]].sum()) if len(mine) else 0
        print(
            f"| {method} | {row['done']}/{row['planned']}{few(int(row['n']))} "
            f"| {_fmt(row['iqm'])} [{_fmt(row['iqm_low'])}, {_fmt(row['iqm_high'])}] "
            f"| {_fmt(final[method], 2)} | {hits} of {len(mine)} "
            f"| {versus(method, 'pixel') if method != 'pixel' else '–'} |"
        )
    print(f"\n\\* fewer than {MIN_RELIABLE} trials or pairs: not reliable.", end=" ")
    chance = random_success(frame)
    if chance is not None:  # the floor: what uniform random actions achieve
        print(f"A uniform random policy's success rate: {chance:.2f}.", end="")
    print("\n")

    def solves(method: str) -> str:
        value = final.get(method, float("nan"))
        if np.isnan(value):
            return f"{method}: no done trial"
        verdict = "holds" if value >= SOLVED else "does not hold here"
        n = int(table.loc[method, "n"])
        if n < MIN_RELIABLE:
            verdict += f" on {n} trial{'s' if n > 1 else ''}, fewer than {MIN_RELIABLE}"
        return f"{verdict} (IQM final success {value:.2f}, bar {SOLVED})"

    def ahead(pairs: Sequence[tuple[str, str]]) -> str:
        """The verdict on "a is ahead of b" for every (a, b), and its evidence."""
        found = [improvement.get(pair) for pair in pairs]
        intervals = [(r.low, r.high) for r in found if r is not None and r.pairs]
        evidence = ", ".join(f"P({a} > {b}) {versus(a, b)}" for a, b in pairs)
        verdict = judge(intervals if len(intervals) == len(pairs) else [])
        if any(r is None or r.pairs < MIN_RELIABLE for r in found):
            verdict += f" on fewer than {MIN_RELIABLE} pairs, not reliable"
        return f"{verdict} ({evidence})"

    print(f"- PIXEL solves FetchReach: {solves('pixel')}")
    print(f"- CONV solves FetchReach: {solves('conv')}")
    print(f"- CONV >= the learned latents: {ahead([('conv', 'vae'), ('conv', 'cvae')])}")
    learning_free = [(m, "vae") for m in ("pixel", "linear", "conv")]
    print(f"- VAE below the learning-free methods: {ahead(learning_free)}")


if __name__ == "__main__":
    main()
