"""The command-line face of every ``cifemu`` command, one module each.

A module here parses its command's options (``add_arguments``) and runs it (``run``);
the work itself is the library code of ``firmware``, ``host_api``, ``dbm_tools`` and
``dpm`` it calls. Commands compose the layers, so they live above them: a host inside
the firmware (``firmware --configure``) or the card commands of ``dbm`` need both
sides, which never import each other. ``cifemu.cli.COMMANDS`` lists them.
"""
