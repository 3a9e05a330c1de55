"""Study specs: the shipped studies load, bad specs fail naming the field, YAML traps."""

from __future__ import annotations

import copy
import dataclasses
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import pytest
import yaml
from conftest import ROOT

from agent.config import SACConfig
from encoders.options import VGGOptions, default_space, hyperparameters
from sweeper import cli
from sweeper.spec._models import SpecError, check_files, load_spec, load_yaml, parse_spec

SAC_DEFAULTS = default_space(SACConfig)
VGG_ENV = hyperparameters(VGGOptions)["weights_path"][2].env

BASE = {
    "study": "t",
    "env": {"name": "point_reach", "image_size": 32},
    "methods": {"pixel": {}, "state": {}},
    "trials_per_method": 2,
    "seeds": [0, 1],
    "budget": {"env_steps": 1000, "seed_steps": 100, "eval_every": 500},
}


def spaces(spec) -> dict:
    """Each method's search space."""
    return {name: method.space for name, method in spec.methods.items()}


def spec_text(change=None) -> str:
    data = copy.deepcopy(BASE)
    if change:
        change(data)
    return yaml.safe_dump(data, sort_keys=False)


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "spec.yaml"
    path.write_text(text)
    return path


@pytest.fixture
def vgg_weights(tmp_path, monkeypatch) -> Path:
    """A stand-in weights file: the spec only checks that it exists."""
    path = tmp_path / "vgg16.pth"
    path.write_bytes(b"not read by the spec")
    monkeypatch.setenv(VGG_ENV, str(path))
    return path


# ---- shipped studies ----------------------------------------------------------------------


@pytest.mark.parametrize("name", ["fetch_reach", "sawyer_door", "fetch_push", "quickstart", "ci"])
def test_shipped_studies_load(name, vgg_weights):
    spec = load_spec(ROOT / "studies" / f"{name}.yaml")
    assert spec.study == name
    assert spec.env.name in ("point_reach", name)
    if name in ("fetch_reach", "sawyer_door", "fetch_push"):
        encoders = {"pixel", "linear", "conv", "vae", "cvae", "vgg"}
        assert set(spec.methods) == encoders | {"true_reward", "state"}  # and the controls
        assert spec.sac.space() == SAC_DEFAULTS  # thesis appendix A.1
        assert spec.methods["vgg"].space["weights_path"] == (str(vgg_weights),)
    if name == "ci":
        assert len(spec.methods) * spec.trials_per_method_total == 2
    scale = {"fetch_reach": (20_000, 20), "sawyer_door": (1_000_000, 8)}
    if name in scale:
        assert (spec.budget.env_steps, spec.trials_per_method) == scale[name]


def test_checking_a_spec_imports_no_torch(vgg_weights):
    """The driver validates specs of every encoder without torch (start-up time, memory)."""
    code = (
        "import sys; from sweeper.run._launch import prepare, study_attrs; "
        "spec, plan = prepare(sys.argv[1]); study_attrs(spec, plan); "
        "assert 'torch' not in sys.modules, 'torch was imported'"
    )
    subprocess.run(
        [sys.executable, "-c", code, str(ROOT / "studies" / "fetch_reach.yaml")],
        cwd=ROOT,
        check=True,
    )


def test_defaults_and_properties():
    spec = parse_spec(copy.deepcopy(BASE))
    assert spec.storage_url == "sqlite:///runs/t/study.db"
    assert spec.run_dir == Path("runs/t")
    assert spec.checkpoint_dir == "runs/t/checkpoints"
    assert spec.trials_per_method_total == 4
    assert spec.execution.address is None and spec.execution.max_concurrent == 2
    assert spec.sac.space() == SAC_DEFAULTS
    assert spec.reward_scale == "auto"
    assert parse_spec({**copy.deepcopy(BASE), "reward_scale": 1}).reward_scale == 1.0
    with pytest.raises(Exception, match="frozen"):
        spec.study = "other"


