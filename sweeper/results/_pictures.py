"""The report's pictures (``sweeper aggregate``): what the agents did and what the
encoders see.

- ``final_frames``: per method, the last frame of the final episode video (observation
  beside goal, captioned) of its best and its median trial by AUC, as one PNG and a
  report section. The frames come from the study's artifact store (``sweeper.storage._artifacts``).
- ``report_pictures``: those, and the env's camera view beside its goal images
  (``sweeper.results._tiles.env_views``).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pandas as pd

from sweeper.results._frame import by_auc, methods_of, scored, study_info, trial_rows
from sweeper.results._tiles import env_views, labelled, save_png, side_by_side, stacked

_VIDEO_RE = re.compile(r"^episode-step(\d+)\.(mp4|gif)$")


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
    """[("best", row), ("median", row)] of one method's scored trials (one row each), in
    ``by_auc``'s order (the AUC table's best trial): the first and the lower median (the
    same trial when there is one)."""
    ordered = by_auc(scored_trials)
    return [("best", ordered.iloc[0]), ("median", ordered.iloc[len(ordered) // 2])]


def final_frames(frame: pd.DataFrame, artifacts: str, out: Path) -> str:
    """Write ``final_frames.png`` into ``out``; return the report section (empty, and no
    file written, when no trial has a video, e.g. ``videos: none``)."""
    from agent.video import decode_video
    from sweeper.storage import ArtifactStore

    store = ArtifactStore(artifacts)
    videos = study_info(frame).videos
    trials = trial_rows(scored(frame))
    rows, table = [], []
    for method in methods_of(frame):
        mine = trials[trials["method"] == method]
        if mine.empty:
            continue
        tiles, cells = [], []
        for which, row in best_and_median(mine):
            found = last_video(videos.get(int(row["trial"])))
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
            tiles.append(labelled(last, title))
            cells.append(f"{which}: trial {row['trial']} (AUC {row['auc']:.3f}, step {step})")
        if tiles:
            rows.append(side_by_side(tiles))
        if cells:
            table.append(f"| {method} | {'; '.join(cells)} |")
    if not rows:
        return ""
    save_png(stacked(rows), out / "final_frames.png")
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


def report_pictures(frame: pd.DataFrame, artifacts: str, out: Path) -> tuple[str, list[Path]]:
    """The report's picture sections (``sweeper aggregate``) and the files written: the
    final frames of each method's best and median trial, and the env's camera view and goal
    images (skipped with a line saying why when the env cannot be built here, e.g. no
    MuJoCo)."""
    text = final_frames(frame, artifacts, out)
    files = [out / "final_frames.png"] if text else []
    env = (study_info(frame).attrs.get("spec") or {}).get("env") or {}
    if not env.get("name"):
        return text, files
    try:
        env_views(
            env["name"],
            out / "env_views.png",
            image_size=env.get("image_size"),
            options=env.get("options"),
        )
    except Exception as e:  # a report without the picture beats no report
        why = f"\n(no camera view: env {env['name']!r} cannot be built here: {e})\n"
        return text + why, files
    return text + _env_views_section(env["name"]), [*files, out / "env_views.png"]


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
