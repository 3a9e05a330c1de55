"""The random agent's success rate on a study's env: the 0 of its normalised scores.

The driver measures it once per study, before the first trial, and stores it as the study
user attr ``random_agent``; a relaunch finds it there and does not measure again
(``sweeper.aggregate.normalize`` reads it).
"""

from __future__ import annotations

import os
import time
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from sweeper.spec import StudySpec

#: the study user attr holding the measurement
ATTR = "random_agent"


def measure_random_agent(spec: StudySpec) -> dict[str, Any]:
    """Run ``spec.random_episodes`` uniformly random episodes on the spec's env (its image
    size and options), seeded by the study seed; return the ``random_agent`` attr:
    ``episodes``, ``seed``, ``seconds``, ``success_rate`` (share of episodes reaching the
    goal at any step, ``encoders.diagnostics.random_exploration``) and every other
    ``<flag>_rate`` the env has."""
    os.environ.setdefault("MUJOCO_GL", "egl")  # headless, as the workers render
    from agent.envs import make_env
    from encoders.diagnostics.exploration import random_exploration

    start = time.perf_counter()
    options = dict(spec.env.options)
    if spec.env.image_size is not None:
        options["image_size"] = spec.env.image_size
    env = make_env(spec.env.name, obs_mode="state", **options)  # same dynamics, no rendering
    try:
        rows = random_exploration(env, spec.random_episodes, seed=spec.seed, progress=False)
    finally:
        env.close()
    rates = {row.metric: float(row.value) for row in rows.itertuples()}
    return {
        "episodes": spec.random_episodes,
        "seed": spec.seed,
        "seconds": round(time.perf_counter() - start, 3),
        **rates,
    }
