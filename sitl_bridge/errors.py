"""Configuration errors with one clear line: which file, which key path, what was expected.

Every reader of user configuration (worlds, scenario tasks, trainer settings) validates through
`Node`, so that a bad file always fails as
`worlds/window.yaml: world.obstacles[2].size: expected 3 positive numbers, got [1, 2]`.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any, TypeVar

import yaml

T = TypeVar("T")

_MISSING = object()


# What str.splitlines() breaks on: escaped in every ConfigError, so a key or value that holds
# one (a YAML key can) still gives a one-line message.
_LINE_BREAKS = {ord(c): repr(c)[1:-1] for c in "\n\r\v\f\x1c\x1d\x1e\x85\u2028\u2029"}

NAME_MAX_CHARS = 200
"""Longest name (world, vehicle, obstacle, goal) a configuration may give."""
TEXT_MAX_CHARS = 4096
"""Longest free text (a description, a rule's text, a path) a configuration may give."""


class ConfigError(ValueError):
    """A configuration file is wrong; the message is one line naming file, key path and problem
    (line breaks in it are escaped, whatever the file held)."""

    def __init__(self, message: object = "") -> None:
        super().__init__(str(message).translate(_LINE_BREAKS))


def _short(value: Any, limit: int = 60) -> str:
    text = repr(value) if not isinstance(value, (list, dict)) else yaml.safe_dump(
        value, default_flow_style=True, width=10_000
    ).strip()
    return text if len(text) <= limit else text[: limit - 3] + "..."


class Node:
    """A value inside a config file, remembering where it came from (file and key path)."""

    def __init__(self, value: Any, source: str, path: str = "") -> None:
        self.value = value
        self.source = source
        self.path = path

    # -- errors -----------------------------------------------------------------------
    def error(self, expected: str, got: Any = _MISSING) -> ConfigError:
        """A ConfigError for this node: `source: path: expected X, got Y`."""
        got_value = self.value if got is _MISSING else got
        where = f"{self.source}: {self.path or '<top>'}"
        return ConfigError(f"{where}: expected {expected}, got {_short(got_value)}")

    # -- navigation ---------------------------------------------------------------------
    def _child_path(self, key: str | int) -> str:
        if isinstance(key, int):
            return f"{self.path}[{key}]"
        text = str(key)
        if len(text) > NAME_MAX_CHARS:  # a hostile key must not make a huge message
            text = f"{text[:40]}...({len(text)} characters)"
        return f"{self.path}.{text}" if self.path else text

    def mapping(self) -> Mapping[str, Any]:
        if not isinstance(self.value, Mapping):
            raise self.error("a mapping")
        return self.value

    def has(self, key: str) -> bool:
        return isinstance(self.value, Mapping) and key in self.value

    def get(self, key: str, default: Any = _MISSING) -> Node:
        """Child node `key`; a missing key without default is an error naming the key."""
        mapping = self.mapping()
        if key in mapping:
            return Node(mapping[key], self.source, self._child_path(key))
        if default is _MISSING:
            child = Node(None, self.source, self._child_path(key))
            raise ConfigError(f"{self.source}: {child.path}: required key is missing")
        return Node(default, self.source, self._child_path(key))

    def items(self) -> Iterator[tuple[str, Node]]:
        for key in self.mapping():
            yield key, Node(self.mapping()[key], self.source, self._child_path(key))

    def list(self, *, min_len: int = 0) -> list[Node]:
        if not isinstance(self.value, list) or len(self.value) < min_len:
            raise self.error(f"a list of at least {min_len} items" if min_len else "a list")
        return [Node(v, self.source, self._child_path(i)) for i, v in enumerate(self.value)]

    def reject_unknown(self, allowed: set[str] | frozenset[str]) -> None:
        """Fail on keys that are not in `allowed` (catches typos such as `sise:`)."""
        for key in self.mapping():
            if key not in allowed:
                child = self._child_path(key)
                raise ConfigError(
                    f"{self.source}: {child}: unknown key (expected one of {', '.join(sorted(allowed))})"
                )

    # -- typed readers ------------------------------------------------------------------
    def number(self, *, positive: bool = False, non_negative: bool = False,
               minimum: float | None = None, maximum: float | None = None) -> float:
        v = self.value
        ok = isinstance(v, (int, float)) and not isinstance(v, bool) and v == v
        ok = ok and (not positive or v > 0) and (not non_negative or v >= 0)
        ok = ok and (minimum is None or v >= minimum) and (maximum is None or v <= maximum)
        if not ok:
            raise self.error(_describe_number(positive, non_negative, minimum, maximum))
        return float(v)

    def integer(self, *, minimum: int | None = None, maximum: int | None = None) -> int:
        v = self.value
        ok = isinstance(v, int) and not isinstance(v, bool)
        ok = ok and (minimum is None or v >= minimum) and (maximum is None or v <= maximum)
        if not ok:
            bounds = "" if minimum is None else f" >= {minimum}"
            bounds += "" if maximum is None else f" <= {maximum}"
            raise self.error(f"an integer{bounds}")
        return int(v)

    def boolean(self) -> bool:
        if not isinstance(self.value, bool):
            raise self.error("true or false")
        return self.value

    def string(self, choices: tuple[str, ...] | None = None, *, max_chars: int = TEXT_MAX_CHARS) -> str:
        """The string here; `max_chars` bounds it (NAME_MAX_CHARS for names)."""
        if not isinstance(self.value, str) or (choices and self.value not in choices):
            raise self.error(f"one of {', '.join(choices)}" if choices else "a string")
        if len(self.value) > max_chars:
            raise ConfigError(f"{self.source}: {self.path or '<top>'}: expected a string of at most "
                              f"{max_chars} characters, got {len(self.value)} characters")
        return self.value

    def vector(self, length: int = 3, *, positive: bool = False, non_negative: bool = False) -> tuple[float, ...]:
        v = self.value
        ok = isinstance(v, list) and len(v) == length and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and x == x for x in v
        )
        ok = ok and (not positive or all(x > 0 for x in v))
        ok = ok and (not non_negative or all(x >= 0 for x in v))
        if not ok:
            kind = "positive numbers" if positive else "non-negative numbers" if non_negative else "numbers"
            raise self.error(f"{length} {kind}")
        return tuple(float(x) for x in v)

    def convert(self, parse: Callable[[Node], T]) -> T:
        return parse(self)


