"""``pose-daemon sim --config FILE [--fly hold|land] [--out DIR]``: rehearse the flight in ArduPilot or PX4 SITL.

The daemon on frames rendered from the simulator's truth and, with --fly, the rehearsal mission.
"""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "sim",
        help="rehearse the flight in ArduPilot or PX4 SITL with your config",
        description="pose-daemon sim: the daemon on frames rendered from ArduPilot or PX4 SITL's true vehicle "
        "pose and, with --fly, the rehearsal mission (take-off, hold, blackout, landing). Exit 0 when the "
        "mission passed, 1 when not (the reason on one line), 2 for a config or link that cannot be used.",
    )
    parser.add_argument(
        "--config", metavar="FILE", required=True, help="TOML config (its [camera] source becomes sitl)"
    )
    parser.add_argument(
        "--fly", choices=("hold", "land"), help="fly the mission: hold (the hover judged) or land (the touchdown too)"
    )
    parser.add_argument("--out", metavar="DIR", default="sim", help="folder for summary.json and sim.png (default sim)")
    parser.add_argument("--hold-s", type=float, default=30.0, help="seconds of the judged hover (default 30)")
    parser.add_argument(
        "--ekf-wait-s", type=float, default=60.0, help="how long the EKF may take to use the feed (default 60)"
    )
    parser.add_argument(
        "--climb-m",
        type=float,
        default=1.0,
        help="height of the hover over where it took off, metres: the landing starts from there (default 1)",
    )
    parser.add_argument(
        "--arm-wait-s",
        type=float,
        default=30.0,
        help="how long a refused arming is retried, every 2 s, as a ground station's user would (default 30)",
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..config import load_config
    from ..errors import UserError
    from ..tools.sim import MissionOptions, run_sim

    if not 1.0 <= args.hold_s <= 3600.0:
        raise UserError(f"--hold-s must be in [1, 3600], got {args.hold_s:g}")
    if not 1.0 <= args.ekf_wait_s <= 3600.0:
        raise UserError(f"--ekf-wait-s must be in [1, 3600], got {args.ekf_wait_s:g}")
    if not 0.0 <= args.arm_wait_s <= 3600.0:
        raise UserError(f"--arm-wait-s must be in [0, 3600], got {args.arm_wait_s:g}")
    if not 0.5 <= args.climb_m <= 100.0:
        raise UserError(f"--climb-m must be in [0.5, 100], got {args.climb_m:g}")
    options = MissionOptions(
        hold_s=args.hold_s, ekf_wait_s=args.ekf_wait_s, arm_wait_s=args.arm_wait_s, climb_m=args.climb_m
    )
    return run_sim(load_config(args.config), fly=args.fly, out_dir=args.out, options=options)
