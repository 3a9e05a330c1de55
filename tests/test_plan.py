"""The equal-budget plan: paired SAC configs, exact counts, reproducible, hashed."""

from __future__ import annotations

import copy
import dataclasses
import re
from collections import Counter

import numpy as np
import pytest

from agent.config import SACConfig, TrialConfig
from encoders.options import default_space
from sweeper.plan._entries import build_plan
from sweeper.spec._models import parse_spec
from sweeper.spec._sampling import derive_rng, param_value, sample_configs, space_size

BASE = {
    "study": "p",
    "seed": 0,
    "env": {"name": "point_reach", "image_size": 32},
    "methods": {"pixel": {}, "state": {}, "linear": {"latent_dim": [16, 32, 64]}},
    "trials_per_method": 5,
    "seeds": [3, 1],
    "budget": {"env_steps": 1000, "seed_steps": 100, "eval_every": 500},
}
SAC_NAMES = list(default_space(SACConfig))


def plan_of(**changes):
    data = copy.deepcopy(BASE)
    data.update(changes)
    return build_plan(parse_spec(data))


def sac_part(entry):
    return {k: v for k, v in entry.params.items() if k in SAC_NAMES}


def test_exact_counts_keys_and_order():
    plan = plan_of()
    counts = Counter(e.method for e in plan.entries)
    assert counts == {"linear": 10, "pixel": 10, "state": 10}  # K x len(seeds) each
    order = [(e.method, e.config_id, e.seed) for e in plan.entries]
    assert order == sorted(order)
    assert len(set(plan.keys())) == 30
    assert plan.keys()[0] == "linear/0/1"
    for e in plan.entries:
        assert e.key == f"{e.method}/{e.config_id}/{e.seed}"
        assert e.config_id in range(5) and e.seed in (1, 3)


def test_sac_configs_are_shared_by_all_methods_and_seeds():
    plan = plan_of()
    by_config = {}
    for e in plan.entries:
        by_config.setdefault(e.config_id, []).append(sac_part(e))
    for config_id, sacs in by_config.items():
        assert all(s == sacs[0] for s in sacs), config_id
    # method params: one value per (method, config), the same for every seed
    linear = {(e.config_id, e.seed): e.params["linear.latent_dim"] for e in plan.entries
              if e.method == "linear"}  # fmt: skip
    assert all(linear[c, 1] == linear[c, 3] for c in range(5))
    # distinct SAC configs while the A.1 space (72 configs) has room
    assert len({tuple(sorted(s[0].items())) for s in by_config.values()}) == 5


def test_same_seed_same_plan_other_seed_other_plan():
    a, b = plan_of(), plan_of()
    assert a == b and a.hash == b.hash
    c = plan_of(seed=1)
    assert c.hash != a.hash
    assert [sac_part(e) for e in c.entries] != [sac_part(e) for e in a.entries]


def test_pinned_sample():
    """The sampling stream is part of the plan: changing it silently breaks resumes."""
    plan = plan_of(trials_per_method=3, methods={"pixel": {}}, seeds=[0])
    got = [
        (e.params["hidden_sizes"], e.params["lr"], e.params["init_temperature"])
        for e in plan.entries
    ]
    assert got == PINNED


PINNED = [("256x256", 0.001, 1.0), ("512x512", 0.0005, 1.0), ("256x256", 0.0001, 0.1)]


def test_adding_a_method_keeps_the_others_params():
    a = plan_of()
    b = plan_of(methods={**BASE["methods"], "conv": {"latent_dim": [8, 16]}})
    for e in a.entries:
        assert b.entries[b.keys().index(e.key)].params == e.params
    assert a.hash != b.hash


def test_hash_ignores_where_trials_run_but_not_what_they_compute():
    spec = parse_spec(copy.deepcopy(BASE))
    base = build_plan(spec).hash
    moved = spec.with_overrides(storage="sqlite:////tmp/o.db", address="auto", max_concurrent=7)
    assert build_plan(moved).hash == base
    runtime = copy.deepcopy(BASE) | {"execution": {"threads_per_trial": 2, "checkpoint_every": 9}}
    assert build_plan(parse_spec(runtime)).hash == base
    threaded = build_plan(spec.with_overrides(threads_per_trial=3))  # `--threads-per-trial 3`
    assert threaded.hash == base
    assert {entry.trial_config.threads for entry in threaded.entries} == {3}
    for change in (
        {"budget": {**BASE["budget"], "env_steps": 2000}},
        {"budget": {**BASE["budget"], "eval_episodes": 3}},
        {"env": {"name": "point_reach", "image_size": 48}},
        {"env": {**BASE["env"], "options": {"success_threshold": 0.1}}},
        {"seeds": [3]},
        {"sac": {"discount": 0.99}},
    ):
        assert plan_of(**change).hash != base, change


