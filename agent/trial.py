"""One trial: env + reward encoder + SAC-DrQ, evaluated on a fixed step grid.

``train(config, report)`` runs ``config.total_steps`` env steps: ``seed_steps`` with
uniform random actions, then ``updates_per_step`` SAC updates after every env step. At
every grid step (``agent.metrics.evaluation_grid``) it runs ``eval_episodes``
deterministic-policy episodes in a separate env on a fixed set of goals and calls
``report(step, metrics)``.

Rewards: an image method's reward ``-||phi(o') - phi(o_g)||`` is computed when the
transition is stored (``phi(o_g)`` once per episode); the state oracle (``method="state"``)
uses the env's true reward on state observations, the image control
(``method="true_reward"``) the env's true reward on image observations. Every reward is
multiplied by the trial's reward scale (``TrialConfig.reward_scale``; "auto" is measured
on a random policy's episodes before training).

Videos: at each of ``config.video_steps`` the first evaluation episode is filmed (each
frame the observation beside the goal image, captioned with the env step, the reward the
agent is trained on, ``scale * latent reward``, or the scaled true reward for the
true-reward methods, and the true distance; ``agent.video``) and handed to
``record(filename, bytes)``, when given. Filming reads the env and never its random
generators, so the curve is the same with or without it.

Checkpoints (``agent.checkpoint``) are written only at episode ends: the next thing the
trial does is reset the env, so no mid-episode simulator state is needed, only the env's
random generator. A checkpoint holds the networks, optimisers, replay, counters, the curve
so far, and the torch and numpy random states; resuming from it gives the same curve on
CPU. Learned encoders are fitted again on resume (deterministic given the seed) rather
than saved, so no encoder needs a serialisation API.
"""

from __future__ import annotations

import contextlib
import time
import warnings
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

import encoders
from agent import checkpoint, machine, video
from agent.config import TRUE_REWARD_METHODS, Outcome, TrialConfig, TrialResult
from agent.envs import make_env
from agent.envs.base import EPISODE_STEPS
from agent.metrics import (
    diverged_metrics,
    evaluation_grid,
    metric_key,
    normalized_auc,
    summarize_episodes,
)
from agent.replay import ReplayBuffer
from agent.sac import SAC
from encoders.torch_base import resolve_device

Report = Callable[[int, dict[str, float]], None]
#: ``record(filename, data)``: a file the trial made (an episode video)
Record = Callable[[str, bytes], None]
#: ``notice(message)``: one line the user should see (a corrupt checkpoint discarded)
Notice = Callable[[str], None]
#: env steps of random policy measured for ``reward_scale="auto"`` (5 episodes, 5 goals)
SCALE_STEPS = 5 * EPISODE_STEPS


class Diverged(Exception):
    """A loss became NaN or infinite."""

    def __init__(self, step: int, loss: str) -> None:
        super().__init__(f"{loss} is not finite at env step {step}")
        self.step, self.loss = step, loss


def _seed(seed: int, stream: int) -> int:
    """An independent seed for one use (training env, evaluation episodes, ...)."""
    return int(np.random.SeedSequence([seed, stream]).generate_state(1)[0])


def _uniform_action(env: Any, rng: np.random.Generator) -> np.ndarray:
    space = env.action_space
    return rng.uniform(space.low, space.high).astype(space.dtype)


def build_encoder(
    config: TrialConfig, image_size: int, device: torch.device
) -> tuple[Any, dict[str, float]]:
    """The trial's reward encoder, fitted on random-policy frames when it learns (None for
    the methods that use the true reward), and what its fit gave (``TrialResult.encoder_fit``;
    empty without a fit)."""
    if config.method in TRUE_REWARD_METHODS:
        return None, {}
    if config.method not in encoders.encoder_names():
        names = ", ".join((*encoders.encoder_names(), *TRUE_REWARD_METHODS))
        raise ValueError(f"method must be one of {names}; got {config.method!r}")
    shape = (image_size, image_size, 3)
    encoder = encoders.make_encoder(
        config.method, shape, config.seed, str(device), **config.encoder_params
    )
    if not encoder.needs_fit:
        return encoder, {}
    fit = encoder.fit(collect_random_images(config, encoder.num_images), progress=False)
    summary = {"latent_dim": encoder.dim, "loss": fit.losses[-1], **fit.extra}
    return encoder, {**summary, "seconds": fit.seconds}


