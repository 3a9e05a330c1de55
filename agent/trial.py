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

Checkpoints are written only at episode ends: the next thing the trial does is reset
the env, so no mid-episode simulator state is needed, only the env's random generator.
A checkpoint holds the networks, optimisers, replay, counters, the curve so far, and the
torch and numpy random states; resuming from it gives the same curve on CPU.
``checkpoint_dir`` is a local directory or an object-store URI (``agent.storage_io``). Each
checkpoint carries a SHA-256 digest of its contents: a truncated or corrupt file is
ignored with a warning. Learned encoders are fitted again on resume (deterministic given
the seed) rather than saved, so no encoder needs a serialisation API.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import time
import warnings
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

import encoders
from agent import storage_io
from agent.config import RUNTIME_FIELDS, TRUE_REWARD_METHODS, TrialConfig, TrialResult
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
CHECKPOINT_NAME = "checkpoint.pt"
CHECKPOINT_FORMAT = 1
DEFAULT_NUM_IMAGES = 1000
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


def build_encoder(config: TrialConfig, image_size: int, device: torch.device) -> Any:
    """The trial's reward encoder, fitted on random-policy frames when it learns; None for
    the methods that use the true reward."""
    if config.method in TRUE_REWARD_METHODS:
        return None
    if config.method not in encoders.encoder_names():
        names = ", ".join((*encoders.encoder_names(), *TRUE_REWARD_METHODS))
        raise ValueError(f"method must be one of {names}; got {config.method!r}")
    shape = (image_size, image_size, 3)
    encoder = encoders.make_encoder(
        config.method, shape, config.seed, str(device), **config.encoder_params
    )
    if encoder.needs_fit:
        num_images = getattr(encoder, "num_images", None) or config.encoder_params.get(
            "num_images", DEFAULT_NUM_IMAGES
        )
        encoder.fit(collect_random_images(config, int(num_images)), progress=False)
    return encoder


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
    from agent import video

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


# ---- checkpoint files -------------------------------------------------------------------
def _digest(obj: Any) -> str:
    """SHA-256 over every value in a nested checkpoint (tensors by their bytes)."""
    h = hashlib.sha256()

    def visit(x: Any) -> None:
        if isinstance(x, torch.Tensor):
            x = x.detach().cpu().contiguous()
            h.update(f"T{x.dtype}{tuple(x.shape)}".encode())
            h.update(x.reshape(-1).view(torch.uint8).numpy())
        elif isinstance(x, dict):
            h.update(f"D{len(x)}".encode())
            for k in sorted(x, key=repr):
                h.update(repr(k).encode())
                visit(x[k])
        elif isinstance(x, list | tuple):
            h.update(f"L{len(x)}".encode())
            for v in x:
                visit(v)
        else:
            h.update(repr(x).encode())

    visit(obj)
    return h.hexdigest()


def _to_tensors(obj: Any) -> Any:
    """numpy arrays -> tensors (no copy), so the file loads with ``weights_only=True``."""
    if isinstance(obj, np.ndarray):
        return torch.from_numpy(obj)
    if isinstance(obj, dict):
        return {k: _to_tensors(v) for k, v in obj.items()}
    return obj


def save_checkpoint(location: str, state: dict[str, Any]) -> None:
    """Write ``state`` atomically (``agent.storage_io.write_atomic``) with its digest."""
    state = _to_tensors(state)
    state["digest"] = _digest(state)
    storage_io.write_atomic(location, lambda f: torch.save(state, f))


