"""``pose-daemon bench {estimator,detector,pipeline,ambiguity}``: benchmarks that print figures."""

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
    _register_ambiguity(benches)


AMBIGUITY_HELP = "mirror-pose flips per way of choosing the planar solution, and the gate on clutter"


def _register_ambiguity(benches: argparse._SubParsersAction) -> None:
    p = benches.add_parser("ambiguity", help=AMBIGUITY_HELP, description=AMBIGUITY_HELP)
    p.add_argument("--frames", type=int, default=300, metavar="N", help="frames per flight (default 300)")
    p.add_argument("--clutter", type=int, default=500, metavar="N",
                   help="marker-free clutter frames (default 500, 0 = none)")
    p.add_argument("--seed", type=int, default=0, help="random seed of flights, noise and clutter")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of tables")
    p.set_defaults(func=_run_ambiguity)


def _run_ambiguity(args: argparse.Namespace) -> int:
    import json

    from ..errors import UserError
    from ..tools.bench_ambiguity import format_tables, run_bench

    if args.frames < 30:
        raise UserError(f"--frames must be at least 30, got {args.frames}")
    if args.clutter < 0:
        raise UserError(f"--clutter must be 0 or more, got {args.clutter}")
    result = run_bench(args.frames, args.clutter, args.seed)
    print(json.dumps(result) if args.json else format_tables(result))
    return 0
