"""What one trial costs on this machine, measured in seconds per unit of its work.

A trial is setup (its two envs built; its reward encoder built and, when it learns, fitted
on random-policy frames; the reward scale measured), ``seed_steps`` env steps with random
actions, the remaining steps each with the policy's action and ``updates_per_step`` SAC updates, and
``eval_episodes`` episodes at every grid step. A ``Calibration`` times each part (``per_call``)
on the trial's own env, encoder and SAC networks with random data, once per distinct set of
the fields the part depends on (an env step per env and image size, an update per
network shape, batch and actor period, ...), so a study of many configurations takes
seconds; ``TrialCosts.seconds`` adds the parts up for any budget.

A learned encoder is fitted for one epoch on ``FIT_IMAGES`` frames and scaled to its
``num_images`` and ``epochs``; VGG is timed with random weights (the same operations, so no
weights file is needed). Not counted: checkpoint writes and videos (each under 1% of a
trial on this machine, benchmarks/bench_video.py).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

import encoders
from agent import machine
from agent.config import TRUE_REWARD_METHODS, TrialConfig
from agent.envs import make_env
from agent.envs.base import EPISODE_STEPS
from agent.metrics import evaluation_grid
from agent.replay import ReplayBuffer
from agent.sac import SAC
from agent.trial import SCALE_STEPS, _uniform_action, collect_random_images
from encoders.torch_base import resolve_device

#: frames a learned encoder is fitted on for timing (one epoch)
FIT_IMAGES = 256


@dataclass(frozen=True)
class TrialCosts:
    """Seconds of one trial's parts: ``setup`` once; ``seed_step`` per random-action step;
    ``train_step`` per policy step with its SAC updates; ``eval_step`` per evaluation step."""

    setup: float
    seed_step: float
    train_step: float
    eval_step: float

    def seconds(self, config: TrialConfig, until: int | None = None) -> float:
        """The trial's wall time from its start to env step ``until`` (default: the end)."""
        until = config.total_steps if until is None else min(until, config.total_steps)
        seeded = min(until, config.seed_steps)
        evaluations = sum(
            1 for s in evaluation_grid(config.total_steps, config.eval_every) if s <= until
        )
        return (
            self.setup
            + self.seed_step * seeded
            + self.train_step * (until - seeded)
            + self.eval_step * evaluations * config.eval_episodes * EPISODE_STEPS
        )


class Stopped(Exception):
    """The calibration was told to stop (``Calibration(stop=...)``) before it finished."""


def per_call(
    fn: Callable[[], Any],
    min_calls: int = 3,
    seconds: float = 0.5,
    stop: threading.Event | None = None,
) -> float:
    """Mean seconds of one warm call of ``fn``: an untimed warm-up call, then at least
    ``min_calls`` calls and more until ``seconds`` have passed; after a warm-up slower than
    ``seconds``, at least one call. The warm-up is never the answer: a first SAC update
    (its allocations, oneDNN's kernels) takes 1.5-2 times a later one, which made the
    estimates of trials at batch 128 that much too long. Raises ``Stopped`` between calls
    once ``stop`` is set."""
    start = time.perf_counter()
    fn()
    if time.perf_counter() - start >= seconds:
        min_calls = 1
    calls, start = 0, time.perf_counter()
    while calls < min_calls or time.perf_counter() - start < seconds:
        if stop is not None and stop.is_set():
            raise Stopped
        fn()
        calls += 1
    return (time.perf_counter() - start) / calls


def timing_encoder(config: TrialConfig, image_size: int, device: str, **override: Any) -> Any:
    """The trial's encoder for timing: VGG with random weights, others as a trial builds
    them (unfitted), with ``override`` options."""
    shape = (image_size, image_size, 3)
    params = config.encoder_params | override
    if config.method == "vgg":
        from encoders.registry import build_options
        from encoders.vgg import VGGEncoder

        options = build_options(encoders.encoder_options("vgg"), params, "vgg")
        return VGGEncoder(shape, config.seed, device, options, pretrained=False)
    return encoders.make_encoder(config.method, shape, config.seed, device, **params)


#: options that scale a learned encoder's fit (timed at one epoch on FIT_IMAGES frames)
FIT_SCALE_OPTIONS = ("epochs", "num_images")
#: options that change an encoder's numbers but not its work: timed once for all values
SAME_COST_OPTIONS = ("beta", "lr", "init", "weights_path")
#: SAC fields that change the cost of an action or an update
ACT_FIELDS = ("hidden_sizes", "feature_dim", "num_filters")
UPDATE_FIELDS = (*ACT_FIELDS, "batch_size", "image_pad", "actor_update_every")


