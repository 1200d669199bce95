"""One module per ``pose-daemon`` subcommand; see pose_daemon/cli.py."""
