"""point_reach: a 2-D point pushed toward a goal point, rendered with numpy.

No MuJoCo: thousands of steps per second, so tests and demos can show real learning
from pixels on a CPU. The point is drawn as a soft Gaussian blob so that pixel
distances change smoothly with the point's position, and the arena has a fixed
shaded border so the image is not translation-invariant.
"""

from __future__ import annotations

from typing import ClassVar

import gymnasium as gym
import numpy as np

from agent.envs.base import GoalImageEnv

ARENA = 1.0  # the point lives in [-ARENA, ARENA]^2
MAX_STEP = 0.15  # displacement per step at |action| = 1


class PointReachEnv(GoalImageEnv):
    """A point in the square [-1, 1]^2; action = 2-D displacement in [-1, 1] (x 0.15).

    Success: distance to the goal below ``success_threshold`` (default 0.15).
    Goals and starts are sampled uniformly from the arena, at least one threshold apart.
    """

    state_names: ClassVar[tuple[str, ...]] = ("x", "y")

    def __init__(
        self,
        image_size: int | None = None,
        obs_mode: str = "image",
        render_mode: str | None = "rgb_array",
        success_threshold: float = 0.15,
        blob_sigma: float = 0.25,
    ) -> None:
        if not 0 < success_threshold < ARENA:
            raise ValueError(f"success_threshold must be in (0, {ARENA}), got {success_threshold}")
        if not 0 < blob_sigma <= ARENA:
            raise ValueError(f"blob_sigma must be in (0, {ARENA}], got {blob_sigma}")
        super().__init__(image_size=image_size, obs_mode=obs_mode, render_mode=render_mode)
        self.success_threshold = float(success_threshold)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        n = self.image_size
        # pixel centres in arena coordinates; y grows upward in the arena, downward in rows
        coords = (np.arange(n) + 0.5) / n * 2 * ARENA - ARENA
        self._xx, self._yy = np.meshgrid(coords, -coords)
        self._inv_two_sigma2 = 1.0 / (2.0 * blob_sigma**2)
        # background: a dim vertical gradient with a border frame, constant per size
        bg = np.empty((n, n, 3), np.float32)
        bg[..., 0] = 30.0
        bg[..., 1] = 40.0 + 40.0 * (self._yy + ARENA) / (2 * ARENA)
        bg[..., 2] = 60.0
        border = max(1, n // 24)
        bg[:border], bg[-border:], bg[:, :border], bg[:, -border:] = 120.0, 120.0, 120.0, 120.0
        self._background = bg
        self._blob_color = np.array([225.0, 215.0, -40.0], np.float32)
        self._pos = np.zeros(2)
        self._goal = np.zeros(2)

    def _reset_sim(self, rng: np.random.Generator) -> None:
        self._goal = rng.uniform(-0.9 * ARENA, 0.9 * ARENA, 2)
        while True:
            self._pos = rng.uniform(-0.9 * ARENA, 0.9 * ARENA, 2)
            if np.linalg.norm(self._pos - self._goal) > 2 * self.success_threshold:
                break

    def _apply_action(self, action: np.ndarray) -> None:
        self._pos = np.clip(self._pos + MAX_STEP * action, -ARENA, ARENA)

    def _task_state(self) -> np.ndarray:
        return self._pos.copy()

    def _metrics(self) -> dict[str, float]:
        distance = float(np.linalg.norm(self._pos - self._goal))
        return {"is_success": float(distance < self.success_threshold), "distance": distance}

    def _draw(self, pos: np.ndarray) -> np.ndarray:
        d2 = (self._xx - pos[0]) ** 2 + (self._yy - pos[1]) ** 2
        blob = np.exp(-d2 * self._inv_two_sigma2)[..., None]
        img = self._background + blob * self._blob_color
        return np.clip(img, 0, 255).astype(np.uint8)

    def _render_goal_image(self) -> np.ndarray:
        return self._draw(self._goal)

    def render_image(self) -> np.ndarray:
        return self._draw(self._pos)

    def controllable_state(self) -> np.ndarray:
        return self._pos.copy()

    def set_controllable_state(self, state: np.ndarray) -> np.ndarray:
        self._pos = np.clip(np.asarray(state, dtype=np.float64), -ARENA, ARENA)
        return self._pos.copy()

    def goal_state(self) -> np.ndarray:
        return self._goal.copy()

    def set_goal_state(self, goal: np.ndarray) -> None:
        self._goal = np.clip(np.asarray(goal, dtype=np.float64), -ARENA, ARENA)
        if self.obs_mode == "image":
            self._goal_image = self._render_goal_image()

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return np.full(2, -0.9 * ARENA), np.full(2, 0.9 * ARENA)

    def sim_state(self) -> np.ndarray:
        return self._pos.copy()

    def set_sim_state(self, state: np.ndarray) -> None:
        self._pos = np.array(state, dtype=np.float64)
