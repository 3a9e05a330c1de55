"""Replay memory: bytes per stored transition, and a 1e6-transition buffer at 48x48.

Prints the allocated bytes per transition at 84x84 and 48x48 (frames stored once per
time step, goals once per episode), checks it against the resident memory actually
taken by filling a buffer, and the size of a 1e6-transition buffer at 48x48
(target: under 8 GB).

Run: ``.venv/bin/python benchmarks/bench_memory.py [--fill 20000]``
"""

from __future__ import annotations

import argparse
import resource

import numpy as np

from agent.envs.base import EPISODE_STEPS
from agent.replay import ReplayBuffer

ACTION_DIM = 4


def rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize()


def buffer(size: int, capacity: int) -> ReplayBuffer:
    shape = (size, size, 3)
    return ReplayBuffer(capacity, shape, np.uint8, shape, ACTION_DIM, EPISODE_STEPS)


def measured_per_transition(size: int, transitions: int) -> float:
    """Resident bytes per transition after filling a buffer with ``transitions``."""
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 256, (size, size, 3), dtype=np.uint8)
    before = rss_bytes()
    b = buffer(size, transitions)
    for _ in range(transitions // EPISODE_STEPS):
        b.start_episode(frame, frame)
        for _ in range(EPISODE_STEPS):
            b.add(np.zeros(ACTION_DIM, np.float32), 0.0, frame)
    return (rss_bytes() - before) / len(b)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fill", type=int, default=20_000, help="transitions to really store")
    args = parser.parse_args()
    for size in (84, 48):
        frame = size * size * 3
        allocated = buffer(size, 1_000_000).nbytes / 1_000_000
        measured = measured_per_transition(size, args.fill)
        print(
            f"{size}x{size}: frame {frame} B; {allocated:.0f} B/transition allocated "
            f"({allocated / frame:.3f} frames), {measured:.0f} B/transition resident "
            f"after storing {args.fill}"
        )
    total = buffer(48, 1_000_000).nbytes
    print(
        f"1e6 transitions at 48x48: {total / 1e9:.2f} GB "
        f"({'PASS' if total < 8e9 else 'FAIL'} at the 8 GB target)"
    )


if __name__ == "__main__":
    main()
