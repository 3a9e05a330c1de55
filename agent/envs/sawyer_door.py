"""sawyer_door: open metaworld's door to a goal angle and put the hand at a goal position.

Built on metaworld 3.1's Sawyer door model (the ``SawyerDoorEnvV3`` class, constructed
directly). Only its model, data, hand reset and hand box are used; stepping, goals
and rendering are ours (metaworld's step needs a task and renders at its own size):

- action: 3-D hand displacement in [-1, 1] x ``action_scale`` m per step, applied to
  the mocap that drives the hand (clipped to ``hand_bounds()``), ``frame_skip``
  physics steps of 2.5 ms per env step; the gripper stays closed. Defaults: 3 cm per
  25 ms (Fetch: 5 cm per 40 ms). metaworld's 1 cm per 12.5 ms is too slow to reach the
  handle, open the door and move the hand away within 50 steps.
- start: the hand at metaworld's home position (0, 0.6, 0.2), the door closed at
  metaworld's default door position (0.1, 0.95, 0.15). Always the same.
- goal: hand xyz (the ``hand`` body) and the door angle (``doorjoint``; metaworld's door
  opens to negative angles, range [-2, 0]), drawn uniformly from ``GOAL_LOW``..``GOAL_HIGH``:
  hand in front of the door, never inside it at any goal angle (checked with MuJoCo's
  contacts on 200 samples), angle in [-0.5, 0]. ``benchmarks/bench_envs.py`` runs a
  scripted hook-pull-and-move policy to show the goals can be reached in 50 steps.
- success: |angle - goal angle| < 0.02 rad and ||hand - goal hand|| < 0.03 m. This goal
  (a door angle and a hand position, both to reach) is harder than the thesis' door task:
  a uniformly random agent succeeds at some step in 0.2% of episodes, the angle alone
  in 4.0% and the hand alone in 4.1% (1,000 episodes).
- workspace bounds, as multiworld bounds RIG's Sawyer hand (hand_low/hand_high): the mocap
  is clipped to ``HAND_TASK_LOW``..``HAND_TASK_HIGH`` (the goal box and the door handle's
  reach, approached from above) widened by ``workspace_margin`` (default 5 cm), inside
  metaworld's own hand box; ``workspace_margin=None`` gives metaworld's box alone.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import mujoco
import numpy as np

from agent.envs import _mujoco as mj

ANGLE_SUCCESS = 0.02  # rad
HAND_SUCCESS = 0.03  # m
#: goal box: hand x, y, z (m), door angle (rad)
GOAL_LOW = np.array([-0.15, 0.45, 0.10, -0.5])
GOAL_HIGH = np.array([0.10, 0.55, 0.25, 0.0])
#: where the hand must be able to go: the goal box's hand part and the handle's hook point
#: (0.33, 0.80, 0.19) from above (see benchmarks/bench_envs.py's scripted policy)
HAND_TASK_LOW = np.array([-0.15, 0.45, 0.10])
HAND_TASK_HIGH = np.array([0.35, 0.80, 0.31])
DOOR_POSITION = (0.1, 0.95, 0.15)  # metaworld's init_config["obj_init_pos"]
GRIPPER_CLOSED = (1.0, -1.0)  # ctrl of the two finger actuators
_DRIVE_SUBSTEPS = 10
#: default view: top-down over the hand's box, as the thesis' door: the door's swing and the
#: hand anywhere in ``hand_bounds()`` are in the picture, the robot's base at the bottom
DEFAULT_CAMERA: dict[str, Any] = {
    "lookat": [0.1, 0.64, 0.12],
    "distance": 1.2,
    "azimuth": 90.0,
    "elevation": -89.0,
}


class SawyerDoorImageEnv(mj.MujocoGoalImageEnv):
    """Sawyer arm, hinged door; goal = hand xyz + door angle (see the module docstring)."""

    state_names: ClassVar[tuple[str, ...]] = ("hand_x", "hand_y", "hand_z", "door_angle")
    metric_names: ClassVar[tuple[str, ...]] = (
        "is_success",
        "angle_success",
        "hand_success",
        "angle_distance",
        "hand_distance",
    )
    default_camera: ClassVar[dict[str, Any]] = DEFAULT_CAMERA

    def __init__(
        self,
        image_size: int | None = None,
        obs_mode: str = "image",
        render_mode: str | None = "rgb_array",
        camera: str | Mapping[str, Any] | None = None,
        action_scale: float = 0.03,
        frame_skip: int = 10,
        workspace_margin: float | None = 0.05,
    ) -> None:
        if not 0 < action_scale <= 0.1:
            raise ValueError(f"action_scale must be in (0, 0.1] m, got {action_scale}")
        if isinstance(frame_skip, bool) or not isinstance(frame_skip, int) or frame_skip < 1:
            raise ValueError(f"frame_skip must be an integer >= 1, got {frame_skip!r}")
        super().__init__(
            image_size=image_size,
            obs_mode=obs_mode,
            render_mode=render_mode,
            camera=camera,
            workspace_margin=workspace_margin,
        )
        self.action_scale = float(action_scale)
        self.frame_skip = frame_skip
        self._door_qpos = self.model.joint("doorjoint").qposadr[0]
        self._door_qvel = self.model.joint("doorjoint").dofadr[0]
        self._door_range = self.model.joint("doorjoint").range.copy()
        # the start state, computed once: metaworld's hand reset, then close the gripper
        self.model.body("door").pos = DOOR_POSITION
        mujoco.mj_resetData(self.model, self.data)
        mujoco.mj_forward(self.model, self.data)
        self._sim._reset_hand()
        for _ in range(10):
            self._physics_step()
        self.data.time = 0.0
        self._home = mj.snapshot(self.model, self.data)
        self._home_qpos = self.data.qpos.copy()

    def _make_sim(self) -> Any:
        # imported only when a door env is built: metaworld takes about a second to import
        from metaworld.envs.sawyer_door_v3 import SawyerDoorEnvV3

        return SawyerDoorEnvV3(render_mode=None)  # its renderer is never used

    # ---- simulator --------------------------------------------------------------------
    def _physics_step(self) -> None:
        self.data.ctrl[:] = GRIPPER_CLOSED
        mujoco.mj_step(self.model, self.data, nstep=self.frame_skip)
        mujoco.mj_forward(self.model, self.data)  # positions now match the state

    def _reset_sim(self, rng: np.random.Generator) -> None:
        mj.restore(self.model, self.data, self._home)
        # the box lies >= 5 cm from the home hand position: no episode starts at the goal
        self._goal = rng.uniform(GOAL_LOW, GOAL_HIGH)

    def _apply_action(self, action: np.ndarray) -> None:
        target = self.data.mocap_pos[0] + self.action_scale * action
        self.data.mocap_pos[0] = np.clip(target, *self.hand_bounds())
        self._physics_step()

    def hand_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The box the hand's mocap is clipped to (see the module docstring)."""
        low, high = self._sim.mocap_low, self._sim.mocap_high
        if self.workspace_margin is None:
            return low.copy(), high.copy()
        return (
            np.maximum(low, HAND_TASK_LOW - self.workspace_margin),
            np.minimum(high, HAND_TASK_HIGH + self.workspace_margin),
        )

    def _task_state(self) -> np.ndarray:
        return self.controllable_state()

    # ---- controllable state -----------------------------------------------------------
    def controllable_state(self) -> np.ndarray:
        hand = self.data.body("hand").xpos
        return np.append(hand, self.data.qpos[self._door_qpos])

    def set_controllable_state(self, state: np.ndarray) -> np.ndarray:
        """Set the door angle, then drive the hand there from its home posture.

        Starting from the same posture each time makes the image a function of the
        state alone. Returns the state reached (angle clipped to the joint range).
        """
        s = mj.check_vector(state, 4, "state")
        angle = float(np.clip(s[3], *self._door_range))
        qpos = self._home_qpos.copy()
        qpos[self._door_qpos] = angle

        def hold() -> None:
            self.data.qpos[self._door_qpos] = angle
            self.data.qvel[self._door_qvel] = 0.0

        def hand() -> np.ndarray:
            return self.data.body("hand").xpos.copy()

        self.data.ctrl[:] = GRIPPER_CLOSED
        mj.drive_mocap(self.model, self.data, qpos, hand, s[:3], _DRIVE_SUBSTEPS, hold)
        return self.controllable_state()

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return GOAL_LOW.copy(), GOAL_HIGH.copy()

    # ---- metrics ----------------------------------------------------------------------
    def _metrics(self) -> dict[str, float]:
        state = self.controllable_state()
        angle_d = float(abs(state[3] - self._goal[3]))
        hand_d = float(np.linalg.norm(state[:3] - self._goal[:3]))
        angle_ok, hand_ok = angle_d < ANGLE_SUCCESS, hand_d < HAND_SUCCESS
        return {
            "is_success": float(angle_ok and hand_ok),
            "angle_success": float(angle_ok),
            "hand_success": float(hand_ok),
            "angle_distance": angle_d,
            "hand_distance": hand_d,
        }
