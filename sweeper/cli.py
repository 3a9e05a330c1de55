"""The ``sweeper`` command line.

Each subcommand lives in its own module, which provides ``add_arguments(parser)`` (its own
options) and ``run``. This module alone adds the spec and ``--storage`` arguments and loads
the spec(s) with ``--storage`` applied (a ``SpecError`` is one line and exit code 2), then
calls ``run(spec, args)``, ``run(specs, args)`` (a command taking several specs: a list) or
``run(args)`` (a command taking none). A command module is imported only when its
subcommand runs, so ``sweeper --help`` stays light (no torch, Ray or MuJoCo).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from dataclasses import dataclass
from enum import Enum

from sweeper.spec import HelpFormatter, SpecError, StudySpec, load_spec


class Specs(Enum):
    """How many study specs a command takes."""

    ONE = "one"
    MANY = "many"
    NONE = "none"


@dataclass(frozen=True)
class Command:
    module: str
    help: str
    specs: Specs = Specs.ONE


COMMANDS: dict[str, Command] = {
    "launch": Command("sweeper.run.cli_launch", "run (or resume) a study from a YAML spec"),
    "confirm": Command(
        "sweeper.run.cli_confirm",
        "re-run each method's top-K configurations on fresh seeds (confirmation stage)",
    ),
    "plan": Command(
        "sweeper.plan.cli_plan", "the plan before it runs: trials per method and their cost here"
    ),
    "status": Command(
        "sweeper.results.cli_status", "per-method ledger of a study: done, running, failed, left"
    ),
    "publish": Command(
        "sweeper.results.cli_publish",
        "copy a study with its ledger, videos and report into a folder (docs/studies/<study>)",
    ),
    "rerun": Command(
        "sweeper.run.cli_rerun",
        "run one recorded trial again and compare its curve with the record",
    ),
    "dashboard": Command("sweeper.dashboard", "open optuna-dashboard on a study's storage"),
    "aggregate": Command(
        "sweeper.results.cli_aggregate",
        "per-method curves, AUC table, figures and report",
        Specs.MANY,
    ),
    "diagnose": Command(
        "sweeper.diagnose.cli_diagnose",
        "encoder diagnostics (thesis chapter 5) on an env",
        Specs.NONE,
    ),
}


def _add_spec_arguments(parser: argparse.ArgumentParser, specs: Specs) -> None:
    """The spec file(s) and the storage override of a command taking ``specs``."""
    if specs is Specs.NONE:
        return
    storage = (
        "SQLAlchemy URL of the study database, overriding the spec's "
        "(default: sqlite:///runs/<study>/study.db; postgresql://user@host/db for a cluster)"
    )
    if specs is Specs.MANY:
        parser.add_argument("spec", nargs="+", help="study specs, YAML files (see studies/)")
        storage += "; several specs: once for all, or once per spec in their order"
        parser.add_argument("--storage", metavar="URL", action="append", help=storage)
    else:
        parser.add_argument("spec", help="the study spec, a YAML file (see studies/)")
        parser.add_argument("--storage", metavar="URL", help=storage)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser; only ``command``'s module is imported to add its arguments."""
    parser = argparse.ArgumentParser(
        prog="sweeper",
        description="Fair sweeps comparing reward encoders for goal-conditioned RL from images.",
        formatter_class=HelpFormatter,
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, entry in COMMANDS.items():
        sub = subparsers.add_parser(
            name, help=entry.help, description=entry.help, formatter_class=HelpFormatter
        )
        if name == command:
            _add_spec_arguments(sub, entry.specs)
            importlib.import_module(entry.module).add_arguments(sub)
    return parser


def _load_specs(args: argparse.Namespace) -> list[StudySpec]:
    """The specs named on the command line, with ``--storage`` applied; raises SpecError."""
    paths = [args.spec] if isinstance(args.spec, str) else args.spec
    specs = [load_spec(path) for path in paths]
    if args.storage is None:
        return specs
    urls = [args.storage] if isinstance(args.storage, str) else args.storage
    if len(urls) == 1:
        urls *= len(specs)
    if len(urls) != len(specs):
        raise SpecError(
            f"--storage: give one URL for all {len(specs)} specs or one per spec, got {len(urls)}"
        )
    return [spec.with_overrides(storage=url) for spec, url in zip(specs, urls, strict=True)]


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    name = next((a for a in argv if not a.startswith("-")), None)
    args = build_parser(name if name in COMMANDS else None).parse_args(argv)
    if args.command is None:
        build_parser().print_help()
        return 2
    command = COMMANDS[args.command]
    module = importlib.import_module(command.module)
    if command.specs is Specs.NONE:
        return int(module.run(args) or 0)
    try:
        specs = _load_specs(args)
    except SpecError as e:
        print(f"sweeper {args.command}: {e}", file=sys.stderr)
        return 2
    return int(module.run(specs if command.specs is Specs.MANY else specs[0], args) or 0)


if __name__ == "__main__":
    sys.exit(main())
