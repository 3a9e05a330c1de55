"""Search spaces: the default choices of every hyperparameter and how configs are sampled.

A search space maps a parameter name to a tuple of choices. A parameter with one choice
is fixed; with more, it is *sampled*. Every parameter, fixed or sampled, becomes an Optuna
param (fixed ones with a one-choice distribution) so the dashboard shows all of them.

SAC defaults are the thesis appendix A.1. Method defaults:

- ``pixel``, ``state``, ``true_reward``: no options.
- ``linear``, ``conv``: ``latent_dim`` 128 | 256 (appendix A.1).
- ``vae``, ``cvae``: ``latent_dim`` 8 | 16 (appendix A.1); ``beta`` 1 | 5 | 20 (from plain
  VAE to the strong bottleneck RIG-style reward encoders use); ``lr`` 1e-3 | 3e-4 (Adam's
  usual range for small VAEs); ``epochs`` 10 | 30 and ``num_images`` 1000 | 5000 (a short
  and a long pre-training; the trial pays for both before SAC starts); ``batch_size`` 64.
- ``vgg``: ``weights_path`` has no default: the spec gives it or ``$GCRL_VGG16_WEIGHTS``.

Options an encoder accepts but a space does not list run with the encoder's own default
(recorded as a fixed param when it is a plain scalar).
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

Scalar = bool | int | float | str

#: Thesis appendix A.1; the fields A.1 does not fix keep ``agent.config.SACConfig``'s defaults.
SAC_DEFAULTS: dict[str, tuple[Any, ...]] = {
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

#: Default search space of each method's own options (see the module docstring).
METHOD_DEFAULTS: dict[str, dict[str, tuple[Scalar, ...]]] = {
    "pixel": {},
    "state": {},
    "true_reward": {},
    "linear": {"latent_dim": (128, 256)},
    "conv": {"latent_dim": (128, 256)},
    "vae": {
        "latent_dim": (8, 16),
        "beta": (1.0, 5.0, 20.0),
        "lr": (1e-3, 3e-4),
        "epochs": (10, 30),
        "num_images": (1000, 5000),
        "batch_size": (64,),
    },
    "vgg": {},
}
METHOD_DEFAULTS["cvae"] = dict(METHOD_DEFAULTS["vae"])

#: Options a spec must give (or take from ``OPTION_ENV_VARS``) even if the encoder has a default.
REQUIRED_OPTIONS: dict[str, tuple[str, ...]] = {"vgg": ("weights_path",)}

#: (method, option) -> environment variable read when the spec omits the option; the value
#: is written into the validated spec, so workers on other machines need not have it set.
#: The name is ``encoders.vgg.WEIGHTS_ENV_VAR`` (not imported here: it would import torch).
OPTION_ENV_VARS: dict[tuple[str, str], str] = {("vgg", "weights_path"): "GCRL_VGG16_WEIGHTS"}

#: Bounds of method options by name, whatever the method: (lower, inclusive?).
OPTION_BOUNDS: dict[str, tuple[float, bool]] = {
    "latent_dim": (1, True),
    "epochs": (1, True),
    "num_images": (1, True),
    "batch_size": (1, True),
    "beta": (0, True),
    "lr": (0, False),
}


def param_value(value: Any) -> Scalar:
    """A choice as an Optuna categorical value: layer sizes ``(256, 256)`` -> ``"256x256"``."""
    if isinstance(value, tuple | list):
        return "x".join(str(int(v)) for v in value)
    return value


def space_size(space: Mapping[str, tuple[Any, ...]]) -> int:
    """Number of distinct configurations in ``space``."""
    return math.prod(len(choices) for choices in space.values())


def derive_rng(seed: int, stream: str) -> np.random.Generator:
    """A generator for one named stream of a study seed.

    Streams are independent, so adding a method does not change another's samples.
    """
    digest = hashlib.sha256(stream.encode()).digest()
    return np.random.default_rng([seed, int.from_bytes(digest[:8], "little")])


def sample_configs(
    space: Mapping[str, tuple[Any, ...]], k: int, rng: np.random.Generator
) -> list[dict[str, Any]]:
    """``k`` configurations drawn uniformly from ``space``, distinct while the space has room.

    Parameters are drawn in the space's order; a fixed parameter consumes no random draw.
    Once all ``space_size(space)`` configs have been drawn, repeats are allowed again.
    """
    names = list(space)
    size = space_size(space)
    seen: set[tuple[int, ...]] = set()
    configs = []
    while len(configs) < k:
        index = tuple(int(rng.integers(len(space[n]))) if len(space[n]) > 1 else 0 for n in names)
        if index in seen:
            continue
        seen.add(index)
        if len(seen) == size:  # space exhausted: start a new round
            seen.clear()
        configs.append({n: space[n][i] for n, i in zip(names, index, strict=True)})
    return configs
