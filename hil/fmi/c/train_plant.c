/* The train group's longitudinal dynamics as an FMU: the same multi-unit coupled model as hil/plant/dynamics.py,
 * integrated by its own classical Runge-Kutta (RK4) with `substeps` steps per communication step.
 *
 *   m_eff a = F + dist - m (c0 sgn v + c1 v + c2 v|v|) - m grade - m curve sgn v + coupler forces
 *
 * per unit (grade and curve in N/kg, as hil/plant/dynamics.py's track lookup gives them); a coupler joins adjacent
 * units of one train: e = x_front - x_rear - length_front, f = k e + d de/dt pulls the front unit back and the rear
 * one forward. The inputs are held over the step (zero-order hold); the outputs after a step are the state at its
 * end, a the mean acceleration over it and e each coupler's displacement. Absolute positions are integrated, so e
 * carries the rounding of x (ulp(x) = 1.5e-11 m at 100 km), unlike the built-in plant's rest-relative coordinates. */
#include <math.h>
#include <stdio.h>
#include "fmu_model.h"

#define P(name, i) (m->v[VR_##name + (i)])

int model_initialize(Model *m) {
    for (int i = 0; i < N_UNITS; i++) {
        if (!(P(M_EFF, i) > 0.0) || !(P(M, i) > 0.0)) {
            snprintf(m->error, sizeof m->error, "m[%d] and m_eff[%d] must be positive masses (kg)", i + 1, i + 1);
            return 1;
        }
        P(X, i) = P(X0, i);
        P(V, i) = P(V0, i);
        P(A, i) = 0.0;
    }
    for (int t = 0, j = 0; t < N_TRAINS; t++)
        for (int k = 0; k < UNITS_PER_TRAIN - 1; k++, j++) {
            int front = t * UNITS_PER_TRAIN + k;
            P(E, j) = P(X, front) - P(X, front + 1) - P(LENGTH, front);
        }
    return 0;
}

static double sgn(double v) { return (v > 0.0) - (v < 0.0); }

/* dx = v, dv = net force / m_eff for the state (x, v), the inputs held. */
static void derivatives(const Model *m, const double *x, const double *v, double *dx, double *dv) {
    double force[N_UNITS];
    for (int i = 0; i < N_UNITS; i++) {
        double mass = P(M, i), s = sgn(v[i]);
        force[i] = P(F, i) + P(DIST, i) - mass * P(GRADE, i)
                   - mass * ((P(C0, i) + P(CURVE, i)) * s + P(C1, i) * v[i] + P(C2, i) * v[i] * fabs(v[i]));
    }
    for (int t = 0; t < N_TRAINS; t++)
        for (int k = 0; k < UNITS_PER_TRAIN - 1; k++) {
            int front = t * UNITS_PER_TRAIN + k, rear = front + 1;
            double e = x[front] - x[rear] - P(LENGTH, front);
            double f = P(K, 0) * e + P(D, 0) * (v[front] - v[rear]);
            force[front] -= f;
            force[rear] += f;
        }
    for (int i = 0; i < N_UNITS; i++) {
        dx[i] = v[i];
        dv[i] = force[i] / P(M_EFF, i);
    }
}

static void rk4(const Model *m, double *x, double *v, double h) {
    double k1x[N_UNITS], k1v[N_UNITS], k2x[N_UNITS], k2v[N_UNITS], k3x[N_UNITS], k3v[N_UNITS];
    double k4x[N_UNITS], k4v[N_UNITS], tx[N_UNITS], tv[N_UNITS];
    derivatives(m, x, v, k1x, k1v);
    for (int i = 0; i < N_UNITS; i++) { tx[i] = x[i] + 0.5 * h * k1x[i]; tv[i] = v[i] + 0.5 * h * k1v[i]; }
    derivatives(m, tx, tv, k2x, k2v);
    for (int i = 0; i < N_UNITS; i++) { tx[i] = x[i] + 0.5 * h * k2x[i]; tv[i] = v[i] + 0.5 * h * k2v[i]; }
    derivatives(m, tx, tv, k3x, k3v);
    for (int i = 0; i < N_UNITS; i++) { tx[i] = x[i] + h * k3x[i]; tv[i] = v[i] + h * k3v[i]; }
    derivatives(m, tx, tv, k4x, k4v);
    for (int i = 0; i < N_UNITS; i++) {
        x[i] += h / 6.0 * (k1x[i] + 2.0 * k2x[i] + 2.0 * k3x[i] + k4x[i]);
        v[i] += h / 6.0 * (k1v[i] + 2.0 * k2v[i] + 2.0 * k3v[i] + k4v[i]);
    }
}

int model_do_step(Model *m, double t, double h) {
    int substeps = (int)P(SUBSTEPS, 0);
    if (substeps < 1 || substeps > 10000) {
        snprintf(m->error, sizeof m->error, "substeps = %g: expected a whole number 1..10000", P(SUBSTEPS, 0));
        return 1;
    }
    double x[N_UNITS], v[N_UNITS], v_start[N_UNITS];
    for (int i = 0; i < N_UNITS; i++) { x[i] = P(X, i); v[i] = v_start[i] = P(V, i); }
    for (int s = 0; s < substeps; s++) rk4(m, x, v, h / substeps);
    for (int i = 0; i < N_UNITS; i++) {
        if (!isfinite(x[i]) || !isfinite(v[i])) {
            snprintf(m->error, sizeof m->error, "the state of unit %d diverged at t = %.6f s (x = %g m, v = %g m/s)",
                     i + 1, t + h, x[i], v[i]);
            return 1;
        }
        P(X, i) = x[i];
        P(V, i) = v[i];
        P(A, i) = (v[i] - v_start[i]) / h;
    }
    for (int tr = 0, j = 0; tr < N_TRAINS; tr++)
        for (int k = 0; k < UNITS_PER_TRAIN - 1; k++, j++) {
            int front = tr * UNITS_PER_TRAIN + k;
            P(E, j) = x[front] - x[front + 1] - P(LENGTH, front);
        }
    return 0;
}
