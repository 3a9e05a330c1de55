"""Typed, frozen configuration of one trial: the env, the reward method, SAC, the budget."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class SACConfig:
    """SAC-DrQ hyperparameters; defaults follow the thesis appendix A.1 where it fixes one."""

    hidden_sizes: tuple[int, ...] = (256, 256)
    discount: float = 0.95
    init_temperature: float = 0.1
    lr: float = 1e-3
    actor_update_every: int = 1
    critic_tau: float = 0.005
    batch_size: int = 256
    updates_per_step: int = 2
    buffer_capacity: int = 1_000_000
    feature_dim: int = 50  # conv features -> Linear -> LayerNorm -> tanh
    num_filters: int = 32
    image_pad: int = 4  # DrQ augmentation: replicate-pad then random crop back


@dataclass(frozen=True)
class TrialConfig:
    """Everything one trial needs; a plain value, so it pickles to a Ray actor.

    ``method`` is an encoder registry name, or "state" for the state oracle (SAC on
    true states and goals, reward = the env's true reward). ``encoder_params`` are the
    method's own hyperparameters (latent size, VAE beta, ...).
    """

    env: str = "point_reach"
    image_size: int | None = None  # None: the env's default
    method: str = "pixel"
    encoder_params: dict[str, Any] = field(default_factory=dict)
    sac: SACConfig = field(default_factory=SACConfig)
    total_steps: int = 10_000
    seed_steps: int = 1_000  # uniform random actions before learning starts
    eval_every: int = 1_000
    eval_episodes: int = 10
    seed: int = 0
    device: str = "auto"  # "auto": CUDA when available, else CPU
    threads: int = 1  # torch intra-op threads on CPU
    checkpoint_dir: str | None = None  # None: no checkpoints
    checkpoint_every: int = 5_000
    env_kwargs: dict[str, Any] = field(default_factory=dict)
