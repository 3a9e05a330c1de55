"""Replay buffer of fixed-length goal-conditioned episodes, storing each frame once.

An episode of T steps has T + 1 observations and one goal. They are stored in episode
slots: ``obs[slot, t]`` is the observation at step t, so a transition's next observation
``obs[slot, t + 1]`` shares storage with the following transition's observation, and the
goal is stored once per episode. A transition is addressed by ``(slot, t)``; sampling draws
transitions uniformly among those stored. Slots are reused oldest-first, so the buffer
holds the last ``capacity`` transitions (rounded up to whole episodes).

Observations are uint8 frames (HxWx3) or, for the state oracle, float32 vectors; the
buffer does not care. Memory is ``(T + 2) / T`` observations per transition (52/50 for
50-step episodes) plus the action and reward.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np


class ReplayBuffer:
    """Episodes of ``episode_steps`` transitions; the reward is given when a step is added.

    Use: ``start_episode(obs, goal)`` then ``add(action, reward, next_obs)`` for each step.
    """

    def __init__(
        self,
        capacity: int,
        obs_shape: tuple[int, ...],
        obs_dtype: np.dtype | type,
        goal_shape: tuple[int, ...],
        action_dim: int,
        episode_steps: int,
    ) -> None:
        if capacity < 1 or episode_steps < 1 or action_dim < 1:
            raise ValueError(
                "capacity, episode_steps and action_dim must be >= 1, got "
                f"{capacity}, {episode_steps}, {action_dim}"
            )
        self.episode_steps = int(episode_steps)
        self.num_slots = math.ceil(capacity / episode_steps)
        self.capacity = self.num_slots * self.episode_steps
        t = self.episode_steps
        # np.empty: pages are only touched (and counted by the OS) when written
        self.obs = np.empty((self.num_slots, t + 1, *obs_shape), obs_dtype)
        self.goals = np.empty((self.num_slots, *goal_shape), obs_dtype)
        self.actions = np.empty((self.num_slots, t, action_dim), np.float32)
        self.rewards = np.empty((self.num_slots, t), np.float32)
        self.lengths = np.zeros(self.num_slots, np.int64)  # transitions stored per slot
        self.episodes = 0  # episodes started; the current one is in slot (episodes - 1) % slots

    def __len__(self) -> int:
        return int(self.lengths.sum())

    @property
    def nbytes(self) -> int:
        """Bytes allocated for the whole capacity."""
        arrays = (self.obs, self.goals, self.actions, self.rewards, self.lengths)
        return sum(a.nbytes for a in arrays)

    def _slot(self) -> int:
        if self.episodes == 0:
            raise RuntimeError("call start_episode() before add()")
        return (self.episodes - 1) % self.num_slots

    def start_episode(self, obs: np.ndarray, goal: np.ndarray) -> None:
        """Begin a new episode in the oldest slot (its old transitions are dropped)."""
        slot = self.episodes % self.num_slots
        self.lengths[slot] = 0
        self.obs[slot, 0] = obs
        self.goals[slot] = goal
        self.episodes += 1

    def add(self, action: np.ndarray, reward: float, next_obs: np.ndarray) -> None:
        """Store one step of the current episode."""
        slot = self._slot()
        t = int(self.lengths[slot])
        if t >= self.episode_steps:
            raise RuntimeError(f"episode longer than episode_steps={self.episode_steps}")
        self.actions[slot, t] = action
        self.rewards[slot, t] = reward
        self.obs[slot, t + 1] = next_obs
        self.lengths[slot] = t + 1

    def sample(self, batch_size: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
        """``batch_size`` transitions drawn uniformly with replacement.

        Returns ``obs``, ``action``, ``reward`` [B, 1], ``next_obs``, ``goal``.
        """
        ends = np.cumsum(self.lengths)
        if ends[-1] == 0:
            raise RuntimeError("cannot sample from an empty replay buffer")
        k = rng.integers(0, ends[-1], size=batch_size)
        slot = np.searchsorted(ends, k, side="right")
        t = k - (ends[slot] - self.lengths[slot])
        return {
            "obs": self.obs[slot, t],
            "action": self.actions[slot, t],
            "reward": self.rewards[slot, t, None],
            "next_obs": self.obs[slot, t + 1],
            "goal": self.goals[slot],
        }

    # ---- checkpoints: only the slots written so far ------------------------------------
    def state_dict(self) -> dict[str, np.ndarray | int]:
        n = min(self.episodes, self.num_slots)
        return {
            "obs": self.obs[:n],
            "goals": self.goals[:n],
            "actions": self.actions[:n],
            "rewards": self.rewards[:n],
            "lengths": self.lengths[:n],
            "episodes": self.episodes,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a ``state_dict()``; arrays may come back as CPU tensors."""
        arrays = {
            k: np.asarray(state[k]) for k in ("obs", "goals", "actions", "rewards", "lengths")
        }
        n = len(arrays["lengths"])
        if n > self.num_slots or arrays["obs"].shape[1:] != self.obs.shape[1:]:
            raise ValueError(
                f"replay state of {n} slots x {arrays['obs'].shape[1:]} does not fit a buffer "
                f"of {self.num_slots} slots x {self.obs.shape[1:]}"
            )
        for name, array in arrays.items():
            getattr(self, name)[:n] = array
        self.lengths[n:] = 0
        self.episodes = int(state["episodes"])
