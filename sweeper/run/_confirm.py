"""The confirmation stage (``sweeper confirm SPEC --top-k K --seeds N``, ``cli_confirm``),
against the winner's curse.

The best of many configurations on a few seeds is partly the luckiest: its search AUC
overstates it. This stage re-runs each method's ``K`` best configurations (by search AUC:
the mean over the config's search seeds, ties to the lower config id) on ``N`` fresh seeds
(``sweeper.plan._entries.fresh_seeds``: after the search's largest), in the same study, as plan keys
``confirm/{method}/{config_id}/{seed}`` (trial attr ``stage: "confirm"``). It runs through
the search's own driver (``sweeper.run._launch.launch`` with a ``stage``), so its ledger, resume
and failure semantics are the search's: one current trial per key, worker deaths re-run from
the checkpoint in the same trial, a killed driver's trials re-run by the next ``sweeper
confirm``, which resumes the stage.

The choice is made once, when the stage is first run on a finished search, and stored as the
study attr ``confirm`` (``top_k``, ``seeds``, ``configs`` per method, their ``search_auc``,
``keys``, ``hash``); later runs reuse it, and a run with another ``K`` or ``N`` is refused
(exit 2), as a changed search plan is. ``sweeper aggregate`` reports the stage apart from
the search. Exit codes as ``sweeper launch``.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from optuna.trial import FrozenTrial, TrialState

from sweeper.plan import Plan, build_plan, confirm_plan, fresh_seeds
from sweeper.run._launch import launch
from sweeper.spec import SpecError, StudySpec
from sweeper.storage import (
    StorageError,
    StudyStore,
    current_trials,
    open_study,
)

#: the study user attr holding the stage's choice
ATTR = "confirm"


def settings(spec: StudySpec, top_k: int | None, seeds: int | None) -> tuple[int, int]:
    """``(top_k, seeds)`` from the flags, else the spec's ``confirm`` section."""
    section = spec.confirm
    top_k = top_k if top_k is not None else (section.top_k if section else None)
    seeds = seeds if seeds is not None else (section.seeds if section else None)
    if top_k is None or seeds is None:
        raise SpecError("confirm: give --top-k K and --seeds N, or a confirm: section")
    return top_k, seeds


def confirm(
    spec: StudySpec,
    plan: Plan,
    top_k: int,
    seeds: int,
    *,
    train: Any = None,
    stream: Any = None,
) -> int:
    """Run (or resume) the confirmation stage of ``spec``'s study; the exit code."""
    stage = functools.partial(confirm_stage, top_k=top_k, seeds=seeds)
    return launch(spec, plan, train=train, stream=stream, stage=stage)


def select(
    trials: Iterable[FrozenTrial], search_keys: Sequence[str], top_k: int
) -> tuple[dict[str, list[int]], dict[str, dict[int, float]]]:
    """Each method's ``top_k`` config ids by search AUC (the mean over the config's search
    seeds; ties to the lower id) and every config's search AUC. Raises StorageError unless
    every search key is done: an unfinished search would choose among fewer configs."""
    current = current_trials(trials)
    missing = [
        k for k in search_keys if k not in current or current[k].state != TrialState.COMPLETE
    ]
    if missing:
        raise StorageError(
            f"the search is not finished: {len(missing)} of {len(search_keys)} trials are not "
            f"done (e.g. {missing[0]}); finish it with `sweeper launch` first"
        )
    aucs: dict[str, dict[int, list[float]]] = {}
    for key in search_keys:
        method, config_id, _ = key.rsplit("/", 2)
        aucs.setdefault(method, {}).setdefault(int(config_id), []).append(current[key].value)
    search_auc = {m: {c: sum(v) / len(v) for c, v in by.items()} for m, by in aucs.items()}
    configs = {
        m: sorted(by, key=lambda c, by=by: (-by[c], c))[:top_k] for m, by in search_auc.items()
    }
    return configs, search_auc


def choice(
    spec: StudySpec,
    stored: Mapping[str, Any] | None,
    trials: Iterable[FrozenTrial],
    search_keys: Sequence[str],
    top_k: int,
    seeds: int,
) -> dict[str, Any]:
    """The stage's ``confirm`` attr: the ``stored`` one when it was made with the same
    ``top_k`` and ``seeds`` (never chosen again), else a new choice from the search.
    Raises StorageError for another ``top_k`` or ``seeds`` than the stored ones."""
    if stored:
        if (stored["top_k"], len(stored["seeds"])) != (top_k, seeds):
            raise StorageError(
                f"study {spec.study!r} was confirmed with --top-k {stored['top_k']} --seeds "
                f"{len(stored['seeds'])}; another choice would mix two budgets in one ledger. "
                "Use the same values, or a new study."
            )
        return dict(stored)
    configs, search_auc = select(trials, search_keys, top_k)
    return {
        "top_k": top_k,
        "seeds": list(fresh_seeds(spec.seeds, seeds)),
        "configs": configs,
        "search_auc": {m: {str(c): a for c, a in by.items()} for m, by in search_auc.items()},
    }


def confirm_stage(spec: StudySpec, store: StudyStore, *, top_k: int, seeds: int) -> Plan:
    """The stage's plan, run by the study's driver (``sweeper.run._launch.Stage``): the choice
    is made (and stored) under the driver's claim, so two drivers never choose twice."""
    search = build_plan(spec, study_uid=store.study_uid)
    stored = store.attrs.get(ATTR)
    made = choice(spec, stored, store.trials(), search.keys(), top_k, seeds)
    configs = {m: [int(c) for c in ids] for m, ids in made["configs"].items()}
    plan = confirm_plan(search, configs, tuple(made["seeds"]))
    if stored is None:
        store.set_study_attr(ATTR, {**made, "keys": plan.keys(), "hash": plan.hash})
    elif stored.get("hash") != plan.hash:
        raise StorageError(f"study {spec.study!r}: the stored confirmation plan does not match")
    return plan


def check_study(spec: StudySpec, plan: Plan, top_k: int, seeds: int) -> None:
    """What ``confirm_stage`` will check, read-only, so a refusal writes nothing: the study
    exists with this search plan, its search is finished, the choice matches a stored one."""
    with open_study(spec.storage_url, spec.study, write=False, plan_hash=plan.hash) as store:
        choice(spec, store.attrs.get(ATTR), store.trials(), plan.keys(), top_k, seeds)
