"""``python -m cloudpose.cli`` (how torchrun starts the command line)."""

from cloudpose.cli import app

app()
