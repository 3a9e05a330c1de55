"""Episode videos (agent/video.py): layout, captions, MP4 and GIF round trips."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import tiny

import agent
from agent import video


def blobs(n: int, size: int) -> tuple[list[np.ndarray], np.ndarray]:
    """``n`` frames of a white square moving right, and a goal frame with it at the end."""
    frames = []
    for i in range(n + 1):
        image = np.full((size, size, 3), 40, np.uint8)
        x = i * (size - 8) // n
        image[10:18, x : x + 8] = 255
        frames.append(image)
    return frames[:-1], frames[-1]


def test_frames_show_observation_beside_goal_with_a_caption() -> None:
    images, goal = blobs(5, 32)
    frames = video.episode_frames(images, goal, [f"t {i}\nr -1.0" for i in range(5)])
    assert len(frames) == 5
    height, width, _ = frames[0].shape
    assert height % 16 == 0 and width % 16 == 0
    panel = 128  # 32 pixels scaled by 4
    assert width >= 2 * panel + video.GAP and height >= panel + video.CAPTION
    for image, frame in zip(images, frames, strict=True):
        assert np.array_equal(frame[:panel:4, :panel:4], image)
        right = frame[:panel, panel + video.GAP : 2 * panel + video.GAP]
        assert np.array_equal(right[::4, ::4], goal)
    band = [f[panel:] for f in frames]
    assert all(b.max() == 255 for b in band)  # the caption is drawn
    assert not np.array_equal(band[0], band[1])  # and differs per frame


def test_frames_refuse_a_caption_count_mismatch() -> None:
    images, goal = blobs(3, 32)
    with pytest.raises(ValueError, match="3 images but 2 captions"):
        video.episode_frames(images, goal, ["a", "b"])


@pytest.mark.parametrize("fmt", ["mp4", "gif"])
def test_video_round_trip_keeps_count_size_and_content(fmt: str) -> None:
    images, goal = blobs(51, 48)
    frames = video.episode_frames(images, goal, [f"step 4000 t {i}" for i in range(51)])
    data = video.encode_video(frames, fmt)
    assert len(data) < 300_000  # a few hundred kB at most per trial
    decoded = video.decode_video(data, fmt)
    assert decoded.shape == (51, *frames[0].shape)
    # lossy (H.264, GIF palette), but the moving square is where it was drawn
    error = np.abs(decoded.astype(int) - np.stack(frames).astype(int)).mean()
    assert error < 6


def test_default_format_is_mp4_with_imageio_ffmpeg_installed() -> None:
    pytest.importorskip("imageio_ffmpeg")
    assert video.default_format() == "mp4"


def test_encode_video_refuses_unknown_formats_and_no_frames() -> None:
    with pytest.raises(ValueError, match="format"):
        video.encode_video([np.zeros((16, 16, 3), np.uint8)], "avi")
    with pytest.raises(ValueError, match="at least one frame"):
        video.encode_video([], "gif")


# ---- filming a trial's evaluation episode (agent.train) -----------------------------------


@pytest.mark.parametrize("method", ["pixel", "state"])
def test_train_films_the_first_evaluation_episode_at_video_steps(method: str) -> None:
    files: list[tuple[str, bytes]] = []
    config = tiny(method=method, video_steps=[200, 0])
    result = agent.train(config, record=lambda name, data: files.append((name, data)))
    fmt = video.default_format()
    assert [name for name, _ in files] == [f"episode-step0.{fmt}", f"episode-step200.{fmt}"]
    frames = video.decode_video(files[-1][1], fmt)
    assert frames.shape == (51, 160, 272, 3)  # reset + 50 steps; 2 x 128 + gap, 128 + caption
    assert 0 < result.video_seconds < result.seconds
    # filming changes nothing the trial computes, and no record callback means no filming
    plain = agent.train(config)
    assert plain.metrics == result.metrics and plain.video_seconds == 0.0


def test_video_steps_must_be_on_the_evaluation_grid() -> None:
    assert tiny(video_steps=[200, 100, 200]).video_steps == (100, 200)
    for bad in ([150], [300], [-100], ["200"]):
        with pytest.raises(ValueError, match="video_steps must be env steps on the evaluation"):
            tiny(video_steps=bad)


def test_goal_image_is_rendered_in_state_mode_as_in_image_mode() -> None:
    from agent.envs import make_env

    image_env = make_env("point_reach", image_size=32)
    state_env = make_env("point_reach", image_size=32, obs_mode="state")
    obs, _ = image_env.reset(seed=3)
    state_env.reset(seed=3)
    assert np.array_equal(state_env.goal_image(), obs["goal_image"])
    assert np.array_equal(image_env.goal_image(), obs["goal_image"])
    assert np.array_equal(state_env.render_image(), obs["image"])
