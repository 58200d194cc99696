"""Which python-can bus a command opens: interface, channel, bit rate and the interface's options.

``cifemu firmware``, ``cifemu sim`` and ``cifemu monitor`` open any python-can
interface, including those that need more than a channel (a host and a port for
socketcand, a URL for python-can-remote). The options come the way python-can
users already write them:

- ``--bus-option KEY=VALUE`` (repeatable), passed to ``can.Bus(**kwargs)``;
- ``--bus-config FILE[:SECTION]``, a python-can configuration file (the INI format
  of ``~/.canrc`` / ``can.ini``, read by python-can's own ``load_file_config``),
  section ``default`` unless named. Its ``interface``, ``channel`` and ``bitrate``
  (or the old ``bustype``) fill in what ``--interface``, ``--channel`` and
  ``--bitrate`` leave open; every other key is an option.

A network description's ``[bus]`` may name its interface, channel and options too
(``interface``, ``channel``, ``[bus.options]``, typed by TOML); ``cifemu sim`` and ``cifemu
firmware --simulate`` use them below everything on the command line.

The command line wins over ``--bus-option``, which wins over the file. Values are
typed as python-can types its own configuration files (``can.util.cast_from_string``):
``123`` an int, ``1.5`` a float, ``true``/``false`` a bool, anything else a string.
python-can itself still merges ``~/.canrc`` (and its other default files) under all of
these, as it does for every ``can.Bus`` [ours: the layering].

This module lives in ``dbm_tools`` because the firmware and the host tools both
parse these options and never import each other; ``dbm_tools`` is the lowest layer
that describes a bus (the network description's ``[bus]``).
"""

from __future__ import annotations

import argparse
import configparser
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from can.util import cast_from_string, load_file_config

from dbm_tools.network import BusDescription

OWN_FLAGS = {"interface": "--interface", "channel": "--channel", "bitrate": "--bitrate",
             "bustype": "--interface"}
"""Keys with a flag of their own: a ``--bus-option`` of these is refused, a file's fills in."""


class BusOptionError(ValueError):
    """An option or configuration file that cannot be used; the text names it."""


@dataclass(frozen=True)
class BusSelection:
    """The bus a command opens."""

    interface: str | None
    channel: str | None
    bitrate: int | None
    options: dict[str, Any] = field(default_factory=dict)
    """Keyword arguments for ``can.Bus`` beyond interface, channel and bit rate."""


def add_bus_arguments(parser: argparse.ArgumentParser) -> None:
    """``--bus-option`` and ``--bus-config``: the same spelling in every command."""
    parser.add_argument("--bus-option", action="append", default=[], metavar="KEY=VALUE",
                        help="a keyword argument for python-can's can.Bus, e.g. host=10.0.0.2 "
                             "port=29536 for socketcand (repeatable; 123 is an int, 1.5 a "
                             "float, true/false a bool, anything else a string)")
    parser.add_argument("--bus-config", default=None, metavar="FILE[:SECTION]",
                        help="a python-can configuration file (the INI format of ~/.canrc), "
                             "section 'default' unless named; its interface, channel and "
                             "bitrate fill in what the flags leave open, its other keys are "
                             "options")


def parse_option(text: str) -> tuple[str, Any]:
    """``KEY=VALUE`` -> (key, typed value), typed as python-can types its files."""
    key, sep, value = text.partition("=")
    key = key.strip()
    if not sep or not key.isidentifier():
        raise BusOptionError(f"--bus-option {text!r}: expected KEY=VALUE, KEY a python "
                             "identifier")
    if key in OWN_FLAGS:
        raise BusOptionError(f"--bus-option {key}: use {OWN_FLAGS[key]}")
    return key, cast_from_string(value)


def load_section(spec: str) -> dict[str, Any]:
    """The typed keys of ``FILE[:SECTION]``; python-can's reader, with its silences made loud.

    ``load_file_config`` returns nothing for a missing file or section, which would
    open some other bus without a word: both are errors here.
    """
    path_text, sep, section = spec.rpartition(":")
    if not sep or not section or Path(spec).is_file():
        path_text, section = spec, "default"
    path = Path(path_text)
    if not path.is_file():
        raise BusOptionError(f"--bus-config {spec}: no such file {path}")
    parser = configparser.ConfigParser()
    try:
        with path.open() as file:
            parser.read_file(file)
    except (OSError, UnicodeDecodeError, configparser.Error) as exc:
        raise BusOptionError(f"--bus-config {spec}: {exc}") from None
    if not parser.has_section(section):
        sections = ", ".join(parser.sections()) or "none"
        raise BusOptionError(f"--bus-config {spec}: no section [{section}] (sections: "
                             f"{sections})")
    return {key: cast_from_string(value)
            for key, value in load_file_config(str(path), section).items()}


def select_bus(interface: str | None, channel: str | None, bitrate: int | None,
               options: list[str], config: str | None,
               described: BusDescription | None = None) -> BusSelection:
    """Merge the flags, ``--bus-option``, ``--bus-config`` and a network description's
    ``[bus]`` (in this precedence).

    The description's channel and options belong to its interface: where the command line
    names another interface, none of them is used [ours]; where it names the same one or
    none, they fill in what it leaves open, key by key for the options.
    """
    from_file = load_section(config) if config is not None else {}
    if "bustype" in from_file:
        from_file.setdefault("interface", from_file["bustype"])
        del from_file["bustype"]
    merged = {key: value for key, value in from_file.items()
              if key not in ("interface", "channel", "bitrate")}
    merged.update(parse_option(text) for text in options)
    # An unknown interface is python-can's to refuse, when the bus opens: the card then
    # stays up with FAT set (seed 4.3), as for any interface that cannot be opened.
    interface = interface if interface is not None else _text(from_file.get("interface"))
    if bitrate is None and from_file.get("bitrate") is not None:
        if not isinstance(from_file["bitrate"], int) or isinstance(from_file["bitrate"], bool):
            raise BusOptionError(f"--bus-config {config}: bitrate = {from_file['bitrate']!r} "
                                 "is not a whole number")
        bitrate = from_file["bitrate"]
    channel = channel if channel is not None else _text(from_file.get("channel"))
    if described is not None and described.interface in (None, interface or described.interface):
        interface = interface or described.interface
        channel = channel if channel is not None else described.channel
        merged = {**described.options, **merged}
    return BusSelection(interface, channel, bitrate, merged)


def with_options(options: dict[str, Any]) -> str:
    """`` with options k=v ...`` for an error line that names what the interface refused."""
    if not options:
        return ""
    return " with options " + " ".join(f"{key}={value}" for key, value in options.items())


def _text(value: Any) -> str | None:
    """A file's channel may look like a number (``channel = 0`` for a PCAN or Kvaser card)."""
    return None if value is None else str(value)
