"""DBM configuration databases and the CAN task's data sets, as pure byte codecs.

- errors: DbmError and the msg.f texts of the data checks;
- container: the DBM file / data-area container (read, write, build);
- parameters: node, bus and extended bus parameter data sets (shared with the firmware);
- tables: the other CANopen table records (GLOBAL, PLC_PARAM, PROJEKT, DESCRIPT, NODES);
- validate: the COM_Download data checks and the whole-database check.
"""
