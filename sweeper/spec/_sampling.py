"""Search spaces: how configurations are sampled from them.

A search space maps a parameter name to a tuple of choices. A parameter with one choice
is fixed; with more, it is *sampled*. Every parameter, fixed or sampled, becomes an Optuna
param (fixed ones with a one-choice distribution) so the dashboard shows all of them.

The default choices of every hyperparameter (thesis appendix A.1) are declared beside the
hyperparameter itself: ``agent.config.SACConfig`` and the encoders' option classes in
``encoders.options``; ``sweeper.spec._models`` derives a spec's search spaces from them.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

Scalar = bool | int | float | str


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
