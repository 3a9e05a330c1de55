"""Side by side with stable-baselines3 SAC: env steps per second, same run, same machine.

Both learners get the same env (``point_reach`` at 48x48 by default, pixel reward), the
DrQ conv encoder (shared by observation and goal, Linear to 50, LayerNorm, tanh), hidden
sizes 256x256, batch 256 and 2 gradient steps per env step after the same random seed
steps. stable-baselines3 runs with its defaults otherwise (``MultiInputPolicy``, a
separate encoder for the actor and for the critic, no augmentation). Target: our env steps
per second >= 2x theirs.

Run: ``.venv/bin/python benchmarks/bench_vs_sb3.py [--env point_reach] [--steps 150]``
(needs the ``bench`` extra: ``pip install -e .[bench]``).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3 import SAC as SB3SAC
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

import agent
from agent.config import SACConfig, TrialConfig
from agent.envs import make_env
from agent.sac import conv_output_size
from encoders import latent_reward, make_encoder


class DrQExtractor(BaseFeaturesExtractor):
    """The DrQ encoder for SB3's Dict observations (already float CHW in [0, 1])."""

    def __init__(self, space: gym.spaces.Dict, feature_dim: int = 50, filters: int = 32):
        super().__init__(space, features_dim=2 * feature_dim)
        size = space["image"].shape[-1]
        layers: list[nn.Module] = [nn.Conv2d(3, filters, 3, stride=2), nn.ReLU()]
        for _ in range(3):
            layers += [nn.Conv2d(filters, filters, 3, stride=1), nn.ReLU()]
        self.convs = nn.Sequential(*layers, nn.Flatten())
        side = conv_output_size(size)
        self.head = nn.Sequential(
            nn.Linear(filters * side * side, feature_dim), nn.LayerNorm(feature_dim), nn.Tanh()
        )

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        n = len(obs["image"])
        h = self.head(self.convs(torch.cat([obs["image"], obs["goal_image"]])))
        return torch.cat([h[:n], h[n:]], dim=1)


class PixelReward(gym.Wrapper):
    """The ``pixel`` encoder reward, as ``agent.train`` computes it."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        size = env.image_size
        self.encoder = make_encoder("pixel", (size, size, 3))

    def reset(self, **kwargs: object) -> tuple[dict, dict]:
        obs, info = self.env.reset(**kwargs)
        self.goal_latent = self.encoder.encode(obs["goal_image"][None])
        return obs, info

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        obs, _, terminated, truncated, info = self.env.step(action)
        reward = float(latent_reward(self.encoder.encode(obs["image"][None]), self.goal_latent)[0])
        return obs, reward, terminated, truncated, info


def timed(steps: int, run: Callable[[], object]) -> tuple[float, float]:
    """Env steps per second of wall time and of this process's CPU time."""
    wall, cpu = time.perf_counter(), time.process_time()
    run()
    return steps / (time.perf_counter() - wall), steps / (time.process_time() - cpu)


def run_ours(env: str, size: int, steps: int, seed_steps: int, threads: int) -> tuple[float, float]:
    config = TrialConfig(
        env=env,
        image_size=size,
        method="pixel",
        sac=SACConfig(hidden_sizes=(256, 256), batch_size=256, updates_per_step=2),
        total_steps=steps,
        seed_steps=seed_steps,
        eval_every=steps,
        eval_episodes=1,
        device="cpu",
        threads=threads,
    )
    return timed(steps, lambda: agent.train(config))


def run_sb3(env: str, size: int, steps: int, seed_steps: int, threads: int) -> tuple[float, float]:
    torch.set_num_threads(threads)
    model = SB3SAC(
        "MultiInputPolicy",
        PixelReward(make_env(env, image_size=size)),
        buffer_size=steps,
        batch_size=256,
        learning_starts=seed_steps,
        train_freq=1,
        gradient_steps=2,
        policy_kwargs={"features_extractor_class": DrQExtractor, "net_arch": [256, 256]},
        device="cpu",
        seed=0,
    )
    return timed(steps, lambda: model.learn(total_timesteps=steps))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="point_reach")
    parser.add_argument("--image-size", type=int, default=48)
    parser.add_argument("--steps", type=int, default=150, help="env steps per learner")
    parser.add_argument("--seed-steps", type=int, default=50)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    args = parser.parse_args()
    common = (args.env, args.image_size, args.steps, args.seed_steps, args.threads)
    print(
        f"{args.env} {args.image_size}x{args.image_size}, {args.steps} env steps "
        f"({args.seed_steps} random), batch 256, 2 updates/step, {args.threads} thread(s)"
    )
    theirs = run_sb3(*common)
    ours = run_ours(*common)
    for name, (wall, cpu) in (("stable-baselines3 SAC", theirs), ("agent.train", ours)):
        print(f"{name:>21}: {wall:.2f} env steps/s wall, {cpu:.2f} per CPU second")
    ratio, cpu_ratio = ours[0] / theirs[0], ours[1] / theirs[1]
    verdict = "PASS" if ratio >= 2 else "FAIL"
    print(
        f"ratio ours/theirs: {ratio:.2f}x wall ({verdict} at the 2x target), {cpu_ratio:.2f}x CPU"
    )


if __name__ == "__main__":
    main()
