"""The config reference (docs/config.md): every key of every table, from the schema itself."""

from __future__ import annotations

from dataclasses import MISSING, fields
from typing import List, Sequence, Tuple

from .rules import show
from .sections import OPTIONAL_SECTIONS, OUTPUTS, SECTIONS


def reference() -> List[Tuple[str, str, str, str, str]]:
    """(section, key, default, expectation, meaning) for every key: the README's config reference."""
    rows: List[Tuple[str, str, str, str, str]] = []
    tables: Sequence[Tuple[str, type]] = (
        list((f"[{k}]", v) for k, v in SECTIONS.items())
        + list((f"[{k}]", v) for k, v in OPTIONAL_SECTIONS.items())
        + list((f"[output.{k}]", v) for k, v in OUTPUTS.items())
    )
    for where, cls in tables:
        for f in fields(cls):
            if "rule" not in f.metadata:
                continue
            default = f.default if f.default is not MISSING else None
            rows.append(
                (
                    where,
                    f.name,
                    "-" if default is None else show(default),
                    f.metadata["rule"].expectation(),
                    f.metadata["doc"],
                )
            )
    return rows