def test_params_choices_and_trial_config():
    spec = parse_spec(copy.deepcopy(BASE) | {"execution": {"threads_per_trial": 2}})
    plan = build_plan(spec)
    for e in plan.entries:
        assert set(e.params) == set(e.choices)
        for name, value in e.params.items():
            assert value in e.choices[name], name
            assert isinstance(value, bool | int | float | str)
        assert e.choices["hidden_sizes"] == ("256x256", "512x512", "1024x1024")
        assert e.choices["discount"] == (0.95,)  # fixed params are still params
        method_params = {k for k in e.params if "." in k}
        assert method_params == ({"linear.latent_dim"} if e.method == "linear" else set())
        tc = e.trial_config
        assert isinstance(tc, TrialConfig) and isinstance(tc.sac, SACConfig)
        assert (tc.method, tc.seed, tc.env, tc.image_size) == (e.method, e.seed, "point_reach", 32)
        assert param_value(tc.sac.hidden_sizes) == e.params["hidden_sizes"]
        assert tc.sac.lr == e.params["lr"]
        assert (tc.total_steps, tc.seed_steps, tc.eval_every) == (1000, 100, 500)
        assert tc.threads == 2
        assert tc.encoder_params == {k.split(".", 1)[1]: v for k, v in e.params.items()
                                     if "." in k}  # fmt: skip
        assert tc.checkpoint_dir == (
            f"runs/p/checkpoints/{plan.hash[:12]}/{e.method}/{e.config_id}/{e.seed}"
        )


def test_sample_configs_distinct_then_repeats():
    space = {"a": (1, 2, 3), "b": ("x",), "c": (True, False)}
    assert space_size(space) == 6
    configs = sample_configs(space, 6, np.random.default_rng(0))
    assert len({tuple(c.values()) for c in configs}) == 6  # the whole space, no repeat
    more = sample_configs(space, 13, np.random.default_rng(0))
    assert more[:6] == configs
    assert Counter(tuple(c.values()) for c in more).most_common(1)[0][1] == 3
    assert all(c["b"] == "x" for c in more)


def test_fixed_params_draw_nothing_and_streams_are_independent():
    a = sample_configs({"a": (1, 2, 3, 4)}, 3, np.random.default_rng(5))
    b = sample_configs({"a": (1, 2, 3, 4), "f": (9,)}, 3, np.random.default_rng(5))
    assert [c["a"] for c in a] == [c["a"] for c in b]
    draws = [derive_rng(0, s).integers(1 << 30) for s in ("sac", "method:vae", "method:cvae")]
    assert len(set(draws)) == 3
    assert derive_rng(0, "sac").integers(1 << 30) == draws[0]


def test_pinned_hash():
    """The hash covers every trial's config, SAC and method defaults included: a changed
    default or declaration order would orphan every study already running."""
    assert plan_of().hash == "13f1b8a9f4f85146d5cdceeae24f6825c2dd3916006690883ac3a5f894de0545"


def test_a_variant_runs_its_encoder_on_the_shared_configs_and_its_encoders_options():
    methods = {
        "conv": {"latent_dim": [8, 16, 32]},
        "conv_pytorch_init": {"encoder": "conv", "init": "pytorch", "latent_dim": [8, 16, 32]},
        "pixel": {},
    }
    plan = plan_of(methods=methods)
    by_key = {e.key: e for e in plan.entries}
    assert Counter(e.method for e in plan.entries) == {m: 10 for m in methods}
    for c in range(5):
        for seed in (1, 3):
            base, variant = by_key[f"conv/{c}/{seed}"], by_key[f"conv_pytorch_init/{c}/{seed}"]
            assert variant.trial_config.method == base.trial_config.method == "conv"
            assert sac_part(variant) == sac_part(base) == sac_part(by_key[f"pixel/{c}/{seed}"])
            # the encoder's stream: the same latent size per config, another init
            assert variant.trial_config.encoder_params == base.trial_config.encoder_params | {
                "init": "pytorch"
            }
            assert variant.params["conv_pytorch_init.init"] == "pytorch"
            assert variant.trial_config.checkpoint_dir.endswith(f"/conv_pytorch_init/{c}/{seed}")


