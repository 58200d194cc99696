"""The command-line modules of ``cifemu``'s commands, one per command (``cifemu.cli``)."""
