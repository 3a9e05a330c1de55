"""fetch_push: which latent dimensions move with the arm, which with the object?

A reward for pushing should change with the object, not with the arm. The latent
variance per dimension is measured twice: with only the arm moving (object held at the
centre of its box) and with only the object moving (arm parked above the box centre, clear
of the block: Fetch's reset leaves the gripper at the block's height there). The env is
reset first, so nothing an earlier analysis left behind is in the pictures.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pandas as pd

from encoders.base import RewardEncoder
from encoders.diagnostics.common import (
    ControllableEnv,
    Progress,
    bounds,
    encode_all,
    fresh_reset,
    render_states,
)

#: arm heights (m) above the object's resting height: clear of the block and the table
ARM_HEIGHTS = (0.06, 0.16)


def has_arm(env: object) -> bool:
    """True if the env can move its arm alone (``gripper_position``/``set_gripper_position``)."""
    return hasattr(env, "gripper_position") and hasattr(env, "set_gripper_position")


def arm_object_variance(
    env: ControllableEnv,
    encoders: Mapping[str, RewardEncoder],
    num_states: int = 100,
    seed: int = 0,
    progress: bool = True,
) -> pd.DataFrame:
    """Per-dimension latent variance with only the arm moving vs only the object moving,
    after ``env.reset(seed=seed)``.

    Object positions are uniform in ``env.state_bounds()``, with the arm parked above the
    box centre at the top of ``ARM_HEIGHTS``; arm positions are uniform over the same x-y
    box at ``ARM_HEIGHTS`` above the object's height, with the object at the box centre.
    Rows: ``encoder, metric in {arm_variance, object_variance}, value, dim`` per dimension, plus
    ``arm_variance_total``, ``object_variance_total`` and ``arm_share`` = arm total /
    (arm + object totals) (dim = -1): 0 = the latent ignores the arm.
    """
    if not has_arm(env):
        raise ValueError("arm_object_variance needs an env with gripper_position()")
    if num_states < 2:
        raise ValueError(f"num_states must be at least 2, got {num_states}")
    fresh_reset(env, seed)
    rng = np.random.default_rng(seed)
    low, high = bounds(env)
    centre = (low + high) / 2
    bar = Progress("arm/object states", 2 * num_states, progress)
    arm_images = []
    env.set_controllable_state(centre)
    for k in range(num_states):
        xy = rng.uniform(low[:2], high[:2])
        z = centre[2] + rng.uniform(*ARM_HEIGHTS)
        env.set_gripper_position(np.array([xy[0], xy[1], z]))
        arm_images.append(env.render_image())
        bar.update(k + 1)
    env.set_gripper_position(centre + np.array([0.0, 0.0, ARM_HEIGHTS[1]]))
    object_states = rng.uniform(low, high, size=(num_states, len(low)))
    object_images = render_states(env, object_states, bar)[1]
    arm_z = encode_all(encoders, np.stack(arm_images))
    object_z = encode_all(encoders, object_images)
    frames = []
    for name in encoders:
        arm_var, object_var = arm_z[name].var(axis=0), object_z[name].var(axis=0)
        dims = np.arange(len(arm_var))
        arm_total, object_total = float(arm_var.sum()), float(object_var.sum())
        share = arm_total / (arm_total + object_total) if arm_total + object_total else np.nan
        frames += [
            pd.DataFrame(
                {"encoder": name, "metric": "arm_variance", "value": arm_var, "dim": dims}
            ),
            pd.DataFrame(
                {"encoder": name, "metric": "object_variance", "value": object_var, "dim": dims}
            ),
            pd.DataFrame(
                {
                    "encoder": name,
                    "metric": ["arm_variance_total", "object_variance_total", "arm_share"],
                    "value": [arm_total, object_total, share],
                    "dim": -1,
                }
            ),
        ]
    return pd.concat(frames, ignore_index=True)
