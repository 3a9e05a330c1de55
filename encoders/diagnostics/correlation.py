"""Correlation of the latent reward with the true reward over (state, goal) pairs."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pandas as pd
from scipy import stats

from encoders.base import RewardEncoder
from encoders.diagnostics.common import (
    ControllableEnv,
    Progress,
    check_start,
    derived_seed,
    draw_pair,
    encode_all,
    fresh_reset,
    render_states,
)
from encoders.reward import latent_reward


def reward_correlation(
    env: ControllableEnv,
    encoders: Mapping[str, RewardEncoder],
    num_pairs: int = 300,
    seed: int = 0,
    start: str = "reset",
    progress: bool = True,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Latent vs true reward at ``num_pairs`` (state, goal) pairs drawn as Algorithm 1 draws
    them: ``start="reset"``, pair ``k`` is what ``env.reset(seed=derived_seed(seed, k))``
    puts there (the env's start and goal distributions); ``"uniform"``: both uniform in
    ``env.state_bounds()``. The env is reset with ``seed`` first; each pair is rendered
    through ``set_controllable_state`` right after it is drawn, and the true reward uses
    the states actually reached.

    Returns (summary rows ``encoder, metric in {pearson, spearman}, value``; pair rows
    ``encoder, pair, true_reward, latent_reward`` for the scatter plot).
    """
    if num_pairs < 3:
        raise ValueError(f"num_pairs must be at least 3, got {num_pairs}")
    check_start(start)
    fresh_reset(env, seed)
    rng = np.random.default_rng(seed)
    bar = Progress("correlation pairs", num_pairs, progress)
    reached, images = [], []
    for k in range(num_pairs):
        state, goal = draw_pair(env, start, rng, derived_seed(seed, k))
        pair_reached, pair_images = render_states(env, np.vstack([state, goal]))
        reached.append(pair_reached)
        images.append(pair_images)
        bar.update(k + 1)
    states, goals = np.stack(reached).transpose(1, 0, 2)
    true = -np.linalg.norm(states - goals, axis=1)
    summary, pairs = [], []
    for name, z in encode_all(encoders, np.concatenate(images)).items():
        z_states, z_goals = z[0::2], z[1::2]
        latent = latent_reward(z_states, z_goals).astype(np.float64)
        for metric, fn in (("pearson", stats.pearsonr), ("spearman", stats.spearmanr)):
            # a constant reward (latent, or true: one start, one goal) has no correlation
            value = fn(true, latent)[0] if np.ptp(latent) > 0 and np.ptp(true) > 0 else np.nan
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
