"""The README a newcomer reads: short, and naming every command and flag the CLI has."""

from __future__ import annotations

import re

from conftest import ROOT

from sweeper.cli import COMMANDS, build_parser

README = (ROOT / "README.md").read_text(encoding="utf-8")


def command_flags() -> dict[str, list[str]]:
    """Each ``sweeper`` command's long options, as ``sweeper COMMAND --help`` lists them."""
    flags = {}
    for name in COMMANDS:
        parser = build_parser(name)
        (sub,) = (a for a in parser._actions if a.dest == "command")
        actions = sub.choices[name]._actions
        flags[name] = [o for a in actions for o in a.option_strings if o.startswith("--")]
    return flags


def test_the_readme_names_every_command_and_flag():
    missing = [
        f"sweeper {name} {flag}"
        for name, flags in command_flags().items()
        for flag in flags
        if flag != "--help" and not re.search(rf"(?<![\w-]){re.escape(flag)}(?![\w-])", README)
    ]
    missing += [f"sweeper {name}" for name in COMMANDS if f"sweeper {name}" not in README]
    assert not missing, f"the README does not name: {missing}"


def test_the_readme_is_short_and_its_links_exist():
    assert len(README.splitlines()) <= 200
    for line in README.splitlines():
        for part in line.split("`"):
            if part.startswith("docs/") and " " not in part and "<" not in part:
                assert (ROOT / part.split("#")[0]).exists(), part
