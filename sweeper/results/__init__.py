"""What a study shows: the read model of a study and everything drawn from it.

Reads a study only (the one write is the comparison card saved into it for
optuna-dashboard). Private modules: ``_frame`` (one row per trial, read once),
``_stats`` (pure statistics over arrays: IQM, bootstrap intervals, probability of
improvement), ``_tables``, ``_figures``, ``_report``, ``_pictures`` and ``_tiles``
(frames laid out as PNGs, shared with the diagnostics), ``_normalize``, ``_combined``
(several studies of one env), ``_budget`` (the same methods at several gradient budgets),
``_halving_replay``, ``_dashboard_card`` (the comparison saved into the study) and
``_live`` (that card refreshed after each trial). Commands: ``cli_aggregate``,
``cli_status``, ``cli_publish``.
"""

from sweeper.results._live import after_trial
from sweeper.results._tiles import env_views

__all__ = ["after_trial", "env_views"]
