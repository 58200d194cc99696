"""``cifemu``, the umbrella command: ``main`` parses ``cifemu COMMAND ...``.

Each command lives in its package (``firmware.cli``, ``firmware.sim.cli``,
``host_api.status``, ``host_api.dbm_commands``, ``host_api.cia309.cli``); this package
only puts them under one name, and adds ``cifemu demo``.
"""

from importlib.metadata import version

from cifemu.cli import build_parser, main

__version__ = version("cifemu")

__all__ = ["__version__", "build_parser", "main"]
