"""Words for the messages and help every command prints."""

from __future__ import annotations

import argparse
import textwrap


def plural(n: int, noun: str) -> str:
    """``n`` and ``noun`` in the number ``n`` takes: ``"1 seed"``, ``"2 seeds"``, ``"0 seeds"``."""
    return f"{n} {noun if n == 1 else noun + 's'}"


class HelpFormatter(argparse.HelpFormatter):
    """argparse's help wrapped between words only: argparse breaks a word longer than the
    room left on a line (``--analyses``' default, a comma-separated list, came out as
    "gr adient"), and a name or value copied from the help would then be wrong."""

    def _split_lines(self, text: str, width: int) -> list[str]:
        return textwrap.wrap(self._one_line(text), width, **WHOLE_WORDS)

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        return textwrap.fill(self._one_line(text), width, initial_indent=indent,
                             subsequent_indent=indent, **WHOLE_WORDS)  # fmt: skip

    def _one_line(self, text: str) -> str:
        return self._whitespace_matcher.sub(" ", text).strip()


#: textwrap's options that keep every word whole (a hyphenated option name included)
WHOLE_WORDS = {"break_long_words": False, "break_on_hyphens": False}
