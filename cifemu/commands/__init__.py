"""The ``cifemu`` commands, one module each (``cifemu.cli.COMMANDS`` lists them)."""
