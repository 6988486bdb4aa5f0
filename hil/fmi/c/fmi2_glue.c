/* FMI 2.0 co-simulation interface around the model core (fmu_model.h). Functions a co-simulation master may call
 * but these models do not support (FMU state, derivatives, asynchronous steps) are generated as stubs returning
 * fmi2Error by hil/fmi/build.py from fmi2FunctionTypes.h. */
#include <stdlib.h>
#include <string.h>
#include <math.h>
#include "fmi2Functions.h"
#include "fmu_model.h"

typedef enum { INSTANTIATED, INITIALIZING, STEPPING, TERMINATED } Phase;

typedef struct {
    Model model;
    fmi2CallbackFunctions callbacks;
    char name[128];
    Phase phase;
    double time;
} Instance;

static fmi2Status fail(Instance *s, const char *message) {
    /* The logger is printf-like: pass the text as an argument so a '%' in it is not read as a format. */
    if (s->callbacks.logger)
        s->callbacks.logger(s->callbacks.componentEnvironment, s->name, fmi2Error, "logStatusError", "%s", message);
    return fmi2Error;
}

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean on, size_t n, const fmi2String categories[]) {
    (void)c; (void)on; (void)n; (void)categories;
    return fmi2OK;
}

fmi2Component fmi2Instantiate(fmi2String name, fmi2Type type, fmi2String guid, fmi2String resources,
                              const fmi2CallbackFunctions *functions, fmi2Boolean visible, fmi2Boolean logging) {
    (void)resources; (void)visible; (void)logging;
    if (type != fmi2CoSimulation || guid == NULL || strcmp(guid, MODEL_GUID) != 0) {
        if (functions && functions->logger)
            functions->logger(functions->componentEnvironment, name, fmi2Error, "logStatusError", "%s",
                              type != fmi2CoSimulation ? "only co-simulation is supported" : "GUID mismatch");
        return NULL;
    }
    Instance *s = calloc(1, sizeof *s);
    if (!s) return NULL;
    if (functions) s->callbacks = *functions;
    strncpy(s->name, name ? name : MODEL_IDENTIFIER, sizeof s->name - 1);
    model_defaults(&s->model);
    s->phase = INSTANTIATED;
    return s;
}

void fmi2FreeInstance(fmi2Component c) { free(c); }

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean has_tol, fmi2Real tol, fmi2Real start,
                               fmi2Boolean has_stop, fmi2Real stop) {
    (void)has_tol; (void)tol; (void)has_stop; (void)stop;
    ((Instance *)c)->time = start;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) {
    ((Instance *)c)->phase = INITIALIZING;
    return fmi2OK;
}

fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    Instance *s = c;
    if (model_initialize(&s->model)) return fail(s, s->model.error);
    s->phase = STEPPING;
    return fmi2OK;
}

fmi2Status fmi2Terminate(fmi2Component c) {
    ((Instance *)c)->phase = TERMINATED;
    return fmi2OK;
}

fmi2Status fmi2Reset(fmi2Component c) {
    Instance *s = c;
    model_defaults(&s->model);
    s->phase = INSTANTIATED;
    s->time = 0.0;
    return fmi2OK;
}

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Real value[]) {
    Instance *s = c;
    for (size_t i = 0; i < n; i++) {
        if (vr[i] >= NVARS) return fail(s, "fmi2GetReal: unknown value reference");
        value[i] = vr[i] == VR_TIME ? s->time : s->model.v[vr[i]];
    }
    return fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Real value[]) {
    Instance *s = c;
    for (size_t i = 0; i < n; i++) {
        if (vr[i] >= NVARS) return fail(s, "fmi2SetReal: unknown value reference");
        char kind = VAR_CAUSALITY[vr[i]];
        if (kind == 'o' || kind == 't' || (kind == 'p' && s->phase == STEPPING))
            return fail(s, kind == 'p' ? "fmi2SetReal: a parameter is fixed after initialization"
                                       : "fmi2SetReal: not an input or parameter");
        s->model.v[vr[i]] = value[i];
    }
    return fmi2OK;
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Integer value[]) {
    (void)vr; (void)value;
    return n ? fail(c, "fmi2GetInteger: this model has no Integer variables") : fmi2OK;
}
fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Integer value[]) {
    (void)vr; (void)value;
    return n ? fail(c, "fmi2SetInteger: this model has no Integer variables") : fmi2OK;
}
fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Boolean value[]) {
    (void)vr; (void)value;
    return n ? fail(c, "fmi2GetBoolean: this model has no Boolean variables") : fmi2OK;
}
fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Boolean value[]) {
    (void)vr; (void)value;
    return n ? fail(c, "fmi2SetBoolean: this model has no Boolean variables") : fmi2OK;
}
fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2String value[]) {
    (void)vr; (void)value;
    return n ? fail(c, "fmi2GetString: this model has no String variables") : fmi2OK;
}
fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2String value[]) {
    (void)vr; (void)value;
    return n ? fail(c, "fmi2SetString: this model has no String variables") : fmi2OK;
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real t, fmi2Real h, fmi2Boolean no_set_state) {
    (void)no_set_state;
    Instance *s = c;
    if (s->phase != STEPPING) return fail(s, "fmi2DoStep: not initialized");
    if (!(h > 0.0) || !isfinite(h)) return fail(s, "fmi2DoStep: the step size must be positive");
    if (model_do_step(&s->model, t, h)) return fail(s, s->model.error);
    s->time = t + h;
    return fmi2OK;
}

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind kind, fmi2Status *value) {
    (void)c; (void)kind;
    *value = fmi2OK;
    return fmi2OK;
}
