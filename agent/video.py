"""Episode videos: each frame the observation beside the goal image, captioned.

``episode_frames`` lays out the frames (images scaled up by an integer factor so a 32-pixel
env is still readable, a caption band below: env step, episode step, reward, true
distance); ``encode_video`` turns them into MP4 (H.264, where the ``imageio-ffmpeg`` wheel
and its ffmpeg binary are installed) or GIF (Pillow, always there) bytes; ``decode_video``
reads either back (the report's final frames, tests). Frame sides are multiples of 16,
so H.264 needs no rescaling and every player shows the pixels as drawn.
"""

from __future__ import annotations

import functools
import io
import os
import tempfile
from collections.abc import Sequence
from typing import Any

import numpy as np

#: frames per second: a 51-frame episode plays in about 5 s
FPS = 10
#: each image is scaled up by an integer factor to at least this many pixels per side
MIN_PANEL = 128
#: pixels between the two images and of the caption band below them
GAP, CAPTION = 4, 30
FORMATS = ("mp4", "gif")


def default_format() -> str:
    """MP4 where imageio-ffmpeg is importable (its wheel ships ffmpeg), else GIF."""
    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        return "gif"
    return "mp4"


@functools.cache
def caption_font() -> Any:
    """Pillow's default font at caption size (no font file needed)."""
    from PIL import ImageFont

    return ImageFont.load_default(size=11)


def _round_up(n: int, multiple: int = 16) -> int:
    return -(-n // multiple) * multiple


def episode_frames(
    images: Sequence[np.ndarray], goal: np.ndarray, captions: Sequence[str]
) -> list[np.ndarray]:
    """One uint8 HxWx3 frame per image: the image left, ``goal`` right, its caption (one or
    two lines, ``\\n``-separated) below."""
    from PIL import Image, ImageDraw

    if len(images) != len(captions):
        raise ValueError(f"{len(images)} images but {len(captions)} captions")
    size = goal.shape[0]
    scale = -(-MIN_PANEL // size)
    panel = size * scale
    width, height = _round_up(2 * panel + GAP), _round_up(panel + CAPTION)
    base = np.zeros((height, width, 3), np.uint8)
    base[:panel, panel + GAP : 2 * panel + GAP] = goal.repeat(scale, 0).repeat(scale, 1)
    frames = []
    for image, caption in zip(images, captions, strict=True):
        frame = base.copy()
        frame[:panel, :panel] = image.repeat(scale, 0).repeat(scale, 1)
        canvas = Image.fromarray(frame)
        ImageDraw.Draw(canvas).multiline_text(
            (3, panel + 2), caption, fill=(255, 255, 255), font=caption_font(), spacing=2
        )
        frames.append(np.asarray(canvas))
    return frames


def encode_video(frames: Sequence[np.ndarray], fmt: str = "mp4", fps: int = FPS) -> bytes:
    """``frames`` (uint8 HxWx3, sides multiples of 16) as MP4 or GIF bytes."""
    if fmt not in FORMATS:
        raise ValueError(f"video format must be one of {FORMATS}, got {fmt!r}")
    if not frames:
        raise ValueError("a video needs at least one frame")
    if fmt == "gif":
        from PIL import Image

        images = [Image.fromarray(f) for f in frames]
        buffer = io.BytesIO()
        images[0].save(
            buffer,
            format="GIF",
            save_all=True,
            append_images=images[1:],
            duration=round(1000 / fps),
            loop=0,
        )
        return buffer.getvalue()
    import imageio_ffmpeg

    height, width = frames[0].shape[:2]
    with tempfile.TemporaryDirectory() as folder:  # ffmpeg's MP4 muxer needs a seekable file
        path = os.path.join(folder, "episode.mp4")
        writer = imageio_ffmpeg.write_frames(
            path,
            (width, height),
            fps=fps,
            codec="libx264",
            pix_fmt_out="yuv420p",  # what browsers play
            quality=None,
            macro_block_size=16,
            ffmpeg_log_level="error",
            output_params=["-crf", "26", "-preset", "fast", "-movflags", "+faststart"],
        )
        writer.send(None)
        for frame in frames:
            writer.send(np.ascontiguousarray(frame))
        writer.close()
        with open(path, "rb") as f:
            return f.read()


def decode_video(data: bytes, fmt: str) -> np.ndarray:
    """The frames of an ``encode_video`` result: uint8 [N, H, W, 3]."""
    import imageio.v3 as iio

    if fmt not in FORMATS:
        raise ValueError(f"video format must be one of {FORMATS}, got {fmt!r}")
    frames = iio.imread(data, extension=f".{fmt}", index=None)
    return np.asarray(frames)[..., :3]
