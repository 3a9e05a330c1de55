"""What the Fetch and Sawyer envs share: exact snapshots, a mocap drive, cameras, one
fast offscreen renderer per env, and a base class that builds the simulator, camera and
action space and renders goal images.

Import this module only from MuJoCo envs: it imports ``mujoco``.
"""

from __future__ import annotations

import math
import numbers
from abc import abstractmethod
from collections.abc import Callable, Mapping, Sequence
from typing import Any, ClassVar

import gymnasium as gym
import mujoco
import numpy as np

from agent.envs.base import GoalImageEnv

#: the full simulator state needed to continue a simulation bit-exactly
#: (qpos, qvel, act, warm start, ctrl, applied forces, mocap, eq_active, time)
_STATE = mujoco.mjtState.mjSTATE_INTEGRATION
#: keys of a free-camera spec: ``{"lookat": [x, y, z], "distance", "azimuth", "elevation"}``
FREE_CAMERA_KEYS = ("lookat", "distance", "azimuth", "elevation")
#: geom group our renderer never draws (mocap handles); MuJoCo's default hides 3..5 too
_HIDDEN_GROUP = 5


def snapshot(model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
    """The full integration state of ``data`` as a flat float64 array."""
    state = np.empty(mujoco.mj_stateSize(model, _STATE))
    mujoco.mj_getState(model, data, state, _STATE)
    return state


def restore(model: mujoco.MjModel, data: mujoco.MjData, state: np.ndarray) -> None:
    """Put ``data`` back into ``state`` exactly and recompute everything derived from it.

    ``mj_forward`` rewrites the solver warm start, so the state is set again after it:
    the next ``mj_step`` then continues exactly as if nothing had happened.
    """
    mujoco.mj_setState(model, data, state, _STATE)
    mujoco.mj_forward(model, data)
    mujoco.mj_setState(model, data, state, _STATE)


def sync_mocap(model: mujoco.MjModel, data: mujoco.MjData) -> None:
    """Move every weld-attached mocap body onto the body it drives.

    After ``mj_resetData`` a mocap sits at its model position (the origin for Fetch);
    stepping physics before this would drag the arm there.
    """
    mujoco.mj_forward(model, data)  # body poses from the current qpos
    for i in range(model.neq):
        if model.eq_type[i] != mujoco.mjtEq.mjEQ_WELD:
            continue
        a, b = model.eq_obj1id[i], model.eq_obj2id[i]
        mocap, body = (a, b) if model.body_mocapid[a] >= 0 else (b, a)
        data.mocap_pos[model.body_mocapid[mocap]] = data.xpos[body]
        data.mocap_quat[model.body_mocapid[mocap]] = data.xquat[body]
    mujoco.mj_forward(model, data)


def drive_mocap(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    qpos: np.ndarray,
    point: Callable[[], np.ndarray],
    target: np.ndarray,
    substeps: int,
    after_step: Callable[[], None] = lambda: None,
    max_move: float = 0.01,
    chunks: int = 300,
    tolerance: float = 1e-4,
) -> None:
    """Put the robot at rest in posture ``qpos`` with mocap 0 synced to its body, then
    drive the mocap until the world point ``point()`` sits on ``target``.

    Starting from the same posture each time makes the result a function of ``qpos``
    and ``target`` alone (a 7-joint arm could otherwise end in other postures), and
    contacts are off while driving, so objects in the way change nothing. The mocap
    moves in a straight line, at most ``max_move`` per ``substeps`` physics steps (a
    jump would make the arm swing wildly); each time the arm is at rest there, the
    mocap's destination is shifted by the remaining error, which removes the weld's sag
    under gravity. ``after_step`` runs after every chunk (e.g. to hold fingers or
    objects in place).
    """
    data.qpos[:] = qpos
    data.qvel[:] = 0.0
    data.qacc_warmstart[:] = 0.0
    sync_mocap(model, data)
    flags = model.opt.disableflags
    model.opt.disableflags = flags | mujoco.mjtDisableBit.mjDSBL_CONTACT
    try:
        destination = data.mocap_pos[0] + (target - point())
        for _ in range(chunks):
            move = destination - data.mocap_pos[0]
            length = np.linalg.norm(move)
            data.mocap_pos[0] += move if length <= max_move else move * (max_move / length)
            mujoco.mj_step(model, data, nstep=substeps)
            after_step()
            if length <= max_move and np.abs(data.qvel).max() < 1e-2:
                error = target - point()
                if np.linalg.norm(error) < tolerance:
                    break
                destination += error
        data.qvel[:] = 0.0
        mujoco.mj_forward(model, data)
    finally:
        model.opt.disableflags = flags


def free_joint(model: mujoco.MjModel, name: str) -> tuple[slice, slice]:
    """The qpos (position, quaternion) and qvel slices of the free joint ``name``."""
    joint = model.joint(name)
    return (
        slice(joint.qposadr[0], joint.qposadr[0] + 7),
        slice(joint.dofadr[0], joint.dofadr[0] + 6),
    )


def make_camera(model: mujoco.MjModel, camera: str | Mapping[str, Any]) -> mujoco.MjvCamera:
    """A camera from a model camera name or a free-camera spec (``FREE_CAMERA_KEYS``).

    Raises a ValueError naming ``camera`` when the name is unknown or the spec is bad.
    """
    cam = mujoco.MjvCamera()
    if isinstance(camera, str):
        cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        if cam_id < 0:
            names = [model.camera(i).name for i in range(model.ncam)]
            raise ValueError(
                f"camera must be one of {names} or a dict with keys {FREE_CAMERA_KEYS}, "
                f"got {camera!r}"
            )
        cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
        cam.fixedcamid = cam_id
        return cam
    if not isinstance(camera, Mapping) or set(camera) != set(FREE_CAMERA_KEYS):
        raise ValueError(
            f"camera must be a camera name or a dict with exactly the keys {FREE_CAMERA_KEYS}, "
            f"got {camera!r}"
        )
    lookat = np.asarray(camera["lookat"], dtype=np.float64)
    scalars = [camera[k] for k in FREE_CAMERA_KEYS[1:]]
    if lookat.shape != (3,) or not np.all(np.isfinite(lookat)):
        raise ValueError(f"camera['lookat'] must be 3 finite numbers, got {camera['lookat']!r}")
    if not all(isinstance(v, numbers.Real) and math.isfinite(v) for v in scalars):
        raise ValueError(f"camera distance/azimuth/elevation must be finite numbers: {camera!r}")
    if camera["distance"] <= 0:
        raise ValueError(f"camera['distance'] must be > 0, got {camera['distance']}")
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.lookat[:] = lookat
    cam.distance, cam.azimuth, cam.elevation = (float(v) for v in scalars)
    return cam


class SceneRenderer:
    """One offscreen ``mujoco.Renderer`` of a fixed square size, tuned for small images.

    Shadows, reflections and multisampling cost most of the frame time and change
    nothing a 48-84 pixel image can show, so they are off. Sites (goal markers, debug
    spheres) and the geoms of ``hidden_bodies`` (translucent mocap handles) are never drawn.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        size: int,
        camera: mujoco.MjvCamera,
        hidden_bodies: Sequence[str] = (),
    ) -> None:
        for name in hidden_bodies:
            model.geom_group[model.geom_bodyid == model.body(name).id] = _HIDDEN_GROUP
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, size)
        model.vis.global_.offheight = max(model.vis.global_.offheight, size)
        model.vis.quality.offsamples = 0  # read when the GL context is made
        model.light_castshadow[:] = 0
        try:
            self._renderer = mujoco.Renderer(model, size, size)
        except mujoco.FatalError as e:  # e.g. mujoco imported before MUJOCO_GL was set
            raise RuntimeError(
                f"cannot create an OpenGL context ({e}); headless machines need MUJOCO_GL=egl "
                "set before mujoco is first imported (importing agent.envs first sets it)"
            ) from e
        flags = self._renderer.scene.flags
        flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        self._option = mujoco.MjvOption()
        self._option.sitegroup[:] = 0
        self._option.geomgroup[_HIDDEN_GROUP] = 0
        self._camera = camera

    def render(self, data: mujoco.MjData) -> np.ndarray:
        """The current frame of ``data`` as uint8 HxWx3."""
        self._renderer.update_scene(data, self._camera, self._option)
        return self._renderer.render()

    def close(self) -> None:
        self._renderer.close()


def check_vector(value: Any, size: int, name: str) -> np.ndarray:
    """``value`` as a float64 vector of ``size`` finite numbers, else a ValueError naming it."""
    v = np.array(value, dtype=np.float64)
    if v.shape != (size,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be {size} finite numbers, got {value!r}")
    return v


def check_margin(margin: Any) -> float | None:
    """``workspace_margin`` as a float in [0, 0.5] m, or None (no bounds); else a ValueError."""
    if margin is None:
        return None
    if isinstance(margin, bool) or not isinstance(margin, numbers.Real) or not 0 <= margin <= 0.5:
        raise ValueError(f"workspace_margin must be None or a number in [0, 0.5] m, got {margin!r}")
    return float(margin)


class MujocoGoalImageEnv(GoalImageEnv):
    """A GoalImageEnv on one MuJoCo model, the simulator of another package's env
    (``_make_sim``) whose stepping, goals and rendering are ours. The action is a 3-D
    hand displacement in [-1, 1]; the renderer is made on the first frame (never in
    state mode); the goal image is rendered by moving the sim to the goal with
    ``set_controllable_state``, rendering and restoring the exact state.

    ``camera``: a model camera name or a free-camera spec (``FREE_CAMERA_KEYS``), None
    for the env's ``default_camera``. ``workspace_margin``: how far (m) the hand may go
    beyond the positions the task needs (``check_margin``), None for no bounds.
    """

    #: body whose geoms (mocap handles) are hidden from the camera
    mocap_body: ClassVar[str] = "mocap"
    default_camera: ClassVar[dict[str, Any]]

    def __init__(
        self,
        image_size: int | None = None,
        obs_mode: str = "image",
        render_mode: str | None = "rgb_array",
        camera: str | Mapping[str, Any] | None = None,
        workspace_margin: float | None = 0.05,
    ) -> None:
        super().__init__(image_size=image_size, obs_mode=obs_mode, render_mode=render_mode)
        self.workspace_margin = check_margin(workspace_margin)
        self._sim = self._make_sim()
        self.model: mujoco.MjModel = self._sim.model
        self.data: mujoco.MjData = self._sim.data
        self._camera = make_camera(self.model, self.default_camera if camera is None else camera)
        self._renderer: SceneRenderer | None = None
        self.action_space = gym.spaces.Box(-1.0, 1.0, (3,), np.float32)
        self._goal = np.zeros(len(self.state_names))

    @abstractmethod
    def _make_sim(self) -> Any:
        """The simulator env this env drives: it has ``model`` and ``data``."""

    def render_image(self) -> np.ndarray:
        if self._renderer is None:
            self._renderer = SceneRenderer(
                self.model, self.image_size, self._camera, hidden_bodies=(self.mocap_body,)
            )
        return self._renderer.render(self.data)

    def _render_goal_image(self) -> np.ndarray:
        saved = snapshot(self.model, self.data)
        self.set_controllable_state(self._goal)
        image = self.render_image()
        restore(self.model, self.data, saved)
        return image

    def goal_state(self) -> np.ndarray:
        return self._goal.copy()

    def sim_state(self) -> np.ndarray:
        return snapshot(self.model, self.data)

    def set_sim_state(self, state: np.ndarray) -> None:
        restore(self.model, self.data, state)

    def set_goal_state(self, goal: np.ndarray) -> None:
        self._goal = check_vector(goal, len(self.state_names), "goal")
        if self.obs_mode == "image":
            self._goal_image = self._render_goal_image()

    def close(self) -> None:
        if getattr(self, "_renderer", None) is not None:
            self._renderer.close()
            self._renderer = None
