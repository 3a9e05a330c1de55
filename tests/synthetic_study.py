"""Write a synthetic study that follows docs/contracts.md "Storage conventions".

Used by the aggregation tests and ``benchmarks/bench_aggregate.py`` so they need no sweep.
Curves are made-up but deterministic given ``seed``; the AUC stored as the trial value is
``agent.metrics.normalized_auc`` of the success curve, as a real trial does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import optuna
from optuna.distributions import CategoricalDistribution
from optuna.trial import TrialState

from agent.metrics import normalized_auc

#: metric keys reported by a sawyer_door trial (docs/contracts.md, "One trial")
DOOR_METRICS = (
    "success_rate",
    "angle_success_rate",
    "hand_success_rate",
    "final_angle_distance",
    "final_hand_distance",
)
SAC_CHOICES = {"lr": (1e-3, 5e-4, 1e-4), "hidden_sizes": ("256x256", "512x512")}


@dataclass(frozen=True)
class Special:
    """Which keys get the unusual fates the aggregation must handle (None: no such key)."""

    diverged: str | None = None  # COMPLETE, outcome "diverged", zeros after diverged_step
    reaped: str | None = None  # a FAIL attempt left by a dead driver, then a COMPLETE re-run
    failed: str | None = None  # FAIL after the retries, partial curve
    running: str | None = None  # RUNNING, partial curve, no value


def write_synthetic_study(
    storage_url: str,
    study_name: str = "synthetic",
    *,
    methods: tuple[str, ...] = ("pixel", "vae"),
    configs: int = 4,
    seeds: tuple[int, ...] = (0,),
    steps: tuple[int, ...] = (0, 1000, 2000, 3000, 4000),
    special: Special | None = None,
    seed: int = 0,
    env: str = "sawyer_door",
    random_success: float | None = None,
) -> optuna.Study:
    """Create ``study_name`` with one trial per (method, config_id, seed) and return it.

    ``special=None`` puts one of each special fate on a different key (needs >= 2 methods
    and >= 2 configs). Methods get increasing skill, so later methods score higher.
    ``random_success``: the random agent's success rate, stored as the driver stores it
    (study attr ``random_agent``); None: not measured.
    """
    if special is None:
        special = Special(
            diverged=f"{methods[-1]}/0/{seeds[0]}",
            reaped=f"{methods[0]}/1/{seeds[0]}",
            failed=f"{methods[1]}/1/{seeds[0]}",
            running=f"{methods[-1]}/{configs - 1}/{seeds[0]}",
        )
    rng = np.random.default_rng(seed)
    grid = np.asarray(steps, dtype=np.float64)
    plan = [f"{m}/{c}/{s}" for m in methods for c in range(configs) for s in seeds]
    study = optuna.create_study(storage=storage_url, study_name=study_name, direction="maximize")
    study.set_user_attr("env", env)
    if random_success is not None:
        study.set_user_attr("random_agent", {"episodes": 100, "success_rate": random_success})
    study.set_user_attr("metric_names", list(DOOR_METRICS))
    study.set_user_attr("plan", plan)
    study.set_user_attr("plan_hash", "synthetic")
    sac = [{k: v[int(rng.integers(len(v)))] for k, v in SAC_CHOICES.items()} for _ in plan]
    trials = []
    for index, key in enumerate(plan):
        method, config_id, trial_seed = key.split("/")
        skill = 0.3 + 0.4 * methods.index(method) / max(len(methods) - 1, 1)
        params = dict(sac[int(config_id)])
        distributions = {k: CategoricalDistribution(SAC_CHOICES[k]) for k in params}
        fit = {}
        if method == "vae":
            params["vae.beta"] = float(rng.choice([1.0, 5.0]))
            distributions["vae.beta"] = CategoricalDistribution((1.0, 5.0))
            collapsed = params["vae.beta"] == 5.0  # what the trial's fit gave: beta 5 collapsed
            fit = {
                "latent_dim": 8,
                "active_dims": 0 if collapsed else 6,
                "kl": 0.0 if collapsed else 4.0,
            }
        progress = grid / grid[-1]
        success = np.clip(skill * progress + rng.normal(0, 0.05, grid.size), 0, 1).round(2)
        curve = {
            "step": [int(s) for s in steps],
            "success_rate": success,
            "angle_success_rate": np.clip(success + 0.1, 0, 1),
            "hand_success_rate": np.clip(success + 0.2, 0, 1),
            "final_angle_distance": 0.5 * (1 - success),
            "final_hand_distance": 0.2 * (1 - success),
        }
        attrs = {
            "method": method,
            "config_id": int(config_id),
            "seed": int(trial_seed),
            "key": key,
            "plan_hash": "synthetic",
            "attempts": 1,
            "outcome": "completed",
            "seconds": 60.0 * (1 + methods.index(method)) + int(config_id),
            "reward_scale": 40.0 if fit.get("active_dims") == 0 else 1.0,
        }
        if fit:
            attrs["encoder_fit"] = fit
        state, end = TrialState.COMPLETE, grid.size
        if key == special.diverged:
            alive = np.arange(grid.size) < grid.size // 2
            curve["success_rate"] = np.where(alive, success, 0.0)
            for name in DOOR_METRICS[1:]:
                curve[name] = np.where(alive, curve[name], np.nan)
            attrs.update(
                outcome="diverged", diverged_step=int(steps[grid.size // 2]), diverged_loss="nan"
            )
        if key == special.reaped:
            trials.append(
                _trial(
                    TrialState.FAIL,
                    params,
                    distributions,
                    {**attrs, "outcome": "failed", "error": "driver died"},
                    curve,
                    1,
                )
            )
            attrs["attempts"] = 2
        if key == special.failed:
            state, end = TrialState.FAIL, 2
            attrs.update(outcome="failed", error="RuntimeError: worker died", attempts=3)
        if key == special.running:
            state, end = TrialState.RUNNING, grid.size - 1
            del attrs["outcome"]
        trials.append(_trial(state, params, distributions, attrs, curve, end))
        if index % 500 == 499:  # bounded memory for big benchmark studies
            study.add_trials(trials)
            trials = []
    study.add_trials(trials)
    return study


def _trial(state, params, distributions, attrs, curve, end) -> optuna.trial.FrozenTrial:
    """A FrozenTrial with the first ``end`` points of ``curve`` reported."""
    reported = {k: [float(v) for v in np.asarray(curve[k])[:end]] for k in curve if k != "step"}
    reported["step"] = curve["step"][:end]
    success = reported["success_rate"]
    value = normalized_auc(curve["step"], success) if state == TrialState.COMPLETE else None
    return optuna.trial.create_trial(
        state=state,
        params=params,
        distributions=distributions,
        value=value,
        intermediate_values=dict(zip(reported["step"], success, strict=True)),
        user_attrs={**attrs, "curve": reported},
    )


def write_planned_study(
    storage_url: str,
    spec,
    *,
    final_success,
    seconds: float = 3600.0,
    random_success: float | None = 0.18,
    skip: frozenset[str] = frozenset(),
) -> None:
    """Create ``spec``'s study (a fetch_reach one: its trials report success_rate and
    final_distance) as the driver does (``StudyStore.sync`` of its plan: the spec, the
    plan, the constant params in ``fixed_params``, the varying ones and ``method`` as
    trial params), then complete every trial as a worker does, so a join over studies sees
    what a real one would. ``final_success(key)``: the trial's last success rate (its curve
    rises linearly to it over the spec's evaluation grid); ``skip``: keys left WAITING."""
    from sweeper.plan._entries import build_plan
    from sweeper.storage import StudyStore, open_storage

    plan = build_plan(spec)
    attrs = {  # as sweeper.run._launch.study_attrs, less the provenance
        "spec": spec.model_dump(mode="json"),
        "plan_hash": plan.hash,
        "plan": plan.keys(),
        "env": spec.env.name,
        "metric_names": ["success_rate", "final_distance"],
    }
    if random_success is not None:
        attrs["random_agent"] = {"episodes": 100, "success_rate": random_success}
    store = StudyStore.open_or_create(open_storage(storage_url), spec.study, attrs)
    steps = list(range(0, spec.budget.env_steps + 1, spec.budget.eval_every))
    for entry, trial in store.sync(plan.entries, plan.hash):
        if entry.key in skip:
            continue
        success = np.round(final_success(entry.key) * np.linspace(0, 1, len(steps)), 3)
        curve = {
            "step": steps,
            "success_rate": success.tolist(),
            "final_distance": (0.02 + 0.15 * (1 - success)).tolist(),
        }
        store.start(trial._trial_id)
        result = {"attempts": 1, "outcome": "completed", "seconds": seconds, "curve": curve}
        store.complete(trial._trial_id, normalized_auc(steps, success), result)