def test_pinned_hashes_of_the_shipped_specs():
    """Specs without CONV kept their hashes when CONV got its init option (issue 20): the
    values are the ones the code before it gave; with CONV the trials changed, so did the
    hash (a study begun with PyTorch's init refuses to resume)."""
    from conftest import ROOT

    from sweeper.spec._models import load_spec, load_yaml

    ci = build_plan(load_spec(ROOT / "studies" / "ci.yaml"))
    assert ci.hash == "830e846cffc46202330169036592bb8d8f81b561df2e82df24eb736a5b768cd5"
    reach = load_yaml((ROOT / "studies" / "fetch_reach.yaml").read_text())
    for method in ("conv", "vgg"):
        del reach["methods"][method]
    no_conv = build_plan(parse_spec(reach)).hash
    assert no_conv == "bc734796c18ec7210c261d0741f23eb97ebae6ee880263b51961cd220ca86b28"
    conv = build_plan(parse_spec(reach | {"methods": {"conv": {}}})).hash
    assert conv != "d7c89eff6bb13755cadd5c47a4ad6db3385e403860177b1502d16143b8bba39b"  # before
    cpu = build_plan(load_spec(ROOT / "studies" / "fetch_reach_cpu.yaml"))
    assert cpu.hash == "1eb028c93daac2f4c3f53562124d592c64add2a8359c79fd4d255b827451a5c7"
    budget = build_plan(load_spec(ROOT / "studies" / "fetch_reach_budget.yaml"))
    assert budget.hash == "6473b5dd99e4566b1d71fd9022a60ec029626e4f74983baf5b20156931aba9a1"
    seeds = build_plan(load_spec(ROOT / "studies" / "fetch_reach_budget_seeds.yaml"))
    assert seeds.hash == "a29f526814456aab2fe9673407ff0828403567ab53efce07d76c8b45b9f12c4e"


def test_precision_bf16_is_part_of_the_plan_and_fp32_keeps_the_hash_of_before():
    """``precision: bf16`` reaches every trial and changes the plan hash; writing the
    default ``fp32`` gives the hash the spec had before the setting existed."""
    from conftest import ROOT

    from sweeper.spec._models import load_yaml

    text = load_yaml((ROOT / "studies" / "ci.yaml").read_text())
    before = "830e846cffc46202330169036592bb8d8f81b561df2e82df24eb736a5b768cd5"
    assert build_plan(parse_spec(text | {"precision": "fp32"})).hash == before
    bf16 = build_plan(parse_spec(text | {"precision": "bf16"}))
    assert bf16.hash != before
    assert {e.trial_config.precision for e in bf16.entries} == {"bf16"}
    assert {e.trial_config.precision for e in build_plan(parse_spec(text)).entries} == {"fp32"}


def test_a_method_fixes_sac_fields_and_stays_paired_with_every_study_of_its_space():
    """``methods.<name>.sac`` replaces those fields for that method only; every other
    sampled value of configuration i is configuration i's of a study without the method
    (the budget ladder pairs with fetch_reach_cpu by construction)."""
    from conftest import ROOT

    from sweeper.spec._models import load_spec

    cpu = build_plan(load_spec(ROOT / "studies" / "fetch_reach_cpu.yaml"))
    budget = build_plan(load_spec(ROOT / "studies" / "fetch_reach_budget.yaml"))
    before = {(e.method, e.config_id, e.seed): e for e in cpu.entries}
    fixed = {
        "pixel_tau01": {"critic_tau": 0.01},
        "pixel_b128": {"batch_size": 128},
        "pixel_b128x2": {"batch_size": 128, "updates_per_step": 2},
        "conv_b128": {"batch_size": 128},
    }
    assert len(budget.entries) == 24
    for entry in budget.entries:
        encoder = entry.trial_config.method
        old = before[(encoder, entry.config_id, entry.seed)]
        expected = dict(old.trial_config.sac.__dict__) | fixed.get(entry.method, {})
        if entry.method in fixed:
            assert entry.trial_config.sac.__dict__ == expected
            for name, value in fixed[entry.method].items():
                assert entry.params[name] == value
        assert entry.trial_config.encoder_params == old.trial_config.encoder_params
        assert entry.trial_config.seed == old.trial_config.seed
    # the follow-up on seeds 2 and 3 runs each of those trials' twins: configuration i is
    # the same SAC values and encoder options, only the seed differs
    seeds = build_plan(load_spec(ROOT / "studies" / "fetch_reach_budget_seeds.yaml"))
    twins = {(e.method, e.config_id): e for e in budget.entries}
    twins |= {(e.method, e.config_id): e for e in cpu.entries if e.method in ("pixel", "conv")}
    assert len(seeds.entries) == 32 and {e.seed for e in seeds.entries} == {2, 3}
    for entry in seeds.entries:
        twin = twins[(entry.method, entry.config_id)]
        assert entry.params == twin.params
        assert entry.trial_config == dataclasses.replace(
            twin.trial_config, seed=entry.seed, checkpoint_dir=entry.trial_config.checkpoint_dir
        )
    # the other methods of a study are untouched by a method's fixed values
    spec = parse_spec(
        BASE | {"methods": {"pixel": {}, "p2": {"encoder": "pixel", "sac": {"lr": 3e-4}}}}
    )
    plain = build_plan(parse_spec(BASE | {"methods": {"pixel": {}}}))
    both = build_plan(spec)
    assert [e.params for e in both.entries if e.method == "pixel"] == [
        e.params for e in plain.entries
    ]
    assert {e.params["lr"] for e in both.entries if e.method == "p2"} == {3e-4}
    # one distribution per param in the study: the fixed value joins the choices
    assert all(e.choices["lr"] == (*default_space(SACConfig)["lr"], 3e-4) for e in both.entries)


