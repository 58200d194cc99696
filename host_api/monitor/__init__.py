"""``cifemu monitor``: the CAN traffic with its CANopen meaning (a candump with CANopen)."""
