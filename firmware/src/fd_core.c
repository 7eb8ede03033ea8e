/* fluxdrive drive firmware core: state machine, protections, sample window and protocol
 * (see fd_core.h). Frame layouts and scalings come only from the codec cantools generates
 * from config/can/fluxdrive.dbc at build time (fd_can.h / fd_can.c). */
#include "fd_core.h"

#include <math.h>
#include <string.h>

#include "fd_can.h"
#include "fd_math.h"

#define FD_SEQ_MASK 0xFFFFu
#define FD_T_MCU_MOD 4294967295u /* t_mcu wraps after 4294.967295 s (the DBC's range) */
#define FD_PI 3.14159265358979f
#define FD_TWO_PI 6.28318530717959f
#define FD_INV_TWO_PI 0.159154943091895f

/* signal ranges of the DBC's sample messages: a saturated reading is sent at the range
 * limit instead of wrapping (the classic layout's converters in the Python emulator clip
 * the same way) */
#define FD_I_RANGE_A 25.0f
#define FD_V_RANGE_V 100.0f
#define FD_VDC_RANGE_V 100.0f

static float clampf(float x, float lo, float hi) { return x < lo ? lo : (x > hi ? hi : x); }

/* Unsigned scaled signals: cantools' generated encoders for these convert through double
 * (its unsigned helper), a soft-float library call on a single-precision FPU. The same
 * rounding in float32, multiplied by the DBC's reciprocal scale (FD_INV_SCALE_*,
 * generated; offsets are 0 in this DBC). */
static uint16_t encode_unsigned(float value, float inv_scale)
{
    float r = fd_roundf(value * inv_scale);
    return r > 0.0f ? (r < 65535.0f ? (uint16_t)r : 65535u) : 0u; /* NaN: 0 */
}

/* Signed scaled signals, in range (sample_values saturates them): the generated encoders
 * divide by the scale and call roundf; the same rounding with the DBC's reciprocal scale
 * (generated, fd_protocol.h), inline. NaN: 0. */
static int32_t encode_signed(float value, float inv_scale)
{
    float r = fd_roundf(value * inv_scale);
    return r == r ? (int32_t)r : 0;
}

/* ------------------------------------------------------------------ parameters */

typedef struct {
    float lo, hi, dflt;
    uint8_t not_while_running;
    uint8_t read_only;
} prm_spec_t;

/* ranges in SI units (DBC prm_id value table): the engine's DRIVE_PARAM_RANGES and
 * DRIVE_PARAMS_STOPPED (fluxdrive.drive.control; tests/test_firmware.py compares them);
 * defaults: safe placeholders, the host writes the design's values before arming */
static const prm_spec_t PRM_SPEC[FD_PRM_COUNT] = {
    [FD_PRM_CUR_KP] = {0.0f, 1.0e4f, 0.0f, 0},
    [FD_PRM_CUR_KI] = {0.0f, 1.0e8f, 0.0f, 0},
    [FD_PRM_L_HAT] = {1.0e-7f, 10.0f, 1.0e-3f, 0},
    [FD_PRM_LAMBDA_HAT] = {0.0f, 10.0f, 0.0f, 0},
    [FD_PRM_DECOUPLE] = {0.0f, 1.0f, 1.0f, 0},
    [FD_PRM_VOLTAGE_ADVANCE] = {0.0f, 3.0f, 1.5f, 0},
    [FD_PRM_DEADTIME_COMP_S] = {0.0f, 1.0e-4f, 0.0f, 0},
    [FD_PRM_CUR_LIMIT_A] = {0.01f, 1.0e3f, 10.0f, 0},
    [FD_PRM_REF_TIMEOUT_S] = {1.0e-4f, 10.0f, 1.0e-2f, 0},
    [FD_PRM_OVERCURRENT_A] = {0.01f, 1.0e3f, 20.0f, 0},
    [FD_PRM_I2T_LIMIT_PU2S] = {0.01f, 1.0e4f, 10.0f, 0},
    [FD_PRM_RATED_CURRENT_A] = {0.01f, 1.0e3f, 10.0f, 1},
    [FD_PRM_VDC_MIN_V] = {0.0f, 1.0e4f, 0.0f, 0},
    [FD_PRM_VDC_MAX_V] = {1.0f, 1.0e4f, 1.0e4f, 0},
    [FD_PRM_HEARTBEAT_TIMEOUT_S] = {0.0f, 60.0f, 0.5f, 0},
    [FD_PRM_POLE_PAIRS] = {1.0f, 64.0f, 4.0f, 1},
    /* drive-only: the largest upper-switch duty, so every period keeps a low-side window
     * for shunt sampling and bootstrap recharge (0.95 of 100 us: 5 us) */
    [FD_PRM_MAX_DUTY] = {0.5f, 1.0f, 0.95f, 0},
    /* the calibration's result, read-only */
    [FD_PRM_CAL_OFFSET_A] = {0.0f, 0.0f, 0.0f, 0, 1},
    [FD_PRM_CAL_OFFSET_B] = {0.0f, 0.0f, 0.0f, 0, 1},
    [FD_PRM_CAL_OFFSET_C] = {0.0f, 0.0f, 0.0f, 0, 1},
    [FD_PRM_CAL_CAPTURE_AB] = {0.0f, 0.0f, 0.0f, 0, 1},
    [FD_PRM_CAL_CAPTURE_BC] = {0.0f, 0.0f, 0.0f, 0, 1},
    [FD_PRM_CAL_CAPTURE_CA] = {0.0f, 0.0f, 0.0f, 0, 1},
    [FD_PRM_CAL_DONE] = {0.0f, 0.0f, 0.0f, 0, 1},
    /* storage and diagnostics */
    [FD_PRM_PARAM_SOURCE] = {0.0f, 0.0f, 0.0f, 0, 1},
    [FD_PRM_PARAM_SAVE] = {0.0f, 1.0f, 0.0f, 0, 0}, /* write 1: store (PWM off) */
    [FD_PRM_FAULT_LOG] = {0.0f, 0.0f, 0.0f, 0, 1},
    [FD_PRM_CAN_TEC] = {0.0f, 0.0f, 0.0f, 0, 1},
    [FD_PRM_CAN_BUS_OFFS] = {0.0f, 0.0f, 0.0f, 0, 1},
};

/* what goes to storage: the writable parameters (not the results and diagnostics) */
static int stored_param(int id)
{
    return !PRM_SPEC[id].read_only && id != FD_PRM_PARAM_SAVE;
}

uint32_t fd_crc32(const void *data, uint32_t n)
{
    const uint8_t *p = (const uint8_t *)data;
    uint32_t crc = 0xFFFFFFFFu;
    for (uint32_t i = 0; i < n; ++i) { /* bitwise: no table in flash, background only */
        crc ^= p[i];
        for (int b = 0; b < 8; ++b) {
            crc = (crc >> 1) ^ (0xEDB88320u & (0u - (crc & 1u)));
        }
    }
    return ~crc;
}

/* PARAM_SAVE: the record built under the critical section, written outside it (a flash
 * write takes milliseconds: the period interrupt must keep running) */
static int save_params(fd_core_t *c)
{
    fd_param_record_t rec;
    memset(&rec, 0, sizeof(rec));
    uint32_t irq = fd_hal_irq_lock(c->hal);
    int running = c->pwm_enabled;
    for (int i = 1; i < (int)FD_PRM_COUNT; ++i) {
        rec.prm[i] = stored_param(i) ? c->prm[i] : 0.0f;
    }
    fd_hal_irq_unlock(c->hal, irq);
    if (running) {
        return FD_PA_NOT_WHILE_RUNNING;
    }
    rec.magic = FD_STORE_MAGIC;
    rec.count = FD_PRM_COUNT;
    rec.crc = fd_crc32(&rec, (uint32_t)offsetof(fd_param_record_t, crc));
    if (!fd_hal_storage_write(c->hal, &rec, (uint32_t)sizeof(rec))) {
        return FD_PA_STORAGE_FAILED;
    }
    c->stats.param_saves++;
    return FD_PA_OK;
}

/* boot: the stored record if its CRC holds (each value checked against its range again),
 * else the defaults; PARAM_SOURCE says which */
