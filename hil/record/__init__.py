"""Recording: the in-memory run log, metrics, the rerun .rrd writer and CAN logs."""
