"""Simulated CANopen nodes from a network description (``cifemu sim``, ``--simulate``).

    from dbm_tools.network import load_network
    from firmware.sim import SimulatedNetwork

    with SimulatedNetwork(load_network("net.toml"), can.Bus(interface="virtual", channel="x")):
        ...  # a master on another bus object of channel "x" sees the nodes boot
"""

from firmware.sim.network import SimulatedNetwork, UnconfiguredSlave, object_dictionary
from firmware.sim.node import SimulatedNode

__all__ = ["SimulatedNetwork", "SimulatedNode", "UnconfiguredSlave", "object_dictionary"]
