"""Pictures of frames, shared by the report (``sweeper.results._pictures``) and the
diagnostics (``sweeper diagnose``): tiles labelled, laid in rows and columns, saved as PNG;
and ``env_views``, an env's camera view after a few resets beside each episode's goal
image: what every image encoder is given.

Images are put together with numpy and written with Pillow (no figure library).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

#: pixels between tiles and of the label band above each row
PAD, LABEL = 6, 16
#: the smallest side an env view is scaled up to (a whole factor) in ``env_views``
VIEW_SIZE = 128


def labelled(image: np.ndarray, text: str) -> np.ndarray:
    """``image`` with a white band above it holding ``text``."""
    from PIL import Image, ImageDraw

    from agent.video import caption_font

    band = Image.new("RGB", (image.shape[1], LABEL), (255, 255, 255))
    ImageDraw.Draw(band).text((2, 2), text, fill=(0, 0, 0), font=caption_font())
    return np.concatenate([np.asarray(band), image])


def side_by_side(tiles: list[np.ndarray]) -> np.ndarray:
    """Tiles side by side on white, top-aligned, ``PAD`` apart."""
    height = max(t.shape[0] for t in tiles)
    width = sum(t.shape[1] for t in tiles) + PAD * (len(tiles) - 1)
    row = np.full((height, width, 3), 255, np.uint8)
    x = 0
    for tile in tiles:
        row[: tile.shape[0], x : x + tile.shape[1]] = tile
        x += tile.shape[1] + PAD
    return row


def stacked(rows: list[np.ndarray]) -> np.ndarray:
    width = max(r.shape[1] for r in rows)
    padded = [np.pad(r, ((0, PAD), (0, width - r.shape[1]), (0, 0)), constant_values=255)
              for r in rows]  # fmt: skip
    return np.concatenate(padded)[:-PAD]


def save_png(image: np.ndarray, path: Path) -> Path:
    from PIL import Image

    Image.fromarray(image).save(path)
    return path


def env_views(
    env_name: str,
    path: Path,
    *,
    image_size: int | None = None,
    options: dict[str, Any] | None = None,
    episodes: int = 4,
    seed: int = 0,
    columns: int = 2,
) -> Path:
    """Write ``path``: for ``episodes`` resets of the env, the camera view beside the goal
    image, each at the env's image size scaled up by a whole factor to at least
    ``VIEW_SIZE`` pixels, labelled, ``columns`` pairs to a row (4 resets: a 2 x 2 grid,
    e.g. 530 x 294 pixels at 32 x 32, 690 x 374 at 84 x 84)."""
    from agent.envs import make_env

    env = make_env(env_name, image_size=image_size, **(options or {}))
    try:
        tiles = []
        for episode in range(episodes):
            obs, _ = env.reset(seed=seed + episode)
            size = obs["image"].shape[0]
            scale = max(1, -(-VIEW_SIZE // size))
            pair = side_by_side([
                obs["image"].repeat(scale, 0).repeat(scale, 1),
                obs["goal_image"].repeat(scale, 0).repeat(scale, 1),
            ])  # fmt: skip
            tiles.append(labelled(pair, f"reset {episode}: view | goal"))
    finally:
        env.close()
    rows = [side_by_side(tiles[i : i + columns]) for i in range(0, len(tiles), columns)]
    return save_png(stacked(rows), path)
