/* Seed 000's ordinary consensus baseline (ecu_sim/controllers/consensus.py) as an FMU, for one power unit:
 *
 *   u = R(v) + sum_q w_q [kx (x~_q - x~_self) + kv (v_q - v_self)] - a_ref [kx_ref x~ + kv_ref v~],  F = m u
 *
 * with (kx, kv) = intra gains for the coupled units, inter gains for the radio neighbours while the gap error is at
 * most radio_range - spacing; k_hat (coupler stiffness / mass, 0 by default) cancels the physical coupler. Each neighbour slot (intra/inter, ahead/behind) has its x, v, valid flag (1/0),
 * degraded-mode weight and slot offset as inputs. The emergency rule and the input checks stay in the firmware
 * around the FMU (ecu_sim/controllers/fmu_law.py). The command is computed in the step from the inputs held over it
 * and read after it. */
#include <math.h>
#include <stdio.h>
#include "fmu_model.h"

#define P(name) (m->v[VR_##name])

int model_initialize(Model *m) {
    if (!(P(MASS) > 0.0)) {
        snprintf(m->error, sizeof m->error, "mass = %g: expected a positive mass (kg)", P(MASS));
        return 1;
    }
    P(FORCE) = 0.0;
    P(ACCEL) = 0.0;
    return 0;
}

/* One neighbour slot's contribution: its inputs are laid out x, v, valid, weight, offset from `base`. */
static double neighbour(const Model *m, int base, double kx, double kv, int inter) {
    const double *s = &m->v[base];
    if (s[2] < 0.5) return 0.0;
    double delta = (s[0] - P(X)) + (s[4] - P(OFFSET)), dv = s[1] - P(V);
    if (inter) {
        double gap_error = base == VR_INTER_AHEAD_X ? delta : -delta;
        if (gap_error > P(RADIO_RANGE) - P(SPACING)) return 0.0;
    }
    return s[3] * (kx * delta + kv * dv);
}

int model_do_step(Model *m, double t, double h) {
    (void)h;
    double v = P(V);
    double u = P(C0) + P(C1) * v + P(C2) * v * v;
    u += neighbour(m, VR_INTRA_AHEAD_X, P(KX_INTRA) - P(K_HAT), P(KV_INTRA), 0);
    u += neighbour(m, VR_INTRA_BEHIND_X, P(KX_INTRA) - P(K_HAT), P(KV_INTRA), 0);
    u += neighbour(m, VR_INTER_AHEAD_X, P(KX_INTER), P(KV_INTER), 1);
    u += neighbour(m, VR_INTER_BEHIND_X, P(KX_INTER), P(KV_INTER), 1);
    if (P(HAS_REFERENCE) > 0.5 && P(REF_VALID) > 0.5)
        u -= P(KX_REF) * (P(X) - (P(REF_X) - P(OFFSET))) + P(KV_REF) * (v - P(REF_V));
    if (!isfinite(u)) {
        snprintf(m->error, sizeof m->error, "the command is not finite at t = %.6f s", t);
        return 1;
    }
    P(ACCEL) = u;
    P(FORCE) = P(MASS) * u;
    return 0;
}
