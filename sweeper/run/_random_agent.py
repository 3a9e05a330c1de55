"""The random agent's success rate on a study's env: the 0 of its normalised scores.

The driver measures it once per study, before the first trial, and stores it as the study
user attr ``random_agent`` (``record_random_agent``); a relaunch finds it there and does not
measure again (``sweeper.results._normalize`` reads it).
"""

from __future__ import annotations

import os
import time
from typing import TYPE_CHECKING, Any, TextIO

from sweeper.spec import plural

if TYPE_CHECKING:
    from sweeper.spec import StudySpec
    from sweeper.storage import StudyStore

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


def record_random_agent(spec: StudySpec, store: StudyStore, stream: TextIO) -> None:
    """Measure the random agent's success rate once per study (the 0 of its normalised
    scores) and store it in the study; a study that has it is not measured again. A
    measurement that fails is a note, not a failure: the study is then not normalised."""
    if not spec.random_episodes or ATTR in store.attrs:
        return
    print(
        f"measuring a random agent's success rate on {spec.env.name} "
        f"({plural(spec.random_episodes, 'episode')})",
        file=stream,
    )
    try:
        measured = measure_random_agent(spec)
    except Exception as e:  # e.g. no renderer on the driver's host
        print(f"sweeper launch: note: could not measure the random agent: {e}", file=stream)
        return
    store.set_study_attr(ATTR, measured)
    print(
        f"random agent: success rate {measured['success_rate']:.3f} in {measured['seconds']:.1f} s",
        file=stream,
    )
