"""``sweeper diagnose``: the encoder diagnostics of thesis chapter 5 on one or more envs.

    sweeper diagnose --env point_reach --encoders pixel,linear,conv
    sweeper diagnose --env fetch_push --encoders pixel,cvae --option cvae.epochs=5

For each env it writes, under ``--out`` (default ``runs/diagnostics/{env}``), one tidy CSV
per analysis (``env, encoder, metric, value, ...``), a PNG figure each,
``summary.csv`` with the headline figures, and ``views.png``: the env's camera view after a
few resets beside each goal image (what the encoders see). Learned encoders are first fit on
``num_images`` frames of a uniformly random policy in the env. Algorithm 1 and the
correlation draw (state, goal) pairs from the env's reset (``--start reset``, the
algorithm) or uniformly from its state box (``--start uniform``); near goals are kept
unless ``--min-goal-distance`` asks otherwise. Both settings are written into the
gradient and correlation CSVs and the summary. Every analysis starts from a freshly reset
env, so the order they run in changes nothing. ``diagnose_env`` takes the analyses'
settings as ``Settings``.
"""

from __future__ import annotations

import argparse
import ast
import sys
from pathlib import Path
from typing import Any

from agent.envs import ENV_NAMES, check_env_name, make_env
from encoders import make_encoder
from encoders.registry import encoder_class
from sweeper.diagnose._settings import (
    START_MODES,
    Settings,
    UsageError,
    grid_dims,
    split,
)
from sweeper.results import env_views
from sweeper.spec import HelpFormatter

ANALYSES = (
    "exploration",
    "gradient",
    "correlation",
    "precision",
    "topology",
    "variance",
    "descent",
)
#: summary.csv; ``start`` is set on the rows of the analyses that draw (state, goal) pairs
SUMMARY_COLUMNS = ["env", "analysis", "encoder", "metric", "value", "start"]
#: the defaults of the options that set ``Settings``
DEFAULTS = Settings()
#: the most torch CPU threads ``--threads`` may ask for
MAX_THREADS = 256


