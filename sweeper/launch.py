"""``sweeper launch SPEC``: run a study, or resume it, on Ray (``sweeper.launcher``).

Exit codes: 0 all done, 1 some trials failed, 2 bad input (nothing written), 3 another
driver runs the study (busy), 130 interrupted (Ctrl-C or SIGTERM).
"""

from __future__ import annotations

import argparse
import sys

from sweeper.spec import StudySpec, positive_int


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``sweeper launch`` (the spec and ``--storage`` come from ``sweeper.cli``)."""
    parser.add_argument(
        "--address",
        metavar="ADDR",
        help="join the Ray cluster at ADDR ('auto' or 'host:6379') instead of starting a local Ray",
    )
    parser.add_argument(
        "--max-concurrent",
        metavar="N",
        type=positive_int,
        help="trials at once, overriding the spec's execution.max_concurrent",
    )


def run(spec: StudySpec, args: argparse.Namespace) -> int:
    """``sweeper launch``: returns the exit code."""
    # the driver loads Ray and Optuna: only when the command runs (`--help` stays light)
    from sweeper.driver import EXIT_INTERRUPTED
    from sweeper.launcher import launch, prepare, sigterm_stops

    with sigterm_stops():
        try:
            try:
                spec, plan = prepare(spec, address=args.address, max_concurrent=args.max_concurrent)
            except ValueError as e:  # SpecError, StorageError
                print(f"sweeper launch: {e}", file=sys.stderr)
                return 2
            return launch(spec, plan)
        except KeyboardInterrupt:  # outside the driver loop, which handles its own
            print("\nsweeper launch: stopped", file=sys.stderr)
            return EXIT_INTERRUPTED
