"""The settings of ``sweeper diagnose`` and their parsing, shared by the command
(``cli_diagnose``) and the analyses it runs (``_analyses``). No heavy import:
``sweeper diagnose --help`` builds its defaults from ``Settings``."""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from dataclasses import dataclass

#: envs with an object and an arm that moves alone: the variance analysis runs on these
ARM_OBJECT_ENVS = ("fetch_push",)
#: ``encoders.diagnostics.START_MODES``, spelled out so ``--help`` imports nothing heavy
START_MODES = ("reset", "uniform")


#: the largest value of each count: generous for real use (the defaults are 8 to 300),
#: bounded so that a slip of the keyboard cannot run for days or fill the memory (an
#: analysis holds the images of its samples at once: 10,000 pairs of 84x84 frames take
#: 0.4 GB; a 64x64 topology grid is 4,096 states and their isomap)
MAX_COUNTS = {
    "episodes": 100_000,
    "gradient_states": 10_000,
    "directions": 1_000,
    "pairs": 10_000,
    "grid_size": 64,
    "variance_states": 10_000,
    "precision_goals": 1_000,
    "precision_states": 10_000,
    "descent_episodes": 10_000,
    "descent_horizon": 1_000,
    "descent_candidates": 100,
}
#: the smallest value of each count (an analysis needs that many to mean anything)
MIN_COUNTS = {"pairs": 3, "grid_size": 5, "precision_states": 2, "descent_candidates": 2}
#: seeds, as a study spec takes them
MAX_SEED = 2**32 - 1


class UsageError(ValueError):
    """A bad argument: reported in one line, exit code 2."""


@dataclass(frozen=True)
class Settings:
    """How much each analysis draws, and where from (the options of ``sweeper diagnose``
    of the same names). Raises UsageError for a size that cannot be used."""

    seed: int = 0
    episodes: int = 100  # random-agent episodes
    gradient_states: int = 50  # Algorithm 1
    directions: int = 16
    alpha: float = 0.03
    start: str = "reset"  # one of START_MODES
    min_goal_distance: float = 0.0
    pairs: int = 300  # (state, goal) pairs of the correlation
    grid_size: int = 15  # topology grid side
    grid_dims: str | None = None  # two state names or indices; None: the env's first two
    variance_states: int = 100  # arm-vs-object states (fetch_push only)
    precision_goals: int = 20  # goals of the near-goal analysis
    precision_states: int = 200  # states around each goal
    precision_radius: float = 0.15  # the ball they are drawn in
    success_radius: float = 0.05  # Fetch's success threshold (m)
    descent_episodes: int = 30  # greedy descent: episodes from the env's reset
    descent_horizon: int = 50  # steps each
    descent_candidates: int = 8  # actions tried a step
    descent_step: float = 0.5  # their size, a fraction of the action box's half-width
    quiet: bool = False  # no progress lines

    def __post_init__(self) -> None:
        if not 0 <= self.seed <= MAX_SEED:
            raise UsageError(f"--seed must be in [0, {MAX_SEED}], got {self.seed}")
        for name, most in MAX_COUNTS.items():
            value, least = getattr(self, name), MIN_COUNTS.get(name, 1)
            if not least <= value <= most:
                raise UsageError(
                    f"--{name.replace('_', '-')} must be in [{least}, {most}], got {value}"
                )
        if not 0 < self.alpha < math.inf:
            raise UsageError(f"--alpha must be positive and finite, got {self.alpha}")
        if not 0 < self.success_radius < self.precision_radius < math.inf:
            raise UsageError("need 0 < --success-radius < --precision-radius")
        if not 0 <= self.min_goal_distance < math.inf:
            raise UsageError("--min-goal-distance must be finite and at least 0")
        if not 0 < self.descent_step <= 1:
            raise UsageError("--descent-step must be in (0, 1]")
        if self.start not in START_MODES:
            raise UsageError(f"--start must be one of {', '.join(START_MODES)}")

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> Settings:
        return cls(**{f.name: getattr(args, f.name) for f in dataclasses.fields(cls)})

    def log(self, message: str) -> None:
        """A progress line on stderr, unless ``quiet``."""
        if not self.quiet:
            print(f"[diagnose] {message}", file=sys.stderr, flush=True)


def split(text: str, what: str) -> list[str]:
    """The non-empty items of a comma-separated argument."""
    items = [t.strip() for t in text.split(",") if t.strip()]
    if not items:
        raise UsageError(f"{what} must name at least one item")
    return items


def grid_dims(text: str | None, state_names: tuple[str, ...]) -> tuple[int, int] | None:
    """``--grid-dims`` ("hand_x,door_angle" or "0,3") as two state indices; None: default."""
    if text is None:
        return None
    dims = split(text, "--grid-dims")
    indices = []
    for d in dims:
        if d in state_names:
            indices.append(state_names.index(d))
        elif d.isdigit() and int(d) < len(state_names):
            indices.append(int(d))
        else:
            raise UsageError(f"--grid-dims: unknown state {d!r}; states: {', '.join(state_names)}")
    if len(indices) != 2 or indices[0] == indices[1]:
        raise UsageError(f"--grid-dims needs two different states, got {text!r}")
    return indices[0], indices[1]