def load_checkpoint(location: str, config: TrialConfig) -> dict[str, Any] | None:
    """The checkpoint at ``location`` if there is one and it is intact, else None (with a
    warning if it is corrupt). A checkpoint of another trial config, or of another owner
    (``config.checkpoint_owner``, e.g. another study with the same spec), is an error:
    resuming it would mix two trials."""
    source = storage_io.open_read(location)
    if source is None:
        return None
    try:
        with source:
            state = torch.load(source, map_location="cpu", weights_only=True)
        digest = state.pop("digest")
        if state.get("format") != CHECKPOINT_FORMAT or digest != _digest(state):
            raise ValueError("digest or format mismatch")
    except Exception as exc:
        warnings.warn(f"ignoring corrupt checkpoint {location}: {exc}", stacklevel=3)
        return None
    if state.get("owner") != config.checkpoint_owner:
        raise ValueError(
            f"checkpoint_dir {config.checkpoint_dir!r} holds a checkpoint of another study "
            f"(owner {state.get('owner')!r}, this trial's is {config.checkpoint_owner!r}); "
            "give each study its own checkpoint_dir"
        )
    if state["config"] != _config_key(config):
        raise ValueError(
            f"checkpoint_dir {config.checkpoint_dir!r} holds a checkpoint of another trial "
            "config; give each trial its own checkpoint_dir"
        )
    return state


def _config_key(config: TrialConfig) -> str:
    fields = dataclasses.asdict(config)
    for name in RUNTIME_FIELDS:
        fields.pop(name)
    return repr(fields)


# ---- the trial ----------------------------------------------------------------------------
def train(
    config: TrialConfig, report: Report | None = None, record: Record | None = None
) -> TrialResult:
    """Run one trial (see the module docstring); ``report(step, metrics)`` sees each
    evaluation, and again every evaluation restored from a checkpoint; ``record(filename,
    data)`` each episode video of ``config.video_steps`` (again after a resume that
    re-runs its step)."""
    start = time.perf_counter()
    torch.set_num_threads(config.threads)
    device = resolve_device(config.device)
    obs_mode = "state" if config.method == "state" else "image"
    make = dict(image_size=config.image_size, obs_mode=obs_mode, **config.env_kwargs)
    with (
        contextlib.closing(make_env(config.env, **make)) as env,
        contextlib.closing(make_env(config.env, **make)) as eval_env,
    ):
        return _run(config, report, record, env, eval_env, device, start)


