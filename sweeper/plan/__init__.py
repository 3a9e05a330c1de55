"""A study's plan: which trials it runs, in what order, and what they cost here.

Private modules: ``_entries`` (the ``PlanEntry`` of each (method, config, seed) key, the
plan hash, pairing, the confirmation plan, A.1's gradient budget), ``_halving`` (paired
successive halving: rung sizes, promotion rules, the live ``Ladder``, the offline replay;
pure), ``_estimate`` (trial and wall time of a plan on this machine). ``cli_plan`` is the
``sweeper plan`` command.
"""

from sweeper.plan._entries import (
    A1_CHOICES,
    A1_SAMPLES,
    CONFIRM,
    Plan,
    PlanEntry,
    build_plan,
    confirm_key,
    confirm_plan,
    fresh_seeds,
    in_spec_order,
    run_order,
)
from sweeper.plan._estimate import (
    InBackground,
    TrialEstimate,
    format_duration,
    machine_at,
    makespan,
    summary_lines,
)
from sweeper.plan._halving import HALVING_ATTR, Curves, Ladder, auc_until

__all__ = [
    "A1_CHOICES",
    "A1_SAMPLES",
    "CONFIRM",
    "HALVING_ATTR",
    "Curves",
    "InBackground",
    "Ladder",
    "Plan",
    "PlanEntry",
    "TrialEstimate",
    "auc_until",
    "build_plan",
    "confirm_key",
    "confirm_plan",
    "format_duration",
    "fresh_seeds",
    "in_spec_order",
    "machine_at",
    "makespan",
    "run_order",
    "summary_lines",
]
