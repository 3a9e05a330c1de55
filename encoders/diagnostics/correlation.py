"""Correlation of the latent reward with the true reward over random states and goals."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pandas as pd
from scipy import stats

from encoders.base import RewardEncoder
from encoders.diagnostics.common import (
    ControllableEnv,
    Progress,
    bounds,
    encode_all,
    render_states,
    sample_states,
)
from encoders.reward import latent_reward


def reward_correlation(
    env: ControllableEnv,
    encoders: Mapping[str, RewardEncoder],
    num_pairs: int = 300,
    seed: int = 0,
    progress: bool = True,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Latent vs true reward at ``num_pairs`` (state, goal) pairs drawn uniformly from
    ``env.state_bounds()``; the true reward uses the states actually reached.

    Returns (summary rows ``encoder, metric in {pearson, spearman}, value``; pair rows
    ``encoder, pair, true_reward, latent_reward`` for the scatter plot).
    """
    if num_pairs < 3:
        raise ValueError(f"num_pairs must be at least 3, got {num_pairs}")
    rng = np.random.default_rng(seed)
    low, high = bounds(env)
    targets = sample_states(rng, low, high, 2 * num_pairs)
    bar = Progress("correlation states", 2 * num_pairs, progress)
    reached, images = render_states(env, targets, bar)
    states, goals = np.split(reached, 2)
    true = -np.linalg.norm(states - goals, axis=1)
    summary, pairs = [], []
    for name, z in encode_all(encoders, images).items():
        z_states, z_goals = np.split(z, 2)
        latent = latent_reward(z_states, z_goals).astype(np.float64)
        for metric, fn in (("pearson", stats.pearsonr), ("spearman", stats.spearmanr)):
            # a constant latent reward has no correlation: NaN, not an error
            value = fn(true, latent)[0] if np.ptp(latent) > 0 else np.nan
            summary.append({"encoder": name, "metric": metric, "value": float(value)})
        pairs.append(
            pd.DataFrame(
                {
                    "encoder": name,
                    "pair": np.arange(num_pairs),
                    "true_reward": true,
                    "latent_reward": latent,
                }
            )
        )
    return pd.DataFrame(summary), pd.concat(pairs, ignore_index=True)
