"""``python -m flowslam`` = the ``flowslam`` command."""

from flowslam.cli import app

app(prog_name="flowslam")