def collect_random_images(config: TrialConfig, num_images: int) -> np.ndarray:
    """``num_images`` frames seen by a uniform random policy in the trial's env."""
    rng = np.random.default_rng(_seed(config.seed, 2))
    frames = []
    make = dict(image_size=config.image_size, **config.env_kwargs)
    with contextlib.closing(make_env(config.env, **make)) as env:
        obs, _ = env.reset(seed=_seed(config.seed, 3))
        while len(frames) < num_images:
            frames.append(obs["image"])
            obs, _, terminated, truncated, _ = env.step(_uniform_action(env, rng))
            if terminated or truncated:
                obs, _ = env.reset()
    return np.stack(frames)


def measure_reward_scale(config: TrialConfig, encoder: Any) -> float:
    """``config.reward_scale``, with "auto" resolved to 1 / the mean distance to the goal
    (the negated reward before scaling) over ``SCALE_STEPS`` steps of a random policy."""
    if config.reward_scale != "auto":
        return float(config.reward_scale)
    rng = np.random.default_rng(_seed(config.seed, 4))
    obs_mode = "image" if encoder is not None else "state"
    make = dict(image_size=config.image_size, obs_mode=obs_mode, **config.env_kwargs)
    distances: list[np.ndarray] = []
    with contextlib.closing(make_env(config.env, **make)) as env:
        env.reset(seed=_seed(config.seed, 5))
        while len(distances) < SCALE_STEPS // EPISODE_STEPS:
            obs, _ = env.reset()
            frames, true_distances, done = [], [], False
            while not done:
                obs, reward, terminated, truncated, _ = env.step(_uniform_action(env, rng))
                if encoder is None:
                    true_distances.append(-reward)
                else:
                    frames.append(obs["image"])
                done = terminated or truncated
            if encoder is None:
                distances.append(np.asarray(true_distances))
            else:
                goal = encoder.encode(obs["goal_image"][None])
                distances.append(-encoders.latent_reward(encoder.encode(np.stack(frames)), goal))
    mean = float(np.mean(np.concatenate(distances)))
    if not mean > 0:
        raise ValueError(
            f"reward_scale='auto': the mean distance to the goal under {config.method!r} is "
            f"{mean} on a random policy; give reward_scale as a number"
        )
    return 1.0 / mean


class Episode:
    """The camera frames of one episode, its goal image and each frame's true distance
    to the goal; ``seconds`` is the time spent collecting them."""

    def __init__(self) -> None:
        self.images: list[np.ndarray] = []
        self.distances: list[float] = []
        self.goal: np.ndarray | None = None
        self.seconds = 0.0

    def add(self, env: Any, obs: dict[str, np.ndarray]) -> None:
        start = time.perf_counter()
        if self.goal is None:
            self.goal = obs["goal_image"] if "goal_image" in obs else env.goal_image()
        self.images.append(obs["image"] if "image" in obs else env.render_image())
        self.distances.append(-env.true_reward(env.controllable_state(), env.goal_state()))
        self.seconds += time.perf_counter() - start


def evaluate(
    agent: SAC, env: Any, seeds: list[int], keys: tuple[str, str], film: Episode | None = None
) -> dict[str, float]:
    """Deterministic-policy episodes, one per seed; metrics from each final step's info.
    ``film`` collects the first episode's frames."""
    finals = []
    for seed in seeds:
        obs, info = env.reset(seed=seed)
        if film is not None:
            film.add(env, obs)
        done = False
        while not done:
            action = agent.act(obs[keys[0]], obs[keys[1]], sample=False)
            obs, _, terminated, truncated, info = env.step(action)
            if film is not None:
                film.add(env, obs)
            done = terminated or truncated
        finals.append(info)
        film = None
    return summarize_episodes(finals, env.metric_names)


