/* The part of Vector SIL Kit's C API (5.0.x, the silkit/capi headers, MIT) this example uses, declared from the public
 * documentation so that the example builds against the libSilKit.so of the silkit-py wheel, which ships no
 * headers. With SIL Kit's own headers at hand, `#include "silkit/capi/SilKit.h"` replaces this file. */
#ifndef SILKIT_CAPI_SUBSET_H
#define SILKIT_CAPI_SUBSET_H
#include <stddef.h>
#include <stdint.h>

typedef int32_t SilKit_ReturnCode;
typedef uint64_t SilKit_NanosecondsTime;
typedef uint8_t SilKit_Bool;
typedef int16_t SilKit_ParticipantState;
typedef struct SilKit_ParticipantConfiguration SilKit_ParticipantConfiguration;
typedef struct SilKit_Participant SilKit_Participant;
typedef struct SilKit_LifecycleService SilKit_LifecycleService;
typedef struct SilKit_TimeSyncService SilKit_TimeSyncService;
typedef struct SilKit_CanController SilKit_CanController;

typedef struct { uint64_t version; uint64_t _reserved[3]; } SilKit_StructHeader;
typedef struct { const uint8_t *data; size_t size; } SilKit_ByteVector;

/* SK_ID_MAKE(service, datatype, version) */
#define SK_ID(service, datatype, version) \
    (((uint64_t)83 << 56) | ((uint64_t)75 << 48) | ((uint64_t)(service) << 40) | ((uint64_t)(datatype) << 32) | \
     ((uint64_t)(version) << 24))
#define SilKit_CanFrame_STRUCT_VERSION SK_ID(1, 1, 1)
#define SilKit_LifecycleConfiguration_STRUCT_VERSION SK_ID(7, 2, 1)
#define SilKit_OperationMode_Coordinated 10
#define SilKit_Direction_Receive 2

typedef struct {
    SilKit_StructHeader structHeader;
    uint32_t id;
    uint32_t flags;
    uint16_t dlc;
    uint8_t sdt;
    uint8_t vcid;
    uint32_t af;
    SilKit_ByteVector data;
} SilKit_CanFrame;

typedef struct {
    SilKit_StructHeader structHeader;
    SilKit_NanosecondsTime timestamp;
    SilKit_CanFrame *frame;
    uint8_t direction;
    void *userContext;
} SilKit_CanFrameEvent;

typedef struct {
    SilKit_StructHeader structHeader;
    int8_t operationMode;
} SilKit_LifecycleConfiguration;

typedef void (*SilKit_CanFrameHandler_t)(void *context, SilKit_CanController *controller, SilKit_CanFrameEvent *event);
typedef void (*SilKit_TimeSyncService_SimulationStepHandler_t)(void *context, SilKit_TimeSyncService *service,
                                                               SilKit_NanosecondsTime now,
                                                               SilKit_NanosecondsTime duration);

SilKit_ReturnCode SilKit_ParticipantConfiguration_FromString(SilKit_ParticipantConfiguration **out, const char *text);
SilKit_ReturnCode SilKit_Participant_Create(SilKit_Participant **out, SilKit_ParticipantConfiguration *config,
                                            const char *name, const char *registryUri);
SilKit_ReturnCode SilKit_Participant_Destroy(SilKit_Participant *participant);
SilKit_ReturnCode SilKit_LifecycleService_Create(SilKit_LifecycleService **out, SilKit_Participant *participant,
                                                 const SilKit_LifecycleConfiguration *config);
SilKit_ReturnCode SilKit_LifecycleService_StartLifecycle(SilKit_LifecycleService *service);
SilKit_ReturnCode SilKit_LifecycleService_WaitForLifecycleToComplete(SilKit_LifecycleService *service,
                                                                     SilKit_ParticipantState *outState);
SilKit_ReturnCode SilKit_TimeSyncService_Create(SilKit_TimeSyncService **out, SilKit_LifecycleService *lifecycle);
SilKit_ReturnCode SilKit_TimeSyncService_SetSimulationStepHandler(
    SilKit_TimeSyncService *service, void *context, SilKit_TimeSyncService_SimulationStepHandler_t handler,
    SilKit_NanosecondsTime initialStepSize);
SilKit_ReturnCode SilKit_CanController_Create(SilKit_CanController **out, SilKit_Participant *participant,
                                              const char *name, const char *network);
SilKit_ReturnCode SilKit_CanController_SetBaudRate(SilKit_CanController *controller, uint32_t rate, uint32_t fdRate,
                                                   uint32_t xlRate);
SilKit_ReturnCode SilKit_CanController_Start(SilKit_CanController *controller);
SilKit_ReturnCode SilKit_CanController_SendFrame(SilKit_CanController *controller, SilKit_CanFrame *frame,
                                                 void *userContext);
SilKit_ReturnCode SilKit_CanController_AddFrameHandler(SilKit_CanController *controller, void *context,
                                                       SilKit_CanFrameHandler_t handler, uint8_t directionMask,
                                                       uint64_t *outHandlerId);
const char *SilKit_GetLastErrorString(void);
#endif
