/* FMI 3.0 co-simulation interface around the model core (fmu_model.h). The functions these models do not support
 * (other types, clocks, FMU state, derivatives, model exchange, scheduled execution) are generated as stubs
 * returning fmi3Error (NULL for the other instantiations) by hil/fmi/build.py from fmi3FunctionTypes.h. */
#include <stdlib.h>
#include <string.h>
#include <math.h>
#include "fmi3Functions.h"
#include "fmu_model.h"

typedef enum { INSTANTIATED, INITIALIZING, STEPPING, TERMINATED } Phase;

typedef struct {
    Model model;
    fmi3InstanceEnvironment environment;
    fmi3LogMessageCallback log;
    Phase phase;
    double time;
} Instance;

static fmi3Status fail(Instance *s, const char *message) {
    if (s->log) s->log(s->environment, fmi3Error, "logStatusError", message);
    return fmi3Error;
}

const char *fmi3GetVersion(void) { return fmi3Version; }

fmi3Status fmi3SetDebugLogging(fmi3Instance c, fmi3Boolean on, size_t n, const fmi3String categories[]) {
    (void)c; (void)on; (void)n; (void)categories;
    return fmi3OK;
}

fmi3Instance fmi3InstantiateCoSimulation(fmi3String name, fmi3String token, fmi3String resources,
                                         fmi3Boolean visible, fmi3Boolean logging, fmi3Boolean event_mode,
                                         fmi3Boolean early_return, const fmi3ValueReference required[],
                                         size_t n_required, fmi3InstanceEnvironment environment,
                                         fmi3LogMessageCallback log, fmi3IntermediateUpdateCallback update) {
    (void)name; (void)resources; (void)visible; (void)logging; (void)event_mode; (void)early_return;
    (void)required; (void)n_required; (void)update;
    if (token == NULL || strcmp(token, MODEL_GUID) != 0) {
        if (log) log(environment, fmi3Error, "logStatusError", "instantiation token mismatch");
        return NULL;
    }
    Instance *s = calloc(1, sizeof *s);
    if (!s) return NULL;
    s->environment = environment;
    s->log = log;
    model_defaults(&s->model);
    s->phase = INSTANTIATED;
    return s;
}

void fmi3FreeInstance(fmi3Instance c) { free(c); }

fmi3Status fmi3EnterInitializationMode(fmi3Instance c, fmi3Boolean has_tol, fmi3Float64 tol, fmi3Float64 start,
                                       fmi3Boolean has_stop, fmi3Float64 stop) {
    (void)has_tol; (void)tol; (void)has_stop; (void)stop;
    Instance *s = c;
    s->time = start;
    s->phase = INITIALIZING;
    return fmi3OK;
}

fmi3Status fmi3ExitInitializationMode(fmi3Instance c) {
    Instance *s = c;
    if (model_initialize(&s->model)) return fail(s, s->model.error);
    s->phase = STEPPING;
    return fmi3OK;
}

fmi3Status fmi3EnterStepMode(fmi3Instance c) {
    (void)c;
    return fmi3OK;
}

fmi3Status fmi3Terminate(fmi3Instance c) {
    ((Instance *)c)->phase = TERMINATED;
    return fmi3OK;
}

fmi3Status fmi3Reset(fmi3Instance c) {
    Instance *s = c;
    model_defaults(&s->model);
    s->phase = INSTANTIATED;
    s->time = 0.0;
    return fmi3OK;
}

fmi3Status fmi3GetFloat64(fmi3Instance c, const fmi3ValueReference vr[], size_t n, fmi3Float64 value[],
                          size_t n_values) {
    Instance *s = c;
    if (n_values != n) return fail(s, "fmi3GetFloat64: these models have scalar variables only");
    for (size_t i = 0; i < n; i++) {
        if (vr[i] >= NVARS) return fail(s, "fmi3GetFloat64: unknown value reference");
        value[i] = vr[i] == VR_TIME ? s->time : s->model.v[vr[i]];
    }
    return fmi3OK;
}

fmi3Status fmi3SetFloat64(fmi3Instance c, const fmi3ValueReference vr[], size_t n, const fmi3Float64 value[],
                          size_t n_values) {
    Instance *s = c;
    if (n_values != n) return fail(s, "fmi3SetFloat64: these models have scalar variables only");
    for (size_t i = 0; i < n; i++) {
        if (vr[i] >= NVARS) return fail(s, "fmi3SetFloat64: unknown value reference");
        char kind = VAR_CAUSALITY[vr[i]];
        if (kind == 'o' || kind == 't' || (kind == 'p' && s->phase == STEPPING))
            return fail(s, kind == 'p' ? "fmi3SetFloat64: a parameter is fixed after initialization"
                                       : "fmi3SetFloat64: not an input or parameter");
        s->model.v[vr[i]] = value[i];
    }
    return fmi3OK;
}

fmi3Status fmi3DoStep(fmi3Instance c, fmi3Float64 t, fmi3Float64 h, fmi3Boolean no_set_state,
                      fmi3Boolean *event_needed, fmi3Boolean *terminate, fmi3Boolean *early_return,
                      fmi3Float64 *last_time) {
    (void)no_set_state;
    Instance *s = c;
    *event_needed = fmi3False;
    *terminate = fmi3False;
    *early_return = fmi3False;
    *last_time = t;
    if (s->phase != STEPPING) return fail(s, "fmi3DoStep: not initialized");
    if (!(h > 0.0) || !isfinite(h)) return fail(s, "fmi3DoStep: the step size must be positive");
    if (model_do_step(&s->model, t, h)) return fail(s, s->model.error);
    s->time = t + h;
    *last_time = s->time;
    return fmi3OK;
}
