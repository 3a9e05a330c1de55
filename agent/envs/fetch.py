"""fetch_reach and fetch_push: gymnasium-robotics ``FetchReach-v4`` / ``FetchPush-v4`` seen
through a camera, with a rendered goal image.

The simulation, reset and action handling are gymnasium-robotics' own (the v4 classes,
built directly); this module adds the goal image, the controllable state and the
camera. The action is the 3-D end-effector displacement in [-1, 1] (x 5 cm, as in
Fetch); the gripper dimension is dropped and the gripper stays blocked.

Goal boxes (``state_bounds()``), with g0 the gripper position after Fetch's reset:
- fetch_reach: gripper xyz in g0 +- 0.15 m (FetchReach-v4's box), except z in
  [g0z - 0.10, g0z + 0.15]: v4's lowest goals lie inside the table top (z = 0.40) and
  cannot be reached or shown.
- fetch_push: object xyz with xy in g0 +- 0.15 m and z = the object's resting height
  (FetchPush-v4's box).
Goals are drawn uniformly from the box, as Fetch draws them (a goal may be reached at
the start, as in Fetch); the block starts where FetchPush-v4 puts it. A uniformly random
agent reaches the goal at some step of an episode in 16.7% of fetch_reach and 7.4% of
fetch_push episodes (1,000 episodes, ``encoders.diagnostics.random_exploration``). On the
same 200 episodes, v4's full z range changes fetch_reach's rate from 25.5% to 22.5%, and
drawing again the goals reached at the start (as this env did before) fetch_push's from
8.5% to 0%.
Success: distance < 0.05 m (Fetch's threshold).

Camera: Fetch's own viewer camera (gymnasium-robotics ``DEFAULT_CAMERA_CONFIG``: distance
2.5, azimuth 132, elevation -14, looking at (1.3, 0.75, 0.55)), the view the thesis used;
it shows the whole robot and table.

Workspace bounds (``hand_bounds()``), as multiworld bounds RIG's Sawyer hand: each step's
commanded gripper position is clipped to a box ``workspace_margin`` (default 5 cm) around
the positions the task needs (reach: the goal box; push: the block's box widened by the
block's size so the gripper can get behind it). An image reward can then never be
improved by moving the arm out of the picture (measured with an unbounded arm: the pixel
distance to the goal image was lower with the gripper 0.4 m above its start than at the
start in 9 of 10 episodes, and a PIXEL agent learned to leave the view).
``workspace_margin=None`` gives Fetch's unbounded arm.
"""

from __future__ import annotations

import contextlib
import io
from abc import abstractmethod
from typing import Any, ClassVar

import mujoco
import numpy as np

from agent.envs import _mujoco as mj

SUCCESS_DISTANCE = 0.05
#: physics steps per drive iteration when moving the gripper to a set position
_DRIVE_SUBSTEPS = 20
#: gymnasium-robotics' Fetch viewer camera (``fetch_env.DEFAULT_CAMERA_CONFIG``)
DEFAULT_CAMERA: dict[str, Any] = {
    "lookat": [1.3, 0.75, 0.55],
    "distance": 2.5,
    "azimuth": 132.0,
    "elevation": -14.0,
}
#: metres the gripper moves per unit of action (Fetch's ``pos_ctrl *= 0.05``)
ACTION_SCALE = 0.05
#: FetchPush's block is 5 cm wide: the gripper box reaches this far past the block's box
_BLOCK_SIZE = 0.05


def _quiet_import() -> contextlib.AbstractContextManager:
    """gymnasium_robotics prints a notice about Adroit envs to stderr on import, in every
    worker; it does not concern Fetch."""
    return contextlib.redirect_stderr(io.StringIO())