static void load_params(fd_core_t *c)
{
    fd_param_record_t rec;
    float src = (float)FD_PRM_SOURCE_DEFAULTS;
    if (fd_hal_storage_read(c->hal, &rec, (uint32_t)sizeof(rec))) {
        int ok = rec.magic == FD_STORE_MAGIC && rec.count == FD_PRM_COUNT &&
                 rec.crc == fd_crc32(&rec, (uint32_t)offsetof(fd_param_record_t, crc));
        for (int i = 1; ok && i < (int)FD_PRM_COUNT; ++i) {
            const prm_spec_t *s = &PRM_SPEC[i];
            ok = !stored_param(i) || (isfinite(rec.prm[i]) && rec.prm[i] >= s->lo &&
                                      rec.prm[i] <= s->hi);
        }
        if (ok) {
            for (int i = 1; i < (int)FD_PRM_COUNT; ++i) {
                if (stored_param(i)) {
                    c->prm[i] = rec.prm[i];
                }
            }
            src = (float)FD_PRM_SOURCE_STORED;
        } else {
            src = (float)FD_PRM_SOURCE_BAD_CRC;
        }
    }
    c->prm[FD_PRM_PARAM_SOURCE] = src;
}

static float minf2(float a, float b) { return a < b ? a : b; }
static float maxf2(float a, float b) { return a > b ? a : b; }

/* the limits in effect: the stricter of the board's (fd_config_t) and the DRIVE_PARAM */
static void update_limits(fd_core_t *c)
{
    c->oc_trip_a = minf2(c->prm[FD_PRM_OVERCURRENT_A], c->cfg.oc_limit_a);
    c->vdc_max_v = minf2(c->prm[FD_PRM_VDC_MAX_V], c->cfg.vdc_max_v);
    c->vdc_min_v = maxf2(maxf2(c->prm[FD_PRM_VDC_MIN_V], c->cfg.vdc_min_v),
                         c->cfg.vdc_modulation_min_v);
    c->max_duty = c->prm[FD_PRM_MAX_DUTY];
}

static uint32_t seconds_to_us(float s) { return (uint32_t)(s * 1.0e6f + 0.5f); }

int fd_core_param_read(const fd_core_t *c, int prm_id, float *value)
{
    if (prm_id < 1 || prm_id >= (int)FD_PRM_COUNT) {
        *value = 0.0f;
        return FD_PA_UNKNOWN_PARAM;
    }
    switch (prm_id) { /* the value in effect where a board limit is stricter */
    case FD_PRM_OVERCURRENT_A:
        *value = c->oc_trip_a;
        break;
    case FD_PRM_VDC_MAX_V:
        *value = c->vdc_max_v;
        break;
    case FD_PRM_VDC_MIN_V:
        *value = c->vdc_min_v;
        break;
    case FD_PRM_FAULT_LOG:
        *value = (float)(c->fault_log_n < FD_FAULT_LOG ? c->fault_log_n : FD_FAULT_LOG);
        break;
    case FD_PRM_CAN_TEC:
        *value = (float)c->hw.can_tec;
        break;
    case FD_PRM_CAN_BUS_OFFS:
        *value = (float)c->stats.can_bus_offs;
        break;
    case FD_PRM_PARAM_SAVE:
        *value = 0.0f;
        break;
    default:
        *value = c->prm[prm_id];
        break;
    }
    return FD_PA_OK;
}

int fd_core_param_write(fd_core_t *c, int prm_id, float value)
{
    if (prm_id < 1 || prm_id >= (int)FD_PRM_COUNT) {
        return FD_PA_UNKNOWN_PARAM;
    }
    const prm_spec_t *s = &PRM_SPEC[prm_id];
    if (s->read_only) {
        return FD_PA_READ_ONLY;
    }
    if (prm_id == FD_PRM_PARAM_SAVE && value == 1.0f) {
        return save_params(c);
    }
    if (!isfinite(value)) {
        return FD_PA_NOT_FINITE;
    }
    if (value < s->lo || value > s->hi) {
        return FD_PA_OUT_OF_RANGE;
    }
    if (s->not_while_running && c->pwm_enabled) {
        return FD_PA_NOT_WHILE_RUNNING;
    }
    c->prm[prm_id] = value;
    update_limits(c);
    return FD_PA_OK;
}

/* ------------------------------------------------------------------ encoders */

int fd_encode_fault(uint8_t out[8], uint8_t code, uint8_t latched, uint8_t active,
                    uint8_t pwm_disabled, uint16_t detail, uint16_t seq, uint8_t count)
{
    struct fd_can_fault_t m;
    fd_can_fault_init(&m);
    m.fault_code = code;
    m.fault_latched = latched;
    m.fault_active = active;
    m.fault_pwm_disabled = pwm_disabled;
    m.fault_detail = detail;
    m.fault_seq = seq;
    m.fault_count = count;
    return fd_can_fault_pack(out, &m, 8);
}

int fd_encode_status(uint8_t out[8], uint8_t alive, uint8_t state, uint8_t armed,
                     uint8_t pwm_enabled, uint8_t fault_latched, uint8_t layout,
                     uint8_t decimation, uint16_t tx_overruns, int8_t temp_c, uint8_t rx_errors)
{
    struct fd_can_status_t m;
    fd_can_status_init(&m);
    m.st_alive = alive;
    m.st_state = state;
    m.st_armed = armed;
    m.st_pwm_enabled = pwm_enabled;
    m.st_fault_latched = fault_latched;
    m.st_sample_layout = layout;
    m.st_protocol_version = (uint8_t)FD_PROTOCOL_VERSION;
    m.st_decimation = decimation;
    m.st_tx_overruns = tx_overruns;
    m.st_temp = temp_c;
    m.st_rx_errors = rx_errors;
    return fd_can_status_pack(out, &m, 8);
}

/* the values a sample carries, saturated to the DBC ranges */
static void sample_values(const float f[10], float g[10])
{
    for (int j = 0; j < 3; ++j) {
        g[j] = clampf(f[j], -FD_I_RANGE_A, FD_I_RANGE_A);
        g[3 + j] = clampf(f[3 + j], -FD_V_RANGE_V, FD_V_RANGE_V);
        g[7 + j] = clampf(f[7 + j], 0.0f, 1.0f);
    }
    g[6] = clampf(f[6], 0.0f, FD_VDC_RANGE_V);
}

int fd_encode_sample_fd(uint8_t out[64], uint16_t seq, const float f[10], int32_t encoder,
                        uint16_t cmd_seq_applied, uint32_t t_mcu_us, uint8_t flags, uint8_t mode,
                        uint8_t fault_code)
{
    float g[10];
    sample_values(f, g);
    struct fd_can_sample_fd_t m;
    fd_can_sample_fd_init(&m);
    m.seq = seq;
    m.i_a = (int16_t)encode_signed(g[0], FD_INV_SCALE_SAMPLE_FD_I_A);
    m.i_b = (int16_t)encode_signed(g[1], FD_INV_SCALE_SAMPLE_FD_I_B);
    m.i_c = (int16_t)encode_signed(g[2], FD_INV_SCALE_SAMPLE_FD_I_C);
    m.v_ab = encode_signed(g[3], FD_INV_SCALE_SAMPLE_FD_V_AB);
    m.v_bc = encode_signed(g[4], FD_INV_SCALE_SAMPLE_FD_V_BC);
    m.v_ca = encode_signed(g[5], FD_INV_SCALE_SAMPLE_FD_V_CA);
    m.vdc = encode_unsigned(g[6], FD_INV_SCALE_SAMPLE_FD_VDC);
    m.duty_a = encode_unsigned(g[7], FD_INV_SCALE_SAMPLE_FD_DUTY_A);
    m.duty_b = encode_unsigned(g[8], FD_INV_SCALE_SAMPLE_FD_DUTY_B);
    m.duty_c = encode_unsigned(g[9], FD_INV_SCALE_SAMPLE_FD_DUTY_C);
    m.encoder = encoder;          /* scale 1: the raw value is the count */
    m.cmd_seq_applied = cmd_seq_applied;
    m.t_mcu = t_mcu_us;           /* scale 1 us: the raw value is the timer */
    m.pwm_enabled = (uint8_t)(flags & 1u);
    m.armed = (uint8_t)((flags >> 1) & 1u);
    m.fault_active = (uint8_t)((flags >> 2) & 1u);
    m.adc_clip = (uint8_t)((flags >> 3) & 1u);
    m.cmd_stale = (uint8_t)((flags >> 4) & 1u);
    m.capture_valid = (uint8_t)((flags >> 5) & 1u);
    m.control_split = (uint8_t)((flags >> 6) & 1u);
    m.mode = mode;
    m.fault_code = fault_code;
    return fd_can_sample_fd_pack(out, &m, 64);
}