def _describe_number(positive: bool, non_negative: bool, minimum: float | None, maximum: float | None) -> str:
    if positive:
        return "a positive number"
    if non_negative:
        return "a non-negative number"
    parts = ["a number"]
    if minimum is not None:
        parts.append(f">= {minimum}")
    if maximum is not None:
        parts.append(f"<= {maximum}")
    return " ".join(parts)


_SafeLoader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
"""libyaml's safe loader where PyYAML was built with it (~30x faster on a large file), else
the pure-Python one; both build plain data only."""

MAX_YAML_BYTES = 16 * 1024 * 1024
"""Scenario files are small; anything larger is refused before parsing."""
MAX_YAML_DEPTH = 64
"""Nesting of lists/mappings a scenario can need is a handful; deeper input is refused (it
would exhaust the parser's recursion)."""


def _short_path(source: str) -> str:
    return source if len(source) <= 200 else source[:120] + f"...({len(source)} characters)"


def load_yaml(path: str | Path) -> Node:
    """Read a YAML file safely into a root Node; unreadable, non-UTF-8, huge, too deeply nested
    or malformed files are one-line ConfigErrors."""
    source = _short_path(str(path))
    try:
        with open(path, "rb") as handle:
            raw = handle.read(MAX_YAML_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"{source}: cannot read file ({exc.strerror or exc})") from None
    except ValueError as exc:  # e.g. an embedded NUL in the name
        raise ConfigError(f"{source}: cannot read file ({exc})") from None
    if len(raw) > MAX_YAML_BYTES:
        raise ConfigError(f"{source}: file is larger than {MAX_YAML_BYTES // (1024 * 1024)} MiB; not a scenario")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{source}: not UTF-8 text (byte {exc.start} is {raw[exc.start]:#04x})") from None
    depth = _bracket_depth(text)
    if depth > MAX_YAML_DEPTH:
        raise ConfigError(f"{source}: nested {depth} levels deep (at most {MAX_YAML_DEPTH}); not a scenario")
    try:
        data = yaml.load(text, Loader=_SafeLoader)  # noqa: S506 (a safe loader: plain data only)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or "malformed YAML"
        raise ConfigError(f"{source}: invalid YAML{where}: {problem}") from None
    except RecursionError:
        raise ConfigError(f"{source}: nested too deeply to read") from None
    return Node(data, source)


def _bracket_depth(text: str) -> int:
    """Deepest nesting of flow brackets ([ and {) in `text`, a cheap guard before parsing
    (indentation nesting is bounded by the line length and the file size)."""
    if text.count("[") + text.count("{") <= MAX_YAML_DEPTH:
        return 0  # cannot nest too deep: skip the character walk (seconds on a large file)
    depth = deepest = 0
    for match in _BRACKETS.finditer(text):
        if match.group() in "[{":
            depth += 1
            deepest = max(deepest, depth)
        else:
            depth = max(0, depth - 1)
    return deepest


_BRACKETS = re.compile(r"[\[\]{}]")
