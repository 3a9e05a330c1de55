"""What the analyses share: the env protocol, state sampling, rendering, progress lines."""

from __future__ import annotations

import sys
import time
from collections.abc import Mapping
from typing import Any, Protocol

import numpy as np

from encoders.base import RewardEncoder


class ControllableEnv(Protocol):
    """The part of ``agent.envs.base.GoalImageEnv`` the diagnostics use (see its docstring)."""

    state_names: tuple[str, ...]
    action_space: Any

    def reset(self, *, seed: int | None = None) -> tuple[Any, dict]: ...
    def step(self, action: np.ndarray) -> tuple[Any, float, bool, bool, dict]: ...

    def controllable_state(self) -> np.ndarray: ...
    def set_controllable_state(self, state: np.ndarray) -> np.ndarray: ...
    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]: ...
    def render_image(self) -> np.ndarray: ...


def bounds(env: ControllableEnv) -> tuple[np.ndarray, np.ndarray]:
    """The env's state box as float64 arrays."""
    low, high = (np.asarray(b, np.float64) for b in env.state_bounds())
    return low, high


def sample_states(
    rng: np.random.Generator, low: np.ndarray, high: np.ndarray, n: int, margin: float = 0.0
) -> np.ndarray:
    """``n`` states uniform in the box shrunk by ``margin`` on every side (a side narrower
    than ``2 * margin`` collapses to its centre)."""
    lo = np.minimum(low + margin, (low + high) / 2)
    hi = np.maximum(high - margin, (low + high) / 2)
    return rng.uniform(lo, hi, size=(n, len(low)))


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
