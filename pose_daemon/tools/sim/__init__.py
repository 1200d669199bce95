"""``pose-daemon sim``'s library half: the daemon on the ``sitl`` source and, with a mission, a
ground station on the same simulator link flying the rehearsal, then its report."""

from __future__ import annotations

import json
import logging
import signal
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Dict, Optional, Tuple

from ...config import Config, SitlConfig, check_whole
from ...errors import SourceError, UserError
from ...geometry import VehicleFrames
from .mission import Mission, MissionFailed, MissionOptions, Recorder
from .report import plot, summarize, table

__all__ = ["run_sim", "sim_config", "MissionOptions"]

log = logging.getLogger("pose_daemon.sim")
#: How long the simulator may take to send its first HEARTBEAT on the [sitl] link.
LINK_TIMEOUT_S = 10.0


def sim_config(cfg: Config) -> Config:
    """``cfg`` with ``[camera] source = "sitl"`` (the rest as on the vehicle), checked whole."""
    cfg = replace(cfg, camera=replace(cfg.camera, source="sitl"))
    check_whole(cfg)
    return cfg


def _open_link(cfg: Config) -> Any:
    from ...capture.sitl_link import SitlLink

    sitl = cfg.sitl if cfg.sitl is not None else SitlConfig()
    link = SitlLink(
        sitl.connection,
        baud=sitl.baud,
        source_system=sitl.source_system,
        source_component=sitl.source_component,
        marker_below_m=sitl.marker_below_m,
        truth_rate_hz=cfg.camera.fps,
    )
    try:
        link.open()
    except SourceError as exc:
        raise UserError(f"{cfg.name}: [sitl] connection: {exc}") from None
    deadline = time.monotonic() + LINK_TIMEOUT_S
    while link.autopilot is None and time.monotonic() < deadline:
        time.sleep(0.05)
    if link.autopilot is None:
        link.close()
        raise UserError(
            f"{cfg.name}: [sitl] connection {sitl.connection}: no autopilot HEARTBEAT in {LINK_TIMEOUT_S:g} s "
            "(is the simulator running, and this its ground-station port?)"
        )
    return link


def run_sim(
    cfg: Config, *, fly: Optional[str] = None, out_dir: str = "sim", options: Optional[MissionOptions] = None
) -> int:
    """The daemon on the sitl source of ``cfg``; with ``fly`` ("hold" / "land") the rehearsal,
    its DIR/summary.json, table and plot. Exit status: 0 passed (or a clean stop without a
    mission), 1 failed (the reason on one line), UserError (exit 2) for a config or link that
    cannot be used."""
    from ...capture.sources import sitl_source
    from ...service import Service, setup_logging

    cfg = sim_config(cfg)
    out = Path(out_dir)
    if fly is not None and cfg.output.mavlink is None:
        raise UserError(f"{cfg.name}: sim --fly needs an [output.mavlink] table (the feed the autopilot flies on)")
    if fly is not None:
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UserError(f"--out {out_dir}: cannot create the folder: {exc.strerror or exc}") from None
    setup_logging(cfg.logging.level)
    link = _open_link(cfg)
    try:
        source = sitl_source(cfg, link)
        service = Service(cfg, source=source)
        if fly is None:
            previous = service.install_signal_handlers()
            try:
                return service.run()
            finally:
                for signum, handler in previous.items():
                    signal.signal(signum, handler)  # type: ignore[arg-type]
        opts = replace(options or MissionOptions(), fly=fly)
        summary, mission, rec = _fly(cfg, link, source, service, opts)
    finally:
        link.close()
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    print(table(summary))
    note = plot(rec, mission, out / "sim.png")
    if note:
        print(note, file=sys.stderr)
    if summary["reasons"]:
        print(f"pose-daemon sim: failed: {summary['reasons'][0]}", file=sys.stderr)
        return 1
    return 0


def _fly(cfg: Config, link: Any, source: Any, service: Any, opts: MissionOptions) -> Tuple[Dict[str, Any], Any, Any]:
    rec = Recorder()
    observe = rec.attach(link, VehicleFrames.from_config(cfg.mount, cfg.placement))
    tap = service.pipeline.frame_observer

    def both(frame: Any, result: Any) -> None:
        observe(frame, result)
        if tap is not None:
            tap(frame, result)

    service.pipeline.frame_observer = both
    daemon = threading.Thread(target=service.run, name="sim-daemon", daemon=True)
    daemon.start()
    mission = Mission(link, source, rec, opts)
    failure: Optional[str] = None
    try:
        mission.fly()
    except MissionFailed as exc:
        failure = str(exc)
        if rec.armed and link.autopilot == "ardupilot":
            link.command_long(176, 1, 9)  # LAND: never leave the simulated vehicle in the air
        elif rec.armed:
            link.command_long(21, 0, 0, 0, float("nan"), float("nan"), float("nan"), float("nan"))
    finally:
        service.request_stop("mission over")
        daemon.join(10.0)
    return summarize(rec, mission, link.autopilot, opts.fly, failure), mission, rec