def _run(
    config: TrialConfig,
    report: Report | None,
    record: Record | None,
    env: Any,
    eval_env: Any,
    device: torch.device,
    start: float,
) -> TrialResult:
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(_seed(config.seed, 0))  # random actions, replay sampling
    keys = ("state", "goal_state") if config.method == "state" else ("image", "goal_image")
    encoder = build_encoder(config, env.image_size, device)
    scale = measure_reward_scale(config, encoder)
    env.reset(seed=_seed(config.seed, 1))  # seeds the env's generator; episodes reset() below
    eval_seeds = [_seed(config.seed, 100 + i) for i in range(config.eval_episodes)]
    obs_space, goal_space = env.observation_space[keys[0]], env.observation_space[keys[1]]
    action_dim = env.action_space.shape[0]

    agent = SAC(obs_space.shape, goal_space.shape, action_dim, config.sac, device)
    replay = ReplayBuffer(
        capacity=min(config.sac.buffer_capacity, config.total_steps),
        obs_shape=obs_space.shape,
        obs_dtype=obs_space.dtype,
        goal_shape=goal_space.shape,
        action_dim=action_dim,
        episode_steps=EPISODE_STEPS,
    )
    grid = evaluation_grid(config.total_steps, config.eval_every)
    grid_set = set(grid)
    curve: dict[str, list[float]] = {"step": []}

    def record_point(step: int, metrics: dict[str, float]) -> None:
        curve["step"].append(step)
        for k, v in metrics.items():
            curve.setdefault(k, []).append(v)
        if report is not None:
            report(step, metrics)

    video_steps = set(config.video_steps) if record is not None else set()
    video_format = ""
    if video_steps:
        from agent.video import default_format

        video_format = default_format()
    filmed = {"seconds": 0.0}

    def evaluation(step: int) -> None:
        film = Episode() if step in video_steps else None
        metrics = evaluate(agent, eval_env, eval_seeds, keys, film)
        if film is not None:
            start_video = time.perf_counter()
            data = episode_video(film, step, config.method, encoder, scale, video_format)
            record(f"episode-step{step}.{video_format}", data)
            filmed["seconds"] += film.seconds + time.perf_counter() - start_video
        record_point(step, metrics)

    # resume: restore everything, re-report the curve so far
    step, seconds_before, resumed_from = 0, 0.0, None
    path = (
        storage_io.join(config.checkpoint_dir, CHECKPOINT_NAME) if config.checkpoint_dir else None
    )
    saved = load_checkpoint(path, config) if path is not None else None
    if saved is not None:
        step = resumed_from = int(saved["step"])
        seconds_before = float(saved["seconds"])
        filmed["seconds"] = float(saved.get("video_seconds", 0.0))
        agent.load_state_dict(saved["agent"])
        replay.load_state_dict(saved["replay"])
        torch.set_rng_state(saved["torch_rng"])
        if device.type == "cuda":
            torch.cuda.set_rng_state_all(saved["cuda_rng"])
        rng.bit_generator.state = saved["numpy_rng"]
        env.np_random.bit_generator.state = saved["env_rng"]
        for i, s in enumerate(saved["curve"]["step"]):
            point = {k: float(v[i]) for k, v in saved["curve"].items() if k != "step"}
            record_point(int(s), point)
    last_checkpoint = step

    def checkpoint() -> None:
        save_checkpoint(path, {
            "format": CHECKPOINT_FORMAT,
            "config": _config_key(config),
            "owner": config.checkpoint_owner,
            "step": step,
            "seconds": seconds_before + time.perf_counter() - start,
            "video_seconds": filmed["seconds"],
            "curve": {k: list(v) for k, v in curve.items()},
            "agent": agent.state_dict(),
            "replay": replay.state_dict(),
            "torch_rng": torch.get_rng_state(),
            "cuda_rng": torch.cuda.get_rng_state_all() if device.type == "cuda" else [],
            "numpy_rng": rng.bit_generator.state,
            "env_rng": env.np_random.bit_generator.state,
        })  # fmt: skip

    outcome, diverged = "completed", None
    if step == 0:
        evaluation(0)
    episode_done, goal_latent = True, None
    try:
        while step < config.total_steps:
            if episode_done:
                obs, _ = env.reset()
                replay.start_episode(obs[keys[0]], obs[keys[1]])
                if encoder is not None:
                    goal_latent = encoder.encode(obs[keys[1]][None])
            if step < config.seed_steps:
                action = _uniform_action(env, rng)
            else:
                action = agent.act(obs[keys[0]], obs[keys[1]], sample=True)
            obs, reward, terminated, truncated, _ = env.step(action)
            if encoder is not None:
                latent = encoder.encode(obs[keys[0]][None])
                reward = float(encoders.latent_reward(latent, goal_latent)[0])
            replay.add(action, scale * reward, obs[keys[0]])
            step += 1

            if step >= config.seed_steps:
                for _ in range(config.sac.updates_per_step):
                    losses = agent.update(replay.sample(config.sac.batch_size, rng))
                    for name, loss in losses.items():
                        if not torch.isfinite(loss):
                            raise Diverged(step, name)

            if step in grid_set:
                evaluation(step)
            episode_done = terminated or truncated
            due = step - last_checkpoint >= config.checkpoint_every and step < config.total_steps
            if episode_done and due and path is not None:
                checkpoint()
                last_checkpoint = step
    except Diverged as exc:
        outcome, diverged = "diverged", exc
        filler = diverged_metrics(tuple(metric_key(name) for name in env.metric_names))
        for s in grid:
            if s > curve["step"][-1]:
                record_point(s, filler)

    metrics = {k: tuple(v) for k, v in curve.items() if k != "step"}
    return TrialResult(
        steps=tuple(curve["step"]),
        metrics=metrics,
        auc=normalized_auc(curve["step"], metrics["success_rate"]),
        outcome=outcome,
        diverged_step=diverged.step if diverged else None,
        diverged_loss=diverged.loss if diverged else None,
        seconds=seconds_before + time.perf_counter() - start,
        resumed_from=resumed_from,
        reward_scale=scale,
        video_seconds=filmed["seconds"],
    )
