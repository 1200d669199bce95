"""Tools around the daemon: benchmarks, calibration, printable markers, plots."""