def test_sac_space_covers_sac_config():
    fields = [f.name for f in dataclasses.fields(SACConfig)]
    assert list(SAC_DEFAULTS) == fields
    assert SAC_DEFAULTS == {  # thesis appendix A.1, and SACConfig's defaults where A.1 is silent
        "hidden_sizes": ((256, 256), (512, 512), (1024, 1024)),
        "discount": (0.95,),
        "init_temperature": (0.1, 1.0),
        "lr": (1e-3, 5e-4, 1e-4),
        "actor_update_every": (1, 2),
        "critic_tau": (0.005, 0.001),
        "batch_size": (256,),
        "updates_per_step": (2,),
        "buffer_capacity": (1_000_000,),
        "feature_dim": (50,),
        "num_filters": (32,),
        "image_pad": (4,),
    }
    assert SAC_DEFAULTS["lr"] == (1e-3, 5e-4, 1e-4)
    assert SAC_DEFAULTS["hidden_sizes"] == ((256, 256), (512, 512), (1024, 1024))
    for name in fields:  # the fixed defaults agree with SACConfig's own
        if len(SAC_DEFAULTS[name]) == 1:
            assert SAC_DEFAULTS[name][0] == getattr(SACConfig(), name), name


@pytest.mark.parametrize("name", [f.name for f in dataclasses.fields(SACConfig)])
def test_spec_and_sac_config_accept_the_same_values(name):
    """One declaration, one rule: a value is a valid SACConfig field iff it is a valid
    one-choice search space in a spec (updates_per_step=0 was one and not the other)."""
    if name == "hidden_sizes":
        values = ((8, 8), (0, 8), (8.0,), (), (True,), ("8",))
    else:
        values = (-1, 0, 0.5, 1, 1.5, 2, 2.0, True, "2", float("inf"), float("nan"), None)
    small_batch = {} if name == "batch_size" else {"batch_size": 1}  # <= any buffer_capacity
    for value in values:
        try:
            SACConfig(**small_batch, **{name: value})
            config_ok = True
        except ValueError:
            config_ok = False
        try:
            parse_spec({**copy.deepcopy(BASE), "sac": {**small_batch, name: [value]}})
            spec_ok = True
        except SpecError:
            spec_ok = False
        assert config_ok == spec_ok, (name, value)


def test_round_trip_through_json_dump(vgg_weights):
    # fetch_reach_cpu has a named variant, fetch_reach_budget methods fixing SAC fields
    for name in ("fetch_reach", "fetch_reach_cpu", "fetch_reach_budget"):
        spec = load_spec(ROOT / "studies" / f"{name}.yaml")
        assert parse_spec(spec.model_dump(mode="json")) == spec


def test_a_named_variant_is_its_encoder_with_fixed_options():
    data = copy.deepcopy(BASE)
    data["methods"] = {"conv": {}, "conv_pytorch_init": {"encoder": "conv", "init": "pytorch"}}
    spec = parse_spec(data)
    assert spec.methods["conv"].encoder == spec.methods["conv_pytorch_init"].encoder == "conv"
    assert spaces(spec) == {
        "conv": {"latent_dim": (128, 256), "init": ("drq",)},
        "conv_pytorch_init": {"latent_dim": (128, 256), "init": ("pytorch",)},
    }
    dumped = spec.model_dump(mode="json")["methods"]
    assert dumped["conv_pytorch_init"] == {
        "encoder": "conv",
        "latent_dim": [128, 256],
        "init": ["pytorch"],
    }
    assert "encoder" not in dumped["conv"]
    assert (
        parse_spec(data | {"methods": {"conv": {"encoder": "conv"}}}).methods["conv"]
        == (spec.methods["conv"])
    )


@pytest.mark.parametrize(
    ("methods", "error"),
    [
        ({"conv_x": {"encoder": "cnov"}}, r"methods\.conv_x\.encoder: a variant's encoder must be "
         r"an encoder name; did you mean 'conv'\?"),
        ({"conv_x": {"encoder": "state"}}, r"methods\.conv_x\.encoder: .*allowed: pixel, linear"),
        ({"conv_x": {"encoder": ["conv"]}}, r"methods\.conv_x\.encoder: .*got \['conv'\]"),
        ({"pixel": {"encoder": "conv"}}, r"methods\.pixel: 'pixel' is a method of its own"),
        ({"confirm": {"encoder": "conv"}}, r"methods\.confirm: a variant's name must be"),
        ({"conv/2": {"encoder": "conv"}}, r"methods\.conv/2: a variant's name must be"),
        ({"conv.2": {"encoder": "conv"}}, r"methods\.conv\.2: a variant's name must be"),
        ({"c" * 65: {"encoder": "conv"}}, r"a variant's name must be .*at most 64"),
        ({"conv_x": {"encoder": "conv", "init": "xavier"}},
         r"methods\.conv_x\.init\[0\]: Input should be one of \('drq', 'pytorch'\)"),
        ({"conv_x": {"init": "pytorch"}},
         r"methods\.conv_x: unknown method; .*or a named variant of an encoder"),
    ],
)  # fmt: skip
def test_bad_variants_are_named(methods, error):
    with pytest.raises(SpecError, match=error):
        parse_spec(copy.deepcopy(BASE) | {"methods": methods})


