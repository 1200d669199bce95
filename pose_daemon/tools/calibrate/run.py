"""``pose-daemon calibrate``'s flow: views from a folder, a recording or the live camera, the fit,
its report with the camera's response exponent, and the [camera] section written out or into
the config."""

from __future__ import annotations

import sys
from datetime import datetime, timezone
from pathlib import Path
from typing import Optional, Union

from ...errors import UserError
from .board import BoardSpec
from .camera_section import camera_toml, update_config_file
from .collect import views_from_path, views_live
from .fit import calibrate_views, refuse_too_few, report
from .response import measure_response

DEFAULT_MIN_COVERAGE = 0.5


def run_calibration(
    spec: BoardSpec,
    input_path: Optional[str] = None,
    *,
    config: Optional[str] = None,
    out: Optional[str] = None,
    max_views: int = 20,
    seconds: Optional[float] = None,
    save_views: Optional[Union[str, Path]] = None,
    drop_outliers: bool = False,
    min_coverage: float = DEFAULT_MIN_COVERAGE,
    fit_k3: bool = False,
) -> int:
    """``pose-daemon calibrate``: views from ``input_path`` (a folder of images or a recording)
    or live from ``config``'s camera, the fit, its report, and the [camera] section written to
    ``out`` ('-' = stdout, the default without ``config``) and/or into ``config`` in place.
    Returns the exit status; UserError for every user mistake or a poor calibration."""
    if config:
        from ...config import load_config

        load_config(config)  # a broken config is reported before the work, not after
    # The TOML goes to stdout when nothing else is asked for: the report then goes to stderr.
    to_stdout = out == "-" or (out is None and not config)
    stream = sys.stderr if to_stdout else sys.stdout

    def say(line: str) -> None:
        print(line, file=stream, flush=True)

    say(f"board: {spec.describe()}")
    if input_path:
        views, size, name = views_from_path(
            Path(input_path), spec, max_views=max_views, seconds=seconds, save_views=save_views, say=say
        )
    else:
        views, size, name = views_live(
            spec, config, max_views=max_views, seconds=seconds, save_views=save_views, say=say
        )
    width, height = size
    refuse_too_few(views, name)

    result = calibrate_views(views, width, height, fit_k3=fit_k3)
    report(result, say)
    if result.outliers and drop_outliers:
        keep = [v for k, v in enumerate(result.views) if k not in set(result.outliers)]
        say(f"dropping {len(result.outliers)} outlier view(s) and calibrating again")
        refuse_too_few(keep, name)
        result = calibrate_views(keep, width, height, fit_k3=fit_k3)
        report(result, say)
    elif result.outliers:
        say(
            f"{len(result.outliers)} view(s) flagged as outliers: check them, or run again with "
            "--drop-outliers to leave them out"
        )
    if result.coverage < min_coverage:
        raise UserError(
            f"poor coverage: the board's corners reached {result.coverage:.0%} of the image "
            f"(need {min_coverage:.0%}); add views with the board near the edges and corners"
        )

    response = measure_response(result.views, spec.square_m)
    if response.exponent is not None and response.shoulder:
        say(
            f"camera response: [detector] gamma = {response.exponent:.2f}, gamma_shoulder = {response.shoulder:.2f} "
            f"put the edge fits on the board's edges ({response.squares} dark squares; the views' size biases "
            f"spread {response.spread_pct:.2f} %, {response.spread_power_pct:.2f} % at one exponent; read as linear "
            f"{response.bias_linear_pct:+.2f} %, as sRGB {response.bias_srgb_pct:+.2f} % size bias): set both in the "
            "config's [detector] section"
        )
    elif response.exponent is not None:
        say(
            f"camera response: [detector] gamma = {response.exponent:.2f} puts the edge fits on the board's edges "
            f"({response.squares} dark squares; read as linear {response.bias_linear_pct:+.2f} %, as sRGB "
            f"{response.bias_srgb_pct:+.2f} % size bias): set it in the config's [detector] section"
        )
    else:
        say(
            f"camera response: not measured ({response.squares} dark squares fitted; read as linear "
            f"{response.bias_linear_pct:+.2f} %, as sRGB {response.bias_srgb_pct:+.2f} % size bias)"
        )
    cam = result.camera
    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    comment = (
        f"pose-daemon calibrate, {stamp}: {len(result.views)} views of {spec.describe()}\n"
        f"RMS reprojection error {result.rms_px:.3f} px, image coverage {result.coverage:.0%}"
    )
    section = camera_toml(cam, comment)
    if out and out != "-":
        try:
            Path(out).write_text(section, encoding="utf-8")
        except OSError as exc:
            raise UserError(f"{out}: cannot write: {exc.strerror or exc}") from None
        say(f"wrote [camera] to {out}")
    elif to_stdout:
        sys.stdout.write(section)
        sys.stdout.flush()
    if config:
        update_config_file(config, cam)
        say(f"updated [camera] in {config}")
    return 0
