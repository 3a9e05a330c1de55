"""Gradient agreement (thesis Algorithm 1): does the latent reward point the way the true
reward does?

Draw a start state ``s`` from the env's reset distribution and a goal ``g`` from its goal
distribution; the latent reward is ``l = -||phi(render(s)) - phi(render(g))||``. ``N``
times: ``h`` uniform on the unit sphere of the controllable state, ask the env for
``s + alpha * h``, read back the state ``s'`` actually reached, record ``s' - s`` and the
change of ``l``. The least-squares solution ``delta`` of ``(s' - s) . delta ~ dl``
estimates the latent reward's gradient in state space; ``d = 1 - cos(delta, -(s - g) /
||s - g||)`` compares it with the gradient of the true reward ``-||s - g||``. The mean of
``d`` over many ``(s, g)`` is the headline figure.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping

import numpy as np
import pandas as pd

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

#: with ``min_goal_distance``, how many pairs may be drawn per sample kept before giving up
DRAWS_PER_SAMPLE = 100


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
    """Gradient in ``state`` of ``-||state - goal||``: ``-(state - goal) / ||state - goal||``.
    At the goal the true reward has no gradient: all NaN there, so no number pretends to
    measure an agreement that is undefined."""
    diff = np.asarray(state, np.float64) - np.asarray(goal, np.float64)
    norm = np.linalg.norm(diff)
    return np.full_like(diff, np.nan) if norm == 0 else -diff / norm


def cosine_distance(a: np.ndarray, b: np.ndarray) -> float:
    """``1 - cos(a, b)`` in [0, 2]; 1 (no agreement) when either vector is zero; NaN when
    either has a NaN (an undefined gradient)."""
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if math.isnan(na) or math.isnan(nb):
        return math.nan
    if na == 0 or nb == 0:
        return 1.0
    return float(1.0 - np.dot(a, b) / (na * nb))


def check_arguments(
    num_states: int, num_directions: int, alpha: float, min_goal_distance: float
) -> None:
    """Raise a ValueError before any work if Algorithm 1 cannot run with these sizes."""
    if num_directions < 1 or num_states < 1 or not alpha > 0:
        raise ValueError("num_states, num_directions and alpha must be positive")
    if not 0 <= min_goal_distance < math.inf:
        raise ValueError(f"min_goal_distance must be finite and >= 0, got {min_goal_distance}")


def far_enough_pairs(
    env: ControllableEnv,
    start: str,
    rng: np.random.Generator,
    seed: int,
    num_states: int,
    min_goal_distance: float,
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Yield ``num_states`` (state, goal) pairs; with ``min_goal_distance > 0`` those closer
    than it are skipped and the next is drawn. Draw ``k`` resets with ``derived_seed(seed,
    k)``. A filter that rejects almost every pair is an error, never silently relaxed."""
    kept = 0
    for draw in range(DRAWS_PER_SAMPLE * num_states):
        state, goal = draw_pair(env, start, rng, derived_seed(seed, draw))
        if np.linalg.norm(state - goal) < min_goal_distance:
            continue
        yield state, goal
        kept += 1
        if kept == num_states:
            return
    raise ValueError(
        f"min_goal_distance={min_goal_distance}: only {kept} of {num_states} (state, goal) "
        f"pairs in {DRAWS_PER_SAMPLE * num_states} draws are that far apart"
    )


def gradient_agreement(
    env: ControllableEnv,
    encoders: Mapping[str, RewardEncoder],
    num_states: int = 50,
    num_directions: int = 16,
    alpha: float = 0.03,
    seed: int = 0,
    start: str = "reset",
    min_goal_distance: float = 0.0,
    progress: bool = True,
) -> pd.DataFrame:
    """Algorithm 1 at ``num_states`` (state, goal) pairs, for every encoder.

    ``start="reset"`` (the algorithm): each pair is what ``env.reset`` draws, start and
    goal from the env's own distributions; ``"uniform"``: both uniform in
    ``env.state_bounds()``. The env is reset with ``seed`` first either way. No pair is
    dropped for a near goal unless ``min_goal_distance > 0`` asks for it (pairs whose drawn
    start and goal are closer are redrawn). A goal exactly at the start has no true
    gradient: that sample's value is NaN. The start and goal are rendered through
    ``set_controllable_state`` like the perturbed states, and the states the env reached
    are the ``s`` and ``g`` used. The images are shared by the encoders.

    Rows: ``encoder, metric="cosine_distance", value, sample, distance`` (one per pair;
    ``distance`` = ``||s - g||``), plus ``min_goal_distance`` when a filter was used.
    """
    check_arguments(num_states, num_directions, alpha, min_goal_distance)
    check_start(start)
    fresh_reset(env, seed)
    rng = np.random.default_rng(seed)
    pairs = far_enough_pairs(env, start, rng, seed, num_states, min_goal_distance)
    rows = []
    bar = Progress("gradient agreement states", num_states, progress)
    for sample, (state, goal) in enumerate(pairs):
        (reached_goal, reached_state), images = render_states(env, np.vstack([goal, state]))
        # perturb around the state the env actually reached, not the one asked for
        steps = alpha * random_directions(rng, num_directions, len(state))
        reached, step_images = render_states(env, reached_state + steps)
        images = np.concatenate([images, step_images])
        true_grad = true_reward_gradient(reached_state, reached_goal)
        for name, z in encode_all(encoders, images).items():
            rewards = latent_reward(z[1:], z[0]).astype(np.float64)
            grad = least_squares_gradient(reached - reached_state, rewards[1:] - rewards[0])
            row = {
                "encoder": name,
                "metric": "cosine_distance",
                "value": cosine_distance(grad, true_grad),
                "sample": sample,
                "distance": float(np.linalg.norm(reached_state - reached_goal)),
            }
            if min_goal_distance > 0:
                row["min_goal_distance"] = min_goal_distance
            rows.append(row)
        bar.update(sample + 1)
    return pd.DataFrame(rows)


def gradient_summary(table: pd.DataFrame) -> pd.DataFrame:
    """Headline rows ``encoder, metric, value`` of a ``gradient_agreement`` table:
    ``mean_cosine_distance`` and ``median_cosine_distance`` over the samples with a true
    gradient, ``undefined_samples`` (goal at the start: NaN, so a mean is never quietly
    over fewer samples), and ``min_goal_distance`` when a filter was used."""
    rows = []
    for name, group in table.groupby("encoder", sort=False):
        values = group["value"]
        rows += [
            {"encoder": name, "metric": "mean_cosine_distance", "value": float(values.mean())},
            {"encoder": name, "metric": "median_cosine_distance", "value": float(values.median())},
            {"encoder": name, "metric": "undefined_samples", "value": float(values.isna().sum())},
        ]
        if "min_goal_distance" in group:
            value = float(group["min_goal_distance"].iloc[0])
            rows.append({"encoder": name, "metric": "min_goal_distance", "value": value})
    return pd.DataFrame(rows, columns=["encoder", "metric", "value"])