def test_a_method_fixes_sac_fields():
    data = copy.deepcopy(BASE)
    data["methods"] = {
        "pixel": {},
        "pixel_b128": {"encoder": "pixel", "sac": {"batch_size": 128, "hidden_sizes": [64, 64]}},
    }
    spec = parse_spec(data)
    assert spec.methods["pixel"].sac == {}
    assert spec.methods["pixel_b128"].sac == {"batch_size": 128, "hidden_sizes": (64, 64)}
    dumped = spec.model_dump(mode="json")["methods"]["pixel_b128"]
    assert dumped["sac"] == {"batch_size": 128, "hidden_sizes": [64, 64]}
    assert parse_spec(spec.model_dump(mode="json")) == spec


@pytest.mark.parametrize(
    ("sac", "error"),
    [
        ({"batch_sise": 128}, r"^spec: methods\.p\.sac\.batch_sise: unknown SAC field; "
         r"did you mean 'batch_size'\?"),
        ({"batch_size": 0}, r"^spec: methods\.p\.sac\.batch_size: .*greater than or equal to 1"),
        ({"batch_size": 2.0}, r"^spec: methods\.p\.sac\.batch_size: .*valid integer"),
        ({"critic_tau": "0.01"}, r"^spec: methods\.p\.sac\.critic_tau: .*valid number"),
        ({"critic_tau": [0.01, 0.02]}, r"methods\.p\.sac\.critic_tau: a method fixes one value"),
        ({"batch_size": 5000}, r"methods\.p\.sac\.batch_size: batch_size 5000 > "
         r"buffer_capacity 1000"),
        ([], r"methods\.p\.sac: must be a mapping of SAC fields"),
        ({}, r"methods\.p\.sac: must be a mapping of SAC fields"),
    ],
)  # fmt: skip
def test_bad_method_sac_fields_are_named(sac, error):
    data = copy.deepcopy(BASE)
    data["sac"] = {"buffer_capacity": 1000}
    data["methods"] = {"p": {"encoder": "pixel", "sac": sac}}
    with pytest.raises(SpecError, match=error) as caught:
        parse_spec(data)
    assert "\n" not in str(caught.value)


def test_overrides_are_validated():
    spec = parse_spec(copy.deepcopy(BASE))
    other = spec.with_overrides(storage="sqlite:////tmp/x.db", address="auto", max_concurrent=4)
    assert other.storage_url == "sqlite:////tmp/x.db"
    assert (other.execution.address, other.execution.max_concurrent) == ("auto", 4)
    assert spec.with_overrides() == spec
    with pytest.raises(SpecError, match=r"execution\.max_concurrent"):
        spec.with_overrides(max_concurrent=0)
    # threads reserve as many CPUs a trial, never fewer than the spec reserves
    threaded = spec.with_overrides(threads_per_trial=2).execution
    assert (threaded.threads_per_trial, threaded.cpus_per_trial) == (2, 2)
    roomy = parse_spec(copy.deepcopy(BASE) | {"execution": {"cpus_per_trial": 4}})
    assert roomy.with_overrides(threads_per_trial=2).execution.cpus_per_trial == 4
    with pytest.raises(SpecError, match=r"execution\.threads_per_trial"):
        spec.with_overrides(threads_per_trial=0)
    with pytest.raises(SpecError, match="storage"):
        spec.with_overrides(storage="not a url")