int fd_encode_sample_classic(uint8_t out[4][8], uint16_t seq, const float f[10], int32_t encoder,
                             uint8_t flags)
{
    float g[10];
    sample_values(f, g);
    struct fd_can_sample_c_cur_t cur;
    struct fd_can_sample_c_vlt_t vlt;
    struct fd_can_sample_c_duty_t dut;
    struct fd_can_sample_c_aux_t aux;
    fd_can_sample_c_cur_init(&cur);
    fd_can_sample_c_vlt_init(&vlt);
    fd_can_sample_c_duty_init(&dut);
    fd_can_sample_c_aux_init(&aux);
    cur.c_seq = vlt.c_seq = dut.c_seq = aux.c_seq = seq;
    cur.c_i_a = (int16_t)encode_signed(g[0], FD_INV_SCALE_SAMPLE_C_CUR_C_I_A);
    cur.c_i_b = (int16_t)encode_signed(g[1], FD_INV_SCALE_SAMPLE_C_CUR_C_I_B);
    cur.c_i_c = (int16_t)encode_signed(g[2], FD_INV_SCALE_SAMPLE_C_CUR_C_I_C);
    vlt.c_v_ab = (int16_t)encode_signed(g[3], FD_INV_SCALE_SAMPLE_C_VLT_C_V_AB);
    vlt.c_v_bc = (int16_t)encode_signed(g[4], FD_INV_SCALE_SAMPLE_C_VLT_C_V_BC);
    vlt.c_v_ca = (int16_t)encode_signed(g[5], FD_INV_SCALE_SAMPLE_C_VLT_C_V_CA);
    dut.c_duty_a = encode_unsigned(g[7], FD_INV_SCALE_SAMPLE_C_DUTY_C_DUTY_A);
    dut.c_duty_b = encode_unsigned(g[8], FD_INV_SCALE_SAMPLE_C_DUTY_C_DUTY_B);
    dut.c_duty_c = encode_unsigned(g[9], FD_INV_SCALE_SAMPLE_C_DUTY_C_DUTY_C);
    aux.c_vdc = encode_unsigned(g[6], FD_INV_SCALE_SAMPLE_C_AUX_C_VDC);
    /* low 24 bits, two's complement (the receiver unwraps) */
    uint32_t low = ((uint32_t)encoder + 0x800000u) & 0xFFFFFFu;
    aux.c_encoder = (int32_t)low - 0x800000;
    aux.c_pwm_enabled = (uint8_t)(flags & 1u);
    aux.c_armed = (uint8_t)((flags >> 1) & 1u);
    aux.c_fault_active = (uint8_t)((flags >> 2) & 1u);
    aux.c_adc_clip = (uint8_t)((flags >> 3) & 1u);
    aux.c_cmd_stale = (uint8_t)((flags >> 4) & 1u);
    aux.c_capture_valid = (uint8_t)((flags >> 5) & 1u);
    aux.c_control_split = (uint8_t)((flags >> 6) & 1u);
    if (fd_can_sample_c_cur_pack(out[0], &cur, 8) < 0 || fd_can_sample_c_vlt_pack(out[1], &vlt, 8) < 0 ||
        fd_can_sample_c_duty_pack(out[2], &dut, 8) < 0 || fd_can_sample_c_aux_pack(out[3], &aux, 8) < 0) {
        return -1;
    }
    return 32;
}

int fd_encode_param_ack(uint8_t out[8], uint8_t id, uint8_t seq, uint8_t status, float value)
{
    struct fd_can_drive_param_ack_t m;
    fd_can_drive_param_ack_init(&m);
    m.pa_id = id;
    m.pa_seq = seq;
    m.pa_status = status;
    m.pa_value = value;
    return fd_can_drive_param_ack_pack(out, &m, 8);
}

/* ------------------------------------------------------------------ transmit */

/* a frame whose payload is already in f->data (encoded in place: no copy) */
static void send_frame(fd_core_t *c, fd_can_frame_t *f, uint32_t id, int len, uint8_t fd)
{
    if (len < 0) {
        return;
    }
    f->id = id;
    f->len = (uint8_t)len;
    f->fd = fd;
    if (!fd_hal_can_tx(c->hal, f)) {
        c->stats.tx_overruns++;
    }
}

/* a classic frame (at most 8 bytes, data[8]): a fixed-size copy, two word moves */
static void send(fd_core_t *c, uint32_t id, const uint8_t *data, int len, uint8_t fd)
{
    if (len < 0 || len > 8) {
        return;
    }
    fd_can_frame_t f;
    memcpy(f.data, data, 8u);
    send_frame(c, &f, id, len, fd);
}

static void send_fault(fd_core_t *c, uint16_t detail)
{
    uint8_t b[8];
    uint8_t l = c->fault_latched;
    int n = fd_encode_fault(b, c->fault_code, l, l, l, detail, (uint16_t)(c->k & FD_SEQ_MASK),
                            c->fault_count);
    send(c, FD_CAN_FAULT_FRAME_ID, b, n, 0);
}

static void send_status(fd_core_t *c, int32_t temp_c)
{
    uint8_t state = FD_ST_IDLE;
    if (c->fault_latched) {
        state = FD_ST_FAULT;
    } else if (c->calibrating) {
        state = FD_ST_CALIBRATING;
    } else if (c->pwm_enabled) {
        state = FD_ST_RUNNING;
    } else if (c->armed) {
        state = FD_ST_ARMED;
    }
    uint8_t b[8];
    int8_t t = (int8_t)(temp_c < -128 ? -128 : (temp_c > 127 ? 127 : temp_c));
    int n = fd_encode_status(b, c->status_alive, state, c->armed, c->pwm_enabled, c->fault_latched,
                             c->cfg.classic_layout, c->cfg.decimation,
                             (uint16_t)(c->stats.tx_overruns & 0xFFFFu), t, c->hw.can_rec);
    c->status_alive = (uint8_t)(c->status_alive + 1u);
    send(c, FD_CAN_STATUS_FRAME_ID, b, n, 0);
}

static void send_sample(fd_core_t *c)
{
    float f[10];
    float inv_n = c->win_n > 1u ? 1.0f / (float)c->win_n : 1.0f; /* D = 1: no division */
    for (int j = 0; j < 3; ++j) {
        f[j] = c->i_abc[j];
        f[3 + j] = c->win_n > 1u ? c->win_v[j] * inv_n : c->v_ll[j];
        f[7 + j] = c->win_n > 1u ? c->win_duty[j] * inv_n : c->duty_applied[j];
    }
    f[6] = c->vdc;
    uint8_t flags = (uint8_t)((c->win_pwm ? 1u : 0u) | (c->armed ? 2u : 0u) |
                              (c->fault_latched ? 4u : 0u) | ((c->win_flags & 1u) ? 8u : 0u) |
                              (c->stale_prev ? 16u : 0u) | (c->win_pwm ? 32u : 0u) |
                              (c->split ? 64u : 0u));
    uint16_t seq = (uint16_t)(c->k & FD_SEQ_MASK);
    if (c->cfg.classic_layout) {
        uint8_t b[4][8];
        if (fd_encode_sample_classic(b, seq, f, c->encoder, flags) > 0) {
            send(c, FD_CAN_SAMPLE_C_CUR_FRAME_ID, b[0], 8, 0);
            send(c, FD_CAN_SAMPLE_C_VLT_FRAME_ID, b[1], 8, 0);
            send(c, FD_CAN_SAMPLE_C_DUTY_FRAME_ID, b[2], 8, 0);
            send(c, FD_CAN_SAMPLE_C_AUX_FRAME_ID, b[3], 8, 0);
        }
    } else {
        fd_can_frame_t fr;
        int n = fd_encode_sample_fd(fr.data, seq, f, c->encoder, c->applied_seq, c->t_us, flags,
                                    c->mode, c->fault_code);
        send_frame(c, &fr, FD_CAN_SAMPLE_FD_FRAME_ID, n, 1);
    }
    c->stats.samples_sent++;
}

