/* A reference external ECU as a Vector SIL Kit participant, in C against SIL Kit's C API, importing nothing of
 * trainhil, as a board's firmware would not. It is unit slot K of train T: it joins the coordinated lifecycle as
 * participant "train<T>/unit<K>", puts a CAN controller on network "bus<T>", reads its Sensor_Uxx frames and the
 * Reference / ReferenceAux frames, and every 10 ms (on its 1 ms SIL Kit steps) sends TractionCmd_Uxx, AgentState_Uxx
 * and AgentAux_Uxx: a PI law on the reference speed, as examples/external_ecu.py.
 *
 * Frame layouts, E2E data IDs and the E2E rule are those of dbc/train.dbc: little-endian signals, byte 0 a CRC-8
 * SAE J1850 (poly 0x1D, init 0xFF, xor-out 0xFF) over the message's E2EDataID and bytes 1..n-1, the low nibble of
 * byte 1 an alive counter (+1 mod 16 per message sent).
 *
 * Build (SIL Kit from `hil silkit install`, or any libSilKit.so 5.x):
 *     H=$(hil silkit info | awk '/^library/ {print $2}' | xargs dirname)
 *     gcc -O2 -Wall -o silkit_ecu examples/silkit_ecu/silkit_ecu.c -L"$H" -lSilKit -Wl,-rpath,"$H" -lm
 * Run, after `hil run seed000 --silkit --external train1/unit2` printed its registry:
 *     ./silkit_ecu --registry silkit://127.0.0.1:PORT --train 1 --unit 2
 * `--crash-at S` makes it exit abruptly at simulated time S without leaving SIL Kit, as a crashing board would
 * (the rig's test of a participant lost mid-run).
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>
#include "silkit_capi.h"

enum { DATA_ID_CMD = 1, DATA_ID_REF = 2, DATA_ID_REF_AUX = 3, DATA_ID_SENSOR = 4, DATA_ID_STATE = 5, DATA_ID_AUX = 6 };
enum { ID_REFERENCE = 0xA0, ID_REFERENCE_AUX = 0xA1 };

typedef struct {
    int unit;                       /* slot in the train, 1-based */
    double mass_kg, kp, ki, period_s;
    uint64_t step_ns, cycle_ns, phase_ns, crash_ns;  /* crash_ns: 0, or when to die as a crashing board would */
    SilKit_CanController *can;
    int have_sample, have_ref;
    double x, v, v_ref, a_ref, integral;
    unsigned sample_counter, cmd_counter;
    long sent, dropped;
} Ecu;

static void check(SilKit_ReturnCode rc, const char *what) {
    if (rc != 0) {
        fprintf(stderr, "silkit_ecu: %s failed (%d): %s\n", what, (int)rc, SilKit_GetLastErrorString());
        exit(1);
    }
}

/* ---- the DBC's encoding: little-endian bit fields, E2E CRC and counter */

static uint64_t get_bits(const uint8_t *data, int start, int length) {
    uint64_t raw = 0;
    for (int i = 0; i < length; i++) raw |= (uint64_t)((data[(start + i) / 8] >> ((start + i) % 8)) & 1) << i;
    return raw;
}

static void put_bits(uint8_t *data, int start, int length, uint64_t raw) {
    for (int i = 0; i < length; i++) {
        int bit = start + i;
        data[bit / 8] = (uint8_t)((data[bit / 8] & ~(1u << (bit % 8))) | (((raw >> i) & 1) << (bit % 8)));
    }
}

static double get_signed(const uint8_t *data, int start, int length, double scale) {
    int64_t raw = (int64_t)get_bits(data, start, length);
    if (raw & ((int64_t)1 << (length - 1))) raw -= (int64_t)1 << length;
    return raw * scale;
}

/* Encode value with scale into a field, saturated to its range (never wrapped). */
static void put_value(uint8_t *data, int start, int length, double value, double scale, int is_signed) {
    double lo = is_signed ? -ldexp(1.0, length - 1) : 0.0, hi = is_signed ? ldexp(1.0, length - 1) - 1 : ldexp(1.0, length) - 1;
    double raw = nearbyint(value / scale);
    if (!(raw >= lo)) raw = lo;  /* NaN too */
    if (raw > hi) raw = hi;
    put_bits(data, start, length, (uint64_t)(int64_t)raw & ((length == 64) ? ~0ull : ((1ull << length) - 1)));
}

