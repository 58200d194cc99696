"""How every ``cifemu`` command prints JSON and reports a failure [ours].

One convention for ``status``, ``dbm``, ``sim``, ``configure``, ``monitor`` and
``top --once --json``, so a script can parse any of them the same way:

- keys are ``snake_case`` (the seed's field names lower-cased, e.g. ``nd_cfg``,
  ``err_event``), numbers are JSON numbers, byte strings are lower-case hex
  strings without separators (``"0a1b"``);
- with ``--json`` a failure is one object ``{"error": {"command": ..., "message":
  ..., ...}}`` on stdout and the exit status is non-zero; without it, one line
  on stderr;
- a reader that closes the pipe early (``--json | head``) ends the command
  quietly (``main`` of ``cifemu.cli`` catches the BrokenPipeError).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable
from typing import Any

EXIT_FAILURE = 1


def print_json(data: Any) -> None:
    """One JSON document on stdout, indented for a person, parseable by a program."""
    print(json.dumps(data, indent=2))


def fail(command: str, message: str, as_json: bool, code: int = EXIT_FAILURE,
         **fields: Any) -> int:
    """Report a user-visible failure and return the exit status to use."""
    if as_json:
        print_json({"error": {"command": command, "message": message, **fields}})
    else:
        print(f"cifemu {command}: {message}", file=sys.stderr)
    return code


def run_guarded(run: Callable[[argparse.Namespace], int], args: argparse.Namespace) -> int:
    """Run a command; a reader that leaves early (BrokenPipeError) ends it quietly."""
    try:
        result = run(args)
        sys.stdout.flush()  # inside the guard: a closed pipe shows at the flush
    except BrokenPipeError:
        return quiet_broken_pipe()
    return result


def quiet_broken_pipe() -> int:
    """After a BrokenPipeError: point stdout at /dev/null so the interpreter's final
    flush does not raise again, and give the exit status of a closed pipe."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)
    return EXIT_FAILURE
