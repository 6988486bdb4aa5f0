"""ECU firmware: the ECU runtime (cycle, DBC codec, E2E and freshness checks) and the control laws.

Firmware never touches plant state: everything it knows arrives in CAN frames.
"""