def episode_video(
    episode: Episode, step: int, method: str, encoder: Any, scale: float, fmt: str
) -> bytes:
    """The video of a filmed episode; each frame's reward is the one the agent is trained
    on: ``scale`` times the latent reward, or the true reward without an encoder."""
    distances = np.asarray(episode.distances)
    if encoder is None:
        rewards = -scale * distances
    else:
        goal = encoder.encode(episode.goal[None])
        rewards = scale * encoders.latent_reward(encoder.encode(np.stack(episode.images)), goal)
    last = len(episode.images) - 1
    captions = [
        f"step {step}  t {t}/{last}  {method}\nreward {r:+.3f}  distance {d:.3f}"
        for t, (r, d) in enumerate(zip(rewards, distances, strict=True))
    ]
    return video.encode_video(video.episode_frames(episode.images, episode.goal, captions), fmt)


# ---- the trial ----------------------------------------------------------------------------
def train(
    config: TrialConfig,
    report: Report | None = None,
    record: Record | None = None,
    notice: Notice | None = None,
) -> TrialResult:
    """Run one trial (see the module docstring); ``report(step, metrics)`` sees each
    evaluation, and again every evaluation restored from a checkpoint; ``record(filename,
    data)`` each episode video of ``config.video_steps`` (again after a resume that
    re-runs its step); ``notice(message)`` a corrupt checkpoint discarded (also a
    warning)."""
    start = time.perf_counter()
    torch.set_num_threads(config.threads)
    device = resolve_device(config.device)
    obs_mode = "state" if config.method == "state" else "image"
    make = dict(image_size=config.image_size, obs_mode=obs_mode, **config.env_kwargs)
    with (
        contextlib.closing(make_env(config.env, **make)) as env,
        contextlib.closing(make_env(config.env, **make)) as eval_env,
    ):
        return _Trial(config, env, eval_env, device, report, record, start, notice).run()


