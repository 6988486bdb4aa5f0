"""ctypes declarations of the parts of SIL Kit's stable C API (5.0.x, ``silkit/capi/*.h``) the rig uses: participant,
lifecycle and time synchronisation, the system monitor and controller, CAN controllers and the (experimental) network
simulator. Written from the public headers; the layouts follow their ``#pragma pack(8)``, which for these structs
is the natural alignment ctypes uses.

Every versioned struct starts with a ``SilKit_StructHeader`` whose ``version`` says which struct it is
(``SK_ID_MAKE``: 'S', 'K', service, datatype, version); :func:`struct_id` computes it and :func:`new` makes a
struct with its header set, as ``SilKit_Struct_Init`` does in C.
"""
from __future__ import annotations

import ctypes
from ctypes import (CFUNCTYPE, POINTER, Structure, c_char_p, c_int8, c_int16, c_int32, c_size_t, c_uint8, c_uint16,
                    c_uint32, c_uint64, c_void_p)
from typing import Any, TypeVar

ReturnCode = c_int32
NanosecondsTime = c_uint64
SUCCESS = 0

# services and datatypes of the struct headers (InterfaceIdentifiers.h)
SERVICE_CAN, SERVICE_PARTICIPANT, SERVICE_NETWORK_SIMULATION = 1, 7, 8

# lifecycle (Orchestration.h)
OPERATION_MODE_COORDINATED, OPERATION_MODE_AUTONOMOUS = 10, 20
STATE_RUNNING, STATE_STOPPED, STATE_ERROR, STATE_SHUTDOWN = 50, 80, 90, 110  # participant and system states

# CAN (Can.h)
FLAG_IDE, FLAG_RTR, FLAG_FDF, FLAG_BRS, FLAG_ESI = 1 << 9, 1 << 4, 1 << 12, 1 << 13, 1 << 14
TRANSMITTED, CANCELED, TRANSMIT_QUEUE_FULL = 1, 2, 4
DIRECTION_SEND, DIRECTION_RECEIVE = 1, 2
CONTROLLER_UNINIT, CONTROLLER_STOPPED, CONTROLLER_STARTED, CONTROLLER_SLEEP = 0, 1, 2, 3
ERROR_NOT_AVAILABLE, ERROR_ACTIVE, ERROR_PASSIVE, BUS_OFF = 0, 1, 2, 3

# network simulator (NetworkSimulator.h)
NETWORK_CAN = 1


def struct_id(service: int, datatype: int, version: int) -> int:
    """``SK_ID_MAKE``: the header value of a struct."""
    return (83 << 56) | (75 << 48) | ((service & 0xFF) << 40) | ((datatype & 0xFF) << 32) | ((version & 0xFF) << 24)


class StructHeader(Structure):
    _fields_ = [("version", c_uint64), ("_reserved", c_uint64 * 3)]


class ByteVector(Structure):
    _fields_ = [("data", POINTER(c_uint8)), ("size", c_size_t)]


class StringList(Structure):
    _fields_ = [("numStrings", c_size_t), ("strings", POINTER(c_char_p))]


class ParticipantConnectionInformation(Structure):
    ID = struct_id(SERVICE_PARTICIPANT, 4, 1)
    _fields_ = [("structHeader", StructHeader), ("participantName", c_char_p)]


class LifecycleConfiguration(Structure):
    ID = struct_id(SERVICE_PARTICIPANT, 2, 1)
    _fields_ = [("structHeader", StructHeader), ("operationMode", c_int8)]


class WorkflowConfiguration(Structure):
    ID = struct_id(SERVICE_PARTICIPANT, 3, 3)  # SilKit_WorkflowConfiguration: datatype 3, version 3 in 5.0.x
    _fields_ = [("structHeader", StructHeader), ("requiredParticipantNames", POINTER(StringList))]


class CanFrame(Structure):
    ID = struct_id(SERVICE_CAN, 1, 1)
    _fields_ = [("structHeader", StructHeader), ("id", c_uint32), ("flags", c_uint32), ("dlc", c_uint16),
                ("sdt", c_uint8), ("vcid", c_uint8), ("af", c_uint32), ("data", ByteVector)]


class CanFrameEvent(Structure):
    ID = struct_id(SERVICE_CAN, 3, 1)
    _fields_ = [("structHeader", StructHeader), ("timestamp", NanosecondsTime), ("frame", POINTER(CanFrame)),
                ("direction", c_uint8), ("userContext", c_void_p)]