class _FetchImageEnv(mj.MujocoGoalImageEnv):
    """Shared Fetch logic; subclasses choose the gymnasium-robotics class and the goal."""

    mocap_body: ClassVar[str] = "robot0:mocap"
    default_image_size: ClassVar[int] = 84
    default_camera: ClassVar[dict[str, Any]] = DEFAULT_CAMERA

    @property
    def _g0(self) -> np.ndarray:
        """The gripper position after Fetch's reset, the centre of the goal box."""
        return self._sim.initial_gripper_xpos

    def _object_joint(self) -> tuple[slice, slice]:
        """The block's qpos and qvel slices; empty without a block (fetch_reach)."""
        if not self._sim.has_object:
            return slice(0, 0), slice(0, 0)
        return mj.free_joint(self.model, "object0:joint")

    # ---- simulator --------------------------------------------------------------------
    def _reset_sim(self, rng: np.random.Generator) -> None:
        self._sim.np_random = rng  # Fetch's own reset (object placement) draws from our rng
        self._sim.reset()
        mj.sync_mocap(self.model, self.data)
        self._goal = rng.uniform(*self.state_bounds())

    def _apply_action(self, action: np.ndarray) -> None:
        # Fetch's step re-syncs the mocap to the gripper, adds ACTION_SCALE * action, steps
        # 20 substeps and re-blocks the gripper with an mj_forward, so the data is
        # consistent afterwards. Bounds: the action that moves the mocap to the clipped point.
        if self.workspace_margin is not None:
            grip = self.gripper_position()
            target = np.clip(grip + ACTION_SCALE * action, *self.hand_bounds())
            action = np.clip((target - grip) / ACTION_SCALE, -1.0, 1.0)
        self._sim.step(np.append(action, 0.0))

    def hand_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The box the commanded gripper position is clipped to (see the module docstring)."""
        low, high = self._task_hand_box()
        margin = self.workspace_margin or 0.0
        return low - margin, high + margin

    @abstractmethod
    def _task_hand_box(self) -> tuple[np.ndarray, np.ndarray]:
        """The box the gripper must be able to reach for the task (before the margin)."""

    def gripper_position(self) -> np.ndarray:
        """The gripper (grip site) position, world xyz."""
        return self.data.site("robot0:grip").xpos.copy()

    def set_gripper_position(self, xyz: np.ndarray) -> np.ndarray:
        """Move only the arm so the gripper sits at ``xyz``, from Fetch's reset posture;
        return the position reached. Objects stay where they are."""
        target = mj.check_vector(xyz, 3, "xyz")
        object_qpos, object_qvel = self._object_joint()
        object_pose = self.data.qpos[object_qpos].copy()
        qpos = self._sim.initial_qpos.copy()
        qpos[object_qpos] = object_pose

        def hold() -> None:
            self._sim._step_callback()  # keep the gripper blocked, as Fetch's step does
            self.data.qpos[object_qpos] = object_pose
            self.data.qvel[object_qvel] = 0.0

        mj.drive_mocap(
            self.model, self.data, qpos, self.gripper_position, target, _DRIVE_SUBSTEPS, hold, 0.02
        )
        return self.gripper_position()

    # ---- goals and metrics ------------------------------------------------------------
    def _metrics(self) -> dict[str, float]:
        distance = float(np.linalg.norm(self.controllable_state() - self._goal))
        return {"is_success": float(distance < SUCCESS_DISTANCE), "distance": distance}


class FetchReachImageEnv(_FetchImageEnv):
    """Move the gripper to a goal position (FetchReach-v4). Goal: gripper xyz."""

    state_names: ClassVar[tuple[str, ...]] = ("gripper_x", "gripper_y", "gripper_z")

    def _make_sim(self) -> Any:
        with _quiet_import():
            from gymnasium_robotics.envs.fetch.reach import MujocoFetchReachEnv
        return MujocoFetchReachEnv(reward_type="dense")

    def _task_state(self) -> np.ndarray:
        return self.gripper_position()

    def controllable_state(self) -> np.ndarray:
        return self.gripper_position()

    def set_controllable_state(self, state: np.ndarray) -> np.ndarray:
        return self.set_gripper_position(mj.check_vector(state, 3, "state"))

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self._g0 - [0.15, 0.15, 0.10], self._g0 + 0.15

    def _task_hand_box(self) -> tuple[np.ndarray, np.ndarray]:
        return self.state_bounds()


class FetchPushImageEnv(_FetchImageEnv):
    """Push a block to a goal position on the table (FetchPush-v4). Goal: object xyz.

    ``gripper_position()`` / ``set_gripper_position(xyz)`` move the arm only.
    """

    state_names: ClassVar[tuple[str, ...]] = ("object_x", "object_y", "object_z")

    def _make_sim(self) -> Any:
        with _quiet_import():
            from gymnasium_robotics.envs.fetch.push import MujocoFetchPushEnv
        return MujocoFetchPushEnv(reward_type="dense")

    def _state_dims(self) -> tuple[int, int]:
        return 9, 3  # gripper xyz, object xyz, object - gripper

    def _task_state(self) -> np.ndarray:
        grip, obj = self.gripper_position(), self.controllable_state()
        return np.concatenate([grip, obj, obj - grip])

    def controllable_state(self) -> np.ndarray:
        return self.data.site("object0").xpos.copy()

    def set_controllable_state(self, state: np.ndarray) -> np.ndarray:
        """Place the block at ``state`` (upright, at rest); the arm does not move."""
        xyz = mj.check_vector(state, 3, "state")
        object_qpos, object_qvel = self._object_joint()
        self.data.qpos[object_qpos] = np.concatenate([xyz, [1.0, 0.0, 0.0, 0.0]])
        self.data.qvel[object_qvel] = 0.0
        mujoco.mj_forward(self.model, self.data)
        return self.controllable_state()

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        z = self._sim.height_offset
        return (
            np.array([self._g0[0] - 0.15, self._g0[1] - 0.15, z]),
            np.array([self._g0[0] + 0.15, self._g0[1] + 0.15, z]),
        )

    def _task_hand_box(self) -> tuple[np.ndarray, np.ndarray]:
        # behind the block anywhere in its box; from the block's height to 15 cm over g0
        low, high = self.state_bounds()
        return (
            np.append(low[:2] - _BLOCK_SIZE, low[2]),
            np.append(high[:2] + _BLOCK_SIZE, self._g0[2] + 0.15),
        )