class Calibration:
    """Measured trial costs on this machine; each part is timed once per distinct set of
    the fields it depends on. Use as a context manager (it keeps the envs it opened).

    ``stop``: once set, the calibration raises ``Stopped`` at its next timed call, so a
    thread calibrating can be ended and joined (a thread still in torch or MuJoCo when
    the process exits aborts it: "terminate called without an active exception")."""

    def __init__(
        self, min_calls: int = 3, seconds: float = 0.5, stop: threading.Event | None = None
    ) -> None:
        self.min_calls, self.seconds, self.stop = min_calls, seconds, stop
        self._parts: dict[tuple, Any] = {}
        self._envs: dict[tuple, Any] = {}
        self._built: dict[tuple, float] = {}  # seconds to build and reset each env
        self._rng = np.random.default_rng(0)

    def __enter__(self) -> Calibration:
        return self

    def __exit__(self, *exc: object) -> None:
        for env in self._envs.values():
            env.close()
        self._envs.clear()

    def costs(self, config: TrialConfig) -> TrialCosts:
        """The costs of ``config``'s trial parts (see the module docstring)."""
        if self.stop is not None and self.stop.is_set():
            raise Stopped
        torch.set_num_threads(config.threads)
        step = self._part(("env", *self._env_key(config)), lambda: self._env_step(config))
        # a trial builds two envs (training, evaluation)
        encode, setup = 0.0, 2 * self._built[self._env_key(config)]
        if config.method not in TRUE_REWARD_METHODS:
            ignored = (*FIT_SCALE_OPTIONS, *SAME_COST_OPTIONS)
            params = {k: v for k, v in config.encoder_params.items() if k not in ignored}
            key = ("encoder", config.method, config.image_size, str(sorted(params.items())))
            encode, fit_per_image_epoch = self._part(key, lambda: self._encoder(config))
            if fit_per_image_epoch is not None:
                encoder = timing_encoder(config, self._env(config).image_size, "cpu")
                epochs = getattr(encoder, "epochs", 1)
                setup = encoder.num_images * (step + epochs * fit_per_image_epoch)
        if config.reward_scale == "auto":
            setup += SCALE_STEPS * (step + encode)
        sac = tuple(getattr(config.sac, f) for f in UPDATE_FIELDS)
        key = ("sac", *self._env_key(config), sac, config.precision)
        act, update = self._part(key, lambda: self._sac(config))
        return TrialCosts(
            setup=setup,
            seed_step=step + encode,
            train_step=step + encode + act + config.sac.updates_per_step * update,
            eval_step=step + act,
        )

    def _part(self, key: tuple, measure: Callable[[], Any]) -> Any:
        if key not in self._parts:
            self._parts[key] = measure()
        return self._parts[key]

    def _time(self, fn: Callable[[], Any]) -> float:
        return per_call(fn, self.min_calls, self.seconds, self.stop)

    @staticmethod
    def _env_key(config: TrialConfig) -> tuple:
        obs_mode = "state" if config.method == "state" else "image"
        return (config.env, config.image_size, obs_mode, str(sorted(config.env_kwargs.items())))

    def _env(self, config: TrialConfig) -> Any:
        key = self._env_key(config)
        if key not in self._envs:
            make = dict(image_size=config.image_size, obs_mode=key[2], **config.env_kwargs)
            start = time.perf_counter()
            self._envs[key] = make_env(config.env, **make)
            self._envs[key].reset(seed=0)
            self._built[key] = time.perf_counter() - start
        return self._envs[key]

    def _env_step(self, config: TrialConfig) -> float:
        """Seconds of one env step with a random action (its image rendered)."""
        env = self._env(config)

        def step() -> None:
            _, _, terminated, truncated, _ = env.step(_uniform_action(env, self._rng))
            if terminated or truncated:
                env.reset()

        return self._time(step)

    def _encoder(self, config: TrialConfig) -> tuple[float, float | None]:
        """(seconds to encode one image, seconds of the fit per image and epoch or None
        for an encoder that does not learn)."""
        env, device = self._env(config), str(resolve_device(config.device))
        image = env.reset()[0]["image"][None]
        encoder = timing_encoder(config, env.image_size, device)
        fit = None
        if encoder.needs_fit:
            images = collect_random_images(config, min(FIT_IMAGES, encoder.num_images))
            one_epoch = {"epochs": 1} if getattr(encoder, "epochs", 1) > 1 else {}
            encoder = timing_encoder(config, env.image_size, device, **one_epoch)
            start = time.perf_counter()
            encoder.fit(images, progress=False)
            fit = (time.perf_counter() - start) / len(images)
        return self._time(lambda: encoder.encode(image)), fit

    def _sac(self, config: TrialConfig) -> tuple[float, float]:
        """(seconds of one sampled action, mean seconds of one SAC update over a cycle of
        ``actor_update_every`` updates, so the actor's share is in the mean)."""
        env, device = self._env(config), resolve_device(config.device)
        keys = ("state", "goal_state") if config.method == "state" else ("image", "goal_image")
        obs_space, goal_space = env.observation_space[keys[0]], env.observation_space[keys[1]]
        agent = SAC(obs_space.shape, goal_space.shape, env.action_space.shape[0], config.sac,
                    device, precision=config.precision,
                    channels_last=machine.conv_layout(device) == "channels_last")  # fmt: skip
        obs = env.reset()[0]
        act = self._time(lambda: agent.act(obs[keys[0]], obs[keys[1]], sample=True))
        replay = _random_replay(env, keys, config.sac.batch_size, self._rng)
        cycle = config.sac.actor_update_every

        def updates() -> None:
            for _ in range(cycle):
                agent.update(replay.sample(config.sac.batch_size, self._rng))

        return act, self._time(updates) / cycle


def _random_replay(
    env: Any, keys: tuple[str, str], batch_size: int, rng: np.random.Generator
) -> ReplayBuffer:
    """A replay buffer of random observations of the env's shapes, enough for a batch."""
    obs_space, goal_space = env.observation_space[keys[0]], env.observation_space[keys[1]]
    steps = max(batch_size, EPISODE_STEPS)
    replay = ReplayBuffer(
        capacity=steps,
        obs_shape=obs_space.shape,
        obs_dtype=obs_space.dtype,
        goal_shape=goal_space.shape,
        action_dim=env.action_space.shape[0],
        episode_steps=EPISODE_STEPS,
    )

    def sample(space: Any) -> np.ndarray:
        if np.issubdtype(space.dtype, np.integer):
            return rng.integers(0, 256, space.shape).astype(space.dtype)
        return rng.standard_normal(space.shape).astype(space.dtype)

    for t in range(steps):
        if t % EPISODE_STEPS == 0:
            replay.start_episode(sample(obs_space), sample(goal_space))
        replay.add(_uniform_action(env, rng), 0.0, sample(obs_space))
    return replay
