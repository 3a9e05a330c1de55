"""The gradient budget as an axis of the result: studies of one env joined by encoder,
configuration and seed (``sweeper aggregate A.yaml B.yaml ...`` when they share an env).

A study such as ``fetch_reach_budget`` re-runs encoders of ``fetch_reach_cpu`` with SAC
fields fixed per method (``methods.<name>.sac``: a larger batch, more updates per env step,
another critic tau) on the same sampled configurations. Joined, each encoder has one row per
*setting*: the gradient samples per env step (batch_size x updates_per_step) as a fraction
of appendix A.1's 512, then every other SAC value outside A.1's choices that not all trials
of the join share ("1/16, critic_tau 0.01"); the departures they all share (num_filters 16)
are stated once instead of in every label. Settings come from each trial's own params.

Pairing: a method's *line* is its encoder with its option space (the stored spec's
``methods.<name>``): conv, conv_b128 and conv_tau01 are one line, conv_pytorch_init
(``init: pytorch``) another, "conv (init pytorch)". A line's trials count only on the
configurations that every setting of the line was planned on (in whichever study), with
every seed planned for them: configurations are a selection (fetch_reach_budget re-runs
fetch_reach_cpu's first two), seeds are replicates, so a follow-up study on new seeds
adds trials to the settings it runs without dropping the others' (each row says its n).
The first study is the reference: a study whose configuration i differs from the
reference's in a sampled SAC value (every SAC field but those some method fixes) or in a
shared line's encoder options, or whose env steps differ, is left out of the join with
the reason, rather than compared wrongly. The controls (``TRUE_REWARD_METHODS``) have no
encoder: their level is reported beside the table, on the configurations every encoder
line is compared on.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from agent.config import TRUE_REWARD_METHODS
from sweeper.plan import A1_CHOICES, A1_SAMPLES
from sweeper.results._frame import (
    methods_of,
    random_success,
    scored,
    study_info,
    trial_rows,
)
from sweeper.results._normalize import trial_scores
from sweeper.results._stats import Group, Interval, iqm, mean, stratified_bootstrap
from sweeper.results._tables import (
    CONFIDENCE,
    RESAMPLES,
    paired_improvement,
    reserved_per_trial,
)
from sweeper.spec import param_value

#: the success rate a trial must reach at some evaluation to count as reaching the goal
SOLVED = 0.8
#: the SAC fields whose product is the gradient samples per env step
BUDGET_FIELDS = ("batch_size", "updates_per_step")
#: the columns of ``budget_table``
TABLE_COLUMNS = (
    "encoder",
    "setting",
    "samples_per_step",
    "fraction_of_a1",
    "departures",
    "methods",
    "n",
    "final_success_iqm",
    "final_success_iqm_low",
    "final_success_iqm_high",
    "auc_iqm",
    "auc_iqm_low",
    "auc_iqm_high",
    "reached",
    "median_final_distance",
    "cpu_hours",
    "versus",
    "p_improvement",
    "p_improvement_low",
    "p_improvement_high",
    "pairs",
)
CONTROL_COLUMNS = (
    "study",
    "method",
    "setting",
    "n",
    "final_success_iqm",
    "final_success_iqm_low",
    "final_success_iqm_high",
    "auc_iqm",
    "auc_iqm_low",
    "auc_iqm_high",
)


# ---- settings ------------------------------------------------------------------------


def a1_departures(values: Mapping[str, Any]) -> dict[str, Any]:
    """The SAC values outside A.1's choices, the gradient budget's fields aside (the
    fraction of A.1's samples says those)."""
    return {
        name: value
        for name, value in values.items()
        if name in A1_CHOICES and name not in BUDGET_FIELDS and value not in A1_CHOICES[name]
    }


def samples_per_step(values: Mapping[str, Any]) -> int | None:
    """Gradient samples per env step: batch_size x updates_per_step (None when a trial
    does not record them: no setting to place it at)."""
    if any(values.get(name) is None for name in BUDGET_FIELDS):
        return None
    return int(values["batch_size"]) * int(values["updates_per_step"])


def fraction_label(samples: int) -> str:
    """``samples`` as a fraction of A.1's gradient samples per env step: 32 -> "1/16"."""
    return str(Fraction(samples, A1_SAMPLES))


def setting_label(samples: int, departures: Mapping[str, Any]) -> str:
    """A setting's name: its fraction of A.1's samples, then its other departures from A.1
    (``"1/16, critic_tau 0.01"``)."""
    return ", ".join([fraction_label(samples), *(f"{k} {v}" for k, v in departures.items())])


# ---- one study's trials --------------------------------------------------------------


@dataclass(frozen=True)
class StudyTrials:
    """What the join needs of one study."""

    name: str
    env_steps: int | None  # the spec's budget.env_steps (else the last evaluation step)
    conditions: dict[str, Any]  # the stored spec's env and budget, "env.image_size": 84
    fixed_sac: frozenset[str]  # SAC fields some method of the study fixes
    lines: dict[str, str]  # method -> its line (``method_lines``), in the spec's order
    settings: dict[str, str]  # method -> its fixed SAC values and precision (``method_settings``)
    planned: dict[str, set[tuple[int, int]]]  # method -> its planned (config_id, seed)
    trials: pd.DataFrame  # ``study_trials``


def line_name(encoder: str, options: Mapping[str, Any]) -> str:
    """A method's line: its encoder, with the options whose choices depart from the
    encoder's declared defaults (``"conv (init pytorch)"``), so variants that search the
    same space share a line and a differently configured one does not."""
    from sweeper.spec import parse_method

    try:
        defaults = json.loads(json.dumps(parse_method(encoder, {}).space))
    except ValueError:  # an encoder this checkout does not know: name every option
        defaults = {}
    differ = [
        f"{name} {'|'.join(str(param_value(c)) for c in choices)}"
        for name, choices in options.items()
        if defaults.get(name, choices) != choices or name not in defaults
    ]
    return f"{encoder} ({', '.join(differ)})" if differ else encoder


def method_lines(frame: pd.DataFrame) -> dict[str, str]:
    """Each method's line (``line_name``; a control's is its name), in the spec's order,
    from the stored spec; a study without one (older, synthetic): the method name is the
    encoder."""
    declared = (study_info(frame).attrs.get("spec") or {}).get("methods") or {}
    lines = {}
    for method in methods_of(frame):
        stored = dict(declared.get(method) or {})
        encoder = stored.pop("encoder", method)
        stored.pop("sac", None)
        lines[method] = method if encoder in TRUE_REWARD_METHODS else line_name(encoder, stored)
    return lines


def method_settings(spec: Mapping[str, Any], methods: Sequence[str]) -> dict[str, str]:
    """Each method's setting as planned, from the stored spec: the study's SAC section with
    the method's own ``sac`` on top, and the precision (JSON). Two methods of one line with
    the same setting run the same SAC values on each configuration (the join checks that the
    sampled ones agree), whichever study they are in."""
    declared = spec.get("methods") or {}
    study_sac = spec.get("sac") or {}
    return {
        method: json.dumps(
            {
                "sac": study_sac | ((declared.get(method) or {}).get("sac") or {}),
                "precision": spec.get("precision", "fp32"),
            },
            sort_keys=True,
        )
        for method in methods
    }


def trial_outcomes(frame: pd.DataFrame) -> pd.DataFrame:
    """Per done trial (index ``trial``): auc, final_success (``trial_scores``),
    final_distance at the last evaluation, ``reached`` (success >= ``SOLVED`` at some
    evaluation, as benchmarks/thesis_result.py counts), ``cpu_s`` (its seconds x the CPUs
    reserved per trial, as ``compute_columns`` counts)."""
    outcomes = trial_scores(frame).set_index("trial")[["auc", "final_success"]]
    rows = scored(frame).dropna(subset=["step"]).sort_values(["trial", "step"])
    last = rows.drop_duplicates("trial", keep="last").set_index("trial")
    outcomes["final_distance"] = last.get("final_distance", np.nan)
    outcomes["reached"] = rows.groupby("trial")["success_rate"].max() >= SOLVED
    cpus, _ = reserved_per_trial(frame)
    outcomes["cpu_s"] = trial_rows(scored(frame)).set_index("trial")["seconds"] * cpus
    return outcomes


def study_trials(name: str, frame: pd.DataFrame) -> StudyTrials:
    """The search-stage ``frame`` of study ``name`` as the join reads it: one row per
    counted trial (done or not) with its study, method, line, config_id, seed, SAC values
    (``sac``, a dict), encoder options (``options``, a dict, names without the method),
    samples per env step, departures from A.1, and the ``trial_outcomes`` of a done one."""
    info = study_info(frame)
    trials = trial_rows(frame)
    trials = trials[trials["counted"]].set_index("trial")
    lines = method_lines(frame)
    spec = info.attrs.get("spec") or {}
    precision = spec.get("precision", "fp32")  # studies from before the setting: fp32
    other_precision = {} if precision == "fp32" else {"precision": precision}
    rows = []
    for number, trial in trials.iterrows():
        method = trial["method"]
        params = {c[len("params_") :]: v for c, v in trial.items() if c.startswith("params_")}
        sac = {k: v for k, v in params.items() if k in A1_CHOICES and pd.notna(v)}
        prefix = f"{method}."
        options = {k[len(prefix) :]: v for k, v in params.items() if k.startswith(prefix)}
        rows.append(
            {
                "trial": number,
                "study": name,
                "method": method,
                "line": lines.get(method, method),
                "control": method in TRUE_REWARD_METHODS,
                "config_id": int(trial["config_id"]),
                "seed": int(trial["seed"]),
                "sac": sac,
                "options": options,
                "samples": samples_per_step(sac),
                "departures": a1_departures(sac) | other_precision,
                "precision": precision,
            }
        )
    columns = ["trial", "study", "method", "line", "control", "config_id", "seed", "sac"]
    columns += ["options", "samples", "departures", "precision"]
    table = pd.DataFrame(rows, columns=columns).set_index("trial")
    table = table.join(trial_outcomes(frame)).reset_index()
    steps = (spec.get("budget") or {}).get("env_steps")
    if steps is None and frame["step"].notna().any():
        steps = int(frame["step"].max())
    conditions = {
        f"{section}.{k}": v
        for section in ("env", "budget")
        for k, v in (spec.get(section) or {}).items()
    }
    conditions.setdefault("budget.env_steps", steps)
    fixed = {k for m in (spec.get("methods") or {}).values() for k in (m or {}).get("sac", {})}
    planned: dict[str, set[tuple[int, int]]] = {}
    for key in info.attrs.get("plan") or trials["key"].tolist():
        method, config_id, seed = key.split("/")
        planned.setdefault(method, set()).add((int(config_id), int(seed)))
    settings = method_settings(spec, list(planned))
    return StudyTrials(name, steps, conditions, frozenset(fixed), lines, settings, planned, table)


# ---- the join ------------------------------------------------------------------------


def first_by_config(trials: pd.DataFrame, column: str, drop: frozenset[str]) -> dict:
    """Per config_id, ``column`` (a dict) of its first trial, without the keys ``drop``."""
    first = trials.sort_values("trial").drop_duplicates("config_id")
    return {
        int(c): {k: v for k, v in values.items() if k not in drop}
        for c, values in zip(first["config_id"], first[column], strict=True)
    }


def differences(mine: Mapping[str, Any], theirs: Mapping[str, Any]) -> list[str]:
    """``"name a (reference: b)"`` for each key whose values differ."""
    return [
        f"{k} {mine.get(k, '–')} (reference: {theirs.get(k, '–')})"
        for k in sorted(set(mine) | set(theirs))
        if mine.get(k) != theirs.get(k)
    ]


def pairing_problems(
    study: StudyTrials, reference: StudyTrials, fixed: frozenset[str]
) -> list[str]:
    """Why ``study``'s configurations are not ``reference``'s: its env or budget (env
    steps, evaluations) where they differ; per configuration both hold, the sampled SAC
    values (fields not in ``fixed``) and each shared line's encoder options that differ."""
    problems = differences(study.conditions, reference.conditions)
    mine = first_by_config(study.trials, "sac", fixed)
    theirs = first_by_config(reference.trials, "sac", fixed)
    for config_id in sorted(set(mine) & set(theirs)):
        for text in differences(mine[config_id], theirs[config_id]):
            problems.append(f"config {config_id}: SAC {text}")
    lines = set(study.trials["line"]) & set(reference.trials["line"])
    for line in sorted(lines):
        part = study.trials[study.trials["line"] == line]
        mine = first_by_config(part, "options", frozenset())
        part = reference.trials[reference.trials["line"] == line]
        theirs = first_by_config(part, "options", frozenset())
        for config_id in sorted(set(mine) & set(theirs)):
            for text in differences(mine[config_id], theirs[config_id]):
                problems.append(f"config {config_id}: {line} option {text}")
    return problems


def planned_by_setting(studies: Sequence[StudyTrials], line: str) -> list[set[tuple[int, int]]]:
    """Per setting of ``line`` (a line's name: an encoder line or a control), the
    (config_id, seed) pairs planned with it in any of ``studies``."""
    by_setting: dict[str, set[tuple[int, int]]] = {}
    for study in studies:
        for method, pairs in study.planned.items():
            if study.lines.get(method, method) == line:
                by_setting.setdefault(study.settings[method], set()).update(pairs)
    return list(by_setting.values())


def line_pairs(studies: Sequence[StudyTrials], line: str) -> set[tuple[int, int]]:
    """Where ``line``'s trials are compared: the configurations every setting of the line
    was planned on (in whichever study), with every seed any setting planned for them."""
    settings = planned_by_setting(studies, line)
    if not settings:
        return set()
    configs = set.intersection(*({c for c, _ in pairs} for pairs in settings))
    return {(c, s) for pairs in settings for c, s in pairs if c in configs}


def control_pairs(
    studies: Sequence[StudyTrials], control: str, configs: set[int] | None
) -> set[tuple[int, int]]:
    """A control's planned pairs (any study) on ``configs``, the configurations every
    encoder line is compared on (None: no encoder line, every configuration)."""
    planned = set().union(*planned_by_setting(studies, control))
    return {(c, s) for c, s in planned if configs is None or c in configs}


@dataclass(frozen=True)
class BudgetJoin:
    """Studies joined by encoder line, configuration and seed."""

    trials: pd.DataFrame  # joined trials (done or not) on their line's common pairs
    lines: tuple[str, ...]  # the encoder lines, in the studies' spec order
    studies: tuple[str, ...]  # the studies joined, the reference first
    left_out: dict[str, list[str]]  # study -> why it is not joined
    shared: tuple[str, ...]  # departures from A.1 every joined trial shares
    pairs: dict[str, set[tuple[int, int]]]  # line (a control: its name) -> its pairs
    env_steps: int | None
    unplaced: int = 0  # trials without batch_size / updates_per_step params, left out


def in_a1_order(values: Mapping[str, Any]) -> dict[str, Any]:
    """``values`` ordered as A.1's SAC fields (the precision after them), so a label reads
    the same in every study."""
    order = list(A1_CHOICES)
    rank = {name: i for i, name in enumerate(order)}
    return dict(sorted(values.items(), key=lambda item: rank.get(item[0], len(order))))


def join_studies(studies: Sequence[StudyTrials]) -> BudgetJoin:
    """Join ``studies`` (the first is the reference) by line, configuration and seed; label
    each trial's setting (columns ``setting``, ``on_line``: no departure but its budget)."""
    reference = studies[0]
    fixed = frozenset().union(*(s.fixed_sac for s in studies))
    left_out = {}
    for study in studies[1:]:
        problems = pairing_problems(study, reference, fixed)
        if problems:
            left_out[study.name] = problems
    joined = [s for s in studies if s.name not in left_out]
    trials = pd.concat([s.trials for s in joined], ignore_index=True)
    unplaced = int(trials["samples"].isna().sum())
    trials = trials[trials["samples"].notna()].astype({"samples": int})
    lines = dict.fromkeys(line for s in joined for line in s.lines.values())
    controls = {s.lines[m] for s in joined for m in s.lines if m in TRUE_REWARD_METHODS}
    pairs = {line: line_pairs(joined, line) for line in lines if line not in controls}
    compared = [{c for c, _ in p} for p in pairs.values()]
    configs = set.intersection(*compared) if compared else None
    pairs |= {line: control_pairs(joined, line, configs) for line in controls}
    keep = np.array(
        [
            (c, s) in pairs[line]
            for line, c, s in zip(trials["line"], trials["config_id"], trials["seed"], strict=True)
        ],
        dtype=bool,
    )
    trials = trials[keep].reset_index(drop=True)
    items = [set(d.items()) for d in trials["departures"]]
    shared = set.intersection(*items) if items else set()
    own = [in_a1_order(dict(d.items() - shared)) for d in trials["departures"]]
    fp32 = [{k: v for k, v in d.items() if k != "precision"} for d in own]
    trials = trials.assign(
        setting=[setting_label(n, d) for n, d in zip(trials["samples"], own, strict=True)],
        on_line=[not d for d in own],
        fp32_setting=[setting_label(n, d) for n, d in zip(trials["samples"], fp32, strict=True)],
    )
    return BudgetJoin(
        trials=trials,
        lines=tuple(line for line in lines if line not in controls),
        studies=tuple(s.name for s in joined),
        left_out=left_out,
        shared=tuple(f"{k} {v}" for k, v in in_a1_order(dict(shared)).items()),
        pairs=pairs,
        env_steps=reference.env_steps,
        unplaced=unplaced,
    )


# ---- statistics ----------------------------------------------------------------------


def iqm_intervals(groups: Mapping[str, pd.DataFrame], score: str, seed: int) -> dict[str, Interval]:
    """IQM of ``score`` with its 95 % bootstrap interval per group of trials; the trials
    of each study resampled among themselves (a setting joined from two studies keeps each
    study's weight)."""
    samples = {
        name: Group((part[score].to_numpy(),), part["study"].to_numpy())
        for name, part in groups.items()
    }
    return stratified_bootstrap(iqm, samples, reps=RESAMPLES, seed=seed, confidence=CONFIDENCE)


def setting_order(part: pd.DataFrame) -> list[str]:
    """A line's settings by samples per env step, the one with no other departure first."""
    settings = part.drop_duplicates("setting")
    ranked = sorted(
        zip(settings["samples"], ~settings["on_line"], settings["setting"], strict=True)
    )
    return [setting for *_, setting in ranked]


def lower_setting(setting: str, part: pd.DataFrame) -> str | None:
    """The setting ``setting`` is compared with: for one on the line the next lower one on
    it; for one with another departure (critic_tau 0.01) the one on the line with the same
    samples (else the next lower). None: the lowest."""
    first = part[part["setting"] == setting].iloc[0]
    line = part[part["on_line"]].drop_duplicates("setting")
    if first["on_line"]:
        below = line[line["samples"] < first["samples"]]
    else:
        below = line[line["samples"] <= first["samples"]]
    return None if below.empty else below.sort_values("samples")["setting"].iloc[-1]


def improvement_over_lower(done: pd.DataFrame, line: str, *, seed: int = 0) -> pd.DataFrame:
    """For each setting of ``line``: P(its AUC > the lower setting's AUC) on the same
    (config_id, seed), with interval and pairs (``paired_improvement``, as
    ``improvement_table``); columns setting, versus, probability, low, high, pairs."""
    part = done[done["line"] == line]
    names = {s: f"{line} @ {s}" for s in part["setting"]}
    comparisons = [(s, lower_setting(s, part)) for s in setting_order(part)]
    comparisons = [(names[x], names[y]) for x, y in comparisons if y is not None]
    wide = part.assign(arm=part["setting"].map(names)).pivot_table(
        index=["config_id", "seed"], columns="arm", values="auc"
    )
    table = paired_improvement(wide, comparisons, seed=seed)
    unnamed = {v: k for k, v in names.items()}
    return table.assign(
        setting=table["method"].map(unnamed), versus=table["versus"].map(unnamed)
    ).drop(columns="method")


def budget_table(join: BudgetJoin, *, seed: int = 0) -> pd.DataFrame:
    """Per encoder line and setting, over the joined done trials: n, IQM final success and
    IQM AUC with 95 % intervals, trials reaching ``SOLVED``, median final distance,
    CPU-hours, and the paired probability that this setting beats the lower one
    (``lower_setting``) on the same (config_id, seed)."""
    done = join.trials[~join.trials["control"] & join.trials["auc"].notna()]
    groups = {f"{line} @ {s}": p for (line, s), p in done.groupby(["line", "setting"])}
    final = iqm_intervals(groups, "final_success", seed)
    auc = iqm_intervals(groups, "auc", seed)
    rows = []
    for line in (line for line in join.lines if line in set(done["line"])):
        part = done[done["line"] == line]
        improvement = improvement_over_lower(done, line, seed=seed).set_index("setting")
        for setting in setting_order(part):
            mine = part[part["setting"] == setting]
            name, samples = f"{line} @ {setting}", int(mine["samples"].iloc[0])
            versus = improvement.loc[setting] if setting in improvement.index else None
            rows.append(
                {
                    "encoder": line,
                    "setting": setting,
                    "samples_per_step": samples,
                    "fraction_of_a1": samples / A1_SAMPLES,
                    "departures": setting.partition(", ")[2],
                    "methods": ", ".join(dict.fromkeys(mine["study"] + ": " + mine["method"])),
                    "n": len(mine),
                    **interval_columns("final_success_iqm", final[name]),
                    **interval_columns("auc_iqm", auc[name]),
                    "reached": int(mine["reached"].sum()),
                    "median_final_distance": float(mine["final_distance"].median()),
                    "cpu_hours": float(mine["cpu_s"].sum()) / 3600,
                    "versus": None if versus is None else versus["versus"],
                    "p_improvement": math.nan if versus is None else versus["probability"],
                    "p_improvement_low": math.nan if versus is None else versus["low"],
                    "p_improvement_high": math.nan if versus is None else versus["high"],
                    "pairs": 0 if versus is None else int(versus["pairs"]),
                }
            )
    return pd.DataFrame(rows, columns=TABLE_COLUMNS)


def interval_columns(name: str, interval: Interval) -> dict[str, float]:
    """``name``, ``name_low``, ``name_high`` of an interval."""
    return {
        name: float(interval.point),
        f"{name}_low": float(interval.low),
        f"{name}_high": float(interval.high),
    }


def controls_table(join: BudgetJoin, *, seed: int = 0) -> pd.DataFrame:
    """The controls' level beside the table: per study, control method and setting, IQM
    final success and IQM AUC with 95 % intervals over its done trials on its pairs
    (``control_pairs``)."""
    done = join.trials[join.trials["control"] & join.trials["auc"].notna()]
    keys = ["study", "method", "setting"]
    parts = dict(iter(done.groupby(keys, sort=False)))
    groups = {" @ ".join(key): part for key, part in parts.items()}
    final = iqm_intervals(groups, "final_success", seed)
    auc = iqm_intervals(groups, "auc", seed)
    rows = [
        {
            **dict(zip(keys, key, strict=True)),
            "n": len(part),
            **interval_columns("final_success_iqm", final[" @ ".join(key)]),
            **interval_columns("auc_iqm", auc[" @ ".join(key)]),
        }
        for key, part in parts.items()
    ]
    return pd.DataFrame(rows, columns=CONTROL_COLUMNS)


#: the columns of ``precision_table``
PRECISION_COLUMNS = (
    "line",
    "precision",
    "settings",
    "pairs",
    "final_success_difference",
    "final_success_difference_low",
    "final_success_difference_high",
    "auc_difference",
    "auc_difference_low",
    "auc_difference_high",
    "seconds_ratio",
)


def precision_table(join: BudgetJoin, *, seed: int = 0) -> pd.DataFrame:
    """Per line (a control: its name) and precision other than fp32: each done trial paired
    with its fp32 twin (the same line, config_id and seed, at the same setting but for the
    precision), the mean paired difference (this precision minus fp32) of final success
    and of AUC with 95 % bootstrap intervals, the pairs, the settings they span, and the
    ratio of the pairs' mean trial CPU seconds."""
    done = join.trials[join.trials["auc"].notna()]
    keys = ["line", "config_id", "seed", "fp32_setting"]
    fp32 = done[done["precision"] == "fp32"].drop_duplicates(keys)
    other = done[done["precision"] != "fp32"].drop_duplicates(keys)
    paired = other.merge(fp32, on=keys, suffixes=("", "_fp32"))
    groups = dict(iter(paired.groupby(["line", "precision"], sort=False)))
    differences = {
        f"{line} {precision}: {score}": Group(
            ((part[score] - part[f"{score}_fp32"]).to_numpy(dtype=float),)
        )
        for (line, precision), part in groups.items()
        for score in ("final_success", "auc")
    }
    intervals = stratified_bootstrap(
        mean, differences, reps=RESAMPLES, seed=seed, confidence=CONFIDENCE
    )
    rows = [
        {
            "line": line,
            "precision": precision,
            "settings": "; ".join(dict.fromkeys(part["fp32_setting"])),
            "pairs": len(part),
            **interval_columns(
                "final_success_difference", intervals[f"{line} {precision}: final_success"]
            ),
            **interval_columns("auc_difference", intervals[f"{line} {precision}: auc"]),
            "seconds_ratio": float(part["cpu_s"].mean() / part["cpu_s_fp32"].mean()),
        }
        for (line, precision), part in groups.items()
    ]
    return pd.DataFrame(rows, columns=PRECISION_COLUMNS)


# ---- the section of the combined report ---------------------------------------------


@dataclass(frozen=True)
class BudgetReport:
    """What ``budget_report`` computed and wrote."""

    join: BudgetJoin
    table: pd.DataFrame  # ``budget_table``
    controls: pd.DataFrame  # ``controls_table``
    precision: pd.DataFrame  # ``precision_table`` (empty: every joined study in fp32)
    files: tuple[Path, ...]
    markdown: str  # the section of report.md


def budget_report(
    frames: Sequence[tuple[str, pd.DataFrame]], out: Path, *, seed: int = 0
) -> BudgetReport:
    """Join the search-stage ``frames`` (``(study, frame)``, the reference first), write
    ``budget_table.csv``, ``budget_controls.csv``, ``budget.png`` and, where a joined trial
    ran in another precision than fp32, ``precision_table.csv`` to ``out``; return them
    with the report's section."""
    join = join_studies([study_trials(name, frame) for name, frame in frames])
    table = budget_table(join, seed=seed)
    controls = controls_table(join, seed=seed)
    precision = precision_table(join, seed=seed)
    random = random_success(frames[0][1])
    table.to_csv(out / "budget_table.csv", index=False)
    controls.to_csv(out / "budget_controls.csv", index=False)
    figure = draw_budget(table, controls, out / "budget.png", random)
    files = (out / "budget_table.csv", out / "budget_controls.csv", figure)
    markdown = budget_markdown(join, table, controls)
    if (join.trials["precision"] != "fp32").any():
        precision.to_csv(out / "precision_table.csv", index=False)
        files += (out / "precision_table.csv",)
        markdown += precision_markdown(precision)
    return BudgetReport(join, table, controls, precision, files, markdown)


#: colour and dashes of the controls' reference lines, apart from the encoders' colours
CONTROL_STYLES = (("0.1", "--"), ("0.4", (0, (6, 2, 1, 2))), ("0.25", (0, (2, 2))))


def draw_budget(
    table: pd.DataFrame, controls: pd.DataFrame, path: Path, random: float | None = None
) -> Path:
    """Final success (IQM, 95 % interval as error bars) against gradient samples per env
    step on a log2 axis: a line per encoder through its settings without another departure,
    those with one (critic_tau 0.01) as open squares beside it; the controls and the random
    agent as horizontal lines. Encoders are nudged apart on x so equal points stay visible."""
    from matplotlib.figure import Figure

    from sweeper.results._figures import random_label

    figure = Figure(figsize=(9.5, 5.2), layout="constrained")
    axes = figure.add_subplot()
    lines = list(dict.fromkeys(table["encoder"]))
    for index, line in enumerate(lines):
        part = table[table["encoder"] == line]
        nudge = 2 ** (0.05 * (index - (len(lines) - 1) / 2))
        on_line = part[part["departures"] == ""]
        n = "/".join(map(str, on_line["n"]))
        style = {"color": f"C{index % 10}", "capsize": 4}
        if len(on_line):
            x = on_line["samples_per_step"] * nudge
            point, error = _with_error(on_line)
            axes.errorbar(x, point, yerr=error, fmt="-o", label=f"{line} (n {n})", **style)
        for row in part[part["departures"] != ""].itertuples():  # beside the line, not on it
            label = f"{line}, {row.departures} (n {row.n})"
            x = row.samples_per_step * nudge * 1.12
            point, error = _with_error(part.loc[[row.Index]])
            axes.errorbar(x, point, yerr=error, fmt="s", mfc="white", label=label, **style)
    for index, row in enumerate(controls.itertuples()):
        style = CONTROL_STYLES[index % len(CONTROL_STYLES)]
        low, high = row.final_success_iqm_low, row.final_success_iqm_high
        axes.axhspan(low, high, color=style[0], alpha=0.07, lw=0)
        label = f"{row.method} ({row.study}, {row.setting}): {row.final_success_iqm:.2f}"
        axes.axhline(row.final_success_iqm, color=style[0], ls=style[1], lw=1.4, label=label)
    if random is not None:
        axes.axhline(random, color="0.35", ls=":", lw=1.2, label=random_label(random))
    ticks = sorted({*table["samples_per_step"], A1_SAMPLES})
    axes.axvline(A1_SAMPLES, color="0.6", ls="-.", lw=1, label=f"A.1: {A1_SAMPLES}")
    axes.set_xscale("log", base=2)
    axes.set_xticks(ticks, [f"{s}\n{fraction_label(s)}" for s in ticks])
    axes.minorticks_off()
    axes.set_ylim(-0.03, 1.03)
    axes.set_xlabel("gradient samples per env step (batch_size x updates_per_step; A.1's fraction)")
    axes.set_ylabel("final success rate (fraction of episodes)")
    axes.set_title(f"IQM final success, {CONFIDENCE:.0%} bootstrap CI, against the gradient budget")
    axes.grid(alpha=0.3)
    if len(table) or len(controls):
        axes.legend(fontsize="small", loc="upper left", bbox_to_anchor=(1.01, 1))
    else:
        axes.text(0.5, 0.5, "no joined trial done yet", ha="center", transform=axes.transAxes)
    figure.savefig(path, dpi=110)
    return path


def _with_error(rows: pd.DataFrame) -> tuple[pd.Series, np.ndarray]:
    """The IQM final success of ``rows`` and its interval as ``errorbar``'s ``yerr``
    (clipped at 0: a percentile interval need not contain the point)."""
    point = rows["final_success_iqm"]
    error = [point - rows["final_success_iqm_low"], rows["final_success_iqm_high"] - point]
    return point, np.maximum(0.0, np.asarray(error, dtype=float))


def pairs_text(pairs: set[tuple[int, int]]) -> str:
    """``"4 (configs 0, 1 x seeds 0, 1)"``: how many pairs, which configs and seeds."""
    configs = ", ".join(str(c) for c in sorted({c for c, _ in pairs}))
    seeds = ", ".join(str(s) for s in sorted({s for _, s in pairs}))
    return f"{len(pairs)} (configs {configs or '–'} x seeds {seeds or '–'})"


def budget_markdown(join: BudgetJoin, table: pd.DataFrame, controls: pd.DataFrame) -> str:
    """The report's section: how the studies were joined, the table, the controls, the
    figure."""
    from sweeper.results._report import MIN_RELIABLE, _fmt, _interval

    studies = ", ".join(f"`{s}`" for s in join.studies)
    steps = f"{join.env_steps:,} env steps" if join.env_steps else "the studies' env steps"
    lines = [
        "## Gradient budget: each encoder at each SAC setting",
        "",
        f"Studies joined by encoder, configuration and seed: {studies} (the first is the "
        f"reference), {steps}. A setting is the gradient samples per env step (batch_size x "
        f"updates_per_step) as a fraction of appendix A.1's {A1_SAMPLES}, then any other SAC "
        "value outside A.1's choices that not every trial here shares.",
    ]
    if join.shared:
        lines[-1] += f" Every trial here also departs from A.1 in: {', '.join(join.shared)}."
    lines += [
        "",
        "An encoder (a line: the encoder with its option space, so variants that only fix SAC "
        "fields share it) is compared only on the configurations every setting of it was "
        "planned on, in whichever study, with every seed planned for them (seeds are "
        "replicates: a study on new seeds adds trials to the settings it runs; each row says "
        "its n); configuration i is the same sampled SAC values and encoder options in every "
        "joined study (checked). Pairs per encoder: "
        + "; ".join(f"{line} {pairs_text(join.pairs[line])}" for line in join.lines)
        + ".",
    ]
    for study, problems in join.left_out.items():
        lines += [
            "",
            f"**`{study}` is left out of the join**: its configurations are not the "
            f"reference's ({'; '.join(problems)}).",
        ]
    if join.unplaced:
        lines += [
            "",
            f"{join.unplaced} trials record no batch_size or updates_per_step: left out.",
        ]
    lines += [
        "",
        f"| encoder | setting | samples / env step | trials | IQM final success "
        f"[{CONFIDENCE:.0%} CI] | IQM AUC [CI] | reaching {SOLVED} | median final distance "
        "| CPU-hours | P(AUC > lower setting) [CI] (pairs) |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for row in table.to_dict("records"):
        few = "*" if 0 < row["pairs"] < MIN_RELIABLE else ""
        versus = "–"
        if row["versus"] is not None and row["pairs"]:
            versus = (
                f"vs {row['versus']}: {_fmt(row['p_improvement'], 2)} "
                f"[{_fmt(row['p_improvement_low'], 2)}, {_fmt(row['p_improvement_high'], 2)}] "
                f"({row['pairs']}{few})"
            )
        lines.append(
            f"| {row['encoder']} | {row['setting']} | {row['samples_per_step']} | {row['n']} "
            f"| {_interval(row, 'final_success_iqm', 2)} | {_interval(row, 'auc_iqm')} "
            f"| {row['reached']} of {row['n']} | {_fmt(row['median_final_distance'])} "
            f"| {_fmt(row['cpu_hours'], 2)} | {versus} |"
        )
    if table.empty:
        lines.append("| no joined trial done yet |  |  |  |  |  |  |  |  |  |")
    controls_where = pairs_text(join.pairs[controls["method"].iloc[0]]) if len(controls) else "–"
    lines += [
        "",
        f"Final success: the success rate at the last evaluation; reaching {SOLVED}: at some "
        "evaluation. CPU-hours: the trials' wall seconds x the CPUs reserved per trial. "
        "P(AUC > lower setting): the paired probability that this setting's AUC beats the "
        "next lower setting's on the same (config_id, seed) (a setting with another "
        "departure: the one without it at the same samples), as the studies' improvement "
        f"tables compute it. \\* fewer than {MIN_RELIABLE} pairs: not reliable.",
        "",
        "Controls (no encoder: not rows of the table; on the configurations every encoder "
        f"is compared on, {controls_where}):",
        "",
        f"| study | control | setting | trials | IQM final success [{CONFIDENCE:.0%} CI] "
        "| IQM AUC [CI] |",
        "|---|---|---|---:|---:|---:|",
    ]
    for row in controls.to_dict("records"):
        lines.append(
            f"| {row['study']} | {row['method']} | {row['setting']} | {row['n']} "
            f"| {_interval(row, 'final_success_iqm', 2)} | {_interval(row, 'auc_iqm')} |"
        )
    if controls.empty:
        lines.append("| no done control trial |  |  |  |  |  |")
    lines += [
        "",
        "![final success against gradient samples per env step](budget.png)",
        "",
        "Data: `budget_table.csv`, `budget_controls.csv`.",
        "",
    ]
    return "\n".join(lines)


def precision_markdown(table: pd.DataFrame) -> str:
    """The report's section on the trials run in another precision than fp32."""
    from sweeper.results._report import MIN_RELIABLE, _fmt, _interval

    lines = [
        "## Precision: the same trials in bf16 and in fp32",
        "",
        "Per encoder line (and control): each done bf16 trial paired with its fp32 twin (the "
        "same configuration, seed and setting but for the precision), the mean paired "
        f"difference bf16 minus fp32 with its {CONFIDENCE:.0%} bootstrap interval; CPU time: "
        "the pairs' mean trial CPU seconds, bf16 / fp32 (the studies may have run on "
        f"different machines, or under different loads). \\* fewer than {MIN_RELIABLE} "
        "pairs: not reliable.",
        "",
        "| line | precision | settings (fp32) | pairs | final success difference [CI] "
        "| AUC difference [CI] | CPU time / fp32's |",
        "|---|---|---|---:|---:|---:|---:|",
    ]
    for row in table.to_dict("records"):
        few = "*" if row["pairs"] < MIN_RELIABLE else ""
        lines.append(
            f"| {row['line']} | {row['precision']} | {row['settings']} | {row['pairs']}{few} "
            f"| {_interval(row, 'final_success_difference', 2)} "
            f"| {_interval(row, 'auc_difference')} | {_fmt(row['seconds_ratio'], 2)} |"
        )
    if table.empty:
        lines.append("| no pair done in both precisions yet |  |  |  |  |  |  |")
    return "\n".join([*lines, "", "Data: `precision_table.csv`.", ""])