static uint8_t crc8(uint8_t data_id, const uint8_t *data, size_t size) {
    uint8_t crc = 0xFF ^ data_id;
    for (int b = 0; b < 8; b++) crc = (crc & 0x80) ? (uint8_t)((crc << 1) ^ 0x1D) : (uint8_t)(crc << 1);
    for (size_t i = 1; i < size; i++) {
        crc ^= data[i];
        for (int b = 0; b < 8; b++) crc = (crc & 0x80) ? (uint8_t)((crc << 1) ^ 0x1D) : (uint8_t)(crc << 1);
    }
    return crc ^ 0xFF;
}

static void protect(uint8_t *data, size_t size, uint8_t data_id, unsigned counter) {
    data[1] = (uint8_t)((data[1] & 0xF0) | (counter & 0xF));
    data[0] = crc8(data_id, data, size);
}

/* ---- SIL Kit handlers */

static void on_frame(void *context, SilKit_CanController *controller, SilKit_CanFrameEvent *event) {
    (void)controller;
    Ecu *ecu = context;
    const SilKit_CanFrame *f = event->frame;
    const uint8_t *d = f->data.data;
    unsigned sensor_id = 0xC0 + (unsigned)ecu->unit - 1;
    uint8_t data_id = f->id == sensor_id ? DATA_ID_SENSOR : f->id == ID_REFERENCE ? DATA_ID_REF
                    : f->id == ID_REFERENCE_AUX ? DATA_ID_REF_AUX : 0;
    if (data_id == 0) return;
    if (f->data.size < 2 || d[0] != crc8(data_id, d, f->data.size)) {
        ecu->dropped++;
        return;
    }
    if (f->id == sensor_id && f->data.size == 8) {
        ecu->x = get_bits(d, 12, 30) * 0.001;
        ecu->v = get_signed(d, 42, 19, 0.0005);
        ecu->sample_counter = d[1] & 0xF;
        ecu->have_sample = 1;
    } else if (f->id == ID_REFERENCE && f->data.size == 8) {
        ecu->v_ref = get_signed(d, 42, 19, 0.0005);
        ecu->have_ref = 1;
    } else if (f->id == ID_REFERENCE_AUX && f->data.size == 4) {
        ecu->a_ref = get_signed(d, 12, 20, 0.001);
    }
}

static void send(Ecu *ecu, uint32_t id, uint8_t *data, uint16_t size) {
    SilKit_CanFrame frame;
    memset(&frame, 0, sizeof frame);
    frame.structHeader.version = SilKit_CanFrame_STRUCT_VERSION;
    frame.id = id;
    frame.dlc = size;
    frame.data.data = data;
    frame.data.size = size;
    check(SilKit_CanController_SendFrame(ecu->can, &frame, NULL), "SilKit_CanController_SendFrame");
    ecu->sent++;
}

/* One control cycle: the PI law on the latest sample, the three frames out. */
static void cycle(Ecu *ecu) {
    double accel = 0.0, force = 0.0;
    int mode = 1;  /* no reference yet: service brake */
    if (ecu->have_ref) {
        double err = ecu->v_ref - ecu->v;
        ecu->integral += err * ecu->period_s;
        accel = ecu->a_ref + ecu->kp * err + ecu->ki * ecu->integral;
        force = ecu->mass_kg * accel;
        mode = 0;
    }
    unsigned k = (unsigned)ecu->unit - 1;
    uint8_t cmd[5] = {0}, state[8] = {0}, aux[7] = {0};
    ecu->cmd_counter = (ecu->cmd_counter + 1) & 0xF;
    put_bits(cmd, 12, 2, (uint64_t)mode);
    put_value(cmd, 14, 20, force, 10.0, 1);
    protect(cmd, sizeof cmd, DATA_ID_CMD, ecu->cmd_counter);
    put_value(state, 12, 30, ecu->x, 0.001, 0);
    put_value(state, 42, 19, ecu->v, 0.0005, 1);
    protect(state, sizeof state, DATA_ID_STATE, ecu->sample_counter);
    put_value(aux, 12, 20, accel, 0.001, 1);
    put_value(aux, 32, 20, force, 10.0, 1);
    protect(aux, sizeof aux, DATA_ID_AUX, ecu->sample_counter);
    send(ecu, 0x80 + k, cmd, sizeof cmd);
    send(ecu, 0x100 + k, state, sizeof state);
    send(ecu, 0x120 + k, aux, sizeof aux);
}