def test_sweeper_plan_says_each_method_s_gradient_samples_and_what_is_outside_a1():
    from conftest import ROOT

    from sweeper.plan.cli_plan import budget_lines
    from sweeper.spec._models import load_spec

    spec = load_spec(ROOT / "studies" / "fetch_reach_budget.yaml")
    lines = budget_lines(spec, build_plan(spec))
    assert (
        lines[0] == "gradient samples per env step (batch x updates per step; A.1: 256 x 2 = 512):"
    )
    rows = {line.split()[0]: line for line in lines[1:]}
    assert "32 x 1 = 32  (1/16 of A.1)" in rows["pixel_tau01"]
    assert "critic_tau 0.01 (A.1: 0.005 | 0.001)" in rows["conv_tau01"]
    assert "128 x 1 = 128  (1/4 of A.1)" in rows["conv_b128"]
    assert "128 x 2 = 256  (1/2 of A.1)" in rows["pixel_b128x2"]
    assert "critic_tau" not in rows["pixel_b128x2"]  # A.1's own choices are not marked
    assert "updates_per_step" not in rows["pixel_b128x2"]  # the variant's 2 is A.1's
    assert rows["every"] == (
        "  every method, outside A.1: buffer_capacity 100000 (A.1: 1000000), num_filters 16 "
        "(A.1: 32)"
    )
    cpu = load_spec(ROOT / "studies" / "fetch_reach_cpu.yaml")
    assert all("(1/16 of A.1)" in line for line in budget_lines(cpu, build_plan(cpu))[1:-1])


@pytest.mark.parametrize("native", [[], ["avx512_bf16"]])
def test_sweeper_plan_shows_the_precision_and_warns_where_bf16_is_not_native(
    monkeypatch: pytest.MonkeyPatch, native: list[str]
) -> None:
    """fp32: one line. bf16 on a CPU without native bf16: a warning with the ratio of one
    trial's calibrated time in bf16 to its time in fp32, both calibrated here."""
    from conftest import ROOT

    from agent import machine
    from sweeper.plan._estimate import estimate_trials
    from sweeper.plan.cli_plan import precision_lines
    from sweeper.spec._models import load_yaml

    text = load_yaml((ROOT / "studies" / "ci.yaml").read_text())
    fp32 = parse_spec(text)
    assert precision_lines(fp32, [], {}) == ["precision: fp32"]
    monkeypatch.setattr(machine, "native_bf16", lambda: native)
    spec = parse_spec(text | {"precision": "bf16"})
    entries = list(build_plan(spec).entries)
    lines = precision_lines(spec, entries, estimate_trials(entries, {}, seconds_per_part=0.05))
    assert lines[0].startswith("precision: bf16 autocast")
    if native:
        assert len(lines) == 1
    else:
        (warning,) = lines[1:]
        assert re.fullmatch(
            r"warning: this CPU has no native bf16 \(no AMX, no AVX512-BF16\): a linear trial "
            r"in bf16 takes \d+\.\dx its time in fp32 here; set precision: fp32",
            warning,
        ), warning


@pytest.mark.parametrize(
    ("fp32", "bf16"),
    [
        ("fetch_reach_cpu", "fetch_reach_bf16"),
        ("point_reach_precision", "point_reach_precision_bf16"),
    ],
)
def test_each_bf16_study_is_its_fp32_study_s_trials_in_bf16(fp32: str, bf16: str) -> None:
    """Every trial of the bf16 study is the trial of the same key in its fp32 twin, in
    every value but the precision, so the report pairs them."""
    from conftest import ROOT

    from sweeper.spec._models import load_spec

    def trials(name: str) -> dict[str, TrialConfig]:
        plan = build_plan(load_spec(ROOT / "studies" / f"{name}.yaml"))
        return {
            e.key: dataclasses.replace(e.trial_config, checkpoint_dir=None) for e in plan.entries
        }

    half, full = trials(bf16), trials(fp32)
    assert half and set(half) <= set(full)
    for key, config in half.items():
        assert config.precision == "bf16" and full[key].precision == "fp32"
        assert dataclasses.replace(config, precision="fp32") == full[key], key
