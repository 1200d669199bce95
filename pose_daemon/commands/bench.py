"""``pose-daemon bench {estimator,detector,pipeline}``: benchmarks that print figures."""

from __future__ import annotations

import argparse
import importlib

BENCHES = {
    "estimator": "accuracy under pixel noise and time per call against OpenCV's solvers",
    "detector": "detection rate, corner and pose error, time per frame against ArUco + IPPE",
    "pipeline": "end-to-end latency (capture -> bytes written) and memory over a long run",
}


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("bench", help="benchmarks: accuracy, speed, latency",
                            description=__doc__.splitlines()[0])
    benches = parser.add_subparsers(dest="bench", metavar="BENCH", required=True,
                                    parser_class=type(parser))
    for name, help_text in BENCHES.items():
        module = importlib.import_module(f"pose_daemon.tools.bench_{name}")
        p = benches.add_parser(name, help=help_text, description=help_text)
        module.add_arguments(p)
        p.set_defaults(func=module.run)
