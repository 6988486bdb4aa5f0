"""The CAN error model's events in words: fault confinement (error passive, bus-off, recovery) and error frames, as
the engine reports them (kind, fields) in both runtimes."""
from __future__ import annotations

ERROR_PASSIVE_AT = 128
BUS_OFF_ABOVE = 255
RECOVERY_SEQUENCES = 128
RECESSIVE_SEQUENCE_BITS = 11


def event_text(kind: str, f: dict) -> tuple[str, str]:
    """(level, text) of an error-model event of ``kind`` with its fields (from this model or the engine's)."""
    if kind == "bus_off":
        return "ERROR", (f"{f['node']}: bus-off (TEC = {f['tec']} > {BUS_OFF_ABOVE}); {f['lost']} queued frames dropped; "
                         f"recovers after {RECOVERY_SEQUENCES} x {RECESSIVE_SEQUENCE_BITS} recessive bits")
    if kind == "error_passive":
        return "WARN", f"{f['node']}: error passive (TEC = {f['tec']}, REC = {f['rec']})"
    if kind == "error_active":
        return "INFO", f"{f['node']}: error active again (TEC = {f['tec']}, REC = {f['rec']})"
    if kind == "recovered":
        return "INFO", (f"{f['node']}: recovered from bus-off after {f['after_ns'] * 1e-6:.3f} ms "
                        f"({RECOVERY_SEQUENCES} x {RECESSIVE_SEQUENCE_BITS} recessive bits), error active")
    if kind == "error_frame":
        what = "an error flag destroyed" if f["error"] == "error flag" else f"{f['error']} error in"
        return "WARN", (f"error frame: {what} 0x{f['frame_id']:03X} from {f['node']}; the receivers reject it, "
                        "the sender retransmits")
    if kind == "episode":
        by_error = f["by_error"]
        kinds = ", ".join(f"{k} {v}" for k, v in sorted(by_error.items()))
        return "INFO", (f"{sum(by_error.values())} error frames from t = {f['start_ns'] * 1e-9:.4f} s to "
                        f"{f['last_ns'] * 1e-9:.4f} s (bus time): {kinds}")
    raise ValueError(f"unknown CAN error event kind {kind!r}")
