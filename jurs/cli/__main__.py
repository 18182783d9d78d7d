"""``python -m jurs.cli``: the ``jurs`` console script (``jurs.cli.command``)."""

from . import command

command()
