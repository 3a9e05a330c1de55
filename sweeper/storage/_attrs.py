"""Which trial attrs the driver keeps as Optuna system attrs, what the trial's page shows of
them instead, and how a reader gets them back (``trial_attr``).

optuna-dashboard shows a trial's user attrs on its page and in its trial table, each value
as ``json.dumps`` writes it; it never shows system attrs. So a machine-readable value (a
dict, a list of dicts, the curve) is written as a system attr, where Optuna's API
(``FrozenTrial.system_attrs``) and this project's readers (``trial_attr``,
``sweeper.storage._open.read_rows``) read it, and, under the same key, a user attr that says it in
words (``shown``), which no reader parses. Trials written before hold the value as a user
attr only; ``trial_attr`` reads both.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from optuna.trial import FrozenTrial

#: a trial's curve: ``{"step": [...], metric: [...], ...}``, every metric at every
#: evaluation (the success rate is also each step's intermediate value)
CURVE_ATTR = "curve"
#: trial attrs kept as Optuna system attrs: the curve (as a user attr it filled a cell of
#: the trial table with 1,024 characters of JSON), the worker (``{"node", "pid"}``), the
#: machines the runs were recorded on (a list of dicts, ``agent.machine``), the videos
#: (file name -> artifact id), the encoder's fit (a dict of numbers) and the worker deaths
#: a trial survived (a list of messages)
SYSTEM_ATTRS = frozenset({CURVE_ATTR, "worker", "machines", "videos", "encoder_fit",
                          "worker_deaths"})  # fmt: skip
#: the system attrs with no user attr in words beside them (the curve: the trial page
#: lists its intermediate values, the success rate at every evaluation)
UNSHOWN = frozenset({CURVE_ATTR})


def trial_attr(trial: FrozenTrial, key: str, default: Any = None) -> Any:
    """A trial attr as the driver wrote it: the system attr for ``SYSTEM_ATTRS`` (its user
    attr is words for people), else, or for a trial written before, the user attr."""
    if key in SYSTEM_ATTRS and key in trial.system_attrs:
        return trial.system_attrs[key]
    return trial.user_attrs.get(key, default)


def curve_of(trial: FrozenTrial) -> dict[str, list] | None:
    """The trial's curve (``CURVE_ATTR``), or None before its first evaluation."""
    return trial.system_attrs.get(CURVE_ATTR) or trial.user_attrs.get(CURVE_ATTR)


def describe_machine(machine: Mapping[str, Any]) -> str:
    """One line: CPU name and id, kernels, torch, conv layout, torch threads, GPU (a record
    of ``agent.machine``; a field older records lack is left out)."""
    layout = f", conv layout {machine['conv_layout']}" if "conv_layout" in machine else ""
    threads = machine.get("threads")
    threads = f", {threads} thread{'' if threads == '1' else 's'}" if threads else ""
    gpu = f", GPU {machine['gpu']}" if "gpu" in machine else ""
    return (
        f"{machine.get('cpu_name', '?')} ({machine.get('cpu', '?')}), kernels "
        f"{machine.get('kernels', '?')}, torch {machine.get('torch', '?')}{layout}{threads}{gpu}"
    )


def shown(key: str, value: Any) -> str | None:
    """What the trial's page shows for the system attr ``key``: ``value`` in words (None:
    nothing, ``UNSHOWN``). Machines: each with the step its runs were recorded from; the
    worker: its node and process; videos: their file names (the page plays them from the
    trial's artifacts); anything else: ``in_words``."""
    if key in UNSHOWN:
        return None
    if key == "machines" and isinstance(value, list):
        return "; ".join(
            f"from step {m.get('from_step', '?')}: {describe_machine(m)}"
            if isinstance(m, Mapping)
            else in_words(m)
            for m in value
        )
    if key == "worker" and isinstance(value, Mapping) and {"node", "pid"} <= value.keys():
        return f"pid {value['pid']} on {value['node']}"
    if key == "videos" and isinstance(value, Mapping):
        return ", ".join(map(str, value)) + " (the trial's artifacts)"
    return in_words(value)


def in_words(value: Any) -> str:
    """``value`` as a line a person reads: a mapping as ``key value, ...``, a list joined by
    "; ", a float to 4 significant digits, anything else as ``str`` does."""
    if isinstance(value, Mapping):
        return ", ".join(f"{k} {in_words(v)}" for k, v in value.items())
    if isinstance(value, list | tuple):
        return "; ".join(in_words(v) for v in value)
    if isinstance(value, float):
        return f"{value:.4g}" if math.isfinite(value) else str(value)
    return str(value)
