"""The documentation works: docs/config.md is what the config schema says."""

from __future__ import annotations

from pathlib import Path

from pose_daemon.config.reference import REGENERATE, page

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def test_the_config_reference_page_is_the_schemas() -> None:
    assert (DOCS / "config.md").read_text(encoding="utf-8") == page(), (
        f"docs/config.md differs from the config schema: regenerate it with `{REGENERATE}`"
    )