static void reset_window(fd_core_t *c)
{
    for (int j = 0; j < 3; ++j) {
        c->win_v[j] = 0.0f;
        c->win_duty[j] = 0.0f;
    }
    c->win_n = 0;
    c->win_pwm = 1;
    c->win_flags = 0;
}

/* ------------------------------------------------------------------ faults */

static void raise_fault(fd_core_t *c, uint8_t code, uint16_t detail)
{
    c->pwm_enabled = 0;
    int is_new = !c->fault_latched || c->fault_code != code;
    c->fault_code = code;
    c->fault_latched = 1;
    c->armed = 0;
    if (is_new) {
        fd_fault_entry_t *e = &c->fault_log[c->fault_log_n % FD_FAULT_LOG];
        e->code = code;
        e->detail = detail;
        e->k = c->k;
        c->fault_log_n++;
        c->fault_count = (uint8_t)(c->fault_count < 255u ? c->fault_count + 1u : 255u);
        c->stats.faults++;
        send_fault(c, detail);
        c->next_fault_k = c->k + c->cfg.status_period;
    }
}

static float max_abs_current(const fd_core_t *c, int *phase)
{
    float m = -1.0f;
    for (int j = 0; j < 3; ++j) {
        float a = fabsf(c->i_abc[j]);
        if (a > m) {
            m = a;
            *phase = j;
        }
    }
    return m;
}

/* is the cause of the latched fault gone (reset allowed)? */
static int cause_gone(const fd_core_t *c)
{
    int ph = 0;
    switch (c->fault_code) {
    case FD_FAULT_OVERCURRENT:
        return max_abs_current(c, &ph) <= c->oc_trip_a && !c->hw.break_event;
    case FD_FAULT_OVERCURRENT_I2T:
        return c->i2t <= c->prm[FD_PRM_I2T_LIMIT_PU2S];
    case FD_FAULT_OVERVOLTAGE:
        return c->vdc <= c->vdc_max_v;
    case FD_FAULT_UNDERVOLTAGE:
        return c->vdc >= c->vdc_min_v;
    case FD_FAULT_ADC_FAULT:
        return !c->clip;
    case FD_FAULT_GATE_DRIVER:
        return !c->hw.gate_fault;
    case FD_FAULT_OVERTEMPERATURE:
        return c->temp_c < c->cfg.temp_max_c - c->cfg.temp_hysteresis_c;
    default:
        return 1; /* timeouts and bad commands: nothing persists once PWM is off */
    }
}

static void clear_fault(fd_core_t *c)
{
    if (c->fault_latched && cause_gone(c)) {
        c->fault_latched = 0;
        c->fault_code = FD_FAULT_NONE;
        send_fault(c, 0);
    }
}

/* the protections on the sample just taken, each latched with PWM off (raise_fault) in
 * this very period. Comparisons are written so that a NaN reading trips (!(x <= limit)).
 * Order: the hardware inputs, ADC saturation, then the engine's _protect order
 * (over-current, I2t, bus over-voltage, bus under-voltage), then the temperature. */
static void protect(fd_core_t *c)
{
    const float sq3 = 1.7320508075688772f;
    float ia = (2.0f * c->i_abc[0] - c->i_abc[1] - c->i_abc[2]) * (1.0f / 3.0f);
    float ib = (c->i_abc[1] - c->i_abc[2]) * (1.0f / sq3);
    c->i2t = fd_i2t_step(c->i2t, ia, ib, c->prm[FD_PRM_RATED_CURRENT_A], c->cfg.ts_s);
    if (c->fault_latched) {
        return;
    }
    if (c->hw.break_event) { /* the comparator already opened the gates */
        raise_fault(c, FD_FAULT_OVERCURRENT, FD_OC_DETAIL_BREAK);
        return;
    }
    if (c->hw.gate_fault) {
        raise_fault(c, FD_FAULT_GATE_DRIVER, 0);
        return;
    }
    if (c->hw.can_bus_off && c->armed) { /* the host can no longer reach the drive */
        raise_fault(c, FD_FAULT_BUS_ERROR, c->hw.can_tec);
        return;
    }
    if (c->clip) { /* a saturated reading: the current is unknown, at least full scale */
        raise_fault(c, FD_FAULT_ADC_FAULT, c->clip_detail);
        return;
    }
    for (int j = 0; j < 3; ++j) {
        float a = fabsf(c->i_abc[j]);
        if (!(a <= c->oc_trip_a)) {
            float a10 = a * 10.0f;
            uint32_t d = a10 >= 0.0f && a10 < 16383.0f ? (uint32_t)a10 : 16383u;
            raise_fault(c, FD_FAULT_OVERCURRENT, (uint16_t)((uint32_t)j | (d << 2)));
            return;
        }
    }
    if (!(c->i2t <= c->prm[FD_PRM_I2T_LIMIT_PU2S])) {
        float d = c->i2t * 100.0f;
        raise_fault(c, FD_FAULT_OVERCURRENT_I2T, (uint16_t)(d < 65535.0f ? d : 65535.0f));
        return;
    }
    float v100 = c->vdc * 100.0f;
    uint16_t vdet = (uint16_t)(v100 > 0.0f ? (v100 < 65535.0f ? v100 : 65535.0f) : 0.0f);
    if (!(c->vdc <= c->vdc_max_v)) {
        raise_fault(c, FD_FAULT_OVERVOLTAGE, vdet);
        return;
    }
    /* under-voltage only while armed: an unpowered bus at boot is no fault */
    if (c->armed && !(c->vdc >= c->vdc_min_v)) {
        raise_fault(c, FD_FAULT_UNDERVOLTAGE, vdet);
        return;
    }
    if (c->temp_c >= c->cfg.temp_max_c) {
        raise_fault(c, FD_FAULT_OVERTEMPERATURE, (uint16_t)(c->temp_c > 0 ? c->temp_c : 0));
    }
}

/* ------------------------------------------------------------------ receive */

static void disarm(fd_core_t *c)
{
    c->armed = 0;
    c->pwm_enabled = 0;
    c->mode = FD_MODE_IDLE;
}

/* ------------------------------------------------------------------ calibration */

/* CALIBRATE_ADC: PWM off (disarmed) for cal_periods periods, the current and capture
 * readings summed; at the end the offsets are stored, readable as DRIVE_PARAMs
 * CAL_OFFSET_* / CAL_CAPTURE_* and CAL_DONE, and used from the next sample on. */
static void start_calibration(fd_core_t *c)
{
    disarm(c);
    c->calibrating = 1;
    c->mode = FD_MODE_CALIBRATE_ADC;
    c->cal_n = 0;
    /* a STATUS (CALIBRATING) from the next interrupt on, then every status_period: the
     * host sees the state whatever the phase of the 10 Hz STATUS, and the next one after
     * the end (cal_periods <= status_period) says it is over */
    c->next_status_k = c->k;
    for (int j = 0; j < 3; ++j) {
        c->cal_sum_i[j] = 0;
        c->cal_sum_cap[j] = 0;
    }
}

