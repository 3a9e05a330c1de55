"""Pictures for the report and the diagnostics: what the agents did and what encoders see.

- ``final_frames``: per method, the last frame of the final episode video (observation
  beside goal, captioned) of its best and its median trial by AUC, as one PNG and a
  report section. The frames come from the study's artifact store (``sweeper.artifacts``).
- ``env_views``: an env's camera view after a few resets beside each episode's goal
  image, as one PNG: what every image encoder is given.

Images are put together with numpy and written with Pillow (no figure library).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    import optuna
    import pandas as pd

_VIDEO_RE = re.compile(r"^episode-step(\d+)\.(mp4|gif)$")
#: pixels between tiles and of the label band above each row
PAD, LABEL = 6, 16


def _label(image: np.ndarray, text: str) -> np.ndarray:
    """``image`` with a white band above it holding ``text``."""
    from PIL import Image, ImageDraw

    from agent.video import caption_font

    band = Image.new("RGB", (image.shape[1], LABEL), (255, 255, 255))
    ImageDraw.Draw(band).text((2, 2), text, fill=(0, 0, 0), font=caption_font())
    return np.concatenate([np.asarray(band), image])


def _row(tiles: list[np.ndarray]) -> np.ndarray:
    """Tiles side by side on white, top-aligned, ``PAD`` apart."""
    height = max(t.shape[0] for t in tiles)
    width = sum(t.shape[1] for t in tiles) + PAD * (len(tiles) - 1)
    row = np.full((height, width, 3), 255, np.uint8)
    x = 0
    for tile in tiles:
        row[: tile.shape[0], x : x + tile.shape[1]] = tile
        x += tile.shape[1] + PAD
    return row


def _column(rows: list[np.ndarray]) -> np.ndarray:
    width = max(r.shape[1] for r in rows)
    padded = [np.pad(r, ((0, PAD), (0, width - r.shape[1]), (0, 0)), constant_values=255)
              for r in rows]  # fmt: skip
    return np.concatenate(padded)[:-PAD]


def _save(image: np.ndarray, path: Path) -> Path:
    from PIL import Image

    Image.fromarray(image).save(path)
    return path


def last_video(videos: dict[str, str] | None) -> tuple[str, str, int] | None:
    """(artifact id, format, step) of the latest-step episode video in a trial's ``videos``
    attr, or None."""
    found = []
    for filename, artifact_id in (videos or {}).items():
        match = _VIDEO_RE.match(filename)
        if match:
            found.append((int(match[1]), artifact_id, match[2]))
    if not found:
        return None
    step, artifact_id, fmt = max(found)
    return artifact_id, fmt, step


def best_and_median(scored_trials: pd.DataFrame) -> list[tuple[str, Any]]:
    """[("best", row), ("median", row)] of one method's scored trials (one row each): the
    highest AUC and the lower median AUC (the same trial when there is one)."""
    ordered = scored_trials.sort_values(["auc", "trial"], ascending=[True, True])
    return [("best", ordered.iloc[-1]), ("median", ordered.iloc[(len(ordered) - 1) // 2])]


def final_frames(
    frame: pd.DataFrame, storage: optuna.storages.BaseStorage, artifacts: str, out: Path
) -> str:
    """Write ``final_frames.png`` into ``out``; return the report section (empty when no
    trial has a video, e.g. ``videos: none``)."""
    from agent.video import decode_video
    from sweeper.aggregate import methods_of, scored, study_info, trial_rows
    from sweeper.artifacts import ArtifactStore

    store = ArtifactStore(artifacts)
    study_id = storage.get_study_id_from_name(study_info(frame).name)
    by_number = {t.number: t for t in storage.get_all_trials(study_id, deepcopy=False)}
    trials = trial_rows(scored(frame))
    rows, table = [], []
    for method in methods_of(frame):
        mine = trials[trials["method"] == method]
        if mine.empty:
            continue
        tiles, cells = [], []
        for which, row in best_and_median(mine):
            found = last_video(by_number[int(row["trial"])].user_attrs.get("videos"))
            if found is None:
                continue
            artifact_id, fmt, step = found
            try:
                with store.open_reader(artifact_id) as f:
                    last = decode_video(f.read(), fmt)[-1]
            except Exception:  # a missing or unreadable video: the row says so
                cells.append(f"{which}: trial {row['trial']}, video unreadable")
                continue
            title = f"{method} {which}: trial {row['trial']}, AUC {row['auc']:.3f}"
            tiles.append(_label(last, title))
            cells.append(f"{which}: trial {row['trial']} (AUC {row['auc']:.3f}, step {step})")
        if tiles:
            rows.append(_row(tiles))
        if cells:
            table.append(f"| {method} | {'; '.join(cells)} |")
    if not rows:
        return ""
    _save(_column(rows), out / "final_frames.png")
    return "\n".join([
        "## What the agents do",
        "",
        "The last frame of the final evaluation's first episode of each method's best and "
        "median trial by AUC: the observation (left) beside the goal image (right), with "
        "the env step, the reward the agent was trained on and the true distance. The whole "
        "episodes play on the trials' pages in optuna-dashboard (`sweeper dashboard`).",
        "",
        "| method | trials shown |",
        "|---|---|",
        *table,
        "",
        "![final frames of the best and median trial per method](final_frames.png)",
        "",
    ])  # fmt: skip


def env_views(
    env_name: str,
    path: Path,
    *,
    image_size: int | None = None,
    options: dict[str, Any] | None = None,
    episodes: int = 4,
    seed: int = 0,
) -> Path:
    """Write ``path``: for ``episodes`` resets of the env, the camera view beside the goal
    image, each at the env's image size scaled up, labelled."""
    from agent.envs import make_env

    env = make_env(env_name, image_size=image_size, **(options or {}))
    try:
        tiles = []
        for episode in range(episodes):
            obs, _ = env.reset(seed=seed + episode)
            size = obs["image"].shape[0]
            scale = max(1, -(-96 // size))
            pair = _row([
                obs["image"].repeat(scale, 0).repeat(scale, 1),
                obs["goal_image"].repeat(scale, 0).repeat(scale, 1),
            ])  # fmt: skip
            tiles.append(_label(pair, f"reset {episode}: view | goal"))
    finally:
        env.close()
    return _save(_row(tiles), path)


def report_pictures(
    frame: pd.DataFrame, storage: optuna.storages.BaseStorage, artifacts: str, out: Path
) -> str:
    """The report's picture sections (``sweeper aggregate``): the final frames of each
    method's best and median trial, and the env's camera view and goal images (skipped
    with a line saying why when the env cannot be built here, e.g. no MuJoCo)."""
    from sweeper.aggregate import study_info

    text = final_frames(frame, storage, artifacts, out)
    env = (study_info(frame).attrs.get("spec") or {}).get("env") or {}
    if not env.get("name"):
        return text
    try:
        env_views(
            env["name"],
            out / "env_views.png",
            image_size=env.get("image_size"),
            options=env.get("options"),
        )
    except Exception as e:  # a report without the picture beats no report
        return text + f"\n(no camera view: env {env['name']!r} cannot be built here: {e})\n"
    return text + _env_views_section(env["name"])


def _env_views_section(env_name: str) -> str:
    """The report section around ``env_views.png``."""
    return "\n".join([
        "## What the encoders see",
        "",
        f"`{env_name}`'s camera view after a reset beside that episode's goal image, at the "
        "size the encoders are given (scaled up for the page):",
        "",
        "![camera view and goal images](env_views.png)",
        "",
    ])  # fmt: skip
