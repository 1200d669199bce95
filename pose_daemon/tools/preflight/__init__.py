"""``pose-daemon preflight``: would the autopilot use the feed? watch.py runs the watch;
ardupilot.py and px4.py judge what it saw; findings.py holds the report's lines."""

from .ardupilot import check_ardupilot
from .findings import Finding, Observation
from .px4 import check_px4
from .watch import run_preflight

__all__ = ["Finding", "Observation", "check_ardupilot", "check_px4", "run_preflight"]
