#!/usr/bin/env python3
"""Regenerate docs/config.md, the config reference, from the config schema.

Usage: python scripts/make_config_page.py [OUT.md]   (default: docs/config.md)
"""

from __future__ import annotations

import sys
from pathlib import Path

from pose_daemon.config.reference import page


def main() -> int:
    default = Path(__file__).resolve().parent.parent / "docs" / "config.md"
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else default
    out.write_text(page(), encoding="utf-8")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
