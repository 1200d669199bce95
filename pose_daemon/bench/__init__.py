"""``pose-daemon bench NAME``: one module per benchmark, ``run_bench(...)`` (parameters in, a
report out) and ``print_report(report)``; commands/bench.py holds their arguments."""