static void calibration_step(fd_core_t *c, const fd_adc_raw_t *adc, const fd_capture_raw_t *cap)
{
    for (int j = 0; j < 3; ++j) {
        c->cal_sum_i[j] += adc->current_counts[j];
        c->cal_sum_cap[j] += cap->high_ticks[j];
    }
    if (c->clip) { /* a saturated reading with the bridge off: the channel is broken */
        c->calibrating = 0;
        c->mode = FD_MODE_IDLE;
        raise_fault(c, FD_FAULT_ADC_FAULT, c->clip_detail);
        return;
    }
    c->cal_n++;
    uint32_t n = c->cal_n;
    if (n < c->cfg.cal_periods) {
        return;
    }
    c->calibrating = 0;
    c->mode = FD_MODE_IDLE;
    float fn = (float)n; /* divides once per calibration, exact for whole means */
    float off[3];
    for (int j = 0; j < 3; ++j) {
        off[j] = (float)c->cal_sum_i[j] / fn;
        float dev = fabsf(off[j] - (float)c->cfg.current_offset_counts[j]);
        if (!(dev <= (float)c->cfg.cal_max_offset_counts)) {
            uint32_t d = dev < 8191.0f ? (uint32_t)dev : 8191u;
            raise_fault(c, FD_FAULT_ADC_FAULT,
                        (uint16_t)(FD_ADC_DETAIL_CALIBRATION | (uint32_t)j | (d << 2)));
            return;
        }
    }
    for (int j = 0; j < 3; ++j) {
        c->cur_off[j] = off[j];
        c->cap_off[j] = (float)c->cal_sum_cap[j] / fn;
        c->prm[FD_PRM_CAL_OFFSET_A + j] = c->cur_off[j];
        c->prm[FD_PRM_CAL_CAPTURE_AB + j] = c->cap_off[j];
    }
    c->cal_valid = 1;
    c->prm[FD_PRM_CAL_DONE] = 1.0f;
}

static void on_arm_mode(fd_core_t *c, const fd_can_frame_t *f)
{
    struct fd_can_arm_mode_t m;
    if (fd_can_arm_mode_unpack(&m, f->data, f->len) != 0) {
        c->stats.bad_rx++;
        return;
    }
    c->stats.arm_rx++;
    if (m.reset_fault && !c->reset_prev) {
        clear_fault(c);
    }
    c->reset_prev = m.reset_fault;
    if (m.sample_layout != c->cfg.classic_layout || m.decimation != c->cfg.decimation) {
        c->stats.layout_mismatch++;
    }
    if (m.control_split != c->split) {
        if (c->pwm_enabled) {
            raise_fault(c, FD_FAULT_BAD_COMMAND, m.control_split); /* no switch while running */
            return;
        }
        c->split = m.control_split;
        c->ref.valid = 0;
        c->ref_box_taken = atomic_load_explicit(&c->ref_box.seq, memory_order_acquire);
    }
    int cal_req = m.arm && m.arm_key == FD_ARM_KEY && m.mode == FD_MODE_CALIBRATE_ADC;
    int cal_edge = cal_req && !c->cal_req_prev;
    c->cal_req_prev = (uint8_t)cal_req;
    if (c->calibrating && !cal_req) { /* anything else ends a calibration unfinished */
        c->calibrating = 0;
        c->mode = FD_MODE_IDLE;
    }
    if (cal_req) {
        if (cal_edge && !c->fault_latched) {
            start_calibration(c);
        }
    } else if (m.arm && m.arm_key == FD_ARM_KEY && !c->fault_latched && c->cfg.require_calibration &&
               !c->cal_valid) {
        disarm(c);
        raise_fault(c, FD_FAULT_NOT_CALIBRATED, 0); /* the refusal, as a FAULT frame */
    } else if (m.arm && m.arm_key == FD_ARM_KEY && !c->fault_latched) {
        if (!c->armed) {
            /* supervision starts at arming: the heartbeat and split mode's reference
             * timeout count from now, not from a first frame; the first switching period
             * is preceded by the bootstrap charge */
            c->hb_last_us = fd_hal_time_us(c->hal);
            c->last_ref_k = c->k;
            c->bootstrap_left = c->cfg.bootstrap_periods;
        }
        c->armed = 1;
        c->mode = m.mode;
    } else {
        if (c->armed) {
            c->stats.disarm_rx++;
        }
        disarm(c);
    }
    if (m.cmd_timeout > 0u) {
        c->cmd_timeout_us = (uint32_t)m.cmd_timeout * 100u; /* raw unit 0.1 ms */
    }
}

static void on_duty_cmd(fd_core_t *c, const fd_can_frame_t *f)
{
    struct fd_can_duty_cmd_t m;
    if (fd_can_duty_cmd_unpack(&m, f->data, f->len) != 0) {
        c->stats.bad_rx++;
        return;
    }
    float d[3] = {fd_can_duty_cmd_cmd_duty_a_decode(m.cmd_duty_a),
                  fd_can_duty_cmd_cmd_duty_b_decode(m.cmd_duty_b),
                  fd_can_duty_cmd_cmd_duty_c_decode(m.cmd_duty_c)};
    for (int j = 0; j < 3; ++j) {
        if (!(d[j] >= 0.0f && d[j] <= 1.0f)) {
            c->stats.bad_rx++;
            return;
        }
    }
    /* to the interrupt: fill the slot at head, then publish it */
    fd_cmd_ring_t *r = &c->cmd_ring;
    unsigned head = atomic_load_explicit(&r->head, memory_order_relaxed);
    unsigned tail = atomic_load_explicit(&r->tail, memory_order_acquire);
    if (head - tail >= FD_CMD_RING) {
        c->stats.cmd_ring_full++;
        return;
    }
    fd_duty_cmd_t *x = &r->slot[head % FD_CMD_RING];
    x->seq = m.cmd_seq;
    x->enable = m.cmd_enable;
    x->valid = 1;
    for (int j = 0; j < 3; ++j) {
        x->duty[j] = d[j];
    }
    atomic_store_explicit(&r->head, head + 1u, memory_order_release);
    c->stats.duty_rx++;
}

/* interrupt: a command into its slots; replace the same seq, else a free slot, else the
 * oldest (furthest behind) */
static void store_command(fd_core_t *c, const fd_duty_cmd_t *in)
{
    unsigned slot = FD_CMD_SLOTS;
    unsigned oldest = 0;
    uint16_t worst = 0;
    for (unsigned s = 0; s < FD_CMD_SLOTS; ++s) {
        if (c->cmds[s].valid && c->cmds[s].seq == in->seq) {
            slot = s;
            break;
        }
        if (!c->cmds[s].valid && slot == FD_CMD_SLOTS) {
            slot = s;
        }
        uint16_t behind = (uint16_t)(in->seq - c->cmds[s].seq);
        if (c->cmds[s].valid && behind >= worst) {
            worst = behind;
            oldest = s;
        }
    }
    if (slot == FD_CMD_SLOTS) {
        slot = oldest;
    }
    c->cmds[slot] = *in;
}

/* interrupt: everything the background published since the last period (bounded by the
 * ring's size) */
static void take_commands_over(fd_core_t *c)
{
    fd_cmd_ring_t *r = &c->cmd_ring;
    unsigned tail = atomic_load_explicit(&r->tail, memory_order_relaxed);
    unsigned head = atomic_load_explicit(&r->head, memory_order_acquire);
    for (unsigned n = 0; tail != head && n < FD_CMD_RING; ++n, ++tail) {
        store_command(c, &r->slot[tail % FD_CMD_RING]);
    }
    atomic_store_explicit(&r->tail, tail, memory_order_release);
}

/* background: publish a reference under the sequence lock */
static void publish_reference(fd_core_t *c, const fd_host_ref_t *r)
{
    fd_ref_box_t *b = &c->ref_box;
    unsigned s = atomic_load_explicit(&b->seq, memory_order_relaxed);
    atomic_store_explicit(&b->seq, s + 1u, memory_order_relaxed); /* odd: writing */
    atomic_thread_fence(memory_order_release);
    b->ref = *r;
    atomic_store_explicit(&b->seq, s + 2u, memory_order_release); /* even: stable */
}

/* interrupt: the newest published reference, if there is a new one and it is whole */
static int take_reference_over(fd_core_t *c, fd_host_ref_t *out)
{
    fd_ref_box_t *b = &c->ref_box;
    unsigned s1 = atomic_load_explicit(&b->seq, memory_order_acquire);
    if (s1 == c->ref_box_taken) {
        return 0;
    }
    if (s1 & 1u) { /* this interrupt preempted the writer: take it next period */
        c->stats.ref_handover_busy++;
        return 0;
    }
    *out = b->ref;
    atomic_thread_fence(memory_order_acquire);
    unsigned s2 = atomic_load_explicit(&b->seq, memory_order_relaxed);
    if (s2 != s1) {
        c->stats.ref_handover_busy++;
        return 0;
    }
    c->ref_box_taken = s1;
    return 1;
}

