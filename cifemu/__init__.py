"""``cifemu``, the umbrella command: ``main`` parses ``cifemu COMMAND ...``.

``cifemu.cli.COMMANDS`` is the one table of commands: each names the module that
implements it, which is imported only when that command runs.
"""

from importlib.metadata import version

from cifemu.cli import build_parser, main

__version__ = version("cifemu")

__all__ = ["__version__", "build_parser", "main"]
