"""Gradient agreement (thesis Algorithm 1): does the latent reward point the way the true
reward does?

At a state ``s`` with goal ``g``, the env is moved to ``s + alpha * d_i`` along ``N`` random
unit directions; with the states ``s_i`` actually reached and the latent rewards ``r_i``
there, the least-squares solution ``w`` of ``(s_i - s) . w = r_i - r(s)`` estimates the
latent reward's gradient in state space. It is compared with the analytic gradient of the
true reward ``-||s - g||``, namely ``-(s - g) / ||s - g||``, by cosine distance.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pandas as pd

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


def random_directions(rng: np.random.Generator, n: int, dim: int) -> np.ndarray:
    """``n`` directions uniform on the unit sphere in ``dim`` dimensions, [n, dim]."""
    d = rng.standard_normal((n, dim))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def least_squares_gradient(delta_states: np.ndarray, delta_rewards: np.ndarray) -> np.ndarray:
    """The ``w`` minimising ``||delta_states @ w - delta_rewards||`` ([N,S], [N] -> [S]);
    the minimum-norm one when the steps do not span the state space."""
    w, *_ = np.linalg.lstsq(np.asarray(delta_states, np.float64), delta_rewards, rcond=None)
    return w


def true_reward_gradient(state: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """Gradient in ``state`` of ``-||state - goal||``: ``-(state - goal) / ||state - goal||``."""
    diff = np.asarray(state, np.float64) - np.asarray(goal, np.float64)
    return -diff / np.linalg.norm(diff)


def cosine_distance(a: np.ndarray, b: np.ndarray) -> float:
    """``1 - cos(a, b)`` in [0, 2]; 1 (no agreement) when either vector is zero."""
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na == 0 or nb == 0:
        return 1.0
    return float(1.0 - np.dot(a, b) / (na * nb))


def gradient_agreement(
    env: ControllableEnv,
    encoders: Mapping[str, RewardEncoder],
    num_states: int = 50,
    num_directions: int = 16,
    alpha: float = 0.03,
    seed: int = 0,
    progress: bool = True,
) -> pd.DataFrame:
    """Algorithm 1 at ``num_states`` random (state, goal) pairs, for every encoder.

    States are drawn from ``env.state_bounds()`` shrunk by ``alpha`` (so the steps stay
    inside), goals from the whole box at least ``4 * alpha`` away. The images are rendered
    once and shared by the encoders. Rows: ``encoder, metric="cosine_distance", value,
    sample, distance`` (one per state; ``distance`` = ``||s - g||``; the mean value is the
    headline figure).
    """
    if num_directions < 1 or alpha <= 0 or num_states < 1:
        raise ValueError("num_states, num_directions and alpha must be positive")
    rng = np.random.default_rng(seed)
    low, high = bounds(env)
    rows = []
    bar = Progress("gradient agreement states", num_states, progress)
    for sample in range(num_states):
        state = sample_states(rng, low, high, 1, margin=alpha)[0]
        goal = sample_states(rng, low, high, 1)[0]
        for _ in range(100):  # the true gradient is undefined at the goal: keep away
            if np.linalg.norm(goal - state) > 4 * alpha:
                break
            goal = sample_states(rng, low, high, 1)[0]
        (reached_goal, reached_state), images = render_states(env, np.vstack([goal, state]))
        # perturb around the state the env actually reached, not the one asked for
        steps = alpha * random_directions(rng, num_directions, len(low))
        reached, step_images = render_states(env, reached_state + steps)
        images = np.concatenate([images, step_images])
        true_grad = true_reward_gradient(reached_state, reached_goal)
        for name, z in encode_all(encoders, images).items():
            rewards = latent_reward(z[1:], z[0])
            grad = least_squares_gradient(reached - reached_state, rewards[1:] - rewards[0])
            rows.append(
                {
                    "encoder": name,
                    "metric": "cosine_distance",
                    "value": cosine_distance(grad, true_grad),
                    "sample": sample,
                    "distance": float(np.linalg.norm(reached_state - reached_goal)),
                }
            )
        bar.update(sample + 1)
    return pd.DataFrame(rows)
