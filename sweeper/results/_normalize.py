"""Normalised scores: each study's trial scores on one scale, so studies of different envs
can be pooled.

A study's anchors are its own: 0 is the random agent's success rate on the study's env
(measured once by the driver before the first trial, study attr ``random_agent``), 1 is the
best control method of the study (``agent.config.TRUE_REWARD_METHODS``: the state oracle
``state`` or the image control ``true_reward``, whichever the study has done trials of; the
best is the one with the higher IQM AUC). For a trial with AUC ``a`` and final success rate
``f`` (the success rate at the last evaluation):

    auc_norm   = (a - random) / (IQM AUC of the best control - random)
    final_norm = (f - random) / (IQM final success of the best control - random)

Both scores use the same zero (the random agent's rate: a curve that stays at it has AUC
equal to it) and the same control method, each at its own score. A study is not normalised,
and the report says why, when it has no random rate, no done control trial, or a control
that does no better than the random agent on either score (no scale).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import pandas as pd

from agent.config import TRUE_REWARD_METHODS
from sweeper.results._frame import scored, study_info
from sweeper.results._stats import iqm, normalize

#: the scores that are normalised, as columns of ``trial_scores``
SCORES = ("auc", "final_success")


@dataclass(frozen=True)
class Anchors:
    """The 0 and 1 of one study's normalised scores, or why it has none (``problem``)."""

    study: str
    env: str | None
    random: float | None  # the random agent's success rate (0)
    control: str | None  # the best control method (1)
    control_auc: float | None  # its IQM AUC
    control_final_success: float | None  # its IQM final success rate
    problem: str | None = None  # why the study is not normalised; None when it is

    def one(self, score: str) -> float | None:
        """The control's value of ``score`` (one of ``SCORES``)."""
        return self.control_auc if score == "auc" else self.control_final_success


def trial_scores(frame: pd.DataFrame) -> pd.DataFrame:
    """One row per scored trial (counted, COMPLETE, finite AUC): method, config_id, seed,
    key, ``auc`` and ``final_success`` (its success rate at its last evaluation step)."""
    rows = scored(frame).dropna(subset=["step"]).sort_values(["trial", "step"])
    last = rows.drop_duplicates("trial", keep="last")
    columns = ["trial", "method", "config_id", "seed", "key", "auc", "success_rate"]
    scores = last[columns].rename(columns={"success_rate": "final_success"})
    return scores.reset_index(drop=True)


def study_anchors(frame: pd.DataFrame, scores: pd.DataFrame | None = None) -> Anchors:
    """The study's anchors from its frame (``scores``: its ``trial_scores``, if computed)."""
    info = study_info(frame)
    scores = trial_scores(frame) if scores is None else scores
    random = (info.attrs.get("random_agent") or {}).get("success_rate")
    controls = {
        method: (float(iqm(part["auc"])), float(iqm(part["final_success"])))
        for method, part in scores.groupby("method")
        if method in TRUE_REWARD_METHODS
    }
    control = max(controls, key=lambda m: controls[m][0]) if controls else None
    auc, final = controls[control] if control else (None, None)
    anchors = Anchors(info.name, info.attrs.get("env"), random, control, auc, final)
    problem = None
    if random is None:
        problem = (
            "no random-agent success rate (study attr random_agent): the study was launched "
            "before the driver measured it, or with random_episodes: 0"
        )
    elif control is None:
        problem = (
            f"no control method ({' or '.join(TRUE_REWARD_METHODS)}) with a done trial, "
            "so no 1 on the scale"
        )
    elif min(auc, final) <= random:
        problem = (
            f"its best control {control} (IQM AUC {auc:.3f}, IQM final success {final:.3f}) "
            f"does no better than the random agent ({random:.3f}): no scale"
        )
    return dataclasses.replace(anchors, problem=problem)


def normalized_scores(scores: pd.DataFrame, anchors: Anchors) -> pd.DataFrame:
    """``scores`` (``trial_scores``) with ``<score>_norm`` columns for every score in
    ``SCORES``; an empty frame when the study has no anchors (``anchors.problem``)."""
    if anchors.problem is not None:
        return scores.iloc[:0].assign(**{f"{s}_norm": [] for s in SCORES})
    return scores.assign(
        **{
            f"{score}_norm": normalize(scores[score], anchors.random, anchors.one(score))
            for score in SCORES
        }
    )
