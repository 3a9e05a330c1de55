"""Encoder diagnostics (thesis chapter 5): how well does a latent reward reflect the task?

Each analysis takes an env with the controllable-state API (``agent.envs.base.GoalImageEnv``;
this package never imports ``agent``) and a ``{name: encoder}`` mapping, renders each
state once for all encoders, and returns tidy pandas tables (``encoder, metric, value``
plus analysis columns). ``plots`` draws them. ``sweeper diagnose`` runs them all.

As the thesis' Algorithm 1 says, (state, goal) pairs come from the env's reset (its start
and goal distributions; ``start="uniform"``: both uniform in the state box), with no
filter on near goals unless one is asked for and reported. Every analysis starts from a
freshly reset env, so none depends on which ran before it.
"""

from encoders.diagnostics.common import START_MODES
from encoders.diagnostics.correlation import reward_correlation
from encoders.diagnostics.descent import candidate_actions, greedy_descent
from encoders.diagnostics.exploration import random_exploration, random_frames
from encoders.diagnostics.gradient import (
    cosine_distance,
    gradient_agreement,
    gradient_summary,
    least_squares_gradient,
    random_directions,
    true_reward_gradient,
)
from encoders.diagnostics.precision import goal_precision
from encoders.diagnostics.topology import default_grid_dims, grid_topology
from encoders.diagnostics.variance import arm_object_variance, has_arm

__all__ = [
    "START_MODES",
    "arm_object_variance",
    "candidate_actions",
    "cosine_distance",
    "default_grid_dims",
    "goal_precision",
    "gradient_agreement",
    "gradient_summary",
    "greedy_descent",
    "grid_topology",
    "has_arm",
    "least_squares_gradient",
    "random_directions",
    "random_exploration",
    "random_frames",
    "reward_correlation",
    "true_reward_gradient",
]
