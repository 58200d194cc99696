"""What ``cifemu top`` shows: a live view of one card for a terminal (Textual), or one
snapshot (Rich); its command line is ``cifemu.commands.top``."""
