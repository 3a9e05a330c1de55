"""The replay buffer returns exactly what was stored, with about one frame per transition."""

from __future__ import annotations

import numpy as np
import pytest

from agent.replay import ReplayBuffer

T = 5  # steps per episode


def frame(episode: int, t: int) -> np.ndarray:
    """A frame whose pixels say which episode and step it is."""
    img = np.zeros((4, 4, 3), np.uint8)
    img[..., 0], img[..., 1] = episode, t
    return img


def fill(buffer: ReplayBuffer, episodes: int, steps: int = T) -> None:
    for e in range(episodes):
        buffer.start_episode(frame(e, 0), frame(e, 200))
        for t in range(steps):
            buffer.add(np.array([e, t], np.float32), 1000.0 * e + t, frame(e, t + 1))


def make(capacity: int = 20) -> ReplayBuffer:
    return ReplayBuffer(capacity, (4, 4, 3), np.uint8, (4, 4, 3), action_dim=2, episode_steps=T)


def check_transitions(batch: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Every sampled field agrees with the transition (episode e, step t) it came from."""
    e, t = batch["action"][:, 0].astype(int), batch["action"][:, 1].astype(int)
    np.testing.assert_array_equal(batch["reward"][:, 0], 1000.0 * e + t)
    np.testing.assert_array_equal(batch["obs"][:, 0, 0], np.stack([e, t, 0 * t], 1))
    np.testing.assert_array_equal(batch["next_obs"][:, 0, 0], np.stack([e, t + 1, 0 * t], 1))
    np.testing.assert_array_equal(batch["goal"][:, 0, 0], np.stack([e, 0 * t + 200, 0 * t], 1))
    return e, t


def test_sample_returns_the_stored_transitions() -> None:
    buffer = make()
    fill(buffer, episodes=3, steps=T)
    buffer.start_episode(frame(3, 0), frame(3, 200))  # a partial episode is sampled too
    buffer.add(np.array([3, 0], np.float32), 3000.0, frame(3, 1))
    assert len(buffer) == 3 * T + 1
    e, t = check_transitions(buffer.sample(4000, np.random.default_rng(0)))
    seen = set(zip(e.tolist(), t.tolist(), strict=True))
    assert seen == {(ep, s) for ep in range(3) for s in range(T)} | {(3, 0)}
    # uniform over transitions: each of the 16 appears about 4000/16 = 250 times
    counts = np.unique(e * T + t, return_counts=True)[1]
    assert counts.min() > 170 and counts.max() < 330


def test_oldest_episodes_are_overwritten() -> None:
    buffer = make(capacity=10)  # two episode slots
    fill(buffer, episodes=5)
    assert len(buffer) == 10
    e, _ = check_transitions(buffer.sample(500, np.random.default_rng(1)))
    assert set(e.tolist()) == {3, 4}


def test_state_dict_round_trip() -> None:
    buffer = make(capacity=15)
    fill(buffer, episodes=4)
    copy = make(capacity=15)
    copy.load_state_dict(buffer.state_dict())
    a = buffer.sample(64, np.random.default_rng(2))
    b = copy.sample(64, np.random.default_rng(2))
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    assert copy.episodes == buffer.episodes


def test_memory_is_about_one_frame_per_transition() -> None:
    capacity, size = 10_000, 48
    buffer = ReplayBuffer(capacity, (size, size, 3), np.uint8, (size, size, 3), 4, 50)
    frame_bytes = size * size * 3
    per_transition = buffer.nbytes / buffer.capacity
    # (50 + 1) frames + 1 goal per 50 transitions, plus action and reward
    assert frame_bytes <= per_transition < 1.05 * frame_bytes


def test_misuse_is_an_error() -> None:
    buffer = make()
    with pytest.raises(RuntimeError, match="start_episode"):
        buffer.add(np.zeros(2), 0.0, frame(0, 0))
    with pytest.raises(RuntimeError, match="empty"):
        buffer.sample(1, np.random.default_rng(0))
    fill(buffer, episodes=1)
    with pytest.raises(RuntimeError, match="episode_steps"):
        buffer.add(np.zeros(2), 0.0, frame(0, 0))
    with pytest.raises(ValueError, match="capacity"):
        make(capacity=0)
