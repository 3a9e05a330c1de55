"""How often a uniformly random agent reaches the goal: the exploration difficulty of a task."""

from __future__ import annotations

import numpy as np
import pandas as pd

from encoders.diagnostics.common import ControllableEnv, Progress

EPISODE_STEPS = 50


def random_exploration(
    env: ControllableEnv,
    episodes: int = 100,
    steps: int = EPISODE_STEPS,
    seed: int = 0,
    progress: bool = True,
) -> pd.DataFrame:
    """Share of ``episodes`` random-action episodes of ``steps`` steps in which the goal is
    reached (``info["is_success"]``) at any step. Episode ``k`` starts from
    ``env.reset(seed=seed + k)``, so nothing an earlier analysis left behind reaches it.

    Rows (encoder ``"none"``): ``success_rate`` (the task's success), then ``<flag>_rate``
    for every other ``*success`` flag of the env (the door: ``angle_success_rate`` and
    ``hand_success_rate``, each part of the goal alone).
    """
    env.action_space.seed(seed)
    hits: dict[str, list[bool]] = {}
    bar = Progress("random agent episodes", episodes, progress)
    for episode in range(episodes):
        env.reset(seed=seed + episode)
        reached: dict[str, bool] = {}
        for _ in range(steps):
            _, _, _, _, info = env.step(env.action_space.sample())
            for key, value in info.items():
                if key.endswith("success"):
                    reached[key] = reached.get(key, False) or bool(value)
        for key, value in reached.items():
            hits.setdefault(key.removeprefix("is_"), []).append(value)
        bar.update(episode + 1)
    keys = ["success", *(k for k in hits if k != "success")]
    rows = [
        {"encoder": "none", "metric": f"{k}_rate", "value": float(np.mean(hits[k]))} for k in keys
    ]
    return pd.DataFrame(rows)


def random_frames(
    env: ControllableEnv, num_images: int, seed: int = 0, progress: bool = True
) -> np.ndarray:
    """``num_images`` camera frames (uint8 [N,H,W,3]) seen by a uniformly random policy in
    episodes of ``EPISODE_STEPS`` frames (the reset frame, then one per step): what the
    learned encoders are fit on."""
    env.action_space.seed(seed)
    bar = Progress("random-policy frames", num_images, progress)
    frames: list[np.ndarray] = []
    while len(frames) < num_images:
        if len(frames) % EPISODE_STEPS == 0:
            env.reset(seed=seed + len(frames) // EPISODE_STEPS)
        else:
            env.step(env.action_space.sample())
        frames.append(env.render_image())
        bar.update(len(frames))
    return np.stack(frames)
