"""Which of a plan entry's parameters become Optuna trial params, and where the rest live.

A plan entry carries every hyperparameter (``sweeper.plan.PlanEntry.params``, all of them in
the plan's hash). Only those the spec lets vary (more than one choice) are registered as
Optuna params, together with ``method`` (a categorical param over the study's methods): so
optuna-dashboard's hyperparameter importance and parallel-coordinate plot show what varies,
the method among it, and its trial table does not open with a dozen constant columns. The
constant ones (one choice) are kept once per study, in the study user attr
``FIXED_PARAMS_ATTR`` (``{name: value}``); readers (``sweeper.results._frame``) put them
back. Trials written before this keep every param, and readers accept both.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

#: the study user attr holding the constant params, ``{name: value}``
FIXED_PARAMS_ATTR = "fixed_params"
#: the Optuna param naming a trial's method (a categorical over the study's methods)
METHOD_PARAM = "method"

Params = Mapping[str, Any]
Choices = Mapping[str, Sequence[Any]]


def is_fixed(choices: Sequence[Any]) -> bool:
    """Whether a param with these choices is a constant of the study (one choice)."""
    return len(tuple(choices)) <= 1


def registered(
    params: Params, choices: Choices, method: str, methods: Sequence[str]
) -> tuple[dict[str, Any], dict[str, tuple[Any, ...]]]:
    """The params and choices a trial is registered with: the entry's params that vary,
    and ``method`` over ``methods``."""
    kept = {k: v for k, v in params.items() if not is_fixed(choices[k])}
    kept_choices = {k: tuple(choices[k]) for k in kept}
    kept[METHOD_PARAM] = method
    kept_choices[METHOD_PARAM] = tuple(methods)
    return kept, kept_choices


def fixed_params(entries: Iterable[tuple[Params, Choices]]) -> dict[str, Any]:
    """``{name: value}`` of every constant param of the ``(params, choices)`` of entries
    (a method's own constants are named ``<method>.<option>``, so names never clash)."""
    fixed: dict[str, Any] = {}
    for params, choices in entries:
        for name, value in params.items():
            if is_fixed(choices[name]):
                fixed[name] = value
    return dict(sorted(fixed.items()))


def method_choices(methods: Iterable[str]) -> tuple[str, ...]:
    """The choices of the ``method`` param: the study's methods, sorted (the same for every
    trial of the study whatever the spec's order or the stage)."""
    return tuple(sorted(set(methods)))


def applies_to(name: str, method: str | None) -> bool:
    """Whether a constant param ``name`` belongs to a trial of ``method``: a SAC param to
    every trial, ``<m>.<option>`` to the trials of method ``m`` only."""
    if "." not in name:
        return True
    return method is not None and name.split(".", 1)[0] == method
