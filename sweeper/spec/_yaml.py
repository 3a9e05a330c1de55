"""Study specs' YAML (``sweeper.spec._models``), read with a strict loader that follows the YAML
1.2 core schema rather than PyYAML's YAML 1.1 defaults, because 1.1 silently changes
values:

- ``1e-4`` is the float 0.0001 (1.1 reads a string); ``1_000_000`` is an integer;
- ``010`` is the integer 10 (1.1 reads octal 8); ``0x1f`` and ``0o17`` still work;
- only ``true``/``false`` are booleans (1.1 turns ``yes``, ``no``, ``on``, ``off`` into
  booleans); dates and ``1:30`` stay strings;
- a key repeated in one mapping is an error naming the key and line (1.1 keeps the last);
- values nest at most ``MAX_DEPTH`` deep and expand to at most ``MAX_VALUES`` values,
  aliases counted each time they are used (``*name`` repeats its anchor's value), so a
  spec of a few nested aliases cannot expand to billions of values, and a deep one cannot
  exhaust the stack: either is one line, read in bounded time and memory.

``SpecError`` is the error of a spec that cannot be used, from its YAML or its fields.
"""

from __future__ import annotations

import math
import re
from typing import Any

import yaml

from sweeper.spec._errors import excerpt

#: how deep values may nest in a spec (a spec needs about 5 levels)
MAX_DEPTH = 50
#: how many values a spec may hold once its aliases are expanded (a spec has ~100)
MAX_VALUES = 100_000


class SpecError(ValueError):
    """A spec that cannot be used. ``errors`` holds ``(dotted_path, message)`` pairs."""

    def __init__(self, message: str, errors: list[tuple[str, str]] | None = None) -> None:
        super().__init__(message)
        self.errors = errors or []


# ---- YAML --------------------------------------------------------------------------------


class _SpecLoader(yaml.SafeLoader):
    """SafeLoader with YAML 1.2 core-schema scalars, duplicate keys rejected, and the
    nesting and the expanded size bounded (``MAX_DEPTH``, ``MAX_VALUES``)."""

    yaml_implicit_resolvers: dict = {}  # noqa: RUF012 (PyYAML's class-level registry)

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0

    def fetch_flow_collection_start(self, TokenClass: type) -> None:
        # each open bracket keeps a possible key that the scanner re-checks at every token:
        # thousands of them take seconds before the composer sees the first one
        if self.flow_level >= MAX_DEPTH:
            raise SpecError(_too_deep(self.get_mark()))
        super().fetch_flow_collection_start(TokenClass)

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node:
        # PyYAML composes recursively: refused here, before Python's stack runs out
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH:
                raise SpecError(_too_deep(self.peek_event().start_mark))
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_document(self, node: yaml.Node) -> Any:
        _expanded_size(node, 1, {})  # before any value is built
        return super().construct_document(node)

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: dict[Any, int] = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=True)
            line = key_node.start_mark.line + 1
            if isinstance(key, list | dict):
                raise SpecError(
                    f"line {line}: a mapping key must be a plain value, got {excerpt(key)}"
                )
            if key in seen:
                raise SpecError(
                    f"line {line}: duplicate key {excerpt(key)} (first at line {seen[key]}); "
                    "each key may appear once per mapping"
                )
            seen[key] = line
        return super().construct_mapping(node, deep=deep)


def _too_deep(mark: yaml.Mark) -> str:
    return (
        f"line {mark.line + 1}: values nested more than {MAX_DEPTH} deep (aliases included); "
        "a spec needs a few levels"
    )


def _expanded_size(node: yaml.Node, depth: int, seen: dict[int, tuple[int, int] | None]) -> int:
    """How many values ``node`` holds with every alias expanded, counted without expanding
    them: ``seen`` keeps each node's (size, height) by id, None while it is being counted
    (met again then, it contains itself). SpecError past ``MAX_DEPTH`` or ``MAX_VALUES``."""
    known = seen.get(id(node), (0, 0))
    if known is None:
        raise SpecError(f"line {node.start_mark.line + 1}: a value contains itself (an alias "
                        "inside its own anchor)")  # fmt: skip
    size, height = known
    if size:  # an alias to a node counted before: its size again, and its height below here
        if depth + height > MAX_DEPTH:
            raise SpecError(_too_deep(node.start_mark))
        return size
    if depth > MAX_DEPTH:
        raise SpecError(_too_deep(node.start_mark))
    seen[id(node)] = None
    children = node.value if isinstance(node, yaml.SequenceNode) else []
    if isinstance(node, yaml.MappingNode):
        children = [child for pair in node.value for child in pair]
    size, height = 1, 0
    for child in children:
        size += _expanded_size(child, depth + 1, seen)
        height = max(height, seen[id(child)][1] + 1)
        if size > MAX_VALUES:
            raise SpecError(
                f"line {node.start_mark.line + 1}: this value expands to more than "
                f"{MAX_VALUES:,} values (each use of an alias repeats its anchor's value); "
                "a spec holds a few hundred"
            )
    seen[id(node)] = (size, height)
    return size


def _construct_int(loader: yaml.SafeLoader, node: yaml.ScalarNode) -> int:
    text = loader.construct_scalar(node).replace("_", "")
    if text[:2] in ("0x", "0o"):
        return int(text, 0)
    return int(text, 10)


def _construct_float(loader: yaml.SafeLoader, node: yaml.ScalarNode) -> float:
    text = loader.construct_scalar(node).replace("_", "").lower()
    if text.endswith(".inf"):
        return -math.inf if text.startswith("-") else math.inf
    if text == ".nan":
        return math.nan
    return float(text)


_SpecLoader.add_implicit_resolver(
    "tag:yaml.org,2002:null", re.compile(r"^(?:~|null|Null|NULL|)$"), ["~", "n", "N", ""]
)
_SpecLoader.add_implicit_resolver(
    "tag:yaml.org,2002:bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), list("tTfF")
)
_SpecLoader.add_implicit_resolver(
    "tag:yaml.org,2002:int",
    re.compile(r"^(?:[-+]?[0-9][0-9_]*|0o[0-7]+|0x[0-9a-fA-F]+)$"),
    list("-+0123456789"),
)
_SpecLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(
        r"^(?:[-+]?(?:\.[0-9]+|[0-9][0-9_]*(?:\.[0-9_]*)?)(?:[eE][-+]?[0-9]+)?"
        r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"
    ),
    list("-+0123456789."),
)
_SpecLoader.add_implicit_resolver("tag:yaml.org,2002:merge", re.compile(r"^<<$"), ["<"])
_SpecLoader.add_constructor("tag:yaml.org,2002:int", _construct_int)
_SpecLoader.add_constructor("tag:yaml.org,2002:float", _construct_float)


def load_yaml(text: str) -> Any:
    """Parse YAML with the spec loader (YAML 1.2 core scalars, no duplicate keys)."""
    try:
        return yaml.load(text, Loader=_SpecLoader)  # a SafeLoader subclass
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise SpecError(f"invalid YAML{where}: {exc.problem or exc.context}") from None
    except yaml.YAMLError as exc:
        raise SpecError(f"invalid YAML: {exc}") from None