class _DefaultsHelp(HelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Shows a default only where there is one to show (not for a required option, a flag,
    an empty list or None, whose help says what happens)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        default = action.default
        if action.required or default is None or default is False or default == []:
            return action.help
        return super()._get_help_string(action)


#: the options that size or place an analysis: ``Settings`` field, type, help (the default
#: is the field's)
SIZES: tuple[tuple[str, type, str], ...] = (
    ("episodes", int, "random-agent episodes"),
    ("gradient_states", int, "Algorithm 1 states"),
    ("directions", int, "Algorithm 1 directions"),
    ("alpha", float, "Algorithm 1 step size"),
    ("pairs", int, "(state, goal) pairs"),
    ("grid_size", int, "topology grid side"),
    ("variance_states", int, "arm-vs-object states (fetch_push only)"),
    ("precision_goals", int, "near-goal precision: goals, each from the env's reset"),
    ("precision_states", int, "near-goal precision: states uniform in a ball around each goal"),
    ("precision_radius", float, "near-goal precision: the ball's radius"),
    ("success_radius", float,
     "near-goal precision: a state this close to the goal succeeds (Fetch: 0.05 m)"),
    ("descent_episodes", int, "greedy descent: episodes, each from the env's reset"),
    ("descent_horizon", int, "greedy descent: steps per episode"),
    ("descent_candidates", int,
     "greedy descent: actions tried in a copy of the simulator at each step"),
    ("descent_step", float,
     "greedy descent: the actions' size, a fraction of the action box's half-width"),
)  # fmt: skip


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``sweeper diagnose`` (it takes no spec)."""
    parser.formatter_class = _DefaultsHelp
    parser.epilog = "Writes one CSV and PNG per analysis and summary.csv per env."
    parser.add_argument(
        "--env", required=True, help=f"env name(s), comma-separated: {', '.join(ENV_NAMES)}"
    )
    parser.add_argument(
        "--encoders", default="pixel,linear,conv", help="encoder names, comma-separated"
    )
    parser.add_argument(
        "--option",
        action="append",
        default=[],
        metavar="ENCODER.KEY=VALUE",
        help="an encoder option, e.g. cvae.latent_dim=8 or vgg.weights_path=vgg16.pth (repeatable)",
    )
    parser.add_argument(  # the default has spaces to wrap at in the help; ``split`` strips them
        "--analyses", default=", ".join(ANALYSES), help="the analyses to run, comma-separated"
    )
    parser.add_argument(
        "--out", default="runs/diagnostics/{env}", help="output directory; {env} is the env name"
    )
    parser.add_argument("--image-size", type=int, default=None, help="default: the env's")
    parser.add_argument(
        "--seed",
        type=int,
        default=DEFAULTS.seed,
        help="seeds the encoders' random weights, the envs and every sample of states",
    )
    parser.add_argument("--device", default="cpu", help="cpu, cuda or auto")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument(
        "--start",
        choices=START_MODES,
        default=DEFAULTS.start,
        help="where Algorithm 1 and the correlation draw (state, goal) pairs: reset = the "
        "env's reset (its start and goal distributions, as Algorithm 1 says); uniform = both "
        "uniform in the env's state box",
    )
    parser.add_argument(
        "--min-goal-distance",
        type=float,
        default=DEFAULTS.min_goal_distance,
        help="Algorithm 1: redraw pairs whose goal is closer than this to the start (0: keep "
        "every pair); recorded in gradient.csv and summary.csv when used",
    )
    parser.add_argument(
        "--grid-dims", default=None, help="two state names or indices (default: first two)"
    )
    for name, kind, text in SIZES:
        parser.add_argument(
            "--" + name.replace("_", "-"), type=kind, default=getattr(DEFAULTS, name), help=text
        )
    parser.add_argument("--quiet", action="store_true", help="no progress lines")


def parse_options(pairs: list[str], encoder_names: list[str]) -> dict[str, dict[str, Any]]:
    """``["vae.beta=5", ...]`` -> ``{"vae": {"beta": 5}}``; values are Python literals or
    plain strings."""
    options: dict[str, dict[str, Any]] = {name: {} for name in encoder_names}
    for pair in pairs:
        key, sep, raw = pair.partition("=")
        encoder, dot, option = key.partition(".")
        if not sep or not dot or not option:
            raise UsageError(f"--option must look like ENCODER.KEY=VALUE, got {pair!r}")
        if encoder not in options:
            raise UsageError(
                f"--option {pair!r} is for {encoder!r}, which is not in --encoders "
                f"({', '.join(encoder_names)})"
            )
        try:
            value = ast.literal_eval(raw)
        except (ValueError, SyntaxError):
            value = raw
        options[encoder][option] = value
    return options


def setup(
    args: argparse.Namespace,
) -> tuple[Settings, list[str], list[tuple[str, Any, dict, Path]]]:
    """Validate everything before any work: (settings, analyses, [(env name, env, encoders,
    out dir)])."""
    settings = Settings.from_args(args)
    envs = split(args.env, "--env")
    names = split(args.encoders, "--encoders")
    analyses = split(args.analyses, "--analyses")
    for a in analyses:
        if a not in ANALYSES:
            raise UsageError(f"unknown analysis {a!r}; analyses: {', '.join(ANALYSES)}")
    for env in envs:
        check_env_name(env)
    for name in names:
        encoder_class(name)
    options = parse_options(args.option, names)
    built: list[tuple[str, Any, dict[str, Any], Path]] = []
    try:
        for env_name in envs:
            try:
                env = make_env(env_name, image_size=args.image_size, obs_mode="state")
            except ImportError as err:
                raise UsageError(f"env {env_name!r} is not available here: {err}") from err
            encoders: dict[str, Any] = {}
            built.append((env_name, env, encoders, out_dir(args.out, env_name, len(envs))))
            grid_dims(args.grid_dims, tuple(env.state_names))  # fail now, not after the work
            shape = (env.image_size, env.image_size, 3)
            for n in names:
                encoders[n] = make_encoder(n, shape, args.seed, args.device, **options[n])
        for *_, out in built:  # last: nothing is created for arguments that fail
            try:
                out.mkdir(parents=True, exist_ok=True)
            except OSError as err:
                raise UsageError(f"--out: cannot create {out}: {err.strerror}") from None
    except ValueError:
        close_all(built)
        raise
    return settings, analyses, built


def out_dir(template: str, env_name: str, num_envs: int) -> Path:
    """``--out`` for one env: ``{env}`` is replaced; several envs without it get subfolders."""
    if "{env}" in template:
        return Path(template.replace("{env}", env_name))
    return Path(template) / env_name if num_envs > 1 else Path(template)


def close_all(built: list[tuple[str, Any, dict[str, Any], Path]]) -> None:
    for _, env, _, _ in built:
        env.close()


def diagnose_env(
    settings: Settings,
    analyses: list[str],
    env_name: str,
    env: Any,
    encoders: dict[str, Any],
    out: Path,
) -> list[Any]:
    """Fit the learned encoders, run the analyses, write CSV + PNG; return summary frames."""
    # pandas, scipy, scikit-learn and matplotlib load only when an env is diagnosed, so
    # `sweeper diagnose --help` stays light
    from encoders import diagnostics as dx
    from sweeper.diagnose._analyses import RUNNERS, Target

    progress = not settings.quiet
    # what the encoders see: the camera view after a few resets beside their goal images
    env_views(env_name, out / "views.png", image_size=env.image_size, seed=settings.seed)
    frames: dict[int, Any] = {}  # by count: VAE and CVAE share their frames
    for name, encoder in encoders.items():
        if encoder.needs_fit:
            n = encoder.num_images
            if n not in frames:
                frames[n] = dx.random_frames(env, n, settings.seed, progress)
            settings.log(f"{env_name}: fitting {name} on {n} random-policy frames")
            encoder.fit(frames[n], progress=progress)
    target = Target(env_name, env, encoders, out)
    summaries = (run(settings, target) for a, run in RUNNERS.items() if a in analyses)
    return [summary for summary in summaries if summary is not None]


def run(args: argparse.Namespace) -> int:
    """``sweeper diagnose``: exit 0, or 2 with a one-line message on a bad argument
    (every one checked before any work: counts within ``MAX_COUNTS``, the seed, the
    output folder) or an output that cannot be written."""
    # torch and pandas load only when the command runs, so `sweeper diagnose --help` stays light
    import pandas as pd
    import torch

    try:
        if not 1 <= args.threads <= MAX_THREADS:
            raise UsageError(f"--threads must be in [1, {MAX_THREADS}], got {args.threads}")
        torch.set_num_threads(args.threads)
        settings, analyses, built = setup(args)
    except ValueError as err:
        print(f"sweeper diagnose: error: {err}", file=sys.stderr)
        return 2
    try:
        for env_name, env, encoders, out in built:
            frames = diagnose_env(settings, analyses, env_name, env, encoders, out)
            print(f"{env_name}: wrote {out}/")
            if frames:
                summary = pd.concat(frames, ignore_index=True)
                summary = summary.reindex(columns=SUMMARY_COLUMNS)
                summary.to_csv(out / "summary.csv", index=False)
                print(summary.to_string(index=False))
    except (ValueError, OSError) as err:  # OSError: the output folder filled up, say
        print(f"sweeper diagnose: error: {err}", file=sys.stderr)
        return 2
    finally:
        close_all(built)
    return 0
