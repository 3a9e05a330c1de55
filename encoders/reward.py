"""The latent reward, a pure function."""

from __future__ import annotations

import numpy as np


def latent_reward(next_latents: np.ndarray, goal_latents: np.ndarray) -> np.ndarray:
    """``-||phi(o') - phi(o_g)||_2`` row by row: float32 [N] from [N,D] and [N,D] (or [D])."""
    diff = np.asarray(next_latents, np.float32) - np.asarray(goal_latents, np.float32)
    return -np.sqrt(np.sum(diff * diff, axis=-1, dtype=np.float32))
