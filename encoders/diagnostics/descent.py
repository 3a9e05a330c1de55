"""Does the reward lead to the goal, apart from learning? Greedy descent on the reward.

From each episode's start (the env's reset), a controller that sees the simulator tries
``candidates`` small actions from the current state, each in an exact copy of the
simulator (``sim_state`` / ``set_sim_state``), and takes the one whose next image is
nearest the goal image under the encoder (the highest latent reward); it repeats for
``horizon`` steps. No learning is involved: where this controller reaches the goal, the
reward has the goal at its optimum and a path to it that small steps can follow; where a
SAC agent on the same reward does not, the shortfall is the learner's.

Controllers: one per encoder; ``true_reward`` (takes the candidate nearest the goal in
true state: the best these candidates allow); ``random`` (takes a random candidate).
The candidates of a step are the same for every controller at the same (episode, step):
``candidates`` random directions of the action box, scaled by ``step_size`` of its
half-width. Per controller and episode: the final distance to the goal in controllable
state (on the door it mixes metres and radians, as ``precision`` does) and the env's
success; per controller the metric rows ``success_rate`` and ``median_final_distance``.
On fetch_push the controllers move the arm, not the block, so a reward that follows the
arm instead of the block shows here as a low success rate (the thesis' chapter 6).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd

from encoders.base import RewardEncoder
from encoders.diagnostics.common import ControllableEnv, Progress, derived_seed, fresh_reset
from encoders.reward import latent_reward

#: the controllers besides the encoders'
BASELINES = ("true_reward", "random")
DESCENT_METRICS = ("success_rate", "median_final_distance")


def candidate_actions(
    rng: np.random.Generator, low: np.ndarray, high: np.ndarray, k: int, step_size: float
) -> np.ndarray:
    """``k`` actions: random unit directions scaled by ``step_size`` of the action box's
    half-width around its centre, clipped to the box."""
    direction = rng.normal(size=(k, len(low)))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    centre, half = (high + low) / 2, (high - low) / 2
    return np.clip(centre + step_size * half * direction, low, high).astype(np.float32)


def _try(env: Any, saved: Any, action: np.ndarray) -> tuple[np.ndarray, float, float, Any]:
    """Step ``action`` from the simulator state ``saved``: (image, true distance to the
    goal, success, simulator state reached)."""
    env.set_sim_state(saved)
    _, _, _, _, info = env.step(action)
    distance = float(np.linalg.norm(env.controllable_state() - env.goal_state()))
    return env.render_image(), distance, float(info["is_success"]), env.sim_state()


def greedy_descent(
    env: ControllableEnv,
    encoders: Mapping[str, RewardEncoder],
    episodes: int = 30,
    horizon: int = 50,
    candidates: int = 8,
    step_size: float = 0.5,
    seed: int = 0,
    progress: bool = True,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The analysis of the module docstring; episode ``e`` starts from
    ``env.reset(seed=derived_seed(seed, e))``. Returns (summary rows ``encoder, metric,
    value``; episode rows ``encoder, episode, final_distance, success``)."""
    if episodes < 1 or horizon < 1 or candidates < 2:
        raise ValueError(
            f"need an episode, a step and two candidates, got {episodes}, {horizon}, {candidates}"
        )
    if not 0 < step_size <= 1:
        raise ValueError(f"step_size must be in (0, 1], got {step_size}")
    fresh_reset(env, seed)
    low, high = (np.asarray(b, np.float64) for b in (env.action_space.low, env.action_space.high))
    controllers = [*encoders, *BASELINES]
    bar = Progress("descent steps", episodes * horizon * len(controllers), progress)
    rows = []
    for episode in range(episodes):
        episode_seed = derived_seed(seed, episode)
        env.reset(seed=episode_seed)
        start, goal_image = env.sim_state(), env.goal_image()
        goals = {name: enc.encode(goal_image[None])[0] for name, enc in encoders.items()}
        for name in controllers:
            rng = np.random.default_rng(episode_seed)  # the same candidates for everyone
            choice_rng = np.random.default_rng([episode_seed, 1])
            state, distance, success = start, np.nan, np.nan
            for _ in range(horizon):
                actions = candidate_actions(rng, low, high, candidates, step_size)
                tried = [_try(env, state, a) for a in actions]
                if name == "random":
                    best = int(choice_rng.integers(candidates))
                elif name == "true_reward":
                    best = int(np.argmin([t[1] for t in tried]))
                else:
                    images = np.stack([t[0] for t in tried])
                    reward = latent_reward(encoders[name].encode(images), goals[name])
                    best = int(np.argmax(reward))
                _, distance, success, state = tried[best]
                bar.update(bar.done + 1)
            rows.append(
                {
                    "encoder": name,
                    "episode": episode,
                    "final_distance": distance,
                    "success": success,
                }
            )
    table = pd.DataFrame(rows)
    grouped = table.groupby("encoder", sort=False)
    summary = pd.concat(
        [
            grouped["success"].mean().rename("success_rate"),
            grouped["final_distance"].median().rename("median_final_distance"),
        ],
        axis=1,
    )
    summary = summary.reset_index().melt(id_vars="encoder", var_name="metric", value_name="value")
    return summary, table
