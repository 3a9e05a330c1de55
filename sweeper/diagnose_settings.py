"""The settings of ``sweeper diagnose`` and their parsing, shared by the command
(``sweeper.diagnose``) and the analyses it runs (``sweeper.analyses``). No heavy import:
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
        counts = ("episodes", "gradient_states", "directions", "pairs", "variance_states",
                  "precision_goals", "precision_states", "descent_episodes",
                  "descent_horizon")  # fmt: skip
        for name in counts:
            if getattr(self, name) < 1:
                raise UsageError(f"--{name.replace('_', '-')} must be positive")
        if self.pairs < 3:
            raise UsageError("--pairs must be at least 3")
        if self.grid_size < 5:
            raise UsageError("--grid-size must be at least 5")
        if not self.alpha > 0:
            raise UsageError("--alpha must be positive")
        if self.precision_states < 2:
            raise UsageError("--precision-states must be at least 2")
        if not 0 < self.success_radius < self.precision_radius < math.inf:
            raise UsageError("need 0 < --success-radius < --precision-radius")
        if not 0 <= self.min_goal_distance < math.inf:
            raise UsageError("--min-goal-distance must be finite and at least 0")
        if self.descent_candidates < 2:
            raise UsageError("--descent-candidates must be at least 2")
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
