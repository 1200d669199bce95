"""One module per ``pose-daemon`` subcommand; see pose_daemon/cli.py."""


def describe(doc: str) -> str:
    """A command's ``--help`` description from its module docstring: the whole first paragraph
    (not its first line, which may stop mid-sentence), on one line, without reST's ````."""
    first = doc.strip().split("\n\n", 1)[0]
    return " ".join(first.split()).replace("``", "")
