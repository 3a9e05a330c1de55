"""Where the latent reward peaks near the goal: could an agent that maximised it succeed?

Algorithm 1 and the correlation look at the reward over the whole state space. An agent
that already moves toward the goal needs more: the reward must still rank states inside
the success radius above states just outside it. For each goal (from the env's reset),
``num_states`` states uniform in a ball of ``radius`` around it are rendered; per encoder:

- ``peak_distance``: the true distance to the goal of the state with the highest latent
  reward (an agent that maximises the reward ends there); the ``true_reward`` row is the
  nearest state's, the best any reward can do with these states;
- ``peak_success``: whether that state is within ``success_radius``;
- ``success_auc``: the probability that a state within ``success_radius`` has a higher
  latent reward than one outside it (0.5: the reward cannot tell success from a near miss);
- ``spearman``: the rank correlation of latent and true reward within the ball.

The distance is the Euclidean one in the controllable state, which is the task's on the
Fetch envs (gripper or object xyz, success within 0.05 m); on the door it mixes metres and
radians.
"""

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
    derived_seed,
    encode_all,
    fresh_reset,
    render_states,
)
from encoders.reward import latent_reward

PRECISION_METRICS = ("peak_distance", "peak_success", "success_auc", "spearman")


def ball(rng: np.random.Generator, center: np.ndarray, radius: float, n: int) -> np.ndarray:
    """``n`` points uniform in the ball of ``radius`` around ``center``."""
    direction = rng.normal(size=(n, len(center)))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    lengths = radius * rng.uniform(size=(n, 1)) ** (1 / len(center))
    return center + lengths * direction


def success_auc(reward: np.ndarray, succeeded: np.ndarray) -> float:
    """P(reward of a succeeding state > reward of a failing one), ties one half (the
    Mann-Whitney statistic); NaN when either group is empty."""
    inside, outside = reward[succeeded], reward[~succeeded]
    if len(inside) == 0 or len(outside) == 0:
        return float("nan")
    greater = (inside[:, None] > outside[None, :]).mean()
    ties = (inside[:, None] == outside[None, :]).mean()
    return float(greater + 0.5 * ties)


def peak_metrics(reward: np.ndarray, distance: np.ndarray, success_radius: float) -> dict:
    """``PRECISION_METRICS`` of one goal's states (``reward`` higher is better)."""
    peak = float(distance[int(np.argmax(reward))])
    spread = np.ptp(reward) > 0 and np.ptp(distance) > 0
    return {
        "peak_distance": peak,
        "peak_success": float(peak < success_radius),
        "success_auc": success_auc(reward, distance < success_radius),
        "spearman": float(stats.spearmanr(reward, -distance)[0]) if spread else float("nan"),
    }


def goal_precision(
    env: ControllableEnv,
    encoders: Mapping[str, RewardEncoder],
    num_goals: int = 20,
    num_states: int = 200,
    radius: float = 0.15,
    success_radius: float = 0.05,
    seed: int = 0,
    progress: bool = True,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The analysis of the module docstring over ``num_goals`` goals, the goal ``k`` being
    what ``env.reset(seed=derived_seed(seed, k))`` draws. States are clipped to the env's
    state box; distances use the states actually reached, the goal's too.

    Returns (summary rows ``encoder, metric, value``: the mean over goals; goal rows
    ``encoder, metric, value, goal``). The ``true_reward`` rows are the true reward's.
    """
    if num_goals < 1 or num_states < 2:
        raise ValueError(f"need a goal and two states, got {num_goals} and {num_states}")
    if not 0 < success_radius < radius:
        raise ValueError(f"need 0 < success_radius < radius, got {success_radius}, {radius}")
    fresh_reset(env, seed)
    rng = np.random.default_rng(seed)
    low, high = bounds(env)
    bar = Progress("precision states", num_goals * (num_states + 1), progress)
    rows = []
    for k in range(num_goals):
        env.reset(seed=derived_seed(seed, k))
        goal = np.asarray(env.goal_state(), np.float64)
        states = np.clip(ball(rng, goal, radius, num_states), low, high)
        reached, images = render_states(env, np.vstack([goal, states]), bar)
        distance = np.linalg.norm(reached[1:] - reached[0], axis=1)
        rewards = {"true_reward": -distance}
        for name, z in encode_all(encoders, images).items():
            rewards[name] = latent_reward(z[1:], z[0]).astype(np.float64)
        for name, reward in rewards.items():
            for metric, value in peak_metrics(reward, distance, success_radius).items():
                rows.append({"encoder": name, "metric": metric, "value": value, "goal": k})
    goals = pd.DataFrame(rows)
    summary = goals.groupby(["encoder", "metric"], sort=False)["value"].mean().reset_index()
    return summary, goals