def test_true_reward_controls_are_methods_without_options():
    data = copy.deepcopy(BASE)
    data["methods"] = {"true_reward": {}, "state": None, "pixel": {}}
    assert spaces(parse_spec(data)) == {"true_reward": {}, "state": {}, "pixel": {}}
    data["methods"] = {"true_reward": {"latent_dim": 8}}
    with pytest.raises(SpecError, match=r"methods\.true_reward\.latent_dim.*allowed: none"):
        parse_spec(data)


def test_method_spaces_merge_defaults_and_encoder_options(vgg_weights):
    from encoders import encoder_names, encoder_options

    for name in encoder_names():  # every default option is one the encoder accepts
        options = [f.name for f in dataclasses.fields(encoder_options(name))]
        assert set(default_space(encoder_options(name))) <= set(options), name
    vae = {
        "latent_dim": (8, 16),
        "beta": (1.0, 5.0, 20.0),
        "lr": (1e-3, 3e-4),
        "epochs": (10, 30),
        "num_images": (1000, 5000),
        "batch_size": (64,),
    }
    data = copy.deepcopy(BASE)
    data["methods"] = {name: {} for name in (*encoder_names(), "state", "true_reward")}
    assert spaces(parse_spec(data)) == {  # the default spaces, in the options' order
        "pixel": {},
        "linear": {"latent_dim": (128, 256)},
        "conv": {"latent_dim": (128, 256), "init": ("drq",)},
        "vae": vae,
        "cvae": vae,
        "vgg": {"weights_path": (str(vgg_weights),), "input_size": (224,)},
        "state": {},
        "true_reward": {},
    }
    assert [list(space) for space in spaces(parse_spec(data)).values()][3] == list(vae)
    data = copy.deepcopy(BASE)
    data["methods"] = {"vae": {"beta": [2, 4.5], "num_images": 300}, "linear": {}}
    spec = parse_spec(data)
    vae = spec.methods["vae"].space
    assert vae["beta"] == (2.0, 4.5) and all(isinstance(b, float) for b in vae["beta"])
    assert vae["num_images"] == (300,)
    assert vae["latent_dim"] == (8, 16)  # sweeper.spec._sampling default, thesis A.1
    assert spec.methods["linear"].space == {"latent_dim": (128, 256)}


def test_vgg_weights_from_env_var_or_spec(tmp_path, monkeypatch, vgg_weights):
    from encoders.options import VGG_WEIGHTS_ENV_VAR as WEIGHTS_ENV_VAR

    assert VGG_ENV == WEIGHTS_ENV_VAR  # the sweeper reads the variable the encoder reads
    data = copy.deepcopy(BASE)
    data["methods"] = {"vgg": {}}
    assert parse_spec(data).methods["vgg"].space["weights_path"] == (str(vgg_weights),)
    monkeypatch.delenv(VGG_ENV)
    # a spec reads without its files (sweeper status); where trials run they are checked
    assert "weights_path" not in parse_spec(data).methods["vgg"].space
    with pytest.raises(SpecError, match=rf"methods\.vgg\.weights_path: required.*{VGG_ENV}"):
        check_files(parse_spec(data), "spec")
    data["methods"] = {"vgg": {"weights_path": str(tmp_path / "missing.pth")}}
    with pytest.raises(SpecError, match=r"methods\.vgg\.weights_path: file not found"):
        check_files(parse_spec(data), "spec")
    data["execution"] = {"address": "auto"}  # a cluster: the file lives on the workers
    assert parse_spec(data).methods["vgg"].space["weights_path"] == (str(tmp_path / "missing.pth"),)
    assert check_files(parse_spec(data), "spec") == frozenset()


def test_a_spec_file_over_a_mebibyte_is_refused_before_it_is_parsed(tmp_path):
    path = write(tmp_path, spec_text() + "# " + "x" * (1 << 20) + "\n")
    with pytest.raises(SpecError, match=r"a spec file must be at most 1 MiB, got 1\.0 MiB"):
        load_spec(path)


def test_yaml_follows_the_1_2_core_schema():
    data = load_yaml(
        "a: 1e-4\nb: 010\nc: no\nd: 1_000_000\ne: 0x10\nf: 2024-01-01\ng: 1:30\nh: ~\ni: True\n"
    )
    assert data == {
        "a": 1e-4,
        "b": 10,
        "c": "no",
        "d": 1_000_000,
        "e": 16,
        "f": "2024-01-01",
        "g": "1:30",
        "h": None,
        "i": True,
    }
    assert isinstance(data["a"], float) and isinstance(data["b"], int)
    # merge keys are not duplicates: an explicit key overrides the merged one
    assert load_yaml("x: &a {k: 1}\ny:\n  <<: *a\n  k: 2\n")["y"] == {"k": 2}


