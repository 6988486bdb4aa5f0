/* What every reference model shares: start values from the generated table. */
#include <string.h>
#include "fmu_model.h"

void model_defaults(Model *m) {
    memcpy(m->v, VAR_START, sizeof m->v);
    m->error[0] = '\0';
}