static void on_host_ref(fd_core_t *c, const fd_can_frame_t *f)
{
    struct fd_can_host_ref_t m;
    if (fd_can_host_ref_unpack(&m, f->data, f->len) != 0) {
        c->stats.bad_rx++;
        return;
    }
    fd_host_ref_t r;
    r.seq = m.ref_seq;
    r.valid = 1;
    r.enable = m.ref_enable;
    r.id = fd_can_host_ref_ref_id_decode(m.ref_id);
    r.iq = fd_can_host_ref_ref_iq_decode(m.ref_iq);
    r.theta = fd_can_host_ref_ref_theta_decode(m.ref_theta);
    r.omega = fd_can_host_ref_ref_omega_decode(m.ref_omega);
    /* its age against the drive's period counter (16-bit, wrap-safe): numbered ahead of
     * the drive it cannot be a sample the drive sent; older than ref_max_age_periods it
     * would be extrapolated too far */
    int16_t age = (int16_t)(uint16_t)((uint16_t)(c->k & FD_SEQ_MASK) - r.seq);
    if (age < 0) {
        c->stats.ref_future++;
        return;
    }
    if ((uint32_t)age > c->cfg.ref_max_age_periods) {
        c->stats.ref_old++;
        return;
    }
    /* a reference older than the one in use arrived too late */
    if (c->ref.valid && (int16_t)(uint16_t)(r.seq - c->ref.seq) <= 0) {
        c->stats.duty_late++;
        return;
    }
    publish_reference(c, &r);
    c->stats.ref_rx++;
}

static void on_drive_param(fd_core_t *c, const fd_can_frame_t *f)
{
    struct fd_can_drive_param_t m;
    if (fd_can_drive_param_unpack(&m, f->data, f->len) != 0) {
        c->stats.bad_rx++;
        return;
    }
    c->stats.param_rx++;
    int status = FD_PA_OK;
    if (m.prm_write && m.prm_id == FD_PRM_PARAM_SAVE && m.prm_value == 1.0f) {
        status = save_params(c); /* locks only while it copies */
    }
    uint32_t irq = fd_hal_irq_lock(c->hal); /* the limits change together */
    if (m.prm_write && !(m.prm_id == FD_PRM_PARAM_SAVE && m.prm_value == 1.0f)) {
        status = fd_core_param_write(c, m.prm_id, m.prm_value);
    }
    float value = 0.0f;
    int rs = fd_core_param_read(c, m.prm_id, &value);
    fd_fault_entry_t log[FD_FAULT_LOG];
    uint32_t n_log = 0;
    if (m.prm_id == FD_PRM_FAULT_LOG && rs == FD_PA_OK) { /* copied under the lock */
        for (; fd_core_fault_log(c, n_log, &log[n_log]); ++n_log) {
        }
    }
    fd_hal_irq_unlock(c->hal, irq);
    if (rs != FD_PA_OK) {
        status = rs;
    }
    uint8_t b[8];
    int n = fd_encode_param_ack(b, m.prm_id, m.prm_seq, (uint8_t)status, value);
    send(c, FD_CAN_DRIVE_PARAM_ACK_FRAME_ID, b, n, 0);
    for (uint32_t i = 0; i < n_log; ++i) { /* the entries, newest first */
        struct fd_can_fault_log_t e;
        fd_can_fault_log_init(&e);
        e.fl_index = (uint8_t)i;
        e.fl_code = log[i].code;
        e.fl_detail = log[i].detail;
        e.fl_period = log[i].k;
        send(c, FD_CAN_FAULT_LOG_FRAME_ID, b, fd_can_fault_log_pack(b, &e, 8), 0);
    }
}

int fd_core_fault_log(const fd_core_t *c, uint32_t i, fd_fault_entry_t *out)
{
    if (i >= FD_FAULT_LOG || i >= c->fault_log_n) {
        return 0;
    }
    *out = c->fault_log[(c->fault_log_n - 1u - i) % FD_FAULT_LOG];
    return 1;
}

void fd_core_handle_frame(fd_core_t *c, const fd_can_frame_t *f)
{
    uint32_t irq;
    c->stats.bg_frames++;
    switch (f->id) {
    case FD_CAN_ARM_MODE_FRAME_ID:
        irq = fd_hal_irq_lock(c->hal); /* the state machine is the interrupt's too */
        on_arm_mode(c, f);
        fd_hal_irq_unlock(c->hal, irq);
        break;
    case FD_CAN_DUTY_CMD_FRAME_ID:
        on_duty_cmd(c, f);
        break;
    case FD_CAN_HOST_REF_FRAME_ID:
        on_host_ref(c, f);
        break;
    case FD_CAN_DRIVE_PARAM_FRAME_ID:
        on_drive_param(c, f);
        break;
    case FD_CAN_HOST_HEARTBEAT_FRAME_ID:
        irq = fd_hal_irq_lock(c->hal);
        c->hb_seen = 1;
        c->hb_last_us = fd_hal_time_us(c->hal);
        fd_hal_irq_unlock(c->hal, irq);
        break;
    default:
        break;
    }
}

unsigned fd_core_background(fd_core_t *c)
{
    fd_can_frame_t f;
    unsigned n = 0;
    /* bus-off seen by the interrupt: start the controller's recovery (once per event) */
    uint32_t offs = c->stats.can_bus_offs;
    if (offs != c->bus_off_recovered) {
        c->bus_off_recovered = offs;
        fd_hal_can_recover(c->hal);
    }
    while (n < FD_BG_FRAMES && fd_hal_can_rx(c->hal, &f)) {
        fd_core_handle_frame(c, &f);
        n++;
    }
    return n;
}

int fd_core_has_answer(const fd_core_t *c, uint16_t seq)
{
    if (c->split) {
        unsigned s = atomic_load_explicit(&c->ref_box.seq, memory_order_acquire);
        return s != c->ref_box_taken && !(s & 1u) && c->ref_box.ref.seq == seq;
    }
    for (unsigned s = 0; s < FD_CMD_SLOTS; ++s) {
        if (c->cmds[s].valid && c->cmds[s].seq == seq) {
            return 1;
        }
    }
    const fd_cmd_ring_t *r = &c->cmd_ring;
    unsigned head = atomic_load_explicit(&r->head, memory_order_acquire);
    for (unsigned i = atomic_load_explicit(&r->tail, memory_order_relaxed); i != head; ++i) {
        if (r->slot[i % FD_CMD_RING].seq == seq) {
            return 1;
        }
    }
    return 0;
}

/* ------------------------------------------------------------------ commands */

/* host mode, at a sample boundary: the DUTY_CMD answering the previous sample (k-D) */
static void take_command(fd_core_t *c)
{
    uint32_t d = c->cfg.decimation;
    if (!c->ran_first) { /* the first boundary: no sample before it to answer */
        c->ran_first = 1;
        return;
    }
    uint16_t want = (uint16_t)((c->k - d) & FD_SEQ_MASK);
    fd_duty_cmd_t *cmd = 0;
    for (unsigned s = 0; s < FD_CMD_SLOTS; ++s) {
        fd_duty_cmd_t *x = &c->cmds[s];
        if (!x->valid) {
            continue;
        }
        uint16_t behind = (uint16_t)(want - x->seq);
        if (behind == 0u) {
            cmd = x;
        } else if (behind < 0x8000u) { /* answers an older sample: too late, dropped */
            x->valid = 0;
            c->stats.duty_late++;
        }
    }
    if (cmd != 0) {
        cmd->valid = 0;
        for (int j = 0; j < 3; ++j) {
            c->duty[j] = clampf(cmd->duty[j], 0.0f, 1.0f);
        }
        c->applied_seq = want;
        c->last_cmd_k = c->k;
        c->stale_prev = 0;
        c->stats.duty_applied++;
        if (cmd->enable && c->armed && !c->fault_latched) {
            c->pwm_enabled = 1;
            c->mode = FD_MODE_RUN;
        } else if (!cmd->enable) {
            c->pwm_enabled = 0;
        }
    } else {
        c->stale_prev = 1;
        c->stats.stale_periods++;
        uint32_t elapsed_us = (c->k - c->last_cmd_k) * c->cfg.period_us;
        if (c->pwm_enabled && elapsed_us >= c->cmd_timeout_us) {
            raise_fault(c, FD_FAULT_WATCHDOG, (uint16_t)(elapsed_us / 100u));
        }
    }
}