class CanFrameTransmitEvent(Structure):
    ID = struct_id(SERVICE_CAN, 2, 2)
    _fields_ = [("structHeader", StructHeader), ("userContext", c_void_p), ("timestamp", NanosecondsTime),
                ("status", c_int32), ("canId", c_uint32)]


class CanStateChangeEvent(Structure):
    ID = struct_id(SERVICE_CAN, 4, 1)
    _fields_ = [("structHeader", StructHeader), ("timestamp", NanosecondsTime), ("state", c_int32)]


class CanErrorStateChangeEvent(Structure):
    ID = struct_id(SERVICE_CAN, 5, 1)
    _fields_ = [("structHeader", StructHeader), ("timestamp", NanosecondsTime), ("errorState", c_int32)]


S = TypeVar("S", bound=Structure)


def new(cls: type[S], **fields: Any) -> S:
    """A struct with its header's version set (``SilKit_Struct_Init``) and the given fields."""
    value = cls()
    value.structHeader.version = cls.ID  # type: ignore[attr-defined]
    for name, field in fields.items():
        setattr(value, name, field)
    return value


# callbacks (the C API's handler types)
StepHandler = CFUNCTYPE(None, c_void_p, c_void_p, NanosecondsTime, NanosecondsTime)
LifecycleHandler = CFUNCTYPE(None, c_void_p, c_void_p)
AbortHandler = CFUNCTYPE(None, c_void_p, c_void_p, c_int16)
DisconnectedHandler = CFUNCTYPE(None, c_void_p, c_void_p, POINTER(ParticipantConnectionInformation))
CanFrameHandler = CFUNCTYPE(None, c_void_p, c_void_p, POINTER(CanFrameEvent))
CanTransmitHandler = CFUNCTYPE(None, c_void_p, c_void_p, POINTER(CanFrameTransmitEvent))
CanStateHandler = CFUNCTYPE(None, c_void_p, c_void_p, POINTER(CanStateChangeEvent))
CanErrorStateHandler = CFUNCTYPE(None, c_void_p, c_void_p, POINTER(CanErrorStateChangeEvent))

_P = c_void_p
_PP = POINTER(c_void_p)
PROTOTYPES: dict[str, list[Any]] = {
    "SilKit_GetLastErrorString": [],
    "SilKit_ParticipantConfiguration_FromString": [_PP, c_char_p],
    "SilKit_ParticipantConfiguration_Destroy": [_P],
    "SilKit_Participant_Create": [_PP, _P, c_char_p, c_char_p],
    "SilKit_Participant_Destroy": [_P],
    "SilKit_LifecycleService_Create": [_PP, _P, POINTER(LifecycleConfiguration)],
    "SilKit_LifecycleService_StartLifecycle": [_P],
    "SilKit_LifecycleService_WaitForLifecycleToComplete": [_P, POINTER(c_int16)],
    "SilKit_LifecycleService_Stop": [_P, c_char_p],
    "SilKit_LifecycleService_ReportError": [_P, c_char_p],
    "SilKit_LifecycleService_SetStopHandler": [_P, _P, LifecycleHandler],
    "SilKit_LifecycleService_SetAbortHandler": [_P, _P, AbortHandler],
    "SilKit_TimeSyncService_Create": [_PP, _P],
    "SilKit_TimeSyncService_SetSimulationStepHandler": [_P, _P, StepHandler, NanosecondsTime],
    "SilKit_SystemMonitor_Create": [_PP, _P],
    "SilKit_SystemMonitor_SetParticipantDisconnectedHandler": [_P, _P, DisconnectedHandler],
    "SilKit_SystemMonitor_GetSystemState": [POINTER(c_int16), _P],
    "SilKit_Experimental_SystemController_Create": [_PP, _P],
    "SilKit_Experimental_SystemController_SetWorkflowConfiguration": [_P, POINTER(WorkflowConfiguration)],
    "SilKit_Experimental_SystemController_AbortSimulation": [_P],
    "SilKit_CanController_Create": [_PP, _P, c_char_p, c_char_p],
    "SilKit_CanController_SetBaudRate": [_P, c_uint32, c_uint32, c_uint32],
    "SilKit_CanController_Start": [_P],
    "SilKit_CanController_Stop": [_P],
    "SilKit_CanController_SendFrame": [_P, POINTER(CanFrame), _P],
    "SilKit_CanController_AddFrameHandler": [_P, _P, CanFrameHandler, c_uint8, POINTER(c_uint64)],
    "SilKit_CanController_AddFrameTransmitHandler": [_P, _P, CanTransmitHandler, c_int32, POINTER(c_uint64)],
    "SilKit_CanController_AddStateChangeHandler": [_P, _P, CanStateHandler, POINTER(c_uint64)],
    "SilKit_CanController_AddErrorStateChangeHandler": [_P, _P, CanErrorStateHandler, POINTER(c_uint64)],
}


