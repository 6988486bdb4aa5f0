"""A SIL Kit participant driven from Python: coordinated lifecycle, virtual-time steps, CAN controllers.

The C API calls handlers on SIL Kit's own threads; ctypes takes the GIL for them. The objects below keep every
callback and struct they hand to C alive as long as the participant."""
from __future__ import annotations

import ctypes
import threading
from collections.abc import Callable
from typing import Any

from hil.silkit import capi
from hil.silkit.capi import Library


class CanController:
    """One CAN controller of a participant on a named network (``bus1``)."""

    def __init__(self, participant: "Participant", name: str, network: str) -> None:
        self.lib, self.participant = participant.lib, participant
        self.handle = ctypes.c_void_p()
        self.lib.call("SilKit_CanController_Create", ctypes.byref(self.handle), participant.handle, name.encode(),
                      network.encode())
        self._keep: list[Any] = []

    def set_baud_rate(self, rate: int, fd_rate: int = 0, xl_rate: int = 0) -> None:
        self.lib.call("SilKit_CanController_SetBaudRate", self.handle, rate, fd_rate, xl_rate)

    def start(self) -> None:
        self.lib.call("SilKit_CanController_Start", self.handle)

    def send(self, can_id: int, data: bytes, flags: int = 0) -> None:
        """Request the transmission of one frame (the acknowledgement comes to ``on_transmit``)."""
        buffer = (ctypes.c_uint8 * max(1, len(data))).from_buffer_copy(data.ljust(1, b"\0"))
        frame = capi.new(capi.CanFrame, id=can_id, flags=flags, dlc=len(data),
                         data=capi.ByteVector(ctypes.cast(buffer, ctypes.POINTER(ctypes.c_uint8)), len(data)))
        self.lib.call("SilKit_CanController_SendFrame", self.handle, ctypes.byref(frame), None)

    def on_frame(self, handler: Callable[[int, int, bytes, int], None], directions: int = capi.DIRECTION_RECEIVE) -> None:
        """``handler(timestamp_ns, can_id, data, flags)`` for every frame in ``directions``."""
        def callback(context: Any, controller: Any, event: Any) -> None:
            e = event.contents
            f = e.frame.contents
            handler(int(e.timestamp), int(f.id), ctypes.string_at(f.data.data, f.data.size), int(f.flags))

        self._add("SilKit_CanController_AddFrameHandler", capi.CanFrameHandler(callback), directions)

    def on_transmit(self, handler: Callable[[int, int, int], None], mask: int = 0x7) -> None:
        """``handler(timestamp_ns, can_id, status)`` for every transmit acknowledgement in ``mask``."""
        def callback(context: Any, controller: Any, event: Any) -> None:
            e = event.contents
            handler(int(e.timestamp), int(e.canId), int(e.status))

        self._add("SilKit_CanController_AddFrameTransmitHandler", capi.CanTransmitHandler(callback), mask)

    def on_error_state(self, handler: Callable[[int, int], None]) -> None:
        """``handler(timestamp_ns, error_state)`` on every error-state change."""
        def callback(context: Any, controller: Any, event: Any) -> None:
            handler(int(event.contents.timestamp), int(event.contents.errorState))

        self._add("SilKit_CanController_AddErrorStateChangeHandler", capi.CanErrorStateHandler(callback))

    def _add(self, name: str, callback: Any, *mask: int) -> None:
        self._keep.append(callback)
        handler_id = ctypes.c_uint64()
        self.lib.call(name, self.handle, None, callback, *mask, ctypes.byref(handler_id))


