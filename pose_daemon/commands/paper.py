"""``pose-daemon paper {table1,table2,sweep,unicycle}``: the paper's results, reproduced."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Callable

from ..errors import UserError

METHODS = ("paper", "iterative")
# The sweep keeps one e_image per orientation: 20 million is 160 MB (the paper's is 729,000).
MAX_SWEEP_ORIENTATIONS = 20_000_000


def _number(
    kind: Callable[[str], float], name: str, *, low: float, high: float = float("inf"), low_open: bool = False
) -> Callable[[str], float]:
    """An argparse type: ``kind`` in [low, high] (or (low, high] with ``low_open``)."""

    def parse(text: str) -> float:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be a number, got {text!r}") from None
        if value != value or value > high or value < low or (low_open and value == low):
            bound = f"> {low:g}" if low_open else f">= {low:g}"
            if high != float("inf"):
                bound += f" and <= {high:g}"
            raise argparse.ArgumentTypeError(f"{name} must be {bound}, got {text}")
        return value

    return parse


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "paper", help="the paper's results: tables I-II, the sweep, the unicycle", description=__doc__.splitlines()[0]
    )
    which = parser.add_subparsers(dest="paper", metavar="RESULT", required=True, parser_class=type(parser))

    def common(p: argparse.ArgumentParser, iterations: int) -> None:
        p.add_argument(
            "--method",
            choices=METHODS,
            default="paper",
            help="yaw/pitch step: the paper's simulated table or the table-free step (default: paper)",
        )
        p.add_argument(
            "--iterations",
            type=_number(int, "--iterations", low=1, high=100),
            default=iterations,
            help=f"correction cycles (default {iterations})",
        )
        p.add_argument("--json", action="store_true", help="print one JSON object")

    for number in (1, 2):
        text = f"Table {'I' * number}: case {number}, iteration by iteration"
        p = which.add_parser(
            f"table{number}",
            help=text,
            description=(
                f"{text}. The image is synthesised with f = 600 px and a square of side 20 "
                "(the paper publishes neither; only side / distance matters)."
            ),
        )
        common(p, 5)
        p.set_defaults(func=run_table, case=number)

    text = "Fig. 4: e_image over all orientations in [-45, 45) deg"
    p = which.add_parser(
        "sweep",
        help=text,
        description=(f"{text}: a square of side 20 at (0, 0, 100), f = 600 px, e_image (eq 17) in pixels."),
    )
    common(p, 10)
    p.add_argument(
        "--step-deg",
        type=_number(float, "--step-deg", low=0.0, high=90.0, low_open=True),
        default=1.0,
        help="grid step in degrees (default 1: 90^3 orientations)",
    )
    p.add_argument("--limit", type=_number(int, "--limit", low=1), default=None, help="only the first N orientations")
    p.add_argument("--plot", metavar="FILE.png", help="draw the Fig. 4 equivalent")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.set_defaults(func=run_sweep)

    text = "Figs. 7-9: a robot steered by the estimated pose"
    p = which.add_parser(
        "unicycle",
        help=text,
        description=(
            f"{text} (eqs 18-22): from (20, -100) cm heading 0 to (0, -50) cm, a 20 cm window "
            "seen by a 640x480 camera with f = 260 px, 10 cm below the window's centre."
        ),
    )
    common(p, 5)
    p.add_argument(
        "--noise-px",
        type=_number(float, "--noise-px", low=0.0, high=50.0),
        default=0.0,
        help="Gaussian corner noise, pixels (default 0)",
    )
    p.add_argument("--seed", type=_number(int, "--seed", low=0), default=0, help="noise seed (default 0)")
    p.add_argument(
        "--refine", action="store_true", help="polish each pose by reprojection error (off: the paper's loop alone)"
    )
    p.add_argument(
        "--kv",
        type=_number(float, "--kv", low=0.0, high=100.0, low_open=True),
        default=0.5,
        help="speed gain, 1/s (default 0.5)",
    )
    p.add_argument(
        "--kw",
        type=_number(float, "--kw", low=0.0, high=100.0, low_open=True),
        default=3.0,
        help="turn gain, 1/s (default 3)",
    )
    p.add_argument(
        "--dt",
        type=_number(float, "--dt", low=0.0, high=1.0, low_open=True),
        default=1.0 / 30.0,
        help="control step = camera frame period, s (default 1/30)",
    )
    p.add_argument(
        "--duration",
        type=_number(float, "--duration", low=0.0, high=3600.0, low_open=True),
        default=10.0,
        help="simulated time, s (default 10)",
    )
    p.add_argument(
        "--goal-radius",
        type=_number(float, "--goal-radius", low=0.0, high=100.0),
        default=1.0,
        help="stop once the feedback is this close to the goal, cm "
        "(default 1; 0 = the paper's controller, never stops)",
    )
    p.add_argument("--plot", metavar="DIR", help="write Figs. 7-9 equivalents into DIR")
    p.set_defaults(func=run_unicycle)


def _print_json(obj: dict) -> None:
    print(json.dumps(obj, allow_nan=False))


def run_table(args: argparse.Namespace) -> int:
    from ..paper.cases import CASES, format_case, run_case

    result = run_case(CASES[args.case], method=args.method, iterations=args.iterations)
    if args.json:
        _print_json(result.to_json_dict())
    else:
        print(format_case(result))
    return 0


def run_sweep(args: argparse.Namespace) -> int:
    from ..paper.progress import ProgressBar
    from ..paper.sweep import angle_grid, format_sweep
    from ..paper.sweep import run_sweep as sweep
    from ..plotting import check_plot_path, require_matplotlib

    if args.plot:
        # Before minutes of work, not after.
        require_matplotlib()
        check_plot_path(args.plot)
    total = angle_grid(args.step_deg).size ** 3
    if args.limit is not None:
        total = min(total, args.limit)
    if total > MAX_SWEEP_ORIENTATIONS:
        raise UserError(
            f"--step-deg {args.step_deg:g} gives {total:,} orientations, more than "
            f"{MAX_SWEEP_ORIENTATIONS:,}; use a larger step or --limit"
        )
    with ProgressBar(total, label="sweep", enabled=not args.no_progress) as bar:
        result = sweep(
            method=args.method,
            iterations=args.iterations,
            step_deg=args.step_deg,
            limit=args.limit,
            progress=bar.update,
        )
    if args.plot:
        from ..paper.figures import plot_sweep

        path = plot_sweep(result, args.plot)
        print(f"wrote {path}", file=sys.stderr)
    if args.json:
        _print_json(result.to_json_dict())
    else:
        print(format_sweep(result))
    return 0


def run_unicycle(args: argparse.Namespace) -> int:
    from ..paper.unicycle import UnicycleSetup, format_unicycle
    from ..paper.unicycle import run_unicycle as simulate
    from ..plotting import check_plot_dir, require_matplotlib

    if args.plot:
        require_matplotlib()
        check_plot_dir(args.plot)
    setup = UnicycleSetup(
        kv=args.kv,
        kw=args.kw,
        dt_s=args.dt,
        duration_s=args.duration,
        goal_radius=args.goal_radius,
        method=args.method,
        iterations=args.iterations,
        refine=args.refine,
        noise_px=args.noise_px,
        seed=args.seed,
    )
    result = simulate(setup)
    if args.plot:
        from ..paper.figures import plot_unicycle

        for path in plot_unicycle(result, args.plot):
            print(f"wrote {path}", file=sys.stderr)
    if args.json:
        _print_json(result.to_json_dict())
    else:
        print(format_unicycle(result))
    return 0
