"""Goal-conditioned image environments, registered with Gymnasium.

``make_env("point_reach", image_size=48)`` or ``gymnasium.make("gcrl/point_reach-v0")``.
Importing this module registers every env; MuJoCo envs import MuJoCo only when built.
"""

from __future__ import annotations

import difflib
import importlib
import os
from typing import Any

import gymnasium as gym

# Headless rendering must be chosen before mujoco is imported anywhere.
os.environ.setdefault("MUJOCO_GL", "egl")

#: short name -> "module:Class"
ENV_ENTRY_POINTS: dict[str, str] = {
    "point_reach": "agent.envs.point_reach:PointReachEnv",
    "fetch_reach": "agent.envs.fetch:FetchReachImageEnv",
    "fetch_push": "agent.envs.fetch:FetchPushImageEnv",
    "sawyer_door": "agent.envs.sawyer_door:SawyerDoorImageEnv",
}
ENV_NAMES: tuple[str, ...] = tuple(ENV_ENTRY_POINTS)


def gym_id(name: str) -> str:
    """The Gymnasium id of a short env name."""
    return f"gcrl/{name}-v0"


def check_env_name(name: str) -> str:
    """Return ``name`` if it is a known env, else raise a ValueError listing the names."""
    if name not in ENV_ENTRY_POINTS:
        close = difflib.get_close_matches(str(name), ENV_NAMES, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ValueError(f"unknown env {name!r}{hint}; known envs: {', '.join(ENV_NAMES)}")
    return name


def env_class(name: str) -> type[gym.Env]:
    """The class of env ``name``, importing its module (and MuJoCo, for those envs)."""
    check_env_name(name)
    module_name, class_name = ENV_ENTRY_POINTS[name].split(":")
    return getattr(importlib.import_module(module_name), class_name)


def make_env(name: str, **kwargs: Any) -> gym.Env:
    """Build env ``name`` (see ``ENV_NAMES``) with its keyword options, unwrapped.

    Our envs count their own 50 steps, so no TimeLimit or order-enforcing wrapper is
    needed; ``gymnasium.make`` adds Gymnasium's standard wrappers on top.
    """
    return env_class(name)(**kwargs)


for _name, _entry in ENV_ENTRY_POINTS.items():
    if gym_id(_name) not in gym.registry:
        gym.register(id=gym_id(_name), entry_point=_entry, disable_env_checker=True)
