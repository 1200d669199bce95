"""``pose-daemon bench {estimator,detector,pipeline,outputs,quality,ambiguity,map,mapbuild}``: figures.

Each benchmark is ``run_bench(...)`` (parameters in, report out) and ``print_report(report)``
in ``pose_daemon/bench/<name>.py``; this file holds their arguments.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os

from ..errors import UserError

BENCHES = {
    "estimator": "accuracy under pixel noise and time per call against OpenCV's solvers",
    "detector": "detection rate, corner and pose error, time per frame against ArUco + IPPE",
    "pipeline": "end-to-end latency (capture -> bytes written) and memory over a long run",
    "outputs": "time each output takes from publish to bytes written on its link",
    "feed": "the MAVLink feed on one core beside busy loops: late poses, the daemon's part and the reader's",
    "map": "marker maps: floor-grid flights, the nested-pad descent, cost with 1/4/9 markers; --real: field frames",
    "quality": "the quality sent to the autopilot against the pose's true error (rendered hovers)",
    "ambiguity": "mirror-pose flips per way of choosing the planar solution, and the gate on clutter",
    "mapbuild": "map build on rendered walk-throughs: marker pose error, time to build, the daemon with the built map",
}


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("bench", help="benchmarks: accuracy, speed, latency", description=__doc__.splitlines()[0])
    benches = parser.add_subparsers(dest="bench", metavar="BENCH", required=True, parser_class=type(parser))
    p = {name: benches.add_parser(name, help=text, description=text) for name, text in BENCHES.items()}
    p["estimator"].add_argument("--n", type=int, default=10_000, help="random poses per noise level (default 10000)")
    p["estimator"].add_argument(
        "--timing-n", type=int, default=1000, help="corner sets timed one call at a time per method (default 1000)"
    )
    p["estimator"].add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    p["detector"].add_argument(
        "--frames",
        type=int,
        default=None,
        metavar="N",
        help="marker frames per marker type (default 300); --sweep view: poses per bin and background (default 20)",
    )
    p["detector"].add_argument(
        "--sweep",
        choices=("view", "size"),
        default=None,
        help="view: only the view-angle sweep (0-80 deg off the face, beside OpenCV ArUco + IPPE); "
        "size: only a tracked frame's cost by marker size",
    )
    p["detector"].add_argument(
        "--empty", type=int, default=200, metavar="N", help="marker-free frames for false detections (default 200)"
    )
    p["detector"].add_argument("--seed", type=int, default=0, help="random seed of poses and images")
    p["detector"].add_argument(
        "--repeat", type=int, default=3, metavar="K", help="time each frame K times and keep the fastest (default 3)"
    )
    p["ambiguity"].add_argument("--frames", type=int, default=300, metavar="N", help="frames per flight (default 300)")
    p["ambiguity"].add_argument(
        "--clutter", type=int, default=500, metavar="N", help="marker-free clutter frames (default 500, 0 = none)"
    )
    p["ambiguity"].add_argument("--seed", type=int, default=0, help="random seed of flights, noise and clutter")
    p["ambiguity"].add_argument(
        "--seeds",
        type=int,
        default=1,
        metavar="N",
        help="fly every flight with seeds SEED..SEED+N-1 and pool them per flight and strategy "
        "(default 1: the one seed's full table)",
    )
    for name in ("estimator", "detector", "quality", "ambiguity"):
        p[name].add_argument("--json", action="store_true", help="print one JSON object instead of tables")
    p["pipeline"].add_argument(
        "--frames", type=int, default=3000, help="frames to run (default 3000; 20000 for the memory figure)"
    )
    p["pipeline"].add_argument(
        "--fps",
        type=float,
        default=None,
        help="rate at which the source hands out frames (default 100; with --config the camera's fps)",
    )
    p["pipeline"].add_argument(
        "--config",
        metavar="FILE",
        default=None,
        help="run this config's camera size and rate, marker, detector and estimator (its outputs are "
        "replaced by a local UDP sink and /dev/null): the per-stage figures of your set-up, on your Pi",
    )
    p["pipeline"].add_argument("--distinct", type=int, default=48, help="distinct rendered frames, cycled (default 48)")
    p["pipeline"].add_argument("--seed", type=int, default=0, help="trajectory and noise seed")
    p["pipeline"].add_argument(
        "--preview",
        choices=("off", "idle", "watch"),
        default="off",
        help="live preview: off (default), idle (served, nobody watching), watch (one viewer reading /stream.mjpg)",
    )
    p["outputs"].add_argument("--poses", type=int, default=3000, help="poses per output (default 3000)")
    p["feed"].add_argument("--poses", type=int, default=2000, help="frames to send (default 2000)")
    p["feed"].add_argument("--fps", type=float, default=30.0, help="frame rate (default 30)")
    p["feed"].add_argument("--work-ms", type=float, default=15.0, help="CPU time per frame, ms (default 15)")
    p["feed"].add_argument("--busy", type=int, default=2, help="busy loops on the core (default 2)")
    p["feed"].add_argument("--core", type=int, default=0, help="the one core for all (default 0)")
    p["feed"].add_argument("--nice", type=int, default=0, help="the daemon side's nice value (default 0; < 0: root)")
    p["map"].add_argument(
        "--frames",
        type=int,
        default=None,
        help="frames per floor-grid flight (default 600); with --real and no DIR: field frames rendered (default 40)",
    )
    p["map"].add_argument(
        "--real",
        nargs="?",
        const="",
        metavar="DIR",
        help="field frames instead: the map pose beside OpenCV's multi-tag solve, in order and shuffled; DIR holds "
        "the frames and config.toml ([camera], [map]); without DIR, frames rendered over a field",
    )
    p["map"].add_argument("--config", metavar="FILE", help="with --real DIR: the config in place of DIR/config.toml")
    p["map"].add_argument(
        "--descent-frames", type=int, default=300, help="frames of the 10 m -> 0.2 m pad descent (default 300)"
    )
    p["map"].add_argument("--repeat", type=int, default=200, help="timed frames per cost row (default 200)")
    p["map"].add_argument("--seed", type=int, default=0, help="trajectory and noise seed")
    p["map"].add_argument("--json", action="store_true", help="print one JSON object instead of tables")
    p["mapbuild"].add_argument("--seed", type=int, default=0, help="placement, walk and noise seed")
    p["mapbuild"].add_argument(
        "--validation-frames", type=int, default=300, help="frames of the flight that compares the maps (default 300)"
    )
    p["mapbuild"].add_argument("--json", action="store_true", help="print one JSON object instead of tables")
    p["quality"].add_argument(
        "--frames", type=int, default=150, metavar="N", help="hover frames per tilt and height (default 150)"
    )
    p["quality"].add_argument("--seed", type=int, default=0, help="random seed of hovers and images")
    for parser in p.values():
        parser.set_defaults(func=run)


def _check(ok: bool, message: str) -> None:
    if not ok:
        raise UserError(message)


def run(a: argparse.Namespace) -> int:
    bench = importlib.import_module(f"pose_daemon.bench.{a.bench}")
    if a.bench == "estimator":
        _check(a.n >= 10, f"--n must be at least 10, got {a.n}")
        _check(a.timing_n >= 1, f"--timing-n must be positive, got {a.timing_n}")
        report = bench.run_bench(a.n, min(a.timing_n, a.n), a.seed, progress=not a.json)
    elif a.bench == "detector":
        frames = a.frames if a.frames is not None else {"view": 20, "size": 10}.get(a.sweep, 300)
        _check(frames >= 1, f"--frames must be at least 1, got {frames}")
        _check(a.repeat >= 1, f"--repeat must be at least 1, got {a.repeat}")
        _check(a.empty >= 0, f"--empty must be 0 or more, got {a.empty}")
        if a.sweep is not None:
            report = bench.run_sweep_bench(a.sweep, frames, a.seed, a.repeat)
        else:
            report = bench.run_bench(frames, a.empty, a.seed, a.repeat)
    elif a.bench == "pipeline":
        user = None
        if a.config is not None:
            from ..config import load_config

            user = load_config(a.config)
            _check(user.map is None, f"--config {a.config}: a [map] config; bench pipeline renders one [marker]")
        fps = a.fps if a.fps is not None else (user.camera.fps if user is not None else 100.0)
        _check(a.frames >= 1 and fps > 0 and a.distinct >= 1, "--frames and --distinct must be >= 1 and --fps > 0")
        report = bench.run_bench(a.frames, fps, a.distinct, a.seed, preview=a.preview, config=user)
    elif a.bench == "map" and a.real is not None:
        bench = importlib.import_module("pose_daemon.bench.map_real")
        frames = 40 if a.frames is None else a.frames
        _check(frames >= 1, f"--frames must be at least 1, got {frames}")
        report = bench.run_bench(a.real or None, config=a.config, frames=frames, seed=a.seed)
    elif a.bench == "map":
        frames = 600 if a.frames is None else a.frames
        _check(
            frames >= 2 and a.descent_frames >= 2 and a.repeat >= 1,
            "--frames and --descent-frames must be >= 2 and --repeat >= 1",
        )
        report = bench.run_bench(frames, a.descent_frames, a.repeat, a.seed, progress=not a.json)
    elif a.bench == "mapbuild":
        _check(a.validation_frames >= 10, f"--validation-frames must be at least 10, got {a.validation_frames}")
        bench.require_scipy()
        report = bench.run_bench(seed=a.seed, validation_frames=a.validation_frames, progress=not a.json)
    elif a.bench == "quality":
        _check(a.frames >= 1, f"--frames must be at least 1, got {a.frames}")
        report = bench.run_bench(a.frames, a.seed)
    elif a.bench == "ambiguity":
        _check(a.frames >= 30, f"--frames must be at least 30, got {a.frames}")
        _check(a.clutter >= 0, f"--clutter must be 0 or more, got {a.clutter}")
        _check(a.seeds >= 1, f"--seeds must be at least 1, got {a.seeds}")
        if a.seeds > 1:
            report = bench.run_pooled(a.frames, range(a.seed, a.seed + a.seeds), a.clutter)
        else:
            report = bench.run_bench(a.frames, a.clutter, a.seed)
    elif a.bench == "feed":
        _check(
            a.poses >= 1 and a.fps > 0 and a.work_ms >= 0 and a.busy >= 0,
            "--poses >= 1, --fps > 0, --work-ms, --busy >= 0",
        )
        _check(
            a.core in os.sched_getaffinity(0), f"--core must be one of {sorted(os.sched_getaffinity(0))}, got {a.core}"
        )
        report = bench.run_bench(a.poses, a.fps, a.work_ms, a.busy, a.core, a.nice)
    else:
        _check(a.poses >= 1, f"--poses must be at least 1, got {a.poses}")
        report = bench.run_bench(a.poses)
    if getattr(a, "json", False):
        print(json.dumps(report))
    else:
        bench.print_report(report)
    return 0
