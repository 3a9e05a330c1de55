"""Paired successive halving: the schedule, the promotion rules, and their offline replay.

Every method starts the same ``K`` configurations (each with all its seeds) and runs them to
the first rung; when all of a method's trials have reached a rung, ``ceil(keep * n)`` of
its ``n`` configurations go on to the next one and the others stop there. The number of
configurations at each rung is the same for every method, so every method gets the same
trials and env steps at every rung: the equal budget of an unpruned study, rung by rung.

Two rules choose who goes on, both from the configurations' AUC so far (the normalised
area under the success curve cut at the rung, the mean over the seeds):

- ``per_method``: each method keeps its own best configurations;
- ``mean_rank``: every method keeps the same configurations, those with the best mean
  rank over all methods, so every comparison stays paired at every rung.

Ties go to the lower configuration id. Everything here is a pure function over plain
numbers; ``replay`` runs the rule on a finished study's recorded curves.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from agent.metrics import normalized_auc

#: the study attr holding a study's decisions (``Ladder.as_attr``)
HALVING_ATTR = "halving"
Rule = Literal["per_method", "mean_rank"]
RULES: tuple[Rule, ...] = ("per_method", "mean_rank")
#: (method, config_id, seed) -> (evaluation steps, success rates)
Curves = Mapping[tuple[str, int, int], tuple[Sequence[int], Sequence[float]]]


@dataclass(frozen=True)
class Schedule:
    """A study's halving: ``stops`` (the rungs, then the full budget), ``sizes[r]`` the
    configurations of each method that run to ``stops[r]``, and the promotion ``rule``."""

    stops: tuple[int, ...]
    sizes: tuple[int, ...]
    keep: float
    rule: Rule

    @property
    def rungs(self) -> tuple[int, ...]:
        return self.stops[:-1]


def rung_sizes(configs: int, rungs: int, keep: float) -> tuple[int, ...]:
    """How many configurations run to each of ``rungs`` stops (the last is the full
    budget): ``configs`` at the first, then ``ceil(keep * previous)``, at least 1."""
    if configs < 1 or rungs < 1 or not 0 < keep <= 1:
        raise ValueError(
            f"need configs >= 1, rungs >= 1, 0 < keep <= 1; got {configs}, {rungs}, {keep}"
        )
    sizes = [configs]
    for _ in range(rungs - 1):
        # a float keep like 0.34 must not round 3 * 1/3 up to 2
        sizes.append(max(1, math.ceil(round(keep * sizes[-1], 9))))
    return tuple(sizes)


def env_steps_spent(stops: Sequence[int], sizes: Sequence[int], seeds: int) -> int:
    """One method's env steps under the schedule: ``sizes[r]`` configurations x ``seeds``
    run from stop ``r - 1`` to stop ``r``."""
    spent, previous = 0, 0
    for stop, size in zip(stops, sizes, strict=True):
        spent += size * seeds * (stop - previous)
        previous = stop
    return spent


def auc_until(steps: Sequence[int], values: Sequence[float], stop: int) -> float:
    """The normalised AUC of a curve cut at env step ``stop`` (which must be one of its
    evaluation steps): what a trial paused at ``stop`` has earned so far."""
    steps_array = np.asarray(steps)
    if stop not in steps_array:
        raise ValueError(f"step {stop} is not an evaluation step of the curve {list(steps)}")
    n = int(np.searchsorted(steps_array, stop)) + 1
    return normalized_auc(steps_array[:n], np.asarray(values, dtype=np.float64)[:n])


def best(scores: Mapping[int, float], count: int, *, low_is_good: bool = False) -> list[int]:
    """The ``count`` best configuration ids by score (highest, or lowest with
    ``low_is_good``), ties to the lower id; returned sorted by id."""
    sign = 1.0 if low_is_good else -1.0
    ranked = sorted(scores, key=lambda c: (sign * scores[c], c))
    return sorted(ranked[:count])


def mean_ranks(scores: Mapping[str, Mapping[int, float]]) -> dict[int, float]:
    """Each configuration's rank within every method (1 = highest score; ties share their
    mean rank), averaged over the methods. Every method must score the same configs."""
    configs = sorted(next(iter(scores.values())))
    total = dict.fromkeys(configs, 0.0)
    for method, by_config in scores.items():
        if sorted(by_config) != configs:
            raise ValueError(f"{method} scores configs {sorted(by_config)}, not {configs}")
        values = np.array([by_config[c] for c in configs])
        for c, value in zip(configs, values, strict=True):
            # 1 + those strictly better + half of the others tied with it
            total[c] += 1 + np.sum(values > value) + (np.sum(values == value) - 1) / 2
    return {c: total[c] / len(scores) for c in configs}


def promote(
    scores: Mapping[str, Mapping[int, float]], count: int, rule: Rule
) -> dict[str, list[int]]:
    """The ``count`` configurations of each method that go on, from each method's scores
    (config id -> AUC so far, the mean over its seeds) at a rung."""
    if rule == "per_method":
        return {method: best(by_config, count) for method, by_config in scores.items()}
    if rule == "mean_rank":
        chosen = best(mean_ranks(scores), count, low_is_good=True)
        return {method: list(chosen) for method in scores}
    raise ValueError(f"rule must be one of {', '.join(RULES)}; got {rule!r}")


def rung_scores(
    curves: Curves, alive: Mapping[str, Sequence[int]], seeds: Sequence[int], stop: int
) -> dict[str, dict[int, float]]:
    """Each method's alive configurations' AUC until ``stop``, the mean over ``seeds``."""
    return {
        method: {
            c: float(np.mean([auc_until(*curves[(method, c, s)], stop) for s in seeds]))
            for c in configs
        }
        for method, configs in alive.items()
    }


@dataclass(frozen=True)
class MethodReplay:
    """What the halving rule would have done to one method of a finished study.

    ``alive``: the configurations run to each stop; ``best_full``: the configuration with
    the best full-budget AUC (mean over seeds) among all, and ``chosen`` the best among the
    survivors of the last rung; ``auc_lost``: best full AUC minus the chosen one's (0 when
    the best survived); ``compute_fraction``: env steps spent over the full study's.
    """

    method: str
    alive: tuple[tuple[int, ...], ...]
    best_full: int
    chosen: int
    best_auc: float
    chosen_auc: float
    compute_fraction: float

    @property
    def survived(self) -> bool:
        return self.best_full in self.alive[-1]

    @property
    def auc_lost(self) -> float:
        return self.best_auc - self.chosen_auc


def reaches(curves: Curves, key: tuple[str, int, int], stop: int) -> bool:
    """Whether ``key`` has a curve evaluated at env step ``stop``."""
    return key in curves and stop in curves[key][0]


class Ladder:
    """Successive halving in a running study: where each configuration runs to next, and
    the decisions taken (the study attr ``halving``: ``{rung step: {method: [config ids
    going on]}}``), each written once and never taken again."""

    def __init__(
        self,
        schedule: Schedule,
        configs: Sequence[int],
        seeds: Sequence[int],
        methods: Sequence[str],
        decisions: Mapping[str, Mapping[str, Sequence[int]]] | None = None,
    ) -> None:
        self.schedule, self.methods = schedule, sorted(methods)
        self.configs, self.seeds = sorted(configs), sorted(seeds)
        self.decisions: dict[int, dict[str, list[int]]] = {
            int(stop): {m: sorted(c) for m, c in chosen.items()}
            for stop, chosen in (decisions or {}).items()
        }

    def target(self, method: str, config: int) -> tuple[int, bool]:
        """(the env step ``config`` of ``method`` runs to next, whether it stops there for
        good): the first rung not yet decided for the method, else where it was dropped,
        else the full budget."""
        for stop in self.schedule.rungs:
            chosen = self.decisions.get(stop, {}).get(method)
            if chosen is None:
                return stop, False
            if config not in chosen:
                return stop, True
        return self.schedule.stops[-1], False

    def alive(self, method: str, rung: int) -> list[int] | None:
        """The configurations of ``method`` that run to rung index ``rung`` (None while an
        earlier rung is undecided)."""
        alive = list(self.configs)
        for stop in self.schedule.rungs[:rung]:
            chosen = self.decisions.get(stop, {}).get(method)
            if chosen is None:
                return None
            alive = chosen
        return alive

    def decide(self, curves: Curves) -> dict[int, dict[str, list[int]]]:
        """Take every decision the ``curves`` so far allow (a method's decision at a rung
        once all its configurations there, every seed, have reached it; with
        ``mean_rank``, once every method's have); return the new ones."""
        new: dict[int, dict[str, list[int]]] = {}
        for r, stop in enumerate(self.schedule.rungs):
            decided = self.decisions.get(stop, {})
            ready = {}
            for method in self.methods:
                alive = self.alive(method, r)
                if method in decided or alive is None:
                    continue
                if all(reaches(curves, (method, c, s), stop) for c in alive for s in self.seeds):
                    ready[method] = alive
            if self.schedule.rule == "mean_rank" and len(ready) < len(self.methods):
                continue  # every method's scores are needed
            if not ready:
                continue
            scores = rung_scores(curves, ready, self.seeds, stop)
            chosen = promote(scores, self.schedule.sizes[r + 1], self.schedule.rule)
            self.decisions.setdefault(stop, {}).update(chosen)
            new.setdefault(stop, {}).update(chosen)
        return new

    def as_attr(self) -> dict[str, dict[str, list[int]]]:
        """The decisions as the study attr stores them (JSON: string keys)."""
        return {
            str(stop): dict(sorted(chosen.items()))
            for stop, chosen in sorted(self.decisions.items())
        }


def replay(
    curves: Curves, rungs: Sequence[int], keep: float, rule: Rule
) -> dict[str, MethodReplay]:
    """Run the halving rule offline on a finished study's full curves (every (method,
    config, seed) of a complete plan, all to the same budget); ``rungs`` below the budget,
    which is the last stop. The decisions are a ``Ladder``'s, as a live study takes them."""
    methods = sorted({m for m, _, _ in curves})
    configs = sorted({c for _, c, _ in curves})
    seeds = sorted({s for _, _, s in curves})
    missing = [
        (m, c, s) for m in methods for c in configs for s in seeds if (m, c, s) not in curves
    ]
    if missing:
        raise ValueError(f"the study is not complete: no curve for {missing[:3]}")
    budget = int(curves[(methods[0], configs[0], seeds[0])][0][-1])
    stops = (*rungs, budget)
    if list(stops) != sorted(set(stops)) or stops[0] <= 0:
        raise ValueError(f"rungs must increase strictly below the budget {budget}; got {rungs}")
    sizes = rung_sizes(len(configs), len(stops), keep)
    ladder = Ladder(Schedule(stops, sizes, keep, rule), configs, seeds, methods)
    ladder.decide(curves)

    full = rung_scores(curves, {m: configs for m in methods}, seeds, budget)
    fraction = env_steps_spent(stops, sizes, len(seeds)) / (len(configs) * len(seeds) * budget)
    result = {}
    for m in methods:
        alive = [ladder.alive(m, r) for r in range(len(stops))]
        best_full = best(full[m], 1)[0]
        chosen = best({c: full[m][c] for c in alive[-1]}, 1)[0]
        result[m] = MethodReplay(
            method=m,
            alive=tuple(tuple(a) for a in alive),
            best_full=best_full,
            chosen=chosen,
            best_auc=full[m][best_full],
            chosen_auc=full[m][chosen],
            compute_fraction=fraction,
        )
    return result
