"""The equal-budget plan: the finite, keyed list of trials a study owes.

``trials_per_method`` (K) SAC configurations are sampled once from the SAC search space
with the study seed and shared by every method (a paired design: config ``c`` of method A
and config ``c`` of method B differ only in the reward). Each method's own options are
sampled per config from a generator derived from (study seed, method name), so adding or
removing a method leaves the others' samples unchanged (a named variant of an encoder
draws from its encoder's stream). Every config runs once per seed.

One ``PlanEntry`` per ``(method, config_id, seed)``; each method has exactly
``K * len(seeds)`` entries. ``Plan.hash`` fingerprints everything that changes what the
trials compute (env, budget, every trial's parameters and seed), not where they run.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from agent.config import SACConfig, TrialConfig, curve_fields
from encoders.options import default_space
from sweeper.plan._halving import Schedule, rung_sizes
from sweeper.spec import StudySpec, derive_rng, param_value, sample_configs


@dataclass(frozen=True)
class PlanEntry:
    """One planned trial.

    ``params``: flat Optuna params (SAC fields by name, ``hidden_sizes`` as "256x256",
    method options as "<method>.<option>"); ``choices``: the categorical choices of each
    param (one choice for a fixed param); ``trial_config``: what ``agent.train`` runs.
    """

    method: str
    config_id: int
    seed: int
    key: str
    params: dict[str, bool | int | float | str]
    choices: dict[str, tuple[bool | int | float | str, ...]]
    trial_config: TrialConfig
    stage: str = "search"  # or "confirm": a re-run of a chosen config on a fresh seed


@dataclass(frozen=True)
class Plan:
    """The entries sorted by (method, config_id, seed), the plan's sha256 ``hash``, and
    its successive halving ``schedule`` (None: every trial runs the full budget)."""

    entries: tuple[PlanEntry, ...]
    hash: str
    schedule: Schedule | None = None

    def keys(self) -> list[str]:
        """The entries' keys ``"{method}/{config_id}/{seed}"``, in plan order."""
        return [e.key for e in self.entries]


#: appendix A.1's SAC settings (``SACConfig``'s defaults and search choices) and its
#: gradient samples per env step: batch 256 x 2 updates
A1 = SACConfig()
A1_SAMPLES = A1.batch_size * A1.updates_per_step
#: A.1's choices of every SAC field, as trial params hold them (layer sizes as "256x256")
A1_CHOICES = {
    name: tuple(param_value(c) for c in choices)
    for name, choices in default_space(SACConfig).items()
}


def outside_a1(values: Mapping[str, Any]) -> list[str]:
    """``"name value (A.1: choices)"`` for each SAC value not among A.1's choices."""
    return [
        f"{name} {param_value(value)} (A.1: {' | '.join(str(c) for c in A1_CHOICES[name])})"
        for name, value in values.items()
        if param_value(value) not in A1_CHOICES[name]
    ]


def trial_key(method: str, config_id: int, seed: int) -> str:
    """The key of one trial: ``"{method}/{config_id}/{seed}"``."""
    return f"{method}/{config_id}/{seed}"


def method_of(key: str) -> str:
    """The method of a plan key, a search key or a confirmation key."""
    return key.removeprefix(f"{CONFIRM}/").split("/")[0]


def in_spec_order(keys: Iterable[str], methods: Sequence[str]) -> list[str]:
    """Plan keys (or method names) with their methods in the order of ``methods``, the
    spec's (the order its author wrote them in, which every listing of methods follows; a
    plan sorts its entries by name, for its hash), each method's keys in their own order,
    other methods last."""
    place = {method: index for index, method in enumerate(methods)}
    return sorted(keys, key=lambda key: place.get(method_of(key), len(place)))


def run_order(entry: PlanEntry) -> tuple[int, int, str]:
    """The order a driver starts trials in: config by config, seed by seed, every method
    of a round together (so a study stopped early is still paired)."""
    return entry.config_id, entry.seed, entry.method


def sac_param_choices(spec: StudySpec) -> dict[str, tuple[bool | int | float | str, ...]]:
    """Each SAC param's choices in the study: the space's, and the values methods fix
    (``methods.<name>.sac``), so every trial registers one distribution per param."""
    choices = {name: [param_value(c) for c in cs] for name, cs in spec.sac.space().items()}
    for method in sorted(spec.methods):
        for name, value in spec.methods[method].sac.items():
            if param_value(value) not in choices[name]:
                choices[name].append(param_value(value))
    return {name: tuple(cs) for name, cs in choices.items()}