class Participant:
    """A participant with a coordinated (or autonomous) lifecycle and a time-sync service stepping ``step_ns``."""

    def __init__(self, lib: Library, name: str, registry_uri: str, *, coordinated: bool = True,
                 config: str = "") -> None:
        self.lib, self.name = lib, name
        self._config = ctypes.c_void_p()
        lib.call("SilKit_ParticipantConfiguration_FromString", ctypes.byref(self._config), config.encode())
        self.handle = ctypes.c_void_p()
        lib.call("SilKit_Participant_Create", ctypes.byref(self.handle), self._config, name.encode(),
                 registry_uri.encode())
        mode = capi.OPERATION_MODE_COORDINATED if coordinated else capi.OPERATION_MODE_AUTONOMOUS
        self._lifecycle_config = capi.new(capi.LifecycleConfiguration, operationMode=mode)
        self.lifecycle = ctypes.c_void_p()
        lib.call("SilKit_LifecycleService_Create", ctypes.byref(self.lifecycle), self.handle,
                 ctypes.byref(self._lifecycle_config))
        self.time_sync = ctypes.c_void_p()
        lib.call("SilKit_TimeSyncService_Create", ctypes.byref(self.time_sync), self.lifecycle)
        self._keep: list[Any] = []
        self._system_controller: ctypes.c_void_p | None = None
        self._monitor: ctypes.c_void_p | None = None

    def can_controller(self, name: str, network: str) -> CanController:
        return CanController(self, name, network)

    def require(self, names: list[str]) -> None:
        """Be the system controller: the simulation starts when every participant named here has joined."""
        controller = ctypes.c_void_p()
        self.lib.call("SilKit_Experimental_SystemController_Create", ctypes.byref(controller), self.handle)
        strings = (ctypes.c_char_p * len(names))(*[n.encode() for n in names])
        names_list = capi.StringList(len(names), strings)
        workflow = capi.new(capi.WorkflowConfiguration, requiredParticipantNames=ctypes.pointer(names_list))
        self._keep += [controller, strings, names_list, workflow]
        self._system_controller = controller
        self.lib.call("SilKit_Experimental_SystemController_SetWorkflowConfiguration", controller,
                      ctypes.byref(workflow))

    def on_step(self, handler: Callable[[int, int], None], step_ns: int) -> None:
        """``handler(now_ns, duration_ns)`` at every simulation step (synchronous: the next step waits for it)."""
        def callback(context: Any, service: Any, now: int, duration: int) -> None:
            handler(int(now), int(duration))

        step = capi.StepHandler(callback)
        self._keep.append(step)
        self.lib.call("SilKit_TimeSyncService_SetSimulationStepHandler", self.time_sync, None, step, step_ns)

    def abort(self) -> None:
        """As the system controller: abort the whole simulation (every participant's lifecycle ends)."""
        if self._system_controller is not None:
            self.lib.call("SilKit_Experimental_SystemController_AbortSimulation", self._system_controller)

    def stop(self, reason: str) -> None:
        self.lib.call("SilKit_LifecycleService_Stop", self.lifecycle, reason.encode())

    def halt(self, reason: str) -> None:
        """Stop the lifecycle in whatever state it is; before it runs (a stop is refused then), abort it."""
        try:
            self.stop(reason)
        except capi.SilKitError:
            self.abort()

    def _system_monitor(self) -> ctypes.c_void_p:
        if self._monitor is None:
            self._monitor = ctypes.c_void_p()
            self.lib.call("SilKit_SystemMonitor_Create", ctypes.byref(self._monitor), self.handle)
        return self._monitor

    def system_state(self) -> int:
        """SIL Kit's system state (``capi.STATE_*``): ``STATE_ERROR`` once a participant was lost, for instance."""
        state = ctypes.c_int16()
        self.lib.call("SilKit_SystemMonitor_GetSystemState", ctypes.byref(state), self._system_monitor())
        return int(state.value)

    def on_disconnected(self, handler: Callable[[str], None]) -> None:
        """``handler(name)`` when another participant leaves (shut down, or its connection lost: killed, crashed)."""
        monitor = self._system_monitor()

        def callback(context: Any, system_monitor: Any, info: Any) -> None:
            handler((info.contents.participantName or b"").decode("utf-8", "replace"))

        disconnected = capi.DisconnectedHandler(callback)
        self._keep.append(disconnected)
        self.lib.call("SilKit_SystemMonitor_SetParticipantDisconnectedHandler", monitor, None, disconnected)

    def run(self, poll: Callable[[], None] | None = None, poll_s: float = 0.1) -> int:
        """Start the lifecycle and wait until it completes; returns the final participant state.

        SIL Kit's wait blocks in C, where Python cannot deliver a signal; it therefore runs on a helper thread and
        this one wakes every ``poll_s`` to call ``poll``, so Ctrl-C (KeyboardInterrupt) and other checks reach the
        caller during a run. On KeyboardInterrupt the lifecycle is stopped, and its end awaited, before it is
        re-raised."""
        self.lib.call("SilKit_LifecycleService_StartLifecycle", self.lifecycle)
        state = ctypes.c_int16()
        errors: list[BaseException] = []

        def wait() -> None:
            try:
                self.lib.call("SilKit_LifecycleService_WaitForLifecycleToComplete", self.lifecycle,
                              ctypes.byref(state))
            except BaseException as exc:  # raised in the caller's thread below
                errors.append(exc)

        waiter = threading.Thread(target=wait, name=f"silkit-lifecycle-{self.name}", daemon=True)
        waiter.start()
        try:
            while waiter.is_alive():
                waiter.join(poll_s)
                if poll is not None and waiter.is_alive():
                    poll()
        except KeyboardInterrupt:
            self.halt("interrupted (Ctrl-C or a stop signal)")
            waiter.join()
            raise
        if errors:
            raise errors[0]
        return int(state.value)

    def close(self) -> None:
        if self.handle:
            self.lib.call("SilKit_Participant_Destroy", self.handle)
            self.handle = ctypes.c_void_p()
        if self._config:
            self.lib.call("SilKit_ParticipantConfiguration_Destroy", self._config)
            self._config = ctypes.c_void_p()
