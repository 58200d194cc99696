"""CANopen benchmarks: PDO loop, PDO throughput, SDO, boot-up and SYNC, against simulated nodes.

Every card figure comes from a firmware process started as ``cifemu firmware
--simulate NETWORK.toml --interface virtual``: the card and the simulated nodes
(``firmware.sim``) share one python-can virtual bus inside that process; phases
2, 4 and 5 instead run the nodes as ``cifemu sim`` in a process of their own, on
a fresh ``shm`` channel, so that what is measured is the card and not the
simulator sharing its interpreter lock (phase 4 measured 1.7 s with the 127
nodes inside the card's process, 1.0 s with them outside). This
process is the host and reaches the card only through the driver API. Every
baseline runs here, in this process, in the same run: python ``canopen`` (or
python-can) talking straight to the same simulated nodes on a virtual bus, with
no card between them; the boot phase's baseline talks to nodes in ``cifemu sim``
on a channel of the card's kind, as the card does.

One module per phase: ``pdo_loop`` (1. ``pdo_loop_latency``), ``throughput``
(2. ``pdo_throughput``), ``sdo`` (3.), ``boot`` (4.), ``sync`` (5. ``sync_jitter``); they
share the card under test (``card``), the in-process baseline side (``baseline``), the
closed PDO loop (``echo``) and the trace reader (``trace``); ``document`` puts the
phases' results into one JSON document.

    python -m bench.can [--count N] [--warmup N] [--only NAME ...] [--profile]
"""

from bench.can.baseline import in_process, sdo_client, start_all
from bench.can.card import configure, network_toml, simulated_card, wait_operating
from bench.can.document import NAME, PHASES, main, run

__all__ = [
    "NAME",
    "PHASES",
    "configure",
    "in_process",
    "main",
    "network_toml",
    "run",
    "sdo_client",
    "simulated_card",
    "start_all",
    "wait_operating",
]