def build_plan(spec: StudySpec, study_uid: str | None = None) -> Plan:
    """Sample the plan of ``spec``; the same spec always gives the same plan and hash.

    Checkpoints: ``<checkpoints>/<folder>/<method>/<config_id>/<seed>``. A plan bound to a
    study (``study_uid``, the random id the study got when it was first driven) has the
    folder ``<study>-<study_uid>`` and names the study the checkpoints' owner, so a new
    database with the same spec never resumes another study's checkpoints; unbound, the
    folder is the plan hash's first 12 characters.
    """
    sac_space = spec.sac.space()
    sac_configs = sample_configs(sac_space, spec.trials_per_method, derive_rng(spec.seed, "sac"))
    sac_choices = sac_param_choices(spec)

    drafts = []  # (method, config_id, seed, params, choices, TrialConfig without checkpoint_dir)
    for method in sorted(spec.methods):
        encoder, space = spec.methods[method].encoder, spec.methods[method].space
        # a variant draws from its encoder's stream: where their spaces agree, its config c
        # has the encoder's options of config c (a paired ablation)
        method_configs = sample_configs(
            space, spec.trials_per_method, derive_rng(spec.seed, f"method:{encoder}")
        )
        choices = sac_choices | {f"{method}.{k}": cs for k, cs in space.items()}
        fixed_sac = spec.methods[method].sac
        for config_id, (sampled, options) in enumerate(
            zip(sac_configs, method_configs, strict=True)
        ):
            sac = sampled | fixed_sac  # the method's own SAC values replace the sampled ones
            params = {name: param_value(v) for name, v in sac.items()}
            params |= {f"{method}.{k}": v for k, v in options.items()}
            for seed in sorted(spec.seeds):
                config = TrialConfig(
                    env=spec.env.name,
                    image_size=spec.env.image_size,
                    method=encoder,
                    encoder_params=dict(options),
                    sac=SACConfig(**sac),
                    reward_scale=spec.reward_scale,
                    total_steps=spec.budget.env_steps,
                    seed_steps=spec.budget.seed_steps,
                    eval_every=spec.budget.eval_every,
                    eval_episodes=spec.budget.eval_episodes,
                    seed=seed,
                    # Ray does not hide GPUs from a trial that asked for none
                    device="auto" if spec.execution.gpus_per_trial else "cpu",
                    threads=spec.execution.threads_per_trial,
                    checkpoint_every=spec.execution.checkpoint_every,
                    env_kwargs=dict(spec.env.options),
                    video_steps=spec.video_steps,
                    precision=spec.precision,
                )
                drafts.append((method, config_id, seed, params, choices, config))

    canonical = [
        {
            "key": trial_key(method, config_id, seed),
            "params": params,
            "trial": curve_fields(config),
        }
        for method, config_id, seed, params, _, config in drafts
    ]
    document: dict[str, Any] = {"version": 1, "entries": canonical}
    schedule = None
    if spec.halving is not None:  # only then: a spec without it keeps its hash
        stops = (*spec.rungs, spec.budget.env_steps)
        sizes = rung_sizes(spec.trials_per_method, len(stops), spec.halving.keep)
        schedule = Schedule(stops, sizes, spec.halving.keep, spec.halving.rule)
        document["halving"] = {"stops": stops, "keep": schedule.keep, "rule": schedule.rule}
    text = json.dumps(document, sort_keys=True, separators=(",", ":"))
    plan_hash = hashlib.sha256(text.encode()).hexdigest()
    folder = plan_hash[:12] if study_uid is None else f"{spec.study}-{study_uid}"

    entries = tuple(
        PlanEntry(
            method=method,
            config_id=config_id,
            seed=seed,
            key=trial_key(method, config_id, seed),
            params=dict(params),
            choices=dict(choices),
            trial_config=dataclasses.replace(
                config,
                checkpoint_dir=f"{spec.checkpoint_dir}/{folder}/{method}/{config_id}/{seed}",
                checkpoint_owner=study_uid,
            ),
        )
        for method, config_id, seed, params, choices, config in drafts
    )
    return Plan(entries=entries, hash=plan_hash, schedule=schedule)


#: the first part of a confirmation key
CONFIRM = "confirm"


def confirm_key(method: str, config_id: int, seed: int) -> str:
    """The key of one confirmation trial: ``"confirm/{method}/{config_id}/{seed}"``."""
    return f"{CONFIRM}/{trial_key(method, config_id, seed)}"


def fresh_seeds(search_seeds: tuple[int, ...], count: int) -> tuple[int, ...]:
    """``count`` seeds the search did not use: the ones after its largest seed."""
    start = max(search_seeds) + 1
    return tuple(range(start, start + count))


def confirm_plan(search: Plan, configs: dict[str, list[int]], seeds: tuple[int, ...]) -> Plan:
    """The confirmation stage: each ``(method, config_id)`` of ``configs`` run again, with
    the same parameters, on every one of ``seeds`` (fresh: not the search's).

    Entries are the search plan's (the study-bound one, so checkpoints are the study's own)
    with the seed, key (``confirm_key``), stage and checkpoint folder
    (``<search folder>/confirm/<method>/<config_id>/<seed>``) replaced. The hash covers the
    search plan's hash and the keys, so a different choice is a different budget.
    """
    first = {}
    for entry in search.entries:
        first.setdefault((entry.method, entry.config_id), entry)
    entries = []
    for method in sorted(configs):
        for config_id in sorted(configs[method]):
            entry = first[(method, config_id)]
            root = (entry.trial_config.checkpoint_dir or "").rsplit("/", 3)[0]
            for seed in seeds:
                config = dataclasses.replace(
                    entry.trial_config,
                    seed=seed,
                    checkpoint_dir=f"{root}/{CONFIRM}/{method}/{config_id}/{seed}",
                )
                key = confirm_key(method, config_id, seed)
                entries.append(
                    dataclasses.replace(
                        entry, seed=seed, key=key, trial_config=config, stage=CONFIRM
                    )
                )
    text = json.dumps({"search": search.hash, "keys": [e.key for e in entries]})
    return Plan(entries=tuple(entries), hash=hashlib.sha256(text.encode()).hexdigest())