def test_light_imports():
    code = (
        "import sys, sweeper.spec, sweeper.plan, agent.envs; "
        "print([m for m in ('torch', 'mujoco', 'ray', 'optuna') if m in sys.modules])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.stdout.strip() == "[]", out.stderr


# ---- malformed specs ---------------------------------------------------------------------------


def _set(path: str, value):
    """A change that sets the dotted ``path`` of the spec dict to ``value``."""

    def change(data):
        *parents, last = path.split(".")
        for p in parents:
            data = data.setdefault(p, {})
        data[last] = value

    return change


def _drop(path: str):
    def change(data):
        *parents, last = path.split(".")
        for p in parents:
            data = data[p]
        del data[last]

    return change


def aliases(levels: int, n: int = 9) -> str:
    """YAML for ``sac.lr``: a flow list of anchors, each of ``n`` aliases of the one before,
    ``levels`` deep (``n ** levels`` values once expanded); a billion at 9 levels."""
    items = ["&a0 [0.001]"]
    items += [f"&a{i} [{', '.join([f'*a{i - 1}'] * n)}]" for i in range(1, levels + 1)]
    return f"sac:\n  lr: [{', '.join(items)}]\n"


#: a list nested 10,000 deep, in a field
DEEP = "sac:\n  lr: " + "[" * 10_000 + "0.001" + "]" * 10_000 + "\n"

# (id, YAML text, the dotted path the message must name, words of what is allowed)
BAD_SPECS = [
    ("missing study", spec_text(_drop("study")), "study", "required"),
    ("missing env name", spec_text(_drop("env.name")), "env.name", "ENV_NAMES"),
    ("missing budget", spec_text(_drop("budget")), "budget", "env_steps"),
    ("missing K", spec_text(_drop("trials_per_method")), "trials_per_method", ">= 1"),
    (
        "unknown top key",
        spec_text(_set("trails_per_method", 3)),
        "trails_per_method",
        "did you mean 'trials_per_method'",
    ),
    ("unknown sac key", spec_text(_set("sac.lrr", 0.1)), "sac.lrr", "did you mean 'lr'"),
    (
        "unknown env",
        spec_text(_set("env.name", "fetch_reech")),
        "env.name",
        "did you mean 'fetch_reach'",
    ),
    (
        "unknown method",
        spec_text(_set("methods", {"pixle": {}})),
        "methods.pixle",
        "did you mean 'pixel'",
    ),
    ("no methods", spec_text(_set("methods", {})), "methods", "allowed: pixel"),
    ("methods as list", spec_text(_set("methods", ["pixel"])), "methods", "dictionary"),
    (
        "unknown method option",
        spec_text(_set("methods", {"conv": {"latent_dims": 8}})),
        "methods.conv.latent_dims",
        "did you mean 'latent_dim'",
    ),
    (
        "method option type",
        spec_text(_set("methods", {"vae": {"latent_dim": [8, "big"]}})),
        "methods.vae.latent_dim[1]",
        "valid integer, got 'big'",
    ),
    (
        "method option range",
        spec_text(_set("methods", {"vae": {"beta": -1}})),
        "methods.vae.beta[0]",
        "greater than 0, got -1",
    ),
    (
        "method option not allowed",
        spec_text(_set("methods", {"cvae": {"latent_dim": [8, 32]}})),
        "methods.cvae.latent_dim[1]",
        "one of (8, 16), got 32",
    ),
    (
        "no sac updates",
        spec_text(_set("sac.updates_per_step", 0)),
        "sac.updates_per_step[0]",
        "greater than or equal to 1, got 0",
    ),
    (
        "empty method space",
        spec_text(_set("methods", {"linear": {"latent_dim": []}})),
        "methods.linear.latent_dim",
        "empty search space",
    ),
    ("empty sac space", spec_text(_set("sac.lr", [])), "sac.lr", "empty search space"),
    ("negative lr choice", spec_text(_set("sac.lr", [1e-3, -1e-3])), "sac.lr[1]", "greater than 0"),
    ("lr as text", spec_text(_set("sac.lr", "fast")), "sac.lr[0]", "valid number"),
    (
        "repeated choices",
        spec_text(_set("sac.critic_tau", [0.1, 0.1])),
        "sac.critic_tau",
        "distinct",
    ),
    (
        "zero layer",
        spec_text(_set("sac.hidden_sizes", [[64, 0]])),
        "sac.hidden_sizes[0][1]",
        "greater than or equal to 1",
    ),
    (
        "batch over buffer",
        spec_text(_set("sac.buffer_capacity", 10)),
        "sac.batch_size",
        "buffer_capacity",
    ),
    (
        "negative budget",
        spec_text(_set("budget.env_steps", -5)),
        "budget.env_steps",
        "greater than or equal to 1",
    ),
    (
        "float steps",
        spec_text(_set("budget.env_steps", 1000.0)),
        "budget.env_steps",
        "valid integer",
    ),
    ("ragged grid", spec_text(_set("budget.eval_every", 300)), "budget.eval_every", "divide"),
    ("reward scale text", spec_text(_set("reward_scale", "big")), "reward_scale", "'auto' or a"),
    ("reward scale zero", spec_text(_set("reward_scale", 0)), "reward_scale", "positive number"),
    (
        "seed steps too many",
        spec_text(_set("budget.seed_steps", 1000)),
        "budget.seed_steps",
        "< env_steps",
    ),
    (
        "K zero",
        spec_text(_set("trials_per_method", 0)),
        "trials_per_method",
        "greater than or equal to 1",
    ),
    ("K as bool", spec_text(_set("trials_per_method", True)), "trials_per_method", "valid integer"),
    ("no seeds", spec_text(_set("seeds", [])), "seeds", "empty"),
    ("negative seed", spec_text(_set("seeds", [0, -1])), "seeds[1]", "greater than or equal"),
    ("image too small", spec_text(_set("env.image_size", 8)), "env.image_size", "[32, 256]"),
    (
        "unknown env option",
        spec_text(_set("env.options", {"sucess_threshold": 0.1})),
        "env.options.sucess_threshold",
        "did you mean 'success_threshold'",
    ),
    (
        "env option type",
        spec_text(_set("env.options", {"blob_sigma": "wide"})),
        "env.options.blob_sigma",
        "a finite number",
    ),
    (
        "reserved env option",
        spec_text(_set("env.options", {"obs_mode": "state"})),
        "env.options.obs_mode",
        "set by the sweeper",
    ),
    ("storage not a url", spec_text(_set("storage", "runs/x.db")), "storage", "SQLAlchemy URL"),
    (
        "negative gpus",
        spec_text(_set("execution.gpus_per_trial", -0.5)),
        "execution.gpus_per_trial",
        "greater than or equal to 0",
    ),
    ("bad study name", spec_text(_set("study", "../escape")), "study", "letters, digits"),
    ("fp16 precision", spec_text(_set("precision", "fp16")), "precision", "'fp32' or 'bf16'"),
    (
        "state has no options",
        spec_text(_set("methods", {"state": {"latent_dim": 4}})),
        "methods.state.latent_dim",
        "allowed: none",
    ),
    # YAML 1.1 traps and broken files
    (
        "yes is not a bool",
        spec_text().replace("seeds:", "seed: no\nseeds:"),
        "seed",
        "valid integer",
    ),
    ("duplicate key", spec_text() + "study: again\n", "line", "duplicate key 'study'"),
    ("invalid yaml", "study: [t\n", "line 2", "invalid YAML"),
    ("not a mapping", "- study\n- t\n", "spec.yaml", "must be a mapping"),
    ("empty file", "", "spec.yaml", "must be a mapping"),
    ("binary file", None, "spec.yaml", "cannot read"),
    # values without bound, and names that would write to the terminal (issue 35)
    ("aliases expand", spec_text() + aliases(9), "line", "more than 100,000 values"),
    ("nested deep", spec_text() + DEEP, "line", "nested more than 50 deep"),
    ("an alias in itself", spec_text() + "sac:\n  lr: &a [*a]\n", "line", "contains itself"),
    (
        "control characters in a name",
        spec_text(_set("methods", {"\x1b[2J\x1b[31mpixel": {}})),
        "methods.\\x1b[2J\\x1b[31mpixel",
        "unknown method",
    ),
]


def write_case(tmp_path: Path, text: str | None) -> Path:
    """The spec file of a BAD_SPECS case; ``None`` is a file that is not UTF-8."""
    if text is None:
        path = tmp_path / "spec.yaml"
        path.write_bytes(b"study: \xff\xfe\n")
        return path
    return write(tmp_path, text)


@pytest.mark.parametrize(("text", "path", "allowed"), [c[1:] for c in BAD_SPECS],
                         ids=[c[0] for c in BAD_SPECS])  # fmt: skip
def test_bad_spec_raises_spec_error_naming_the_field(tmp_path, text, path, allowed):
    with pytest.raises(SpecError) as info:
        load_spec(write_case(tmp_path, text))
    message = str(info.value)
    assert "\n" not in message
    assert path in message and allowed in message, message
    if info.value.errors:  # a validation error: the exact dotted path is listed
        assert path in [p for p, _ in info.value.errors], info.value.errors


@pytest.mark.parametrize("text", [aliases(9), DEEP], ids=["aliases", "deep"])
def test_a_spec_that_expands_or_nests_without_bound_is_refused_at_once(tmp_path, text):
    """Nine levels of nine aliases (a billion values) took minutes and GBs; a list nested
    10,000 deep was a RecursionError of 3,000 lines. Now: one short line, in milliseconds
    and a few MB."""
    path = write(tmp_path, spec_text() + text)
    tracemalloc.start()
    start = time.perf_counter()
    try:
        with pytest.raises(SpecError) as info:
            load_spec(path)
        seconds = time.perf_counter() - start
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert seconds < 2 and peak < 20 * 2**20, (seconds, peak)
    assert len(str(info.value)) < len(str(path)) + 200 and "\n" not in str(info.value)


def test_an_error_shows_an_excerpt_of_a_value_and_a_name_escaped(tmp_path):
    """Three levels of aliases (729 values) are allowed, but the error about them shows a
    few of them, not all; a control character of a name is shown escaped."""
    with pytest.raises(SpecError) as info:
        load_spec(write(tmp_path, spec_text() + aliases(3)))
    message = str(info.value)
    assert "sac.lr[3]: Input should be a valid number, got [[[...]" in message, message
    assert len(message) < 600 and message.count("0.001") < 10
    many = spec_text(_set("sac.lr", ["fast"] * 10_000))  # 10,000 errors: five are listed
    with pytest.raises(SpecError) as info:
        load_spec(write(tmp_path, many))
    assert str(info.value).endswith("; and 9995 more errors") and len(info.value.errors) == 10_000
    with pytest.raises(SpecError) as info:
        load_spec(write(tmp_path, spec_text(_set("methods", {"\x1b]0;owned\x07pixel": {}}))))
    assert not any(c in str(info.value) for c in "\x1b\x07"), repr(str(info.value))
    assert "methods.\\x1b]0;owned\\x07pixel" in str(info.value)


def test_unreadable_files(tmp_path):
    with pytest.raises(SpecError, match="cannot read the spec file"):
        load_spec(tmp_path / "missing.yaml")
    with pytest.raises(SpecError, match="cannot read the spec file"):
        load_spec(tmp_path)  # a directory


def test_bad_spec_count():
    assert len(BAD_SPECS) >= 20


@pytest.mark.parametrize(("text", "path", "allowed"), [c[1:] for c in BAD_SPECS],
                         ids=[c[0] for c in BAD_SPECS])  # fmt: skip
def test_launch_exits_2_and_writes_nothing(tmp_path, monkeypatch, capsys, text, path, allowed):
    monkeypatch.chdir(tmp_path)
    spec_file = write_case(tmp_path, text)
    db = tmp_path / "db" / "study.db"
    code = cli.main(["launch", str(spec_file), "--storage", f"sqlite:///{db}"])
    err = capsys.readouterr().err
    assert code == 2
    assert path in err and allowed in err and len(err.strip().splitlines()) == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["spec.yaml"]  # no db, no runs/
