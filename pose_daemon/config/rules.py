"""The rule of one config key (type, bounds, choices) and the field that carries it.

Each section is a dataclass whose fields carry their own rule in ``field(metadata=...)`` (made
by ``setting``), so adding a key is one line: the validator, the error messages and the config
reference (docs/config.md) all read the same declaration.
"""

from __future__ import annotations

import json
import math
from dataclasses import MISSING, dataclass, field, fields
from typing import Any, Dict, List, Optional, Tuple

__all__ = ["Invalid", "Rule", "UNKNOWN_KEY", "build_section", "message", "num", "setting", "show"]


class Invalid(Exception):
    """Raised by a rule or a section check: ``key`` failed, ``expected`` says what was wanted."""

    def __init__(self, key: str, expected: str, got: Any = MISSING) -> None:
        super().__init__(key)
        self.key = key
        self.expected = expected
        self.got = got


@dataclass(frozen=True)
class Rule:
    """What one key accepts.

    kind: "int", "float", "str", "bool", "floats" (list of numbers), "strs" (list of strings).
    lo/hi: bounds (inclusive unless lo_open/hi_open); choices: allowed values (strings compare
    case-insensitively when ``upper`` is set, and are stored upper-case); lengths: allowed list
    lengths.
    """

    kind: str
    lo: Optional[float] = None
    hi: Optional[float] = None
    lo_open: bool = False
    hi_open: bool = False
    choices: Optional[Tuple[Any, ...]] = None
    lengths: Optional[Tuple[int, ...]] = None
    nonempty: bool = False
    unique: bool = False
    upper: bool = False

    def expectation(self) -> str:
        noun = {
            "int": "an integer",
            "float": "a number",
            "str": "a string",
            "bool": "true or false",
            "floats": "a list of numbers",
            "strs": "a list of strings",
        }[self.kind]
        if self.choices is not None and self.kind in ("str", "int"):
            return "one of " + ", ".join(show(c) for c in self.choices)
        if self.kind in ("floats", "strs"):
            parts = [noun]
            if self.lengths:
                parts = [
                    f"a list of {' or '.join(str(n) for n in self.lengths)} "
                    f"{'numbers' if self.kind == 'floats' else 'strings'}"
                ]
            if self.choices is not None:
                parts.append("each one of " + ", ".join(show(c) for c in self.choices))
            elif self.lo is not None or self.hi is not None:
                parts.append("each " + self._bounds())
            if self.nonempty:
                parts.append("not empty")
            if self.unique:
                parts.append("no repeats")
            return ", ".join(parts)
        bounds = self._bounds()
        if self.kind == "str" and self.nonempty:
            return "a non-empty string"
        return f"{noun} {bounds}".strip()

    def _bounds(self) -> str:
        lo, hi = self.lo, self.hi
        if lo is not None and hi is not None:
            left = "(" if self.lo_open else "["
            right = ")" if self.hi_open else "]"
            return f"in {left}{num(lo)}, {num(hi)}{right}"
        if lo is not None:
            return f"{'>' if self.lo_open else '>='} {num(lo)}"
        if hi is not None:
            return f"{'<' if self.hi_open else '<='} {num(hi)}"
        return ""

    def _in_bounds(self, v: float) -> bool:
        if self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo):
            return False
        if self.hi is not None and (v >= self.hi if self.hi_open else v > self.hi):
            return False
        return True

    def convert(self, key: str, value: Any) -> Any:
        """The value as stored in the dataclass, or Invalid."""
        bad = Invalid(key, self.expectation(), value)
        if self.kind == "bool":
            if not isinstance(value, bool):
                raise bad
            return value
        if self.kind == "int":
            if isinstance(value, bool) or not isinstance(value, int):
                raise bad
            if self.choices is not None and value not in self.choices:
                raise bad
            if not self._in_bounds(value):
                raise bad
            return int(value)
        if self.kind == "float":
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise bad
            value = float(value)
            if not math.isfinite(value) or not self._in_bounds(value):
                raise bad
            return value
        if self.kind == "str":
            if not isinstance(value, str):
                raise bad
            if self.upper:
                value = value.upper()
            if self.choices is not None and value not in self.choices:
                raise bad
            if self.nonempty and not value.strip():
                raise bad
            return value
        if not isinstance(value, list):
            raise bad
        if self.lengths is not None and len(value) not in self.lengths:
            raise bad
        if self.nonempty and not value:
            raise bad
        out: List[Any] = []
        for item in value:
            if self.kind == "floats":
                if isinstance(item, bool) or not isinstance(item, (int, float)):
                    raise bad
                item = float(item)
                if not math.isfinite(item) or not self._in_bounds(item):
                    raise bad
            else:
                if not isinstance(item, str):
                    raise bad
                if self.upper:
                    item = item.upper()
                if self.choices is not None and item not in self.choices:
                    raise bad
            out.append(item)
        if self.unique and len(set(out)) != len(out):
            raise bad
        return tuple(out)


SHOW_DEPTH = 4


def num(v: float) -> str:
    return str(int(v)) if float(v).is_integer() and abs(v) < 1e15 else repr(float(v))


def show(value: Any, _depth: int = 0) -> str:
    """A value as it would be written in TOML (for error messages); deep lists end in "[...]"."""
    if value is MISSING:
        return "nothing"
    if isinstance(value, (list, tuple)):
        if _depth >= SHOW_DEPTH:  # hundreds of levels would exhaust the stack, and say nothing
            return "[...]"
        return "[" + ", ".join(show(v, _depth + 1) for v in value) + "]"
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    try:
        return json.dumps(value)
    except (TypeError, ValueError):
        return str(value)


def setting(default: Any, rule: Rule, doc: str, *, default_from: Optional[str] = None) -> Any:
    """A dataclass field with its rule and its meaning (the config reference's text).

    ``default_from``: when the key is absent but that key of the same table is given, take
    its value (a marker's height is its width unless told otherwise). Mutable defaults
    (lists) are stored as tuples.
    """
    if isinstance(default, list):
        default = tuple(default)
    if default_from is not None:
        doc = f"{doc} (default: {default_from})"
    return field(default=default, metadata={"rule": rule, "doc": doc, "default_from": default_from})


def build_section(cls: type, table: Dict[str, Any], where: str) -> Any:
    """One section's dataclass from its TOML table; Invalid names the key (with ``where``)."""
    known = {f.name: f for f in fields(cls) if "rule" in f.metadata}
    kwargs: Dict[str, Any] = {}
    for key, value in table.items():
        f = known.get(key)
        if f is None:
            raise Invalid(key, "one of " + ", ".join(known), UNKNOWN_KEY)
        kwargs[key] = f.metadata["rule"].convert(key, value)
    for f in known.values():
        source = f.metadata["default_from"]
        if source is not None and f.name not in kwargs and source in kwargs:
            kwargs[f.name] = kwargs[source]
    obj = cls(**kwargs)
    check = getattr(obj, "check", None)
    if check is not None:
        check()
    return obj


UNKNOWN_KEY = object()


def message(name: str, where: str, err: Invalid) -> str:
    if err.got is UNKNOWN_KEY:
        return f"{name}: {where} {err.key}: unknown key (expected {err.expected})"
    got = "" if err.got is MISSING else f", got {show(err.got)}"
    return f"{name}: {where} {err.key}: expected {err.expected}{got}"
