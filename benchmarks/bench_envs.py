"""Milliseconds per env step including the rendered observation, for every env.

    .venv/bin/python benchmarks/bench_envs.py [--steps 300] [--envs fetch_reach ...]

Prints, per env at its default image size: ms per step+render in image mode (wall
clock, the figure with a target, and CPU time of this process, which is what the env
costs when other processes compete for the CPUs), ms per step in state mode (no
rendering), and ms per reset (which renders the goal image). Then the door rendered at
MuJoCo's default quality (shadows, reflections, 4x multisampling), to show what the
fast settings save, and the final metrics of a scripted door policy, to show its
goals can be reached. Random actions; nothing else should be running.
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import dataclass

import numpy as np

from agent.envs import ENV_NAMES, make_env  # sets MUJOCO_GL before mujoco loads

#: ms per step+render at the default image size (the issue's targets)
TARGET_MS = {"fetch_reach": 15.0, "fetch_push": 15.0, "sawyer_door": 15.0, "point_reach": 0.2}


@dataclass(frozen=True)
class Timing:
    step_ms: float  # wall clock per step
    step_cpu_ms: float  # CPU time of this process (all threads: Mesa renders with threads)
    reset_ms: float  # wall clock per reset
    image_size: int


def time_env(name: str, obs_mode: str, steps: int) -> Timing:
    """Time ``steps`` random steps of env ``name``, resetting every 50 steps."""
    env = make_env(name, obs_mode=obs_mode)
    actions = np.random.default_rng(0).uniform(-1, 1, (steps, *env.action_space.shape))
    env.reset(seed=0)
    env.step(actions[0])  # warm up (the first frame makes the GL context)
    wall = cpu = reset = 0.0
    resets = 0
    for t, action in enumerate(actions):
        start, start_cpu = time.perf_counter(), time.process_time()
        *_, truncated, _ = env.step(action)
        wall += time.perf_counter() - start
        cpu += time.process_time() - start_cpu
        if truncated:
            start = time.perf_counter()
            env.reset(seed=t)
            reset += time.perf_counter() - start
            resets += 1
    env.close()
    return Timing(1000 * wall / steps, 1000 * cpu / steps, 1000 * reset / resets, env.image_size)


def door_default_quality_ms(frames: int = 10) -> float:
    """ms per 48x48 frame of the door scene with MuJoCo's default render settings."""
    import mujoco
    from metaworld.envs.sawyer_door_v3 import SawyerDoorEnvV3

    from agent.envs._mujoco import make_camera
    from agent.envs.sawyer_door import DEFAULT_CAMERA

    sim = SawyerDoorEnvV3(render_mode=None)
    renderer = mujoco.Renderer(sim.model, 48, 48)
    camera = make_camera(sim.model, DEFAULT_CAMERA)
    renderer.update_scene(sim.data, camera)
    renderer.render()
    start = time.perf_counter()
    for _ in range(frames):
        renderer.update_scene(sim.data, camera)
        renderer.render()
    elapsed = time.perf_counter() - start
    renderer.close()
    return 1000 * elapsed / frames


def scripted_door(episodes: int = 30) -> dict[str, float]:
    """Mean final metrics of a scripted sawyer_door policy: hook the hand between the
    handle bar and the door, pull along the door's arc (slowing down: the door coasts),
    lift the hand over the bar, move it to the goal. Shows the goals can be reached in
    50 steps; a learned policy can do better (the script often misses the 0.02 rad)."""
    env = make_env("sawyer_door", obs_mode="state")
    hinge = env.data.body("door_link").xpos[:2].copy()
    hook = np.array([0.33, 0.80, 0.19])  # between the bar and the closed door
    totals: dict[str, float] = {}
    for seed in range(episodes):
        env.reset(seed=seed)
        goal, phase, info = env.goal_state(), "hook", {}
        for _ in range(50):
            mocap = env.data.mocap_pos[0].copy()
            state = env.controllable_state()
            if phase == "hook":
                above = np.linalg.norm(mocap[:2] - hook[:2]) > 0.03
                target = hook + np.array([0.0, 0.0, 0.12]) if above else hook
                phase = "pull" if np.linalg.norm(mocap - hook) < 0.02 else phase
            if phase == "pull":
                rel = mocap[:2] - hinge
                left = state[3] - goal[3]  # radians still to open
                coasting = abs(env.data.joint("doorjoint").qvel[0]) >= 1.0
                turn = 0.0 if coasting else float(np.clip(0.3 * left, 0.0, 0.08))
                angle = np.arctan2(rel[1], rel[0]) - turn
                target = np.r_[
                    hinge + np.linalg.norm(rel) * np.r_[np.cos(angle), np.sin(angle)], 0.19
                ]
                phase = "lift" if left < 0.005 else phase
            if phase == "lift":
                target = np.r_[mocap[:2], 0.32]
                phase = "move" if state[2] > 0.29 else phase
            if phase == "move":
                target = goal[:3]
            *_, info = env.step(np.clip((target - mocap) / env.action_scale, -1.0, 1.0))
        for k, v in info.items():
            totals[k] = totals.get(k, 0.0) + v / episodes
    env.close()
    return totals


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300, help="timed steps per env (>= 50)")
    parser.add_argument("--envs", nargs="+", default=list(ENV_NAMES), choices=ENV_NAMES)
    args = parser.parse_args()
    if args.steps < 50:
        parser.error("--steps must be >= 50 (one episode)")
    print(f"load average (1 min) at start: {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    print(
        f"{'env':<12} {'size':>4} {'step+render ms':>15} {'(cpu ms)':>9} {'target':>9} "
        f"{'state-mode ms':>14} {'reset ms':>9}"
    )
    for name in args.envs:
        image = time_env(name, "image", args.steps)
        state = time_env(name, "state", args.steps)
        verdict = "ok" if image.step_ms <= TARGET_MS[name] else "SLOW"
        print(
            f"{name:<12} {image.image_size:>4} {image.step_ms:>15.3f} {image.step_cpu_ms:>9.3f} "
            f"{TARGET_MS[name]:>4.1f} {verdict:<4} {state.step_ms:>14.3f} {image.reset_ms:>9.1f}",
            flush=True,
        )
    if "sawyer_door" in args.envs:
        print(
            f"sawyer_door 48x48 at MuJoCo's default render quality: "
            f"{door_default_quality_ms():.1f} ms per frame"
        )
        results = ", ".join(f"{k} {v:.3f}" for k, v in scripted_door().items())
        print(f"sawyer_door scripted policy, 30 episodes, mean final: {results}")


if __name__ == "__main__":
    main()
