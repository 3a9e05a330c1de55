"""``sweeper launch SPEC``: run a study, or resume it, on Ray (``sweeper.run._launch``).

Exit codes: 0 all done, 1 some trials failed, 2 bad input (nothing written), 3 another
driver runs the study (busy), 130 interrupted (Ctrl-C or SIGTERM).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from sweeper.spec import SpecError, StudySpec, check_files, plural, positive_int, suggest

if TYPE_CHECKING:
    from sweeper.plan import Plan


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
    parser.add_argument(
        "--threads-per-trial",
        metavar="N",
        type=positive_int,
        help="torch threads of each trial, overriding the spec's execution.threads_per_trial "
        "(and reserving as many CPUs a trial): e.g. one long trial alone with every core; "
        "the plan stays the same",
    )
    parser.add_argument(
        "--skip-missing",
        action="store_true",
        help="launch without the methods whose files are missing here (e.g. vgg's "
        "weights_path): their trials stay left in the study for a launch with the files; "
        "the other methods run their full budget",
    )
    parser.add_argument(
        "--only",
        metavar="METHODS",
        help="run only these methods (comma-separated) in this launch, e.g. one arm of a "
        "study at a time; the others' trials stay left in the study, and the plan is whole",
    )
    parser.add_argument(
        "--max-trials",
        metavar="N",
        type=positive_int,
        help="start at most N of the trials left in this launch (round by round, so what is "
        "done stays paired), e.g. what fits before the machine is gone; the others stay "
        "left for a later launch",
    )


def only_skip(spec: StudySpec, only: str | None) -> frozenset[str]:
    """The methods ``--only METHODS`` leaves out; raises SpecError on an unknown name."""
    if only is None:
        return frozenset()
    names = [name.strip() for name in only.split(",") if name.strip()]
    for name in names:
        if name not in spec.methods:
            raise SpecError(
                f"--only: no method {name!r} in the spec; "
                f"{suggest(name, list(spec.methods))}methods: {', '.join(spec.methods)}"
            )
    if not names:
        raise SpecError(f"--only: name one or more methods, e.g. {next(iter(spec.methods))}")
    return frozenset(spec.methods) - frozenset(names)


def run(spec: StudySpec, args: argparse.Namespace) -> int:
    """``sweeper launch``: returns the exit code."""
    # the driver loads Ray and Optuna: only when the command runs (`--help` stays light)
    from sweeper.run._driver import EXIT_INTERRUPTED
    from sweeper.run._launch import launch, prepare
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
                skip = check_files(spec, str(Path(args.spec)), args.skip_missing)
                left_out = only_skip(spec, args.only)
            except ValueError as e:  # SpecError, StorageError
                print(f"sweeper launch: {e}", file=sys.stderr)
                return 2
            if skip:
                print("\n".join(skip_lines(spec, plan, skip)), file=sys.stderr)
            return launch(spec, plan, skip=skip | left_out, max_trials=args.max_trials)
        except KeyboardInterrupt:  # outside the driver loop, which handles its own
            print("\nsweeper launch: stopped", file=sys.stderr)
            return EXIT_INTERRUPTED


def skip_lines(spec: StudySpec, plan: Plan, skip: frozenset[str]) -> list[str]:
    """What a launch with ``--skip-missing`` runs: which methods are left out and why, and
    the budget of the others (trials per method as planned, so their comparison is fair)."""
    lines = [
        f"sweeper launch: skipping {item.method}: {item.at}: {item.message}"
        for item in spec.missing_files()
        if item.method in skip
    ]
    runs = [m for m in spec.methods if m not in skip]
    left = [m for m in spec.methods if m in skip]
    per_method = spec.trials_per_method_total
    skipped = sum(e.method in skip for e in plan.entries)
    lines.append(
        f"sweeper launch: this launch runs {len(runs)} of {len(spec.methods)} methods "
        f"({', '.join(runs)}), {plural(per_method, 'trial')} each as planned: "
        f"{len(plan.entries) - skipped} of the plan's {len(plan.entries)} trials; "
        f"the {skipped} of {', '.join(left)} stay left in the "
        "study (`sweeper status` counts them) for a launch with the files"
    )
    return lines
