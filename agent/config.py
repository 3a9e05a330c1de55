"""Typed, frozen values in and out of one trial: the env, the reward method, SAC, the budget,
and the result. Numeric fields are checked at construction; a bad value raises a ValueError
naming its field. Names (env, method) are checked by ``agent.train`` against the registries.
SAC's hyperparameters are declared with ``encoders.options.hparam`` (type, bounds, default,
A.1 search choices), from which the sweeper derives its search space.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any, ClassVar, Literal

from encoders.options import Hyperparameters, hparam


def _check(ok: bool, name: str, must: str, value: Any) -> None:
    if not ok:
        raise ValueError(f"{name} must be {must}, got {value!r}")


def _is_int(value: Any) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)


@dataclass(frozen=True)
class SACConfig(Hyperparameters):
    """SAC-DrQ hyperparameters: defaults and search choices follow the thesis appendix A.1
    where it fixes them. A bad value raises a ValueError naming ``sac.<field>``."""

    prefix: ClassVar[str] = "sac."  # errors name sac.<field>, as a spec does

    hidden_sizes: tuple[int, ...] = hparam(
        (256, 256), ge=1, search=((256, 256), (512, 512), (1024, 1024)), help="MLP layers"
    )
    discount: float = hparam(0.95, gt=0, le=1)
    init_temperature: float = hparam(0.1, gt=0, search=(0.1, 1.0))
    lr: float = hparam(1e-3, gt=0, search=(1e-3, 5e-4, 1e-4))
    actor_update_every: int = hparam(1, ge=1, search=(1, 2))
    critic_tau: float = hparam(0.005, gt=0, le=1, search=(0.005, 0.001))
    batch_size: int = hparam(256, ge=1)
    updates_per_step: int = hparam(2, ge=1)  # SAC updates per env step after seed_steps
    buffer_capacity: int = hparam(1_000_000, ge=1)
    feature_dim: int = hparam(50, ge=1)  # conv features -> Linear -> LayerNorm -> tanh
    num_filters: int = hparam(32, ge=1)
    image_pad: int = hparam(4, ge=0)  # DrQ augmentation: replicate-pad then random crop back


#: the precisions of acting and the update: fp32, or bf16 autocast (``agent.sac``)
PRECISIONS = ("fp32", "bf16")

#: env steps per episode, in every env (episodes truncate there and never terminate)
EPISODE_STEPS = 50

#: methods that train on the env's true reward instead of an encoder's: the state oracle
#: (SAC on true states and goals: the learner's ceiling) and the image-observation control
#: (images in, true reward: can the agent learn from pixels here, whatever the reward?)
TRUE_REWARD_METHODS = ("state", "true_reward")


@dataclass(frozen=True)
class TrialConfig:
    """Everything one trial needs; a plain value, so it pickles to a Ray actor.

    ``method`` is an encoder registry name or one of ``TRUE_REWARD_METHODS``.
    ``encoder_params`` are the method's own hyperparameters (latent size, VAE beta, ...).
    ``reward_scale`` multiplies the reward: a positive number, or "auto" for 1 / the mean
    distance (under the method's own reward) between a random policy's frames and their
    goals, measured before training, so every method's reward is about 1 in size.
    Checkpoints are written at the first episode end at least ``checkpoint_every`` env
    steps after the previous one. ``stop_at`` (successive halving's rungs): pause at the
    first episode end from that env step on, with a checkpoint, and return
    ``Outcome.PAUSED``; run again with a later ``stop_at`` (or None: to the end), the
    trial goes on from there.
    """

    env: str = "point_reach"
    image_size: int | None = None  # None: the env's default
    method: str = "pixel"
    encoder_params: dict[str, Any] = field(default_factory=dict)
    sac: SACConfig = field(default_factory=SACConfig)
    reward_scale: float | Literal["auto"] = 1.0
    total_steps: int = 10_000
    seed_steps: int = 1_000  # uniform random actions before learning starts
    eval_every: int = 1_000
    eval_episodes: int = 10
    seed: int = 0
    device: str = "auto"  # "auto": CUDA when available, else CPU
    threads: int = 1  # torch intra-op threads on CPU
    checkpoint_dir: str | None = None  # None: no checkpoints
    checkpoint_every: int = 5_000
    # whose checkpoints these are (the sweeper's study id): another owner's are refused
    checkpoint_owner: str | None = None
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    # evaluation steps whose first episode is filmed and handed to ``train``'s ``record``
    video_steps: tuple[int, ...] = ()
    stop_at: int | None = None
    precision: str = "fp32"  # one of PRECISIONS

    def __post_init__(self) -> None:
        _check(isinstance(self.sac, SACConfig), "sac", "a SACConfig", self.sac)
        for name in ("total_steps", "eval_every", "eval_episodes", "threads", "checkpoint_every"):
            v = getattr(self, name)
            _check(_is_int(v) and v >= 1, name, "an integer >= 1", v)
        for name in ("seed_steps", "seed"):
            v = getattr(self, name)
            _check(_is_int(v) and v >= 0, name, "an integer >= 0", v)
        _check(self.image_size is None or _is_int(self.image_size), "image_size",
               "an integer or None", self.image_size)  # fmt: skip
        scale = self.reward_scale
        _check(
            scale == "auto" or (_is_number(scale) and scale > 0),
            "reward_scale",
            "'auto' or a positive number",
            scale,
        )
        _check(self.precision in PRECISIONS, "precision", f"one of {PRECISIONS}", self.precision)
        for name in ("encoder_params", "env_kwargs"):
            v = getattr(self, name)
            _check(isinstance(v, dict), name, "a dict", v)
        _check(
            isinstance(self.device, str)
            and (self.device in ("auto", "cpu", "cuda") or self.device.startswith("cuda:")),
            "device",
            "'auto', 'cpu', 'cuda' or 'cuda:N'",
            self.device,
        )
        stop = self.stop_at
        _check(
            stop is None or (_is_int(stop) and 0 < stop < self.total_steps),
            "stop_at",
            f"None or an env step in (0, total_steps={self.total_steps})",
            stop,
        )
        steps = self.video_steps
        _check(
            isinstance(steps, tuple | list)
            and all(
                _is_int(s)
                and 0 <= s <= self.total_steps
                and (s % self.eval_every == 0 or s == self.total_steps)
                for s in steps
            ),
            "video_steps",
            f"env steps on the evaluation grid (multiples of eval_every={self.eval_every} "
            f"up to total_steps={self.total_steps}, or total_steps)",
            steps,
        )
        object.__setattr__(self, "video_steps", tuple(sorted(set(steps))))


#: TrialConfig fields that change how a trial runs but not its curve (a checkpoint written
#: under one value resumes under another)
RUNTIME_FIELDS = (
    "device",
    "threads",
    "checkpoint_dir",
    "checkpoint_every",
    "checkpoint_owner",
    "video_steps",
    "stop_at",
)


def curve_fields(config: TrialConfig) -> dict[str, Any]:
    """The fields of ``config`` that set its curve: all but ``RUNTIME_FIELDS``, and
    ``precision`` only when not fp32 (so a trial from before that field keeps its identity:
    its plan hash and its checkpoints)."""
    fields = dataclasses.asdict(config)
    for name in RUNTIME_FIELDS:
        fields.pop(name)
    if fields["precision"] == "fp32":
        del fields["precision"]
    return fields


class Outcome(StrEnum):
    """How a trial ended; stored by value as the trial's ``outcome`` user attr. A trial
    returns COMPLETED, DIVERGED or PAUSED (at ``stop_at``); the driver records FAILED,
    INTERRUPTED and PRUNED (stopped at a rung of successive halving)."""

    COMPLETED = "completed"
    DIVERGED = "diverged"
    FAILED = "failed"
    INTERRUPTED = "interrupted"
    PAUSED = "paused"
    PRUNED = "pruned"


@dataclass(frozen=True)
class TrialResult:
    """What ``agent.train`` returns: the whole evaluation curve and its normalised AUC.

    ``metrics[k][i]`` is metric ``k`` at env step ``steps[i]``. After a divergence the
    remaining grid points hold ``success_rate = 0`` and NaN for the other metrics.
    ``seconds`` is the wall time summed over every run of the trial (resumes included);
    ``resumed_from`` the env step of the checkpoint this run started from, if any;
    ``reward_scale`` the factor the reward was multiplied by (``"auto"`` resolved);
    ``video_seconds`` the wall time spent filming and encoding episode videos (included in
    ``seconds``; the runs that recorded them); ``machines`` one ``agent.machine.describe``
    per run of the trial with its ``from_step``, the first run's 0 (runs before a
    checkpoint written by code older than this field are not listed); ``encoder_fit``
    what fitting a learned reward encoder gave (``latent_dim``, ``active_dims``, the last
    epoch's ``loss``, ``recon`` and ``kl``, ``seconds``), empty for the others.
    """

    steps: tuple[int, ...]
    metrics: dict[str, tuple[float, ...]]
    auc: float
    outcome: Outcome = Outcome.COMPLETED
    diverged_step: int | None = None
    diverged_loss: str | None = None
    seconds: float = 0.0
    resumed_from: int | None = None
    reward_scale: float = 1.0
    video_seconds: float = 0.0
    machines: tuple[dict[str, Any], ...] = ()
    encoder_fit: dict[str, float] = field(default_factory=dict)