class SilKitError(RuntimeError):
    """A C API call returned an error; the message names the call and SIL Kit's last error string."""


class Library:
    """libSilKit.so with the prototypes above; ``call(name, *args)`` raises SilKitError on a non-zero return."""

    def __init__(self, path: str) -> None:
        self.dll = ctypes.CDLL(path)
        for name, argtypes in PROTOTYPES.items():
            function = getattr(self.dll, name)
            function.argtypes = argtypes
            function.restype = c_char_p if name == "SilKit_GetLastErrorString" else ReturnCode

    def call(self, name: str, *args: Any) -> None:
        code = getattr(self.dll, name)(*args)
        if code != SUCCESS:
            last = self.dll.SilKit_GetLastErrorString() or b""
            raise SilKitError(f"{name} failed (return code {code}): {last.decode('utf-8', 'replace')}")


# --------------------------------------------------------------------------- network simulator (experimental API)


class EventReceivers(Structure):
    ID = struct_id(SERVICE_NETWORK_SIMULATION, 1, 1)
    _fields_ = [("structHeader", StructHeader), ("numReceivers", c_size_t),
                ("controllerDescriptors", POINTER(c_uint64))]


class NetSimCanFrameRequest(Structure):
    ID = struct_id(SERVICE_NETWORK_SIMULATION, 9, 1)
    _fields_ = [("structHeader", StructHeader), ("frame", POINTER(CanFrame)), ("userContext", c_void_p)]


class NetSimCanConfigureBaudrate(Structure):
    ID = struct_id(SERVICE_NETWORK_SIMULATION, 7, 1)
    _fields_ = [("structHeader", StructHeader), ("rate", c_uint32), ("fdRate", c_uint32), ("xlRate", c_uint32)]


class NetSimCanControllerMode(Structure):
    ID = struct_id(SERVICE_NETWORK_SIMULATION, 8, 1)
    _fields_ = [("structHeader", StructHeader), ("canControllerModeFlags", c_int32), ("state", c_int32)]


ProvideController = CFUNCTYPE(None, POINTER(c_void_p), POINTER(c_void_p), c_uint64, c_void_p)
ControllerRemoved = CFUNCTYPE(None, c_uint64, c_void_p)
SetEventProducer = CFUNCTYPE(None, c_void_p, c_void_p)
OnSetBaudrate = CFUNCTYPE(None, c_void_p, POINTER(NetSimCanConfigureBaudrate))
OnFrameRequest = CFUNCTYPE(None, c_void_p, POINTER(NetSimCanFrameRequest))
OnSetControllerMode = CFUNCTYPE(None, c_void_p, POINTER(NetSimCanControllerMode))


class SimulatedNetworkFunctions(Structure):
    ID = struct_id(SERVICE_NETWORK_SIMULATION, 2, 1)
    _fields_ = [("structHeader", StructHeader), ("ProvideSimulatedController", ProvideController),
                ("SimulatedControllerRemoved", ControllerRemoved), ("SetEventProducer", SetEventProducer)]


class SimulatedCanControllerFunctions(Structure):
    ID = struct_id(SERVICE_NETWORK_SIMULATION, 3, 1)
    _fields_ = [("structHeader", StructHeader), ("OnSetBaudrate", OnSetBaudrate), ("OnFrameRequest", OnFrameRequest),
                ("OnSetControllerMode", OnSetControllerMode)]


PROTOTYPES.update({
    "SilKit_Experimental_NetworkSimulator_Create": [_PP, _P],
    "SilKit_Experimental_NetworkSimulator_SimulateNetwork": [_P, c_char_p, c_uint32, _P,
                                                              POINTER(SimulatedNetworkFunctions)],
    "SilKit_Experimental_NetworkSimulator_Start": [_P],
    "SilKit_Experimental_CanEventProducer_Produce": [_P, POINTER(StructHeader), POINTER(EventReceivers)],
})
