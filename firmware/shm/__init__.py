"""``shm``, cifemu's python-can interface over shared memory, in a package of its own [ours].

It is a transport, not a part of the card: the firmware's controller, the simulated
nodes, the tests and the benchmarks all open it through python-can
(``can.Bus(interface="shm")``, registered by the ``can.interface`` entry point in
pyproject.toml), so it sits under ``firmware`` (whose ``__init__`` loads nothing on
import) without depending on the device or the CANopen master. Its timer process
(``python -m firmware.shm.cyclic``) must start within a fraction of a second, which is
why nothing here imports more of the project than ``firmware.frames`` and ``dpm.image``,
and the timer process not even python-can or numpy (``firmware.shm.station``).

- ``firmware.shm.station``: the channel's file and one station's writing side;
- ``firmware.shm.bus``: ``ShmBus``, the interface itself;
- ``firmware.shm.tasks``: cyclic sending, the parent's side;
- ``firmware.shm.cyclic``: the timer process;
- ``firmware.shm.watch``: ``ChannelWatch``, a benchmark's copy of every ring, with numpy.
"""
