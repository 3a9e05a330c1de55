"""Rewriting the trials a study recorded in an older format in today's
(``StudyStore.upgrade``, which ``sweeper publish`` runs on the copy it publishes).

Today (``sweeper.storage._params``, ``sweeper.storage._writer``): a plan key's trial has as
Optuna params the ones that vary and ``method``, the study's constants are kept once in
the study attr ``fixed_params``, and its curve and other machine-readable values (the worker,
machines, videos: ``SYSTEM_ATTRS``) are system attrs, each but the curve with a user attr in
words beside it (``shown``: what the dashboard's trial page shows). Before, a trial
registered every param (a constant as a param of one choice) and no ``method``, and kept
those values as user attrs, which the page showed as raw JSON. Readers accept both
(``trial_attr``); ``rewrite`` leaves one format, and nothing a reader gets changes: each
trial's params with the constants that apply to it (as ``sweeper.results._frame`` reads
them) are checked to be the same before and after, a value moves as the same JSON text,
and values, intermediate values, states and every other attr are not touched.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from sweeper.storage._attrs import CURVE_ATTR as CURVE
from sweeper.storage._attrs import SYSTEM_ATTRS, shown
from sweeper.storage._errors import StorageError
from sweeper.storage._params import METHOD_PARAM, applies_to, is_fixed, method_choices

if TYPE_CHECKING:
    from sqlalchemy.engine import Connection


@dataclass(frozen=True)
class Upgrade:
    """What ``rewrite`` changed."""

    params: int  # trials whose constants went to ``fixed_params``, and that got ``method``
    curves: int  # trials whose curve went from a user attr to a system attr
    values: int  # trials whose other ``SYSTEM_ATTRS`` did (a user attr in words left)
    fixed: dict[str, Any]  # the study's ``fixed_params`` after


def rewrite(
    connection: Connection, study_id: int, fixed: Mapping[str, Any], planned: Iterable[str]
) -> Upgrade:
    """Rewrite study ``study_id``'s old-format trials in ``connection``'s transaction;
    ``fixed``: its ``fixed_params`` attr now, ``planned``: its methods (from its plan).
    Raises StorageError, writing nothing, when a trial's params would read differently."""
    from optuna.distributions import (
        CategoricalDistribution,
        distribution_to_json,
        json_to_distribution,
    )
    from optuna.storages._rdb.models import (
        TrialModel,
        TrialParamModel,
        TrialSystemAttributeModel,
        TrialUserAttributeModel,
    )
    from sqlalchemy import delete, insert, select, update

    trials, params = TrialModel.__table__, TrialParamModel.__table__
    users, systems = TrialUserAttributeModel.__table__, TrialSystemAttributeModel.__table__
    ours = select(trials.c.trial_id).where(trials.c.study_id == study_id)
    attrs: dict[int, dict[str, str]] = {}  # trial id -> key, method, system attrs: JSON text
    wanted = users.c.key.in_(("key", "method", *SYSTEM_ATTRS))
    query = select(users.c.trial_id, users.c.key, users.c.value_json)
    for trial_id, key, text in connection.execute(query.where(users.c.trial_id.in_(ours), wanted)):
        attrs.setdefault(trial_id, {})[key] = text
    rows: dict[int, list[Any]] = {}  # trial id -> its param rows
    for row in connection.execute(select(params).where(params.c.trial_id.in_(ours))):
        rows.setdefault(row.trial_id, []).append(row)
    keyed = {t: json.loads(a.get("method", "null")) for t, a in attrs.items() if "key" in a}

    # the params: an old trial's constants go to ``fixed`` (as the writer keeps them), and
    # it gets ``method`` over the study's methods (the distribution its newer trials have)
    texts = {row.distribution_json for trial in rows.values() for row in trial}
    parsed = {text: json_to_distribution(text) for text in texts}

    def value(row: Any) -> Any:
        return parsed[row.distribution_json].to_external_repr(row.param_value)

    def constant(row: Any) -> bool:  # a categorical of one choice (sweeper writes no other)
        choices = getattr(parsed[row.distribution_json], "choices", None)
        return choices is not None and is_fixed(choices)

    old = [t for t in keyed if all(r.param_name != METHOD_PARAM for r in rows.get(t, []))]
    after = dict(fixed)
    dropped = set()
    for t in old:
        for row in filter(constant, rows.get(t, [])):
            name, mine = row.param_name, value(row)
            if name in after and _json(after[name]) != _json(mine):
                raise StorageError(
                    f"{_key(attrs[t])}: its constant {name}={mine!r} is not the study's "
                    f"{name}={after[name]!r}: it cannot be kept once per study"
                )
            after[name] = mine
            dropped.add(row.param_id)
    for t, method in keyed.items():  # what a reader gets, before and after
        before = {r.param_name: value(r) for r in rows.get(t, [])}
        kept = {r.param_name: value(r) for r in rows.get(t, []) if r.param_id not in dropped}
        before.pop(METHOD_PARAM, None)  # the method is the ``method`` column, not a param
        kept.pop(METHOD_PARAM, None)
        if _read(before, fixed, method) != _read(kept, after, method):
            raise StorageError(
                f"{_key(attrs[t])}: its params would read differently in today's format "
                "(a constant of another method, or one another trial lacks)"
            )
    existing = [r.distribution_json for rs in rows.values() for r in rs
                if r.param_name == METHOD_PARAM]  # fmt: skip
    choices = method_choices([*planned, *(m for m in keyed.values() if m is not None)])
    text = existing[0] if existing else distribution_to_json(CategoricalDistribution(choices))
    methods = json_to_distribution(text)
    added = []
    for t in old:
        if keyed[t] not in methods.choices:
            raise StorageError(
                f"{_key(attrs[t])}: method {keyed[t]!r} is not among the study's methods "
                f"{list(methods.choices)}"
            )
        added.append({"trial_id": t, "param_name": METHOD_PARAM,
                      "param_value": methods.to_internal_repr(keyed[t]),
                      "distribution_json": text})  # fmt: skip

    # the machine-readable values: the same JSON text, as system attrs (one already there
    # wins: its user attr is the words), and the words as the user attr (none for a curve)
    present = select(systems.c.trial_id, systems.c.key).where(
        systems.c.key.in_(SYSTEM_ATTRS), systems.c.trial_id.in_(ours)
    )
    have = set(connection.execute(present).tuples())
    old_values = [
        (t, k)
        for t, a in attrs.items()
        for k in sorted(SYSTEM_ATTRS & a.keys())
        if (t, k) not in have or k == CURVE
    ]  # a user attr curve is never words
    moved = [{"trial_id": t, "key": k, "value_json": attrs[t][k]} for t, k in old_values
             if (t, k) not in have]  # fmt: skip
    words = {(t, k): shown(k, json.loads(attrs[t][k])) for t, k in old_values}

    if dropped:
        connection.execute(delete(params).where(params.c.param_id.in_(dropped)))
    if added:
        connection.execute(insert(params), added)
    if moved:
        connection.execute(insert(systems), moved)
    for (t, k), text in words.items():
        where = (users.c.trial_id == t) & (users.c.key == k)
        if text is None:
            connection.execute(delete(users).where(where))
        else:
            connection.execute(update(users).where(where).values(value_json=json.dumps(text)))
    curves = {t for t, k in old_values if k == CURVE}
    values = {t for t, k in old_values if k != CURVE}
    return Upgrade(params=len(old), curves=len(curves), values=len(values),
                   fixed=dict(sorted(after.items())))  # fmt: skip


def _read(own: Mapping[str, Any], fixed: Mapping[str, Any], method: str | None) -> str:
    """A trial's params as a reader gets them: its own over the constants that apply to it
    (``sweeper.results._frame``), as JSON, so that 1, 1.0 and True stay apart."""
    constants = {k: v for k, v in fixed.items() if applies_to(k, method)}
    return _json({**constants, **own})


def _json(value: Any) -> str:
    return json.dumps(value, sort_keys=True)


def _key(attrs: Mapping[str, str]) -> str:
    """How a trial is named in an error: its plan key."""
    return json.loads(attrs["key"])
