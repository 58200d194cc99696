"""The CANopen services behind the CAN task, one module per service (as canopen does)."""