class _Trial:
    """One trial's parts (envs, encoder, SAC, replay, random generators) and its progress
    (env step, curve so far, time spent); ``run`` is the training loop."""

    def __init__(
        self,
        config: TrialConfig,
        env: Any,
        eval_env: Any,
        device: torch.device,
        report: Report | None,
        record: Record | None,
        start: float,
        notice: Notice | None = None,
    ) -> None:
        self.config, self.env, self.eval_env, self.device = config, env, eval_env, device
        self.report, self.record, self.notice = report, record, notice
        self.start = start  # time.perf_counter() when this run of the trial began
        torch.manual_seed(config.seed)
        self.rng = np.random.default_rng(_seed(config.seed, 0))  # random actions, replay sampling
        keys = ("state", "goal_state") if config.method == "state" else ("image", "goal_image")
        self.keys = keys  # the observation's and the goal's key in the env's observations
        self.encoder, self.encoder_fit = build_encoder(config, env.image_size, device)
        self.scale = measure_reward_scale(config, self.encoder)
        env.reset(seed=_seed(config.seed, 1))  # seeds the env's generator; episodes reset() later
        self.eval_seeds = [_seed(config.seed, 100 + i) for i in range(config.eval_episodes)]
        obs_space, goal_space = env.observation_space[keys[0]], env.observation_space[keys[1]]
        action_dim = env.action_space.shape[0]
        self.machine = machine.describe(device)
        self.agent = SAC(
            obs_space.shape, goal_space.shape, action_dim, config.sac, device,
            precision=config.precision,
            channels_last=self.machine["conv_layout"] == "channels_last",
        )  # fmt: skip
        self.replay = ReplayBuffer(
            capacity=min(config.sac.buffer_capacity, config.total_steps),
            obs_shape=obs_space.shape,
            obs_dtype=obs_space.dtype,
            goal_shape=goal_space.shape,
            action_dim=action_dim,
            episode_steps=EPISODE_STEPS,
        )
        self.grid = evaluation_grid(config.total_steps, config.eval_every)
        self.video_steps = set(config.video_steps) if record is not None else set()
        self.video_format = video.default_format() if self.video_steps else ""
        self.curve: dict[str, list[float]] = {"step": []}
        self.step = 0
        self.resumed_from: int | None = None
        self.checkpointed_at: int | None = None  # the step of the last checkpoint written or read
        self.seconds_before = 0.0  # wall time of the runs before the resumed checkpoint
        self.video_seconds = 0.0
        self.machines_before: list[dict[str, Any]] = []  # the runs before the checkpoint

    def run(self) -> TrialResult:
        """Resume or evaluate the untrained agent, then train to ``total_steps``, evaluating
        on the grid and checkpointing at episode ends; a divergence ends the trial."""
        config, (obs_key, goal_key) = self.config, self.keys
        self.resume()
        if self.step == 0:
            self.evaluate_at(0)
        grid, last_checkpoint = set(self.grid), self.step
        done, diverged = True, None
        try:
            while self.step < config.total_steps:
                if done and config.stop_at is not None and self.step >= config.stop_at:
                    return self.pause()
                if done:
                    obs, goal_latent = self.start_episode()
                if self.step < config.seed_steps:
                    action = _uniform_action(self.env, self.rng)
                else:
                    action = self.agent.act(obs[obs_key], obs[goal_key], sample=True)
                obs, reward, terminated, truncated, _ = self.env.step(action)
                if self.encoder is not None:
                    latent = self.encoder.encode(obs[obs_key][None])
                    reward = float(encoders.latent_reward(latent, goal_latent)[0])
                self.replay.add(action, self.scale * reward, obs[obs_key])
                self.step += 1

                if self.step >= config.seed_steps:
                    self.update_agent()
                if self.step in grid:
                    self.evaluate_at(self.step)
                done = terminated or truncated
                due = self.step - last_checkpoint >= config.checkpoint_every
                if done and due and self.step < config.total_steps and config.checkpoint_dir:
                    self.save_checkpoint()
                    last_checkpoint = self.step
        except Diverged as exc:
            diverged = exc
            self.fill_diverged()
        return self.result(diverged)

    def pause(self) -> TrialResult:
        """Stop at an episode end at or past ``stop_at``: checkpoint (unless the checkpoint
        already written is this step's) and return the curve so far, ``Outcome.PAUSED``."""
        if self.config.checkpoint_dir and self.checkpointed_at != self.step:
            self.save_checkpoint()
        return self.result(None, paused=True)

    def start_episode(self) -> tuple[dict[str, np.ndarray], np.ndarray | None]:
        """Reset the training env: its first observation and the goal's latent (None
        without an encoder)."""
        obs, _ = self.env.reset()
        obs_key, goal_key = self.keys
        self.replay.start_episode(obs[obs_key], obs[goal_key])
        if self.encoder is None:
            return obs, None
        return obs, self.encoder.encode(obs[goal_key][None])

    def update_agent(self) -> None:
        """``updates_per_step`` SAC updates; Diverged at the first loss that is not finite."""
        for _ in range(self.config.sac.updates_per_step):
            losses = self.agent.update(self.replay.sample(self.config.sac.batch_size, self.rng))
            for name, loss in losses.items():
                if not torch.isfinite(loss):
                    raise Diverged(self.step, name)

    def evaluate_at(self, step: int) -> None:
        """Evaluate the agent at ``step``, filming the first episode if ``step`` is one of
        the video steps, and record the point."""
        film = Episode() if step in self.video_steps else None
        metrics = evaluate(self.agent, self.eval_env, self.eval_seeds, self.keys, film)
        if film is not None:
            start = time.perf_counter()
            data = episode_video(
                film, step, self.config.method, self.encoder, self.scale, self.video_format
            )
            self.record(f"episode-step{step}.{self.video_format}", data)
            self.video_seconds += film.seconds + time.perf_counter() - start
        self.add_point(step, metrics)

    def add_point(self, step: int, metrics: dict[str, float]) -> None:
        """Append an evaluation to the curve and report it."""
        self.curve["step"].append(step)
        for k, v in metrics.items():
            self.curve.setdefault(k, []).append(v)
        if self.report is not None:
            self.report(step, metrics)

    def fill_diverged(self) -> None:
        """Give the grid points after the last evaluation the diverged metrics."""
        metric_keys = tuple(metric_key(name) for name in self.env.metric_names)
        filler = diverged_metrics(metric_keys)
        for step in self.grid:
            if step > self.curve["step"][-1]:
                self.add_point(step, filler)

    def seconds(self) -> float:
        """Wall time of the trial so far, over every run of it."""
        return self.seconds_before + time.perf_counter() - self.start

    def machines(self) -> list[dict[str, Any]]:
        """Where each run of the trial so far ran, from which step."""
        return [*self.machines_before, {"from_step": self.resumed_from or 0, **self.machine}]

    def save_checkpoint(self) -> None:
        self.checkpointed_at = self.step
        checkpoint.save(
            self.config.checkpoint_dir,
            self.config,
            checkpoint.Snapshot(
                step=self.step,
                seconds=self.seconds(),
                video_seconds=self.video_seconds,
                curve={k: list(v) for k, v in self.curve.items()},
                agent=self.agent.state_dict(),
                replay=self.replay.state_dict(),
                torch_rng=torch.get_rng_state(),
                cuda_rng=torch.cuda.get_rng_state_all() if self.device.type == "cuda" else [],
                numpy_rng=self.rng.bit_generator.state,
                env_rng=self.env.np_random.bit_generator.state,
                machines=self.machines(),
            ),
        )

    def resume(self) -> None:
        """Continue from the checkpoint in ``checkpoint_dir``, if there is one: restore
        everything it holds and report the curve so far again."""
        if not self.config.checkpoint_dir:
            return
        try:
            saved = checkpoint.load(self.config.checkpoint_dir, self.config)
        except checkpoint.CorruptCheckpoint as e:
            # not resumable: the trial starts again, and says so where the user looks
            message = f"discarded its {e}; the trial restarts from step 0"
            warnings.warn(message, stacklevel=2)
            if self.notice is not None:
                self.notice(message)
            return
        if saved is None:
            return
        self.step = self.resumed_from = self.checkpointed_at = saved.step
        self.seconds_before = saved.seconds
        self.video_seconds = saved.video_seconds
        self.machines_before = saved.machines
        self.agent.load_state_dict(saved.agent)
        self.replay.load_state_dict(saved.replay)
        torch.set_rng_state(saved.torch_rng)
        if self.device.type == "cuda":
            torch.cuda.set_rng_state_all(saved.cuda_rng)
        self.rng.bit_generator.state = saved.numpy_rng
        self.env.np_random.bit_generator.state = saved.env_rng
        for i, step in enumerate(saved.curve["step"]):
            point = {k: float(v[i]) for k, v in saved.curve.items() if k != "step"}
            self.add_point(int(step), point)

    def result(self, diverged: Diverged | None, paused: bool = False) -> TrialResult:
        metrics = {k: tuple(v) for k, v in self.curve.items() if k != "step"}
        outcome = Outcome.PAUSED if paused else Outcome.DIVERGED if diverged else Outcome.COMPLETED
        return TrialResult(
            steps=tuple(self.curve["step"]),
            metrics=metrics,
            auc=normalized_auc(self.curve["step"], metrics["success_rate"]),
            outcome=outcome,
            diverged_step=diverged.step if diverged else None,
            diverged_loss=diverged.loss if diverged else None,
            seconds=self.seconds(),
            resumed_from=self.resumed_from,
            reward_scale=self.scale,
            video_seconds=self.video_seconds,
            machines=tuple(self.machines()),
            encoder_fit=self.encoder_fit,
        )