static void on_step(void *context, SilKit_TimeSyncService *service, SilKit_NanosecondsTime now,
                    SilKit_NanosecondsTime duration) {
    (void)service; (void)duration;
    Ecu *ecu = context;
    if (ecu->crash_ns && now >= ecu->crash_ns) {  /* --crash-at: gone at once, SIL Kit never told */
        printf("silkit_ecu: crashing at t = %.3f s (--crash-at)\n", now * 1e-9);
        fflush(stdout);
        _exit(3);
    }
    if (now % ecu->cycle_ns == ecu->phase_ns && ecu->have_sample) cycle(ecu);
}

static const char *arg(int argc, char **argv, const char *name, const char *fallback) {
    for (int i = 1; i + 1 < argc; i++)
        if (strcmp(argv[i], name) == 0) return argv[i + 1];
    return fallback;
}

int main(int argc, char **argv) {
    const char *registry = arg(argc, argv, "--registry", NULL);
    if (registry == NULL) {
        fprintf(stderr, "usage: silkit_ecu --registry URI [--train 1] [--unit 2] [--mass-kg 80000] [--kp 0.5] "
                        "[--ki 0.05] [--bitrate 500000] [--crash-at SECONDS]\n");
        return 2;
    }
    Ecu ecu = {0};
    int train = atoi(arg(argc, argv, "--train", "1"));
    ecu.unit = atoi(arg(argc, argv, "--unit", "2"));
    ecu.mass_kg = atof(arg(argc, argv, "--mass-kg", "80000"));
    ecu.kp = atof(arg(argc, argv, "--kp", "0.5"));
    ecu.ki = atof(arg(argc, argv, "--ki", "0.05"));
    ecu.crash_ns = (uint64_t)llround(atof(arg(argc, argv, "--crash-at", "0")) * 1e9);
    ecu.step_ns = 1000000, ecu.cycle_ns = 10000000, ecu.phase_ns = 2000000, ecu.period_s = 0.01;
    if (train < 1 || ecu.unit < 1 || ecu.unit > 16) {
        fprintf(stderr, "silkit_ecu: --train must be >= 1 and --unit 1..16\n");
        return 2;
    }
    char name[64], network[32];
    snprintf(name, sizeof name, "train%d/unit%d", train, ecu.unit);
    snprintf(network, sizeof network, "bus%d", train);

    SilKit_ParticipantConfiguration *config;
    SilKit_Participant *participant;
    SilKit_LifecycleService *lifecycle;
    SilKit_TimeSyncService *time_sync;
    check(SilKit_ParticipantConfiguration_FromString(&config, ""), "SilKit_ParticipantConfiguration_FromString");
    check(SilKit_Participant_Create(&participant, config, name, registry), "SilKit_Participant_Create");
    SilKit_LifecycleConfiguration lc;
    memset(&lc, 0, sizeof lc);
    lc.structHeader.version = SilKit_LifecycleConfiguration_STRUCT_VERSION;
    lc.operationMode = SilKit_OperationMode_Coordinated;
    check(SilKit_LifecycleService_Create(&lifecycle, participant, &lc), "SilKit_LifecycleService_Create");
    check(SilKit_TimeSyncService_Create(&time_sync, lifecycle), "SilKit_TimeSyncService_Create");
    check(SilKit_CanController_Create(&ecu.can, participant, "CAN1", network), "SilKit_CanController_Create");
    uint64_t handler;
    check(SilKit_CanController_AddFrameHandler(ecu.can, &ecu, on_frame, SilKit_Direction_Receive, &handler),
          "SilKit_CanController_AddFrameHandler");
    check(SilKit_CanController_SetBaudRate(ecu.can, (uint32_t)atoi(arg(argc, argv, "--bitrate", "500000")), 0, 0),
          "SilKit_CanController_SetBaudRate");
    check(SilKit_CanController_Start(ecu.can), "SilKit_CanController_Start");
    check(SilKit_TimeSyncService_SetSimulationStepHandler(time_sync, &ecu, on_step, ecu.step_ns),
          "SilKit_TimeSyncService_SetSimulationStepHandler");
    printf("silkit_ecu %s on %s at %s\n", name, network, registry);
    fflush(stdout);
    check(SilKit_LifecycleService_StartLifecycle(lifecycle), "SilKit_LifecycleService_StartLifecycle");
    SilKit_ParticipantState final_state;
    check(SilKit_LifecycleService_WaitForLifecycleToComplete(lifecycle, &final_state),
          "SilKit_LifecycleService_WaitForLifecycleToComplete");
    printf("silkit_ecu %s: sent %ld frames, dropped %ld with a bad E2E CRC, final state %d\n", name, ecu.sent,
           ecu.dropped, (int)final_state);
    SilKit_Participant_Destroy(participant);
    return 0;
}
