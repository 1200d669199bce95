#!/usr/bin/env python3
"""Regenerate pose_daemon/data/paper_table.json, the paper's simulated e -> angle cubics.

Usage: python scripts/make_paper_table.py [OUT.json]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from pose_daemon.paper.table_build import build_table
from pose_daemon.pose.paper_table import TABLE_FILE


def main() -> int:
    default = Path(__file__).resolve().parent.parent / "pose_daemon" / "data" / TABLE_FILE
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else default
    table = build_table()
    out.write_text(json.dumps(table, indent=None, separators=(",", ":")) + "\n", encoding="utf-8")
    print(f"wrote {out} ({len(table['z_rel'])} depths)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
