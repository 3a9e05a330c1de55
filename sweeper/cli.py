"""The ``sweeper`` command line. Each subcommand lives in its own module, which provides
``add_arguments(parser)`` and ``run(args) -> int``; modules are imported only when their
subcommand runs, so ``sweeper --help`` stays light (no torch, Ray or MuJoCo)."""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from sweeper.spec import StudySpec

#: subcommand -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "launch": ("sweeper.launch", "run (or resume) a study from a YAML spec"),
    "confirm": (
        "sweeper.confirm",
        "re-run each method's top-K configurations on fresh seeds (confirmation stage)",
    ),
    "status": ("sweeper.status", "per-method ledger of a study: done, running, failed, left"),
    "dashboard": ("sweeper.dashboard", "open optuna-dashboard on a study's storage"),
    "aggregate": ("sweeper.aggregate", "per-method curves, AUC table, figures and report"),
    "diagnose": ("sweeper.diagnose", "encoder diagnostics (thesis chapter 5) on an env"),
}


def add_spec_arguments(parser: argparse.ArgumentParser, many: bool = False) -> None:
    """The arguments every study subcommand takes: the spec file (``many``: one or more, as
    a list) and a storage override."""
    if many:
        parser.add_argument("spec", nargs="+", help="study specs, YAML files (see studies/)")
    else:
        parser.add_argument("spec", help="the study spec, a YAML file (see studies/)")
    parser.add_argument(
        "--storage",
        metavar="URL",
        help="SQLAlchemy URL of the study database, overriding the spec's "
        "(default: sqlite:///runs/<study>/study.db; postgresql://user@host/db for a cluster)",
    )


def spec_from_args(args: argparse.Namespace, path: str | None = None) -> StudySpec:
    """The spec named by ``path`` (default ``args.spec``) with ``--storage`` applied;
    raises ``SpecError``."""
    from sweeper.spec import load_spec

    spec = load_spec(args.spec if path is None else path)
    return spec if args.storage is None else spec.with_overrides(storage=args.storage)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser; only ``command``'s module is imported to add its arguments."""
    parser = argparse.ArgumentParser(
        prog="sweeper",
        description="Fair sweeps comparing reward encoders for goal-conditioned RL from images.",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module_name, help_text) in COMMANDS.items():
        sub = subparsers.add_parser(name, help=help_text, description=help_text)
        if name == command:
            importlib.import_module(module_name).add_arguments(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    command = next((a for a in argv if not a.startswith("-")), None)
    if command not in COMMANDS:
        command = None
    args = build_parser(command).parse_args(argv)
    if args.command is None:
        build_parser().print_help()
        return 2
    return int(importlib.import_module(COMMANDS[args.command][0]).run(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
