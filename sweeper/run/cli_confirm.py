"""``sweeper confirm SPEC --top-k K --seeds N``: run (or resume) the confirmation stage
(``sweeper.run._confirm``). Exit codes as ``sweeper launch``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sweeper.spec import StudySpec, check_files, positive_int


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``sweeper confirm`` (the spec and ``--storage`` come from ``sweeper.cli``)."""
    parser.add_argument(
        "--top-k",
        metavar="K",
        type=positive_int,
        help="configurations per method to re-run (default: the spec's confirm.top_k)",
    )
    parser.add_argument(
        "--seeds",
        metavar="N",
        type=positive_int,
        help="fresh seeds per configuration (default: the spec's confirm.seeds)",
    )
    parser.add_argument("--address", metavar="ADDR", help="as `sweeper launch --address`")
    parser.add_argument("--max-concurrent", metavar="N", type=positive_int, help="trials at once")
    parser.add_argument(
        "--threads-per-trial",
        metavar="N",
        type=positive_int,
        help="as `sweeper launch --threads-per-trial`",
    )


def run(spec: StudySpec, args: argparse.Namespace) -> int:
    """``sweeper confirm``: check everything read-only first (exit 2 writes nothing), then
    drive the stage."""
    # the stage loads the driver, Ray and Optuna: only when the command runs
    from sweeper.run._confirm import check_study, confirm, settings
    from sweeper.run._driver import EXIT_INTERRUPTED
    from sweeper.run._launch import prepare
    from sweeper.run._signals import stop_on_signals

    with stop_on_signals():
        try:
            try:
                spec, plan = prepare(
                    spec,
                    address=args.address,
                    max_concurrent=args.max_concurrent,
                    threads_per_trial=args.threads_per_trial,
                )
                check_files(spec, str(Path(args.spec)), can_skip=False)
                top_k, seeds = settings(spec, args.top_k, args.seeds)
                check_study(spec, plan, top_k, seeds)
            except ValueError as e:  # SpecError, StorageError
                print(f"sweeper confirm: {e}", file=sys.stderr)
                return 2
            return confirm(spec, plan, top_k, seeds)
        except KeyboardInterrupt:
            print("\nsweeper confirm: stopped", file=sys.stderr)
            return EXIT_INTERRUPTED