/* angle of reference r extrapolated to this period: theta_j + omega_j (t_k - t_j) */
static float ref_angle(const fd_core_t *c, const fd_host_ref_t *r)
{
    uint16_t n = (uint16_t)((c->k - r->seq) & FD_SEQ_MASK);
    return r->theta + r->omega * ((float)n * c->cfg.ts_s);
}

/* split mode, every period: the newest HOST_REF, the reference timeout */
static void take_reference(fd_core_t *c)
{
    fd_host_ref_t nr;
    int fresh = take_reference_over(c, &nr);
    if (fresh) { /* still newer than the one in use, and not too old by now */
        int16_t age = (int16_t)(uint16_t)((uint16_t)(c->k & FD_SEQ_MASK) - nr.seq);
        if (c->ref.valid && (int16_t)(uint16_t)(nr.seq - c->ref.seq) <= 0) {
            c->stats.duty_late++;
            fresh = 0;
        } else if (age < 0 || (uint32_t)age > c->cfg.ref_max_age_periods) {
            c->stats.ref_old++;
            fresh = 0;
        }
    }
    if (fresh) {
        if (c->ref.valid && c->pwm_enabled) {
            /* keep the current PIs' integrators in the new frame: a fixed voltage vector
             * seen from a frame advanced by (new - old) turns by (old - new) */
            float dth = ref_angle(c, &c->ref) - ref_angle(c, &nr);
            dth = dth - FD_TWO_PI * fd_floorf((dth + FD_PI) * FD_INV_TWO_PI);
            float cs, sn;
            fd_sincosf(dth, &sn, &cs);
            float cid = c->cur.id_i;
            float ciq = c->cur.iq_i;
            c->cur.id_i = cid * cs - ciq * sn;
            c->cur.iq_i = cid * sn + ciq * cs;
        }
        c->ref = nr;
        c->stats.refs_applied++;
        c->last_ref_k = c->k;
        if (c->ref.enable && c->armed && !c->fault_latched) {
            c->pwm_enabled = 1;
            c->mode = FD_MODE_RUN;
        } else if (!c->ref.enable) {
            c->pwm_enabled = 0;
        }
    } else if (c->armed) { /* supervised from arming (last_ref_k set there) */
        uint32_t elapsed_us = (c->k - c->last_ref_k) * c->cfg.period_us;
        if (elapsed_us > seconds_to_us(c->prm[FD_PRM_REF_TIMEOUT_S])) {
            raise_fault(c, FD_FAULT_WATCHDOG, (uint16_t)(elapsed_us / 100u));
        }
    }
}

/* split mode: the current loop on this sample; its duty is written in this interrupt and
 * applies from the next update event (t_(k+1)), like every duty (fd_hal.h). 0: no duty
 * (the reference is beyond the horizon, or the bus too low to modulate) */
static int run_current_loop(fd_core_t *c)
{
    const float sq3 = 1.7320508075688772f;
    fd_cur_params_t p;
    p.kp = c->prm[FD_PRM_CUR_KP];
    p.ki = c->prm[FD_PRM_CUR_KI];
    p.l_hat = c->prm[FD_PRM_L_HAT];
    p.lambda_hat = c->prm[FD_PRM_LAMBDA_HAT];
    p.decouple = c->prm[FD_PRM_DECOUPLE];
    p.advance = c->prm[FD_PRM_VOLTAGE_ADVANCE];
    p.tdcomp_s = c->prm[FD_PRM_DEADTIME_COMP_S];
    float lim = c->prm[FD_PRM_CUR_LIMIT_A];
    /* the extrapolation horizon: periods since the reference's sample */
    uint16_t n = (uint16_t)((c->k - c->ref.seq) & FD_SEQ_MASK);
    if (n > c->cfg.ref_horizon_periods) {
        raise_fault(c, FD_FAULT_STALE_INPUT, n);
        return 0;
    }
    if (!(c->vdc >= c->cfg.vdc_modulation_min_v)) { /* no duty from a bus that low */
        return 0;
    }
    float ia = (2.0f * c->i_abc[0] - c->i_abc[1] - c->i_abc[2]) * (1.0f / 3.0f);
    float ib = (c->i_abc[1] - c->i_abc[2]) * (1.0f / sq3);
    float th = ref_angle(c, &c->ref);
    th = th - FD_TWO_PI * fd_floorf((th + FD_PI) * FD_INV_TWO_PI); /* [-pi, pi) */
    c->theta_used = th;
    fd_current_loop(&c->cur, &p, ia, ib, th, c->ref.omega, clampf(c->ref.id, -lim, lim),
                    clampf(c->ref.iq, -lim, lim), c->vdc, c->cfg.ts_s, &c->cur_out);
    return 1;
}

/* ------------------------------------------------------------------ the interrupt */

static void read_sample(fd_core_t *c)
{
    fd_adc_raw_t adc;
    fd_capture_raw_t cap;
    fd_hal_adc_read(c->hal, &adc);
    fd_hal_capture_read(c->hal, &cap);
    fd_hal_status_read(c->hal, &c->hw);
    if (c->hw.can_bus_off && !c->bus_off_prev) {
        c->stats.can_bus_offs++; /* the background starts the recovery */
    }
    c->bus_off_prev = c->hw.can_bus_off;
    uint8_t clip = 0;
    uint16_t clip_detail = 0;
    for (int j = 0; j < 3; ++j) {
        int32_t raw = adc.current_counts[j];
        int32_t x = raw - c->cfg.current_offset_counts[j];
        /* saturated: at either rail of the converter, or beyond the calibrated span */
        if (raw <= 0 || raw >= c->cfg.current_adc_max_counts || x >= c->cfg.current_clip_counts ||
            x <= -c->cfg.current_clip_counts) {
            if (!clip) {
                int32_t r = raw < 0 ? 0 : (raw > 16383 ? 16383 : raw);
                clip_detail = (uint16_t)((uint32_t)j | ((uint32_t)r << 2));
            }
            clip = 1;
        }
        c->i_abc[j] = ((float)raw - c->cur_off[j]) * c->cfg.current_lsb_a;
    }
    c->clip = clip;
    c->clip_detail = clip_detail;
    c->stats.adc_clipped += clip;
    c->vdc = (float)adc.vdc_counts * c->cfg.vdc_lsb_v;
    float per = cap.period_ticks > 0 ? (float)cap.period_ticks : 1.0f;
    float v_per_tick = c->vdc / per; /* one division for the three phases */
    for (int j = 0; j < 3; ++j) {
        c->v_ll[j] = ((float)cap.high_ticks[j] - c->cap_off[j]) * v_per_tick;
    }
    c->encoder = cap.encoder_counts;
    c->temp_c = adc.temp_c;
    if (c->calibrating) {
        calibration_step(c, &adc, &cap);
    }
}

/* The duties reaching the timer: a non-finite duty is refused (returns 0); each is put in
 * [0, 1]; a triplet above MAX_DUTY is moved down by a common shift (the line voltages stay
 * as they were) while its lowest duty allows it, else each duty is clamped to MAX_DUTY. */
static int guard_duties(fd_core_t *c, const float in[3], float out[3])
{
    float hi = 0.0f;
    float lo = 1.0f;
    for (int j = 0; j < 3; ++j) {
        float d = in[j];
        if (!isfinite(d)) {
            return 0;
        }
        d = clampf(d, 0.0f, 1.0f);
        hi = d > hi ? d : hi;
        lo = d < lo ? d : lo;
        out[j] = d;
    }
    float md = c->max_duty;
    if (hi > md) {
        float shift = hi - md;
        c->stats.duty_limited++;
        for (int j = 0; j < 3; ++j) {
            out[j] = lo >= shift ? out[j] - shift : minf2(out[j], md);
        }
    }
    return 1;
}

static void heartbeat_check(fd_core_t *c)
{
    float hb_s = c->prm[FD_PRM_HEARTBEAT_TIMEOUT_S];
    if (hb_s > 0.0f && c->armed) { /* hb_last_us: the last heartbeat or the arming */
        uint32_t since = fd_hal_time_us(c->hal) - c->hb_last_us;
        if (since > seconds_to_us(hb_s)) {
            uint32_t d = since / 100u;
            raise_fault(c, FD_FAULT_HOST_HEARTBEAT_LOST, (uint16_t)(d > 65535u ? 65535u : d));
        }
    }
}

