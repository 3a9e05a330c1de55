"""The thesis' FetchReach claims judged on a study the sweep made (the README's table).

    .venv/bin/python benchmarks/thesis_result.py [--storage URL] [--study NAME]
        [--budget NAME=URL ...]

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
figures match the study's ``auc_table.csv`` and ``improvement.csv``. A "solves" claim
on fewer than 5 trials is "not settled"; a comparison on fewer than 5 pairs says so.

With the budget studies (default the published databases of
``studies/fetch_reach_budget.yaml`` and of its follow-up on more seeds,
``studies/fetch_reach_budget_seeds.yaml``; one not published yet is said in one line), the
two "solves" claims are judged at every gradient budget the studies ran, joined as
``sweeper aggregate`` joins them (``sweeper.results._budget``: the same configurations,
every seed a setting ran), each with its condition: "PIXEL solves FetchReach: holds at 1/4
of A.1's gradient samples, 15k steps, 8 trials". The rule (``solved_at``) is printed with
them.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import pandas as pd

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

#: the final success rate at which a method "solves" the task
SOLVED = 0.8
#: the published study
STORAGE = f"sqlite:///{ROOT / 'docs' / 'studies' / 'fetch_reach_cpu' / 'study.db'}"
#: the budget studies (the ladder, then its follow-up on more seeds) and their published
#: databases (absent until published)
BUDGET_STUDIES = tuple(
    (name, f"sqlite:///{ROOT / 'docs' / 'studies' / name / 'study.db'}")
    for name in ("fetch_reach_budget", "fetch_reach_budget_seeds")
)
#: the encoders whose "solves FetchReach" the thesis claims
SOLVERS = ("pixel", "conv")


def solved_at(final_iqm: float, low: float, random: float | None) -> bool:
    """The rule for "solves" at one setting: the IQM final success rate reaches ``SOLVED``
    and the lower end of its 95 % interval lies above the random agent's success rate
    (so the level is not what chance gives); without a measured random agent, the first
    part alone."""
    return final_iqm >= SOLVED and (random is None or low > random)


def rule_text(random: float | None, min_trials: int) -> str:
    """``solved_at`` in words, for the output."""
    floor = (
        ""
        if random is None
        else (
            f" and the lower end of its 95% interval lies above the random agent's success "
            f"rate ({random:.2f})"
        )
    )
    return (
        f"Rule: a claim holds at a setting when the IQM final success rate (the last "
        f"evaluation) is >= {SOLVED}{floor}; otherwise it does not hold there; on fewer "
        f"than {min_trials} trials it is not settled."
    )


def condition(setting: str, env_steps: int | None, n: int) -> str:
    """Where a claim is judged: ``"1/4 of A.1's gradient samples, 15k steps, 4 trials"``
    (a setting's other departures from A.1 follow its fraction)."""
    fraction, _, departures = setting.partition(", ")
    parts = [f"{fraction} of A.1's gradient samples", *filter(None, [departures])]
    if env_steps:
        parts.append(f"{env_steps / 1000:g}k steps")
    parts.append(f"{n} trial{'s' if n != 1 else ''}")
    return ", ".join(parts)


def sqlite_file(url: str) -> Path | None:
    """The file of a ``sqlite:///`` URL (None for another database)."""
    prefix = "sqlite:///"
    return Path(url[len(prefix) :]) if url.startswith(prefix) else None


def study_and_storage(text: str) -> tuple[str, str]:
    """``NAME=URL`` as (NAME, URL); anything else is a usage error."""
    name, equals, url = text.partition("=")
    if not (name and equals and url):
        raise argparse.ArgumentTypeError(f"expected NAME=URL, got {text!r}")
    return name, url


def read_budget(study: str, storage: str) -> pd.DataFrame | str:
    """The search stage of ``study`` at ``storage``, or why it cannot be read (one line)."""
    from sweeper.results._frame import load_study_frame, stage_frame

    path = sqlite_file(storage)
    if path is not None and not path.is_file():
        shown = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path
        return f"{shown} does not exist (studies/{study}.yaml, not published yet)"
    try:
        return stage_frame(load_study_frame(storage, study), "search")
    except ValueError as e:
        return str(e)


def budget_claims(frame, budgets: Sequence[tuple[str, str]], seed: int = 0) -> list[str]:
    """The "solves" claims at every setting of the budget join of ``frame`` (the published
    study, read) with the ``budgets`` (``(study, storage)``: the ladder, then follow-ups);
    one line for each that cannot be read (the ladder: then no claim)."""
    from sweeper.results._budget import budget_table, join_studies, study_trials
    from sweeper.results._frame import random_success, stage_frame, study_info
    from sweeper.results._report import MIN_RELIABLE, _fmt

    studies, missing = [study_trials(study_info(frame).name, stage_frame(frame, "search"))], []
    for index, (study, storage) in enumerate(budgets):
        budget = read_budget(study, storage)
        if not isinstance(budget, str):
            studies.append(study_trials(study, budget))
        elif index == 0:
            return [
                f"No budget study: {budget}, so the claims above are judged at 1/16 of "
                "A.1's gradient samples only."
            ]
        else:
            missing.append(f"{study} is not joined: {budget}.")
    join = join_studies(studies)
    table = budget_table(join, seed=seed)
    random = random_success(frame)
    rule = rule_text(random, MIN_RELIABLE)
    lines = [f"Each claim at each gradient budget ({' + '.join(join.studies)}). {rule}"]
    lines += missing
    for left, problems in join.left_out.items():
        lines.append(f"{left} is left out: its configurations differ ({'; '.join(problems)}).")
    for encoder in SOLVERS:
        for row in table[table["encoder"] == encoder].itertuples():
            held = solved_at(row.final_success_iqm, row.final_success_iqm_low, random)
            verdict = "holds" if held else "does not hold"
            evidence = (
                f"IQM final success {_fmt(row.final_success_iqm, 2)} "
                f"[{_fmt(row.final_success_iqm_low, 2)}, {_fmt(row.final_success_iqm_high, 2)}]"
            )
            if row.n < MIN_RELIABLE:  # an interval over so few trials says little
                verdict = "not settled"
                evidence += f"; fewer than {MIN_RELIABLE} trials"
            lines.append(
                f"- {encoder.upper()} solves FetchReach: {verdict} "
                f"at {condition(row.setting, join.env_steps, row.n)} ({evidence})"
            )
    return lines


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


def main(argv: Sequence[str] | None = None) -> None:
    import numpy as np

    from sweeper.results import _stats as stats
    from sweeper.results._frame import (
        load_study_frame,
        random_success,
        scored,
        stage_frame,
        study_info,
    )
    from sweeper.results._report import MIN_RELIABLE, _fmt
    from sweeper.results._tables import study_tables

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--storage", default=STORAGE)
    parser.add_argument("--study", default="fetch_reach_cpu")
    parser.add_argument(
        "--budget",
        action="append",
        type=study_and_storage,
        metavar="NAME=URL",
        help="a budget study and its storage (repeat: the ladder first, then follow-ups); "
        "default the published fetch_reach_budget and fetch_reach_budget_seeds",
    )
    args = parser.parse_args(argv)

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
            verdict = f"not settled on {n} trial{'s' if n > 1 else ''}, fewer than {MIN_RELIABLE}"
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
    print()
    print("\n".join(budget_claims(frame, args.budget or BUDGET_STUDIES, seed)))


if __name__ == "__main__":
    main()
