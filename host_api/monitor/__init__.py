"""What ``cifemu monitor`` knows: the CAN traffic's CANopen meaning (its command line is
``cifemu.commands.monitor``)."""
