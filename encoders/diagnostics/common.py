"""What the analyses share: the env protocol, fresh resets, (state, goal) pairs, rendering,
progress lines."""

from __future__ import annotations

import sys
import time
from collections.abc import Mapping
from typing import Any, Protocol

import numpy as np

from encoders.base import RewardEncoder

#: where (state, goal) pairs come from: the env's reset (its own start and goal
#: distributions, as Algorithm 1 says) or uniform in ``state_bounds()``
START_MODES = ("reset", "uniform")


class ControllableEnv(Protocol):
    """The part of ``agent.envs.base.GoalImageEnv`` the diagnostics use (see its docstring)."""

    state_names: tuple[str, ...]
    action_space: Any

    def reset(self, *, seed: int | None = None) -> tuple[Any, dict]: ...
    def step(self, action: np.ndarray) -> tuple[Any, float, bool, bool, dict]: ...

    def controllable_state(self) -> np.ndarray: ...
    def set_controllable_state(self, state: np.ndarray) -> np.ndarray: ...
    def goal_state(self) -> np.ndarray: ...
    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]: ...
    def render_image(self) -> np.ndarray: ...
    def goal_image(self) -> np.ndarray: ...
    def sim_state(self) -> Any: ...
    def set_sim_state(self, state: Any) -> None: ...


def bounds(env: ControllableEnv) -> tuple[np.ndarray, np.ndarray]:
    """The env's state box as float64 arrays."""
    low, high = (np.asarray(b, np.float64) for b in env.state_bounds())
    return low, high


def check_start(start: str) -> str:
    """``start`` if it is one of ``START_MODES``; a ValueError that lists them otherwise."""
    if start not in START_MODES:
        raise ValueError(f"start must be one of {', '.join(START_MODES)}, got {start!r}")
    return start


def derived_seed(seed: int, *keys: int) -> int:
    """A seed fixed by ``seed`` and ``keys``: draw ``k`` of a run gets its own stream, and
    runs with seeds 0 and 1 share no draws (``seed + k`` would shift them by one)."""
    return int(np.random.SeedSequence([seed, *keys]).generate_state(1)[0])


def fresh_reset(env: ControllableEnv, seed: int) -> None:
    """Reset ``env`` before an analysis: what an earlier analysis left behind must not reach
    this one (on fetch_push ``set_controllable_state`` moves only the block, so a leftover
    arm changed every result)."""
    env.reset(seed=seed)


def sample_states(
    rng: np.random.Generator, low: np.ndarray, high: np.ndarray, n: int
) -> np.ndarray:
    """``n`` states uniform in the box ``[low, high]``."""
    return rng.uniform(low, high, size=(n, len(low)))


def draw_pair(
    env: ControllableEnv, start: str, rng: np.random.Generator, reset_seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """One (start state, goal) pair. ``"reset"``: ``env.reset(seed=reset_seed)`` draws both
    from the env's own distributions (Fetch: the gripper's start) and they are read back;
    ``"uniform"``: both uniform in ``env.state_bounds()`` from ``rng``, no reset."""
    if check_start(start) == "reset":
        env.reset(seed=reset_seed)
        return (
            np.asarray(env.controllable_state(), np.float64),
            np.asarray(env.goal_state(), np.float64),
        )
    state, goal = sample_states(rng, *bounds(env), 2)
    return state, goal


def render_states(
    env: ControllableEnv, states: np.ndarray, bar: Progress | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Move the env to each state; return (states actually reached, uint8 images).
    ``bar``, if given, is advanced by one per state."""
    reached, images = [], []
    for state in states:
        reached.append(np.asarray(env.set_controllable_state(state), np.float64))
        images.append(env.render_image())
        if bar is not None:
            bar.update(bar.done + 1)
    return np.stack(reached), np.stack(images)


def encode_all(encoders: Mapping[str, RewardEncoder], images: np.ndarray) -> dict[str, np.ndarray]:
    """Latents of ``images`` under every encoder, as float64 (for stable statistics)."""
    return {name: enc.encode(images).astype(np.float64) for name, enc in encoders.items()}


class Progress:
    """``[diagnose] <label> i/n`` on stderr, at most once a second and at the end."""

    def __init__(self, label: str, total: int, enabled: bool = True) -> None:
        self.label, self.total, self.enabled = label, total, enabled
        self.start = self.last = time.perf_counter()
        self.done = 0

    def update(self, done: int) -> None:
        self.done = done
        now = time.perf_counter()
        if self.enabled and (done >= self.total or now - self.last >= 1.0):
            self.last = now
            print(
                f"[diagnose] {self.label} {done}/{self.total} ({now - self.start:.0f}s)",
                file=sys.stderr,
                flush=True,
            )
