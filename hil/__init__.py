"""trainhil rig: CAN bus emulation, radio bridge, plant, runtimes, recording and the CLI."""
__version__ = "0.1.0"
