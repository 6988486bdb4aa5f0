"""Fault injection: a scenario's ``[[faults]]`` schedule, its injectors and its detection report.

schedule.py (triggers), ecu.py, sensor.py, actuator.py, radio.py, bus.py + guardian.py (one injector or monitor
per target), virtual.py and realtime.py (the two runtimes' wiring), report.py (injected vs detected).
See docs/faults.md.
"""
