"""How the emulator's processes tune CPython: the card's firmware and the simulated nodes.

Both run many threads that hand the interpreter lock around thousands of times a second,
so both set the same switch interval. It lives apart from either process's command line,
so the simulator does not import the card's to get it.
"""

from __future__ import annotations

SWITCH_INTERVAL = 0.0002
"""Seconds a thread may hold the interpreter lock while another waits for it (CPython's
default is 5 ms). The SYNC producer must not wait that long for its turn, and at full
PDO load the receive thread, the CAN tick and the device loop hand the lock around
thousands of times a second: ``python -m bench.can --only throughput`` measured
11,400 PDO frames/s at 5 ms, 12,500 at 0.5 ms, 15,000-21,000 at 0.2 ms, 19,000 at 0.1 ms."""