/* wrap-safe "k has reached t" on the 32-bit period counter */
static int reached(uint32_t k, uint32_t t) { return (int32_t)(k - t) >= 0; }

void fd_core_period(fd_core_t *c)
{
    if (c->in_isr) { /* entered again before the last one returned: never wait */
        raise_fault(c, FD_FAULT_DEADLINE_MISSED, 0xFFFFu);
        const uint32_t half[3] = {c->cfg.pwm_period_ticks / 2u, c->cfg.pwm_period_ticks / 2u,
                                  c->cfg.pwm_period_ticks / 2u};
        fd_hal_pwm_write(c->hal, half, false);
        return;
    }
    c->in_isr = 1;
    read_sample(c);
    /* window: the period [t_(k-1), t_k] just ended (frame 0 opens the first window) */
    for (int j = 0; j < 3; ++j) {
        c->win_v[j] += c->v_ll[j];
        c->win_duty[j] += c->duty_applied[j];
    }
    c->win_n++;
    c->win_pwm = (uint8_t)(c->win_pwm && c->pwm_applied);
    c->win_flags = (uint8_t)(c->win_flags | c->clip);
    protect(c);

    int boundary = (c->k % c->cfg.decimation) == 0u;
    if (boundary) {
        send_sample(c);
        reset_window(c);
    }
    if (reached(c->k, c->next_status_k)) {
        send_status(c, c->temp_c);
        c->next_status_k = c->k + c->cfg.status_period;
    }
    if (c->fault_latched && reached(c->k, c->next_fault_k)) {
        send_fault(c, 0);
        c->next_fault_k = c->k + c->cfg.status_period;
    }
    take_commands_over(c); /* bounded: FD_CMD_RING at most */
    if (c->split) {
        take_reference(c);
    } else if (boundary) {
        take_command(c);
    }
    heartbeat_check(c);
    if (!c->armed) {
        c->pwm_enabled = 0;
    }

    /* output: written now, in force from the update event at t_(k+1) (compare preload);
     * an enable cleared here opens the switches at once (fd_hal.h) */
    uint8_t enable = c->pwm_enabled;
    uint8_t boot = (uint8_t)(enable && c->bootstrap_left > 0u);
    if (c->split) {
        int have = 0;
        if (c->pwm_enabled && !boot) { /* after the bootstrap charge: the current loop */
            have = run_current_loop(c);
            for (int j = 0; j < 3; ++j) {
                c->duty[j] = have ? c->cur_out.duty[j] : 0.5f;
            }
            if (!have) {
                enable = 0; /* no duty this period: the gates stay open */
            }
        } else if (!c->pwm_enabled) {
            for (int j = 0; j < 3; ++j) {
                c->duty[j] = 0.5f;
            }
            c->cur.id_i = 0.0f;
            c->cur.iq_i = 0.0f;
        }
        enable = (uint8_t)(enable && c->pwm_enabled); /* the loop may have tripped */
    }
    float d[3];
    if (boot && enable) { /* bootstrap charge: low sides on (upper duty 0) */
        c->bootstrap_left--;
        d[0] = d[1] = d[2] = 0.0f;
    } else if (!guard_duties(c, c->duty, d)) {
        raise_fault(c, FD_FAULT_INTERNAL, 1u); /* a non-finite duty never reaches the gates */
        enable = 0;
        d[0] = d[1] = d[2] = 0.5f;
    }
    uint32_t cmp[3];
    for (int j = 0; j < 3; ++j) {
        cmp[j] = (uint32_t)(d[j] * c->ticks_f + 0.5f); /* d in [0, 1] */
        /* the period [t_k, t_(k+1)] runs on what the previous interrupt wrote */
        c->duty_applied[j] = c->duty_preload[j];
        c->duty_preload[j] = (float)cmp[j] * c->inv_ticks;
    }
    c->pwm_applied = (uint8_t)(c->pwm_preload && enable);
    c->pwm_preload = enable;
    fd_hal_pwm_write(c->hal, cmp, enable);
    if (fd_hal_period_overrun(c->hal)) { /* this interrupt ran past its deadline */
        raise_fault(c, FD_FAULT_DEADLINE_MISSED, (uint16_t)(c->k & FD_SEQ_MASK));
        c->pwm_applied = 0; /* a cleared enable acts at once */
        c->pwm_preload = 0;
        fd_hal_pwm_write(c->hal, cmp, false);
    }
    c->k++;
    /* t_mcu of the next sample: k * period mod (2^32 - 1) us, kept without a 64-bit product */
    uint32_t p = c->cfg.period_us;
    c->t_us = c->t_us >= FD_T_MCU_MOD - p ? c->t_us - (FD_T_MCU_MOD - p) : c->t_us + p;
    c->stats.periods++;
    c->in_isr = 0;
}

/* ------------------------------------------------------------------ init */

void fd_config_default(fd_config_t *cfg)
{
    memset(cfg, 0, sizeof(*cfg));
    cfg->period_us = 100u;
    cfg->ts_s = 1.0e-4f;
    cfg->decimation = 1u;
    cfg->classic_layout = 0u;
    cfg->current_lsb_a = 40.0f / 4096.0f; /* 12 bit over +-20 A */
    for (int j = 0; j < 3; ++j) {
        cfg->current_offset_counts[j] = 2048;
    }
    cfg->current_clip_counts = 2048;
    cfg->vdc_lsb_v = 100.0f / 4096.0f;
    cfg->pwm_period_ticks = 50000u;
    cfg->cmd_timeout_us = 1000u;
    cfg->status_period = 1000u;
    /* the reference board: 12-bit current ADC over +-20 A, 100 V bus ADC, a 48 V stage */
    cfg->current_adc_max_counts = 4095;
    cfg->oc_limit_a = 0.9f * 20.0f;    /* 18 A: 10 % below the ADC's full scale */
    cfg->vdc_max_v = 60.0f;            /* the stage's 60 V rating (100 V ADC span) */
    cfg->vdc_min_v = 10.0f;            /* gate-driver supply limit of a 48 V stage */
    cfg->vdc_modulation_min_v = 6.0f;  /* below: no duty computed or applied */
    cfg->temp_max_c = 90;
    cfg->temp_hysteresis_c = 10;
    cfg->bootstrap_periods = 10u;      /* 1 ms low sides on before the first switching */
    cfg->ref_max_age_periods = 100u;   /* 10 ms */
    cfg->ref_horizon_periods = 200u;   /* 20 ms of extrapolation at most */
    cfg->cal_periods = 1000u;          /* 0.1 s with the bridge off */
    cfg->cal_max_offset_counts = 205;  /* 2 A of a 20 A full scale */
    cfg->require_calibration = 1u;
}

void fd_core_init(fd_core_t *c, const fd_config_t *cfg, void *hal)
{
    memset(c, 0, sizeof(*c));
    c->cfg = *cfg;
    if (c->cfg.decimation == 0u) {
        c->cfg.decimation = 1u;
    }
    c->hal = hal;
    for (int i = 1; i < (int)FD_PRM_COUNT; ++i) {
        c->prm[i] = PRM_SPEC[i].dflt;
    }
    c->cmd_timeout_us = cfg->cmd_timeout_us;
    for (int j = 0; j < 3; ++j) {
        c->duty[j] = 0.5f;
        c->duty_applied[j] = 0.5f;
        c->duty_preload[j] = 0.5f;
    }
    c->win_pwm = 1;
    c->mode = FD_MODE_IDLE;
    for (int j = 0; j < 3; ++j) {
        c->cur_off[j] = (float)c->cfg.current_offset_counts[j];
        c->cap_off[j] = 0.0f;
    }
    if (c->cfg.cal_periods == 0u || c->cfg.cal_periods > 65536u) {
        c->cfg.cal_periods = c->cfg.cal_periods == 0u ? 1u : 65536u; /* sums fit int32 */
    }
    load_params(c);
    c->ticks_f = (float)c->cfg.pwm_period_ticks;
    c->inv_ticks = c->cfg.pwm_period_ticks > 0u ? 1.0f / c->ticks_f : 0.0f;
    update_limits(c);
}
