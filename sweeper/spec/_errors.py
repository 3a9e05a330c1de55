"""How a spec's validation errors are made and read.

``spec_error`` is the error every spec validator raises: pydantic reports it at the field
being validated, and its ``at`` extends that path (``methods.vae`` + ``beta``).
``format_errors`` turns a pydantic ``ValidationError`` into (dotted path, message) pairs
(``sac.lr[1]``, ``methods.vae.beta``), a missing field's message with its description;
``suggest`` names the closest allowed word for a typo. A message shows a value as a short
``excerpt`` and a name with its control characters escaped (``printable``): a spec can
hold a value of any size, and an escape sequence in a name must not reach the terminal.
"""

from __future__ import annotations

import difflib
import reprlib
from typing import Any

from pydantic import ValidationError
from pydantic_core import PydanticCustomError

#: the most characters of a value an error message shows
EXCERPT = 60
#: the most characters of one error (its field path, its message)
MAX_MESSAGE = 400
_REPR = reprlib.Repr()  # Python 3.11's takes no arguments
_REPR.maxlevel, _REPR.maxstring, _REPR.maxother = 2, EXCERPT, EXCERPT
_REPR.maxdict = _REPR.maxlist = _REPR.maxtuple = _REPR.maxset = 4


def excerpt(value: Any) -> str:
    """``repr(value)`` cut short (a few items of a container, ``EXCERPT`` characters), in
    time and memory bounded whatever the value's size; control characters escaped."""
    text = _REPR.repr(value)
    return text if len(text) <= EXCERPT else text[: EXCERPT - 3] + "..."


def printable(text: str, limit: int = MAX_MESSAGE) -> str:
    """``text`` with its control characters escaped (``\\x1b``, ``\\n``), cut at ``limit``."""
    text = text[: limit + 1]
    text = "".join(c if c.isprintable() else c.encode("unicode_escape").decode() for c in text)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def spec_error(message: str, at: str = "") -> PydanticCustomError:
    """A validation error; ``at`` extends the field path pydantic reports (``vae.beta``)."""
    return PydanticCustomError("spec", "{message}", {"message": message, "at": at})


def suggest(word: Any, allowed: list[str]) -> str:
    """``"did you mean 'x'? "`` for the closest of ``allowed`` to ``word``, else ``""``."""
    close = difflib.get_close_matches(str(word), allowed, n=1)
    return f"did you mean {close[0]!r}? " if close else ""


def _describe(model: Any, loc: tuple[Any, ...]) -> str:
    """The description of the field at ``loc`` of ``model`` (for "missing" errors), if any."""
    info = None
    for part in loc:
        fields = getattr(model, "model_fields", None)
        if not fields or part not in fields:
            return ""
        info = fields[part]
        model = info.annotation
    return info.description or "" if info else ""


def _dotted(loc: tuple[Any, ...] | list[Any]) -> str:
    """A pydantic error location as a spec path: ``("sac", "lr", 1)`` -> ``sac.lr[1]``."""
    path = ""
    for part in loc:
        if isinstance(part, int):
            path += f"[{part}]"
        elif part == "[key]":
            path += " (key)"
        else:
            path += f".{part}" if path else str(part)
    return path


def format_errors(exc: ValidationError, model: Any) -> list[tuple[str, str]]:
    """(dotted path, message) of each error of validating ``model``."""
    errors = []
    for err in exc.errors(include_url=False):
        loc = tuple(err["loc"])
        ctx = err.get("ctx") or {}
        if err["type"] == "spec":
            path, message = _dotted(loc), ctx["message"]
            at = ctx.get("at", "")
            if at:
                path = f"{path}{'' if at.startswith('[') or not path else '.'}{at}"
        elif err["type"] == "missing":
            path, message = _dotted(loc), "required field is missing"
            description = _describe(model, loc)
            if description:
                message += f"; {description}"
        else:
            path, message = _dotted(loc), err["msg"]
            if not isinstance(err.get("input"), dict):
                message += f", got {excerpt(err['input'])}"
        errors.append((printable(path or "spec"), printable(message)))
    return errors
