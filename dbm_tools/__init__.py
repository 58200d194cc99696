"""DBM configuration databases and the CAN task's data sets, as pure byte codecs.

- errors: DbmError, the root of every exception of this package, and the msg.f texts of
  the data checks;
- container: the DBM file / data-area container (read, write, build);
- parameters: node, bus and extended bus parameter data sets (shared with the firmware);
- tables: the other CANopen table records (GLOBAL, PLC_PARAM, PROJEKT, DESCRIPT, NODES);
- validate: the COM_Download data checks and the whole-database check;
- network, eds, builder: the network description, EDS files and the DBM builder;
- cli: the file commands of ``cifemu dbm`` (the card commands are ``cifemu.commands.dbm``'s).

Nothing here talks to a card: the package never imports host_api or firmware.
"""

from importlib import import_module
from importlib.metadata import version
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from dbm_tools.builder import BuildError, build_dbm
    from dbm_tools.container import (
        DbmFile,
        DbmTable,
        data_area,
        load_dbm,
        read_data_area,
        read_dbm,
        save_dbm,
        write_dbm,
    )
    from dbm_tools.eds import EdsError
    from dbm_tools.errors import DbmError
    from dbm_tools.network import Network, NetworkError, load_network, parse_network
    from dbm_tools.validate import Finding, check_dbm

_HOMES = {
    "BuildError": "builder", "build_dbm": "builder",
    "DbmFile": "container", "DbmTable": "container", "data_area": "container",
    "load_dbm": "container", "read_data_area": "container", "read_dbm": "container",
    "save_dbm": "container", "write_dbm": "container",
    "EdsError": "eds", "DbmError": "errors",
    "Network": "network", "NetworkError": "network", "load_network": "network",
    "parse_network": "network",
    "Finding": "validate", "check_dbm": "validate",
}
"""Each name's module. They load on first use: the builder pulls in canopen's EDS parser,
which a command that only reads a card should not pay for at start-up."""


def __getattr__(name: str) -> Any:
    if name in _HOMES:
        return getattr(import_module(f"dbm_tools.{_HOMES[name]}"), name)
    raise AttributeError(f"module 'dbm_tools' has no attribute {name!r}")


__version__ = version("cifemu")

__all__ = [
    "BuildError",
    "DbmError",
    "DbmFile",
    "DbmTable",
    "EdsError",
    "Finding",
    "Network",
    "NetworkError",
    "__version__",
    "build_dbm",
    "check_dbm",
    "data_area",
    "load_dbm",
    "load_network",
    "parse_network",
    "read_data_area",
    "read_dbm",
    "save_dbm",
    "write_dbm",
]
