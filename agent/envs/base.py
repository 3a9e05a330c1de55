"""The goal-conditioned image env contract shared by every env in this package.

An env shows the agent only two images: the current camera frame and a goal frame,
rendered by putting the simulator into the goal state and restoring it exactly.
The true state lives in ``info`` (for evaluation) and behind the *controllable state*
methods (for the encoder diagnostics); it never enters the observation unless the env
is built with ``obs_mode="state"`` (the state-oracle check of the learner).

Subclasses implement the abstract methods; this base class owns the episode
bookkeeping, argument checking and the Gymnasium spaces.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from agent.config import EPISODE_STEPS

OBS_MODES = ("image", "state")


def check_image_size(image_size: int, minimum: int, maximum: int = 256) -> int:
    """Return ``image_size`` or raise a ValueError that names the argument."""
    if isinstance(image_size, bool) or not isinstance(image_size, int | np.integer):
        raise ValueError(f"image_size must be an integer, got {image_size!r}")
    if not minimum <= image_size <= maximum:
        raise ValueError(f"image_size must be in [{minimum}, {maximum}], got {image_size}")
    return int(image_size)


def check_action(action: Any, space: gym.spaces.Box) -> np.ndarray:
    """Return ``action`` as float64, or raise a ValueError naming the problem.

    NaN/inf or out-of-range actions are errors, not silently clipped: a learner that
    emits them has a bug we want to hear about.
    """
    a = np.asarray(action, dtype=np.float64)
    if a.shape != space.shape:
        raise ValueError(f"action must have shape {space.shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"action must be finite, got {a.tolist()}")
    tol = 1e-6
    if np.any(a < space.low - tol) or np.any(a > space.high + tol):
        raise ValueError(
            f"action must lie in [{space.low.min()}, {space.high.max()}], got {a.tolist()}"
        )
    return np.clip(a, space.low, space.high)


class GoalImageEnv(gym.Env[dict[str, np.ndarray], np.ndarray], ABC):
    """Base class: image observation + goal image, 50-step episodes, true state in info.

    Observation (``obs_mode="image"``): ``{"image": uint8 HxWx3, "goal_image": uint8 HxWx3}``.
    Observation (``obs_mode="state"``): ``{"state": float32 [S], "goal_state": float32 [G]}``
    where ``state`` is the full task state the oracle needs and ``goal_state`` the goal.
    Reward: ``true_reward(controllable_state(), goal_state())``, the true negative goal
    distance (used only by the state oracle; image methods replace it with their
    encoder reward). ``info`` has every key of
    ``metric_names``; episodes truncate after ``EPISODE_STEPS`` and never terminate.

    Controllable state (used by ``encoders.diagnostics``): a vector in the space where
    goals live (``state_names``), which can be read, set (the env reports the state
    actually reached), sampled, and rendered, together with the true reward
    ``-||s - g||`` whose gradient in ``s`` is analytic.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 25}
    #: names of the controllable-state dimensions, e.g. ("x", "y")
    state_names: ClassVar[tuple[str, ...]] = ()
    #: info keys reported by evaluation; "is_success" is always first
    metric_names: ClassVar[tuple[str, ...]] = ("is_success", "distance")
    min_image_size: ClassVar[int] = 32
    default_image_size: ClassVar[int] = 48

    def __init__(
        self,
        image_size: int | None = None,
        obs_mode: str = "image",
        render_mode: str | None = "rgb_array",
    ) -> None:
        size = self.default_image_size if image_size is None else image_size
        self.image_size = check_image_size(size, self.min_image_size)
        if obs_mode not in OBS_MODES:
            raise ValueError(f"obs_mode must be one of {OBS_MODES}, got {obs_mode!r}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be 'rgb_array' or None, got {render_mode!r}")
        self.obs_mode = obs_mode
        self.render_mode = render_mode
        self._elapsed: int | None = None
        self._goal_image: np.ndarray | None = None
        image = gym.spaces.Box(0, 255, (self.image_size, self.image_size, 3), np.uint8)
        if obs_mode == "image":
            self.observation_space = gym.spaces.Dict({"image": image, "goal_image": image})
        else:
            s_dim, g_dim = self._state_dims()
            self.observation_space = gym.spaces.Dict(
                {
                    "state": gym.spaces.Box(-np.inf, np.inf, (s_dim,), np.float32),
                    "goal_state": gym.spaces.Box(-np.inf, np.inf, (g_dim,), np.float32),
                }
            )

    # ---- hooks for subclasses -------------------------------------------------------
    def _state_dims(self) -> tuple[int, int]:
        """(dim of the oracle's full task state, dim of the goal); override when the task
        state holds more than the controllable state (fetch_push: gripper and object)."""
        return len(self.state_names), len(self.state_names)

    @abstractmethod
    def _reset_sim(self, rng: np.random.Generator) -> None:
        """Reset the simulator and sample a new goal with ``rng``."""

    @abstractmethod
    def _apply_action(self, action: np.ndarray) -> None:
        """Advance the simulator by one control step."""

    @abstractmethod
    def _task_state(self) -> np.ndarray:
        """The oracle's full task state (e.g. gripper and object positions)."""

    @abstractmethod
    def _metrics(self) -> dict[str, float]:
        """True-state metrics for ``info``: every key of ``metric_names``."""

    @abstractmethod
    def _render_goal_image(self) -> np.ndarray:
        """Render the goal: move the sim to the goal state, render, restore exactly."""

    @abstractmethod
    def render_image(self) -> np.ndarray:
        """The current camera frame, uint8 HxWx3."""

    @abstractmethod
    def controllable_state(self) -> np.ndarray:
        """The current controllable state (same space as ``goal_state``)."""

    @abstractmethod
    def set_controllable_state(self, state: np.ndarray) -> np.ndarray:
        """Move the sim to ``state`` as far as it can; return the state actually reached."""

    @abstractmethod
    def goal_state(self) -> np.ndarray:
        """The current goal in controllable-state space."""

    @abstractmethod
    def set_goal_state(self, goal: np.ndarray) -> None:
        """Replace the episode's goal (and its goal image)."""

    @abstractmethod
    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Box (low, high) from which goals and diagnostic states are sampled."""

    @abstractmethod
    def sim_state(self) -> Any:
        """An exact copy of the simulator's state (not the episode's bookkeeping)."""

    @abstractmethod
    def set_sim_state(self, state: Any) -> None:
        """Put the simulator back into ``state`` (from ``sim_state``) exactly: the next
        ``step`` continues as it would have from there."""

    # ---- Gymnasium API --------------------------------------------------------------
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        super().reset(seed=seed)
        self._elapsed = 0
        self._reset_sim(self.np_random)
        self._goal_image = self._render_goal_image() if self.obs_mode == "image" else None
        return self._observation(), self._info()

    def step(
        self, action: np.ndarray
    ) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        if self._elapsed is None:
            raise RuntimeError("call reset() before step()")
        self._apply_action(check_action(action, self.action_space))
        self._elapsed += 1
        info = self._info()
        reward = self.true_reward(self.controllable_state(), self.goal_state())
        truncated = self._elapsed >= EPISODE_STEPS
        return self._observation(), reward, False, truncated, info

    def render(self) -> np.ndarray | None:
        return self.render_image() if self.render_mode == "rgb_array" else None

    def goal_image(self) -> np.ndarray:
        """The goal's camera frame: the observation's in image mode, rendered on demand in
        state mode (so the state oracle's episodes can be filmed too)."""
        if self._goal_image is not None:
            return self._goal_image.copy()
        return self._render_goal_image()

    # ---- helpers --------------------------------------------------------------------
    def _observation(self) -> dict[str, np.ndarray]:
        if self.obs_mode == "image":
            return {"image": self.render_image(), "goal_image": self._goal_image.copy()}
        return {
            "state": self._task_state().astype(np.float32),
            "goal_state": self.goal_state().astype(np.float32),
        }

    def _info(self) -> dict[str, Any]:
        info: dict[str, Any] = dict(self._metrics())
        info["is_success"] = float(info["is_success"])
        return info

    @staticmethod
    def true_reward(state: np.ndarray, goal: np.ndarray) -> float:
        """The true reward ``-||s - g||`` in controllable-state space."""
        return -math.sqrt(float(np.sum((np.asarray(state) - np.asarray(goal)) ** 2)))
