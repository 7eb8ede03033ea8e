/* C unit tests of the drive core on the software-in-the-loop HAL: arm key, duty watchdog,
 * fault latch and reset, decimation averages, protections, DRIVE_PARAM, reference timeout.
 * Expected values follow from the DBC's rules (CM_ comments) and the configuration; the
 * comparisons with the engine's Python reference (I2t, current loop, codec, emulator) are
 * in tests/test_firmware.py. Exit status 0 = all passed. */
#include <math.h>
#include <stdatomic.h>
#include <stdio.h>
#include <string.h>

#include "fd_can.h"
#include "fd_core.h"
#include "fd_sil.h"

static int failures = 0;
#define CHECK(cond)                                                                        \
    do {                                                                                   \
        if (!(cond)) {                                                                     \
            fprintf(stderr, "%s:%d: CHECK failed: %s\n", __FILE__, __LINE__, #cond);       \
            failures++;                                                                    \
        }                                                                                  \
    } while (0)

static fd_core_t core;
static fd_sil_t sil;
static int32_t cur_counts[3] = {2048, 2048, 2048};
static int32_t ticks[3] = {0, 0, 0};
static int32_t vdc_counts = 983; /* 24.0 V at 100/4096 V per count */

static void setup(uint8_t decimation)
{
    fd_config_t cfg;
    fd_config_default(&cfg);
    cfg.decimation = decimation;
    cfg.bootstrap_periods = 0u;   /* the bootstrap charge and the calibration have */
    cfg.require_calibration = 0u; /* tests of their own */
    fd_sil_init(&sil);
    fd_core_init(&core, &cfg, &sil);
}

static void period(void)
{
    fd_sil_set_inputs(&sil, cur_counts, vdc_counts, ticks, 4096, 0, 35,
                      core.k * core.cfg.period_us);
    while (fd_core_background(&core) > 0u) { /* the background before the interrupt */
    }
    fd_core_period(&core);
}

static void push(uint32_t id, const uint8_t *data, uint32_t len, uint32_t fd)
{
    CHECK(fd_sil_rx_push(&sil, id, data, len, fd) == 1);
}

static void send_arm(uint8_t arm, uint8_t key, uint8_t reset, uint8_t split)
{
    struct fd_can_arm_mode_t m;
    uint8_t b[8];
    fd_can_arm_mode_init(&m);
    m.arm = arm;
    m.arm_key = key;
    m.reset_fault = reset;
    m.control_split = split;
    m.mode = FD_MODE_RUN;
    m.decimation = core.cfg.decimation;
    CHECK(fd_can_arm_mode_pack(b, &m, 8) == 8);
    push(FD_CAN_ARM_MODE_FRAME_ID, b, 8, 0);
}

static void send_duty(uint16_t seq, float d, uint8_t enable)
{
    struct fd_can_duty_cmd_t m;
    uint8_t b[8];
    fd_can_duty_cmd_init(&m);
    m.cmd_seq = seq;
    m.cmd_duty_a = m.cmd_duty_b = m.cmd_duty_c = fd_can_duty_cmd_cmd_duty_a_encode(d);
    m.cmd_enable = enable;
    CHECK(fd_can_duty_cmd_pack(b, &m, 8) == 8);
    push(FD_CAN_DUTY_CMD_FRAME_ID, b, 8, 0);
}

/* pop every sent frame; remember the last FAULT / SAMPLE_FD / ACK */
static struct fd_can_fault_t last_fault;
static int n_fault;
static struct fd_can_sample_fd_t last_sample;
static int n_sample;
static struct fd_can_drive_param_ack_t last_ack;
static int n_ack;

static void drain(void)
{
    uint32_t id, len, fd;
    uint8_t b[64];
    while (fd_sil_tx_pop(&sil, &id, b, &len, &fd)) {
        if (id == FD_CAN_FAULT_FRAME_ID) {
            CHECK(fd_can_fault_unpack(&last_fault, b, len) == 0);
            n_fault++;
        } else if (id == FD_CAN_SAMPLE_FD_FRAME_ID) {
            CHECK(fd == 1 && len == 64);
            CHECK(fd_can_sample_fd_unpack(&last_sample, b, len) == 0);
            n_sample++;
        } else if (id == FD_CAN_DRIVE_PARAM_ACK_FRAME_ID) {
            CHECK(fd_can_drive_param_ack_unpack(&last_ack, b, len) == 0);
            n_ack++;
        }
    }
}

/* arm, and run host mode with PWM on for a few periods answering every sample */
static void run_armed(void)
{
    send_arm(1, FD_ARM_KEY, 0, 0);
    for (int i = 0; i < 5; ++i) {
        if (core.k >= 1) {
            send_duty((uint16_t)(core.k - 1), 0.5f, 1);
        }
        period();
    }
    drain();
}

static void test_arm_key(void)
{
    setup(1);
    period();
    send_arm(1, 0x5A, 0, 0); /* wrong key: stays disarmed */
    period();
    CHECK(!core.armed);
    send_duty(1, 0.6f, 1); /* enable while disarmed: ignored */
    period();
    CHECK(!core.pwm_enabled && sil.pwm_enable == 0);
    send_arm(1, FD_ARM_KEY, 0, 0);
    send_duty(2, 0.6f, 1);
    period();
    CHECK(core.armed && core.pwm_enabled && sil.pwm_enable == 1);
    CHECK(sil.pwm_compare[0] == 30000u); /* 0.6 of 50000 ticks */
    send_arm(0, FD_ARM_KEY, 0, 0); /* disarm: PWM off in this very period */
    period();
    CHECK(!core.armed && !core.pwm_enabled && sil.pwm_enable == 0);
}

static void test_watchdog(void)
{
    setup(1);
    run_armed();
    CHECK(core.pwm_enabled);
    uint32_t last = core.k; /* the last command was taken in period last-1 */
    n_fault = 0;
    int tripped_at = -1;
    for (int i = 0; i < 20 && tripped_at < 0; ++i) {
        period();
        if (core.fault_latched) {
            tripped_at = (int)(core.k - 1u);
        }
    }
    drain();
    /* default cmd_timeout 1 ms = 10 periods after the last fresh command */
    CHECK(tripped_at == (int)(last - 1u + 10u));
    CHECK(core.fault_code == FD_FAULT_WATCHDOG && !core.pwm_enabled && sil.pwm_enable == 0);
    CHECK(n_fault == 1 && last_fault.fault_code == FD_FAULT_WATCHDOG && last_fault.fault_latched == 1);
    CHECK(last_fault.fault_detail == 10); /* elapsed 1.0 ms in 0.1 ms */
    CHECK(last_fault.fault_seq == (uint16_t)tripped_at);
    /* FAULT repeated at 10 Hz while latched */
    n_fault = 0;
    for (int i = 0; i < 2000; ++i) {
        period();
        drain();
    }
    CHECK(n_fault == 2); /* at trip + 1000 and trip + 2000 periods */
}

static void test_fault_latch_reset(void)
{
    setup(1);
    fd_core_param_write(&core, FD_PRM_OVERCURRENT_A, 10.0f);
    run_armed();
    cur_counts[1] = 2048 - 1100; /* -10.74 A on phase b */
    period();
    drain();
    CHECK(core.fault_latched && core.fault_code == FD_FAULT_OVERCURRENT && !core.armed);
    CHECK(last_fault.fault_code == FD_FAULT_OVERCURRENT);
    CHECK((last_fault.fault_detail & 3u) == 1u);           /* phase b */
    CHECK((last_fault.fault_detail >> 2) == 107u);         /* 10.7 A in 0.1 A */
    send_arm(1, FD_ARM_KEY, 1, 0); /* reset while the cause persists: refused, stays off */
    period();
    CHECK(core.fault_latched && !core.armed);
    cur_counts[1] = 2048;
    send_arm(1, FD_ARM_KEY, 1, 0); /* no rising edge: nothing */
    period();
    CHECK(core.fault_latched);
    send_arm(0, FD_ARM_KEY, 0, 0);
    period();
    n_fault = 0;
    send_arm(0, FD_ARM_KEY, 1, 0); /* rising edge, cause gone: cleared, FAULT code 0 */
    period();
    drain();
    CHECK(!core.fault_latched && core.fault_code == FD_FAULT_NONE);
    CHECK(n_fault == 1 && last_fault.fault_code == FD_FAULT_NONE && last_fault.fault_latched == 0);
}

static void test_decimation_average(void)
{
    setup(4);
    n_sample = 0;
    period(); /* k = 0: a sample of frame 0 alone */
    drain();
    CHECK(n_sample == 1 && last_sample.seq == 0);
    const int32_t t[4] = {100, 300, -200, 1000};
    for (int i = 0; i < 4; ++i) {
        ticks[0] = t[i];
        ticks[1] = 2 * t[i];
        period();
    }
    drain();
    ticks[0] = ticks[1] = 0;
    CHECK(n_sample == 2 && last_sample.seq == 4);
    /* v_ab = mean(ticks) / 4096 * vdc, vdc = 983 * 100/4096 V */
    double vdc = 983.0 * 100.0 / 4096.0;
    double v_ab = (100.0 + 300.0 - 200.0 + 1000.0) / 4.0 / 4096.0 * vdc;
    CHECK(last_sample.v_ab == (int32_t)lround(v_ab / 0.001));
    CHECK(last_sample.v_bc == (int32_t)lround(2.0 * v_ab / 0.001));
    CHECK(last_sample.vdc == (uint16_t)lround(vdc / 0.002));
    CHECK(last_sample.capture_valid == 0 && last_sample.pwm_enabled == 0);
    CHECK(last_sample.t_mcu == 400u);
}

static void test_bus_voltage(void)
{
    setup(1);
    fd_core_param_write(&core, FD_PRM_VDC_MIN_V, 20.0f);
    fd_core_param_write(&core, FD_PRM_VDC_MAX_V, 30.0f);
    vdc_counts = 700; /* 17.1 V: below the minimum, but not armed: no fault */
    period();
    CHECK(!core.fault_latched);
    vdc_counts = 983;
    run_armed();
    vdc_counts = 700;
    period();
    drain();
    CHECK(core.fault_code == FD_FAULT_UNDERVOLTAGE && last_fault.fault_detail == 1708u);
    vdc_counts = 1300; /* 31.7 V */
    period(); /* a reset is judged (in the background) on the last sample taken */
    CHECK(core.fault_code == FD_FAULT_UNDERVOLTAGE);
    send_arm(0, FD_ARM_KEY, 1, 0);
    n_fault = 0;
    period(); /* the reset clears UV (the bus is above its minimum), this sample trips OV */
    drain();
    CHECK(core.fault_code == FD_FAULT_OVERVOLTAGE && n_fault == 2);
    CHECK(last_fault.fault_code == FD_FAULT_OVERVOLTAGE);
    vdc_counts = 983;
}

static void test_params(void)
{
    setup(1);
    CHECK(fd_core_param_write(&core, 0, 1.0f) == FD_PA_UNKNOWN_PARAM);
    CHECK(fd_core_param_write(&core, FD_PRM_COUNT, 1.0f) == FD_PA_UNKNOWN_PARAM);
    CHECK(fd_core_param_write(&core, FD_PRM_CUR_KP, NAN) == FD_PA_NOT_FINITE);
    CHECK(fd_core_param_write(&core, FD_PRM_CUR_KP, -1.0f) == FD_PA_OUT_OF_RANGE);
    CHECK(fd_core_param_write(&core, FD_PRM_CUR_KP, 2.5f) == FD_PA_OK && core.prm[1] == 2.5f);
    run_armed();
    CHECK(fd_core_param_write(&core, FD_PRM_POLE_PAIRS, 5.0f) == FD_PA_NOT_WHILE_RUNNING);
    CHECK(fd_core_param_write(&core, FD_PRM_CUR_KI, 100.0f) == FD_PA_OK); /* live */
    /* over the bus: a write answered by one ACK with the value in effect */
    struct fd_can_drive_param_t m;
    uint8_t b[8];
    fd_can_drive_param_init(&m);
    m.prm_id = FD_PRM_REF_TIMEOUT_S;
    m.prm_seq = 7;
    m.prm_write = 1;
    m.prm_value = 50.0f; /* beyond 10 s */
    CHECK(fd_can_drive_param_pack(b, &m, 8) == 8);
    push(FD_CAN_DRIVE_PARAM_FRAME_ID, b, 8, 0);
    n_ack = 0;
    period();
    drain();
    CHECK(n_ack == 1 && last_ack.pa_seq == 7 && last_ack.pa_status == FD_PA_OUT_OF_RANGE);
    CHECK(last_ack.pa_value == 1.0e-2f);
}

static void send_ref(uint16_t seq, float iq, uint8_t enable)
{
    struct fd_can_host_ref_t m;
    uint8_t b[12];
    fd_can_host_ref_init(&m);
    m.ref_seq = seq;
    m.ref_iq = fd_can_host_ref_ref_iq_encode(iq);
    m.ref_enable = enable;
    CHECK(fd_can_host_ref_pack(b, &m, 12) == 12);
    push(FD_CAN_HOST_REF_FRAME_ID, b, 12, 1);
}

static void test_reference_timeout(void)
{
    setup(1);
    send_arm(1, FD_ARM_KEY, 0, 1);
    period();
    CHECK(core.armed && core.split);
    send_ref(0, 1.0f, 1);
    period(); /* reference taken, PWM on: the first duty written, in force from t_(k+1) */
    CHECK(core.pwm_enabled && sil.pwm_enable == 1);
    period();
    CHECK(sil.pwm_enable == 1);
    uint32_t taken = core.k - 2u;
    n_fault = 0;
    while (!core.fault_latched && core.k < 200u) {
        period();
        drain();
    }
    drain();
    /* REF_TIMEOUT_S default 10 ms: the first period more than 100 periods after the
     * reference was taken */
    CHECK(core.k - 1u == taken + 101u);
    CHECK(core.fault_code == FD_FAULT_WATCHDOG && sil.pwm_enable == 0 && n_fault == 1);
}

static void send_heartbeat(void)
{
    struct fd_can_host_heartbeat_t m;
    uint8_t b[2];
    fd_can_host_heartbeat_init(&m);
    m.hb_protocol_version = 2;
    CHECK(fd_can_host_heartbeat_pack(b, &m, 2) == 2);
    push(FD_CAN_HOST_HEARTBEAT_FRAME_ID, b, 2, 0);
}

static void test_host_heartbeat(void)
{
    setup(1);
    /* armed without any heartbeat yet: no timeout runs */
    for (int i = 0; i < 3; ++i) {
        period();
    }
    send_heartbeat();
    run_armed(); /* heartbeat taken at t = 0.3 ms; default HEARTBEAT_TIMEOUT_S 0.5 s */
    uint32_t hb_k = 3u;
    while (!core.fault_latched && core.k < 6000u) {
        if (core.k >= 1u) {
            send_duty((uint16_t)(core.k - 1u), 0.5f, 1);
        }
        period();
        drain();
    }
    /* the first period more than 0.5 s (5000 periods of 100 us) after the heartbeat */
    CHECK(core.fault_code == FD_FAULT_HOST_HEARTBEAT_LOST && core.k - 1u == hb_k + 5001u);
    CHECK(last_fault.fault_code == FD_FAULT_HOST_HEARTBEAT_LOST && last_fault.fault_detail == 5001u);
    CHECK(!core.armed && sil.pwm_enable == 0);
    /* 0 turns the timeout off */
    setup(1);
    CHECK(fd_core_param_write(&core, FD_PRM_HEARTBEAT_TIMEOUT_S, 0.0f) == FD_PA_OK);
    send_heartbeat();
    run_armed();
    for (int i = 0; i < 6000; ++i) {
        send_duty((uint16_t)(core.k - 1u), 0.5f, 1);
        period();
        drain();
    }
    CHECK(!core.fault_latched && core.pwm_enabled);
}

/* ---------------------------------------------------------------- fault injection
 * Each protection: the injected condition in sample k -> PWM off in the output of the
 * same period interrupt (0 periods), the fault latched, one FAULT frame with its code. */

static int32_t temp_c = 35;

static void period_t(void)
{
    fd_sil_set_inputs(&sil, cur_counts, vdc_counts, ticks, 4096, 0, temp_c,
                      core.k * core.cfg.period_us);
    while (fd_core_background(&core) > 0u) {
    }
    fd_core_period(&core);
}

/* host mode, PWM on (board defaults but no bootstrap), then one period with `inject`
 * applied before it; checks the trip in that very period */
static void expect_trip(uint8_t code, void (*inject)(void))
{
    setup(1);
    run_armed();
    CHECK(core.pwm_enabled && sil.pwm_enable == 1);
    n_fault = 0;
    inject();
    send_duty((uint16_t)(core.k - 1u), 0.5f, 1);
    period_t();
    drain();
    if (core.fault_code != code) {
        fprintf(stderr, "expected fault %u, got %u\n", code, core.fault_code);
    }
    CHECK(core.fault_latched && core.fault_code == code);
    CHECK(!core.pwm_enabled && sil.pwm_enable == 0); /* off from this period's output */
    CHECK(n_fault == 1 && last_fault.fault_code == code && last_fault.fault_pwm_disabled == 1);
    /* held: 20 more periods of the condition, PWM stays off, no new FAULT frame but the
     * 10 Hz repeat */
    for (int i = 0; i < 20; ++i) {
        period_t();
        CHECK(sil.pwm_enable == 0);
    }
    cur_counts[0] = cur_counts[1] = cur_counts[2] = 2048;
    vdc_counts = 983;
    temp_c = 35;
    fd_sil_inject(&sil, 0, 0, 0, 0, 0);
    fd_sil_set_break(&sil, 0, 0);
}

static void inj_adc_low(void) { cur_counts[0] = 0; }          /* held at count 0 */
static void inj_adc_high(void) { cur_counts[2] = 4095; }      /* held at count 4095 */
static void inj_overcurrent(void) { cur_counts[1] = 2048 + 1850; } /* 18.07 A > 18 A cap */
static void inj_break(void) { fd_sil_set_break(&sil, 2048, 600); cur_counts[0] = 2048 + 700; }
static void inj_gate(void) { fd_sil_inject(&sil, 1, 0, 0, 0, 0); }
static void inj_hot(void) { temp_c = 90; }
static void inj_overvoltage(void) { vdc_counts = 2500; } /* 61.0 V > the 60 V rating */
static void inj_zero_bus(void) { vdc_counts = 0; }
static void inj_overrun(void) { fd_sil_inject(&sil, 0, 0, 0, 0, 1); }

static void test_fault_injection(void)
{
    expect_trip(FD_FAULT_ADC_FAULT, inj_adc_low);
    CHECK((last_fault.fault_detail & 3u) == 0u && (last_fault.fault_detail >> 2) == 0u);
    expect_trip(FD_FAULT_ADC_FAULT, inj_adc_high);
    CHECK((last_fault.fault_detail & 3u) == 2u && (last_fault.fault_detail >> 2) == 4095u);
    expect_trip(FD_FAULT_OVERCURRENT, inj_overcurrent);
    CHECK((last_fault.fault_detail & 3u) == 1u && (last_fault.fault_detail >> 2) == 180u);
    expect_trip(FD_FAULT_OVERCURRENT, inj_break);
    CHECK(last_fault.fault_detail == FD_OC_DETAIL_BREAK);
    expect_trip(FD_FAULT_GATE_DRIVER, inj_gate);
    expect_trip(FD_FAULT_OVERTEMPERATURE, inj_hot);
    CHECK(last_fault.fault_detail == 90u);
    expect_trip(FD_FAULT_OVERVOLTAGE, inj_overvoltage);
    expect_trip(FD_FAULT_UNDERVOLTAGE, inj_zero_bus);
    CHECK(last_fault.fault_detail == 0u);
    expect_trip(FD_FAULT_DEADLINE_MISSED, inj_overrun);
}

static void test_board_caps(void)
{
    setup(1);
    float v = 0.0f;
    /* the host may ask for more; the drive keeps its board limit and says so */
    CHECK(fd_core_param_write(&core, FD_PRM_OVERCURRENT_A, 1000.0f) == FD_PA_OK);
    CHECK(fd_core_param_read(&core, FD_PRM_OVERCURRENT_A, &v) == FD_PA_OK && v == 18.0f);
    CHECK(v < 2048.0f * core.cfg.current_lsb_a); /* below the ADC's full scale */
    CHECK(fd_core_param_write(&core, FD_PRM_VDC_MAX_V, 1.0e4f) == FD_PA_OK);
    CHECK(fd_core_param_read(&core, FD_PRM_VDC_MAX_V, &v) == FD_PA_OK && v == 60.0f);
    CHECK(fd_core_param_write(&core, FD_PRM_VDC_MIN_V, 0.0f) == FD_PA_OK);
    CHECK(fd_core_param_read(&core, FD_PRM_VDC_MIN_V, &v) == FD_PA_OK && v == 10.0f);
    CHECK(fd_core_param_write(&core, FD_PRM_OVERCURRENT_A, 5.0f) == FD_PA_OK); /* tighter */
    CHECK(fd_core_param_read(&core, FD_PRM_OVERCURRENT_A, &v) == FD_PA_OK && v == 5.0f);
    /* the fault reset needs the cause gone: a hot stage until 10 degC below the trip */
    expect_trip(FD_FAULT_OVERTEMPERATURE, inj_hot);
    temp_c = 81;
    period_t(); /* a reset is judged on the last sample taken */
    send_arm(0, FD_ARM_KEY, 1, 0);
    period_t();
    CHECK(core.fault_latched);
    send_arm(0, FD_ARM_KEY, 0, 0);
    temp_c = 79;
    period_t();
    send_arm(0, FD_ARM_KEY, 1, 0);
    period_t();
    CHECK(!core.fault_latched);
    temp_c = 35;
}

/* a NaN bus (a broken scale) trips like a 0 V bus: nothing NaN reaches the timer */
static void test_nan_bus(void)
{
    fd_config_t cfg;
    fd_config_default(&cfg);
    cfg.bootstrap_periods = 0u;
    cfg.require_calibration = 0u;
    cfg.vdc_lsb_v = NAN;
    fd_sil_init(&sil);
    fd_core_init(&core, &cfg, &sil);
    send_arm(1, FD_ARM_KEY, 0, 1); /* split mode: the current loop divides by the bus */
    period();
    /* !(NaN <= VDC_MAX) is the first bus check to trip */
    CHECK(core.fault_code == FD_FAULT_OVERVOLTAGE && sil.pwm_enable == 0);
    for (int j = 0; j < 3; ++j) {
        CHECK(sil.pwm_compare[j] <= cfg.pwm_period_ticks);
    }
    /* the last line: a NaN duty (here a NaN gain forced past the parameter checks) is
     * refused at the timer with fault INTERNAL */
    setup(1);
    CHECK(fd_core_param_write(&core, FD_PRM_CUR_KP, 1.0f) == FD_PA_OK);
    CHECK(fd_core_param_write(&core, FD_PRM_HEARTBEAT_TIMEOUT_S, 0.0f) == FD_PA_OK);
    send_arm(1, FD_ARM_KEY, 0, 1);
    period();
    send_ref(0, 1.0f, 1);
    period();
    period();
    CHECK(sil.pwm_enable == 1);
    core.prm[FD_PRM_CUR_KP] = NAN;
    send_ref((uint16_t)(core.k - 1u), 1.0f, 1);
    period(); /* the loop computes a NaN duty for the next period */
    send_ref((uint16_t)(core.k - 1u), 1.0f, 1);
    period();
    drain();
    CHECK(core.fault_code == FD_FAULT_INTERNAL && sil.pwm_enable == 0);
    for (int j = 0; j < 3; ++j) {
        CHECK(sil.pwm_compare[j] == 25000u);
    }
}

static void test_heartbeat_from_arming(void)
{
    setup(1);
    period();
    run_armed(); /* armed in period 1 at 100 us, no heartbeat ever: supervised from there */
    while (!core.fault_latched && core.k < 6000u) {
        send_duty((uint16_t)(core.k - 1u), 0.5f, 1);
        period();
        drain();
    }
    CHECK(core.fault_code == FD_FAULT_HOST_HEARTBEAT_LOST && core.k - 1u == 1u + 5001u);
    CHECK(sil.pwm_enable == 0);
}

static void test_reference_from_arming(void)
{
    setup(1);
    send_arm(1, FD_ARM_KEY, 0, 1);
    period(); /* armed in split mode in period 0; no HOST_REF ever */
    while (!core.fault_latched && core.k < 300u) {
        period();
    }
    CHECK(core.fault_code == FD_FAULT_WATCHDOG && core.k - 1u == 101u);
}

static void test_max_duty(void)
{
    setup(1);
    send_arm(1, FD_ARM_KEY, 0, 0);
    period();
    struct fd_can_duty_cmd_t m;
    uint8_t b[8];
    fd_can_duty_cmd_init(&m);
    m.cmd_seq = 0;
    m.cmd_duty_a = fd_can_duty_cmd_cmd_duty_a_encode(1.0f); /* full on: refused at 0.95 */
    m.cmd_duty_b = fd_can_duty_cmd_cmd_duty_b_encode(0.5f);
    m.cmd_duty_c = fd_can_duty_cmd_cmd_duty_c_encode(0.2f);
    m.cmd_enable = 1;
    CHECK(fd_can_duty_cmd_pack(b, &m, 8) == 8);
    push(FD_CAN_DUTY_CMD_FRAME_ID, b, 8, 0);
    period();
    /* shifted down by 0.05 together (line voltages kept): 0.95, 0.45, 0.15 of 50000 */
    CHECK(sil.pwm_enable == 1 && sil.pwm_compare[0] == 47500u);
    CHECK(sil.pwm_compare[1] == 22500u && sil.pwm_compare[2] == 7500u);
    m.cmd_seq = 1;
    m.cmd_duty_c = fd_can_duty_cmd_cmd_duty_c_encode(0.0f); /* no room below: clamped */
    CHECK(fd_can_duty_cmd_pack(b, &m, 8) == 8);
    push(FD_CAN_DUTY_CMD_FRAME_ID, b, 8, 0);
    period();
    CHECK(sil.pwm_compare[0] == 47500u && sil.pwm_compare[1] == 25000u);
    CHECK(sil.pwm_compare[2] == 0u && core.stats.duty_limited == 2u);
    CHECK(fd_core_param_write(&core, FD_PRM_MAX_DUTY, 0.4f) == FD_PA_OUT_OF_RANGE);
}

static void test_bootstrap(void)
{
    fd_config_t cfg;
    fd_config_default(&cfg); /* 10 bootstrap periods */
    cfg.require_calibration = 0u;
    fd_sil_init(&sil);
    fd_core_init(&core, &cfg, &sil);
    send_arm(1, FD_ARM_KEY, 0, 0);
    period();
    int boot = 0;
    for (int i = 0; i < 20; ++i) {
        send_duty((uint16_t)(core.k - 1u), 0.6f, 1);
        period();
        if (sil.pwm_enable && sil.pwm_compare[0] == 0u && sil.pwm_compare[1] == 0u) {
            CHECK(i == boot); /* the first enabled periods, consecutively */
            boot++;
        } else {
            CHECK(sil.pwm_enable == 1 && sil.pwm_compare[0] == 30000u);
        }
    }
    CHECK(boot == 10);
    /* a fresh arming charges again; PWM on without re-arming does not */
    send_duty((uint16_t)(core.k - 1u), 0.6f, 0);
    period();
    send_duty((uint16_t)(core.k - 1u), 0.6f, 1);
    period();
    CHECK(sil.pwm_enable == 1 && sil.pwm_compare[0] == 30000u);
}

/* references with an age and an order */
static void test_reference_age(void)
{
    setup(1);
    CHECK(fd_core_param_write(&core, FD_PRM_HEARTBEAT_TIMEOUT_S, 0.0f) == FD_PA_OK);
    CHECK(fd_core_param_write(&core, FD_PRM_REF_TIMEOUT_S, 10.0f) == FD_PA_OK);
    send_arm(1, FD_ARM_KEY, 0, 1);
    for (int i = 0; i < 1200; ++i) {
        period();
    }
    /* 100 ms old (1000 periods) and 5 periods ahead of the drive: refused, counted */
    send_ref((uint16_t)(core.k - 1000u), 1.0f, 1);
    send_ref((uint16_t)(core.k + 5u), 1.0f, 1);
    period();
    CHECK(core.stats.ref_old == 1u && core.stats.ref_future == 1u);
    CHECK(core.stats.refs_applied == 0u && !core.pwm_enabled);
    /* 60 references each 100 ms old: none applied */
    for (int i = 0; i < 60; ++i) {
        send_ref((uint16_t)(core.k - 1000u), 1.0f, 1);
        period();
    }
    CHECK(core.stats.ref_old == 61u && core.stats.refs_applied == 0u);
    /* a fresh one is taken; then none: the extrapolation ends at the horizon (200
     * periods after the reference's sample) with STALE_INPUT, before the 10 s timeout */
    uint32_t j = core.k - 1u;
    send_ref((uint16_t)j, 1.0f, 1);
    period();
    CHECK(core.pwm_enabled && core.stats.refs_applied == 1u);
    n_fault = 0;
    while (!core.fault_latched && core.k < j + 1000u) {
        period();
        drain();
    }
    CHECK(core.fault_code == FD_FAULT_STALE_INPUT && core.k - 1u == j + 201u);
    CHECK(n_fault == 1 && last_fault.fault_detail == 201u && sil.pwm_enable == 0);
}

/* the 16-bit sequence wrap in split mode: references across 65535 -> 0 are taken, the
 * angle extrapolates continuously */
static void test_seq_wrap(void)
{
    setup(1);
    CHECK(fd_core_param_write(&core, FD_PRM_HEARTBEAT_TIMEOUT_S, 0.0f) == FD_PA_OK);
    core.k = 65500u;
    core.next_status_k = 65500u;
    core.t_us = 65500u * 100u;
    send_arm(1, FD_ARM_KEY, 0, 1);
    period();
    float prev = 0.0f;
    int jumps = 0;
    for (int i = 0; i < 100; ++i) {
        struct fd_can_host_ref_t m;
        uint8_t b[12];
        fd_can_host_ref_init(&m);
        uint16_t seq = (uint16_t)(core.k - 1u);
        m.ref_seq = seq;
        m.ref_iq = fd_can_host_ref_ref_iq_encode(1.0f);
        /* theta(t_j) of a 50 rad/s frame, omega 50 rad/s */
        float th = fmodf(50.0f * (float)(core.k - 1u) * 1.0e-4f, 6.2831853f);
        m.ref_theta = fd_can_host_ref_ref_theta_encode(th);
        m.ref_omega = fd_can_host_ref_ref_omega_encode(50.0f);
        m.ref_enable = 1;
        CHECK(fd_can_host_ref_pack(b, &m, 12) == 12);
        push(FD_CAN_HOST_REF_FRAME_ID, b, 12, 1);
        period();
        if (i > 2) {
            float d = core.theta_used - prev;
            d = d - 6.2831853f * floorf((d + 3.14159265f) / 6.2831853f);
            jumps += fabsf(d - 50.0f * 1.0e-4f) > 2.0e-3f;
        }
        prev = core.theta_used;
    }
    CHECK(core.k == 65601u && !core.fault_latched && core.stats.refs_applied == 100u);
    CHECK(core.stats.ref_old == 0u && core.stats.ref_future == 0u && jumps == 0);
}

/* the 32-bit period counter wrap (4.97 days at 10 kHz): STATUS stays at 10 Hz, commands
 * keep being taken, no fault */
static void test_period_wrap(void)
{
    setup(1);
    CHECK(fd_core_param_write(&core, FD_PRM_HEARTBEAT_TIMEOUT_S, 0.0f) == FD_PA_OK);
    core.k = 0xFFFFFFFFu - 1500u;
    core.next_status_k = core.k;
    run_armed();
    uint32_t status0 = 0;
    uint32_t id, len, fdf;
    uint8_t b[64];
    for (int i = 0; i < 3000; ++i) {
        send_duty((uint16_t)(core.k - 1u), 0.5f, 1);
        period();
        while (fd_sil_tx_pop(&sil, &id, b, &len, &fdf)) {
            status0 += id == FD_CAN_STATUS_FRAME_ID;
        }
    }
    CHECK(core.k < 2000u && !core.fault_latched && core.pwm_enabled);
    CHECK(status0 == 3u); /* 3000 periods at one STATUS per 1000 */
    CHECK(core.stats.duty_applied == 3004u && core.stats.stale_periods == 0u);
}

/* offset calibration: ARM_MODE mode CALIBRATE_ADC */
static void send_arm_mode(uint8_t arm, uint8_t mode)
{
    struct fd_can_arm_mode_t m;
    uint8_t b[8];
    fd_can_arm_mode_init(&m);
    m.arm = arm;
    m.arm_key = FD_ARM_KEY;
    m.mode = mode;
    m.decimation = core.cfg.decimation;
    CHECK(fd_can_arm_mode_pack(b, &m, 8) == 8);
    push(FD_CAN_ARM_MODE_FRAME_ID, b, 8, 0);
}

static float read_param(uint8_t id)
{
    struct fd_can_drive_param_t m;
    uint8_t b[8];
    fd_can_drive_param_init(&m);
    m.prm_id = id;
    m.prm_seq = id;
    CHECK(fd_can_drive_param_pack(b, &m, 8) == 8);
    push(FD_CAN_DRIVE_PARAM_FRAME_ID, b, 8, 0);
    n_ack = 0;
    period();
    drain();
    CHECK(n_ack == 1 && last_ack.pa_id == id && last_ack.pa_status == FD_PA_OK);
    return last_ack.pa_value;
}

static void test_calibration(void)
{
    fd_config_t cfg;
    fd_config_default(&cfg); /* requires calibration, 1000 periods */
    cfg.bootstrap_periods = 0u;
    fd_sil_init(&sil);
    fd_core_init(&core, &cfg, &sil);
    /* uncalibrated: arming refused with NOT_CALIBRATED, PWM stays off */
    n_fault = 0;
    send_arm_mode(1, FD_MODE_RUN);
    send_duty(0, 0.5f, 1);
    period();
    period();
    drain();
    CHECK(!core.armed && sil.pwm_enable == 0 && core.fault_code == FD_FAULT_NOT_CALIBRATED);
    CHECK(n_fault == 1 && last_fault.fault_code == FD_FAULT_NOT_CALIBRATED);
    send_arm(0, FD_ARM_KEY, 1, 0); /* the refusal resets at once */
    period();
    CHECK(!core.fault_latched);
    /* offsets of +30, -20, +7 counts and a capture offset of 3 ticks on v_ab; the
     * calibration averages exactly cal_periods periods with PWM off */
    cur_counts[0] = 2048 + 30;
    cur_counts[1] = 2048 - 20;
    cur_counts[2] = 2048 + 7;
    ticks[0] = 3;
    send_arm_mode(1, FD_MODE_CALIBRATE_ADC);
    uint32_t n = 0;
    int state5 = 0;
    uint32_t id, len, fdf;
    uint8_t b[64];
    do {
        period();
        n++;
        CHECK(sil.pwm_enable == 0 && !core.armed);
        while (fd_sil_tx_pop(&sil, &id, b, &len, &fdf)) {
            struct fd_can_status_t st;
            if (id == FD_CAN_STATUS_FRAME_ID && fd_can_status_unpack(&st, b, len) == 0) {
                state5 += st.st_state == FD_ST_CALIBRATING;
            }
        }
        if ((n % 100u) == 0u) {
            send_arm_mode(1, FD_MODE_CALIBRATE_ADC); /* the host's 10 Hz repeat: no restart */
        }
    } while (core.calibrating && n < 5000u);
    /* taken in the background before the first: 1000 periods of readings */
    CHECK(n == 1000u && core.cal_valid && !core.fault_latched && state5 == 1);
    CHECK(read_param(FD_PRM_CAL_OFFSET_A) == 2078.0f && read_param(FD_PRM_CAL_OFFSET_B) == 2028.0f);
    CHECK(read_param(FD_PRM_CAL_OFFSET_C) == 2055.0f && read_param(FD_PRM_CAL_CAPTURE_AB) == 3.0f);
    CHECK(read_param(FD_PRM_CAL_DONE) == 1.0f);
    CHECK(fd_core_param_write(&core, FD_PRM_CAL_OFFSET_A, 2048.0f) == FD_PA_READ_ONLY);
    /* the offsets in use: the same readings are 0 A and 0 V now */
    period();
    CHECK(core.i_abc[0] == 0.0f && core.i_abc[1] == 0.0f && core.i_abc[2] == 0.0f);
    CHECK(core.v_ll[0] == 0.0f);
    /* and arming works */
    send_arm_mode(1, FD_MODE_RUN);
    send_duty((uint16_t)(core.k), 0.5f, 1);
    period();
    send_duty((uint16_t)(core.k - 1u), 0.5f, 1);
    period();
    CHECK(core.armed && sil.pwm_enable == 1);
    /* an offset beyond 205 counts (2 A): the calibration fails with ADC_FAULT */
    send_arm_mode(0, FD_MODE_IDLE);
    period();
    cur_counts[1] = 2048 - 300;
    send_arm_mode(1, FD_MODE_CALIBRATE_ADC);
    for (int i = 0; i < 1001; ++i) {
        period();
        drain();
    }
    CHECK(core.fault_code == FD_FAULT_ADC_FAULT && !core.calibrating);
    CHECK(last_fault.fault_detail == (FD_ADC_DETAIL_CALIBRATION | 1u | (300u << 2)));
    CHECK(read_param(FD_PRM_CAL_OFFSET_B) == 2028.0f); /* the last good result is kept */
    cur_counts[0] = cur_counts[1] = cur_counts[2] = 2048;
    ticks[0] = 0;
}

/* ---------------------------------------------------------------- the two contexts */

/* 60 queued DRIVE_PARAM requests: the period interrupt handles none of them (it sends
 * only its sample and STATUS); the background answers FD_BG_FRAMES per call */
static void test_bounded_interrupt(void)
{
    setup(1);
    period();
    drain();
    for (int i = 0; i < 60; ++i) {
        struct fd_can_drive_param_t m;
        uint8_t b[8];
        fd_can_drive_param_init(&m);
        m.prm_id = FD_PRM_CUR_KP;
        m.prm_seq = (uint8_t)i;
        CHECK(fd_can_drive_param_pack(b, &m, 8) == 8);
        push(FD_CAN_DRIVE_PARAM_FRAME_ID, b, 8, 0);
    }
    core.next_status_k = core.k; /* a STATUS in this period too: the most it sends */
    uint32_t sent0 = sil.tx_head;
    fd_sil_set_inputs(&sil, cur_counts, vdc_counts, ticks, 4096, 0, 35, core.k * 100u);
    fd_core_period(&core); /* the interrupt alone */
    CHECK(sil.tx_head - sent0 == 2u && core.stats.param_rx == 0u);
    CHECK(sil.rx_head - sil.rx_tail == 60u);
    n_ack = 0;
    drain();
    unsigned per_call[5];
    for (int i = 0; i < 5; ++i) {
        per_call[i] = fd_core_background(&core);
        drain();
    }
    CHECK(per_call[0] == 16u && per_call[1] == 16u && per_call[2] == 16u);
    CHECK(per_call[3] == 12u && per_call[4] == 0u);
    CHECK(n_ack == 60 && core.stats.param_rx == 60u && last_ack.pa_seq == 59u);
}

/* the DUTY_CMD ring: at most FD_CMD_RING waiting; more are dropped and counted */
static void test_command_ring(void)
{
    setup(1);
    send_arm(1, FD_ARM_KEY, 0, 0);
    period();
    for (int i = 0; i < 10; ++i) {
        send_duty((uint16_t)(100 + i), 0.5f, 1);
    }
    while (fd_core_background(&core) > 0u) {
    }
    CHECK(core.stats.duty_rx == 8u && core.stats.cmd_ring_full == 2u);
    CHECK(fd_core_has_answer(&core, 107) && !fd_core_has_answer(&core, 108));
    fd_sil_set_inputs(&sil, cur_counts, vdc_counts, ticks, 4096, 0, 35, core.k * 100u);
    fd_core_period(&core); /* takes all eight over into its slots */
    CHECK(atomic_load(&core.cmd_ring.tail) == 8u && fd_core_has_answer(&core, 107));
}

static void send_ref_th(uint16_t seq, float theta, float omega)
{
    struct fd_can_host_ref_t m;
    uint8_t b[12];
    fd_can_host_ref_init(&m);
    m.ref_seq = seq;
    m.ref_iq = fd_can_host_ref_ref_iq_encode(1.0f);
    m.ref_theta = fd_can_host_ref_ref_theta_encode(theta);
    m.ref_omega = fd_can_host_ref_ref_omega_encode(omega);
    m.ref_enable = 1;
    CHECK(fd_can_host_ref_pack(b, &m, 12) == 12);
    push(FD_CAN_HOST_REF_FRAME_ID, b, 12, 1);
}

/* a reference handed over while the interrupt runs: the interrupt lands in the middle of
 * a background write (sequence odd, half the fields new); it keeps extrapolating the
 * reference it has, and takes the new one, whole, in the next period */
static void test_reference_handover_interleaved(void)
{
    setup(1);
    CHECK(fd_core_param_write(&core, FD_PRM_HEARTBEAT_TIMEOUT_S, 0.0f) == FD_PA_OK);
    send_arm(1, FD_ARM_KEY, 0, 1);
    period();
    send_ref_th((uint16_t)(core.k - 1u), 1.0f, 100.0f);
    period();
    period();
    CHECK(core.pwm_enabled && core.ref.theta == fd_can_host_ref_ref_theta_decode(
                                                     fd_can_host_ref_ref_theta_encode(1.0f)));
    float th_old = core.ref.theta;
    uint16_t seq_old = core.ref.seq;
    /* the background begins a write: seq odd, seq and theta written, the rest not yet */
    unsigned s = atomic_load(&core.ref_box.seq);
    atomic_store(&core.ref_box.seq, s + 1u);
    core.ref_box.ref.seq = (uint16_t)(core.k - 1u);
    core.ref_box.ref.theta = 2.5f;
    core.ref_box.ref.valid = 1;
    core.ref_box.ref.enable = 1;
    fd_sil_set_inputs(&sil, cur_counts, vdc_counts, ticks, 4096, 0, 35, core.k * 100u);
    fd_core_period(&core); /* the interrupt preempts the writer */
    CHECK(core.ref.theta == th_old && core.ref.seq == seq_old);
    CHECK(core.stats.ref_handover_busy == 1u && !core.fault_latched && sil.pwm_enable == 1);
    /* the extrapolated angle is the old reference's: theta + omega (k - seq) Ts */
    float want = th_old + 100.0f * (float)(uint16_t)(core.k - 1u - seq_old) * 1.0e-4f;
    CHECK(fabsf(core.theta_used - want) < 1.0e-4f);
    /* the writer finishes; the next interrupt takes it */
    core.ref_box.ref.iq = 1.0f;
    core.ref_box.ref.omega = 100.0f;
    core.ref_box.ref.id = 0.0f;
    atomic_store(&core.ref_box.seq, s + 2u);
    period();
    CHECK(core.ref.theta == 2.5f && core.stats.refs_applied == 2u);
    CHECK(core.stats.ref_handover_busy == 1u);
}

/* an interrupt entered again before the last one returned */
static void test_reentry(void)
{
    setup(1);
    run_armed();
    n_fault = 0;
    core.in_isr = 1;
    fd_core_period(&core);
    drain();
    CHECK(core.fault_code == FD_FAULT_DEADLINE_MISSED && sil.pwm_enable == 0);
    CHECK(n_fault == 1 && last_fault.fault_detail == 0xFFFFu);
}

/* ---------------------------------------------------------------- fault log, storage, CAN */

static int n_log;
static struct fd_can_fault_log_t logs[FD_FAULT_LOG];

static void drain_log(void)
{
    uint32_t id, len, fdf;
    uint8_t b[64];
    while (fd_sil_tx_pop(&sil, &id, b, &len, &fdf)) {
        if (id == FD_CAN_FAULT_LOG_FRAME_ID && n_log < (int)FD_FAULT_LOG) {
            CHECK(fd_can_fault_log_unpack(&logs[n_log], b, len) == 0);
            n_log++;
        } else if (id == FD_CAN_DRIVE_PARAM_ACK_FRAME_ID) {
            CHECK(fd_can_drive_param_ack_unpack(&last_ack, b, len) == 0);
            n_ack++;
        }
    }
}

static void request(uint8_t id, uint8_t write, float value)
{
    struct fd_can_drive_param_t m;
    uint8_t b[8];
    fd_can_drive_param_init(&m);
    m.prm_id = id;
    m.prm_write = write;
    m.prm_value = value;
    CHECK(fd_can_drive_param_pack(b, &m, 8) == 8);
    push(FD_CAN_DRIVE_PARAM_FRAME_ID, b, 8, 0);
}

static void test_fault_log(void)
{
    setup(1);
    uint32_t k_trip[10];
    for (int i = 0; i < 10; ++i) { /* ten over-temperature trips, each reset */
        temp_c = 95;
        period_t();
        k_trip[i] = core.k - 1u;
        temp_c = 35;
        period_t();
        send_arm(0, FD_ARM_KEY, 1, 0);
        period_t();
        send_arm(0, FD_ARM_KEY, 0, 0);
        period_t();
    }
    CHECK(!core.fault_latched && core.fault_log_n == 10u);
    drain();
    request(FD_PRM_FAULT_LOG, 0, 0.0f);
    n_log = 0;
    n_ack = 0;
    period_t();
    drain_log();
    CHECK(n_ack == 1 && last_ack.pa_value == 8.0f && n_log == 8);
    for (int i = 0; i < n_log; ++i) { /* newest first: the last eight */
        CHECK(logs[i].fl_index == i && logs[i].fl_code == FD_FAULT_OVERTEMPERATURE);
        CHECK(logs[i].fl_detail == 95u && logs[i].fl_period == k_trip[9 - i]);
    }
}

static void test_param_storage(void)
{
    setup(1);
    float v = -1.0f;
    CHECK(fd_core_param_read(&core, FD_PRM_PARAM_SOURCE, &v) == FD_PA_OK &&
          v == (float)FD_PRM_SOURCE_DEFAULTS);
    CHECK(fd_core_param_write(&core, FD_PRM_CUR_KP, 2.5f) == FD_PA_OK);
    CHECK(fd_core_param_write(&core, FD_PRM_MAX_DUTY, 0.9f) == FD_PA_OK);
    n_ack = 0;
    request(FD_PRM_PARAM_SAVE, 1, 1.0f); /* over the bus, PWM off */
    period();
    drain();
    CHECK(n_ack == 1 && last_ack.pa_status == FD_PA_OK && core.stats.param_saves == 1u);
    /* the next boot loads them */
    fd_config_t cfg = core.cfg;
    fd_core_init(&core, &cfg, &sil);
    CHECK(core.prm[FD_PRM_CUR_KP] == 2.5f && core.max_duty == 0.9f);
    CHECK(core.prm[FD_PRM_PARAM_SOURCE] == (float)FD_PRM_SOURCE_STORED);
    /* one flipped bit in the record: the defaults, and PARAM_SOURCE says why */
    sil.store[12] ^= 0x10u;
    fd_core_init(&core, &cfg, &sil);
    CHECK(core.prm[FD_PRM_CUR_KP] == 0.0f && core.max_duty == 0.95f);
    CHECK(core.prm[FD_PRM_PARAM_SOURCE] == (float)FD_PRM_SOURCE_BAD_CRC);
    /* a failing store and a save with PWM on are refused */
    sil.store_fail = 1;
    CHECK(fd_core_param_write(&core, FD_PRM_PARAM_SAVE, 1.0f) == FD_PA_STORAGE_FAILED);
    sil.store_fail = 0;
    run_armed();
    CHECK(core.pwm_enabled);
    CHECK(fd_core_param_write(&core, FD_PRM_PARAM_SAVE, 1.0f) == FD_PA_NOT_WHILE_RUNNING);
    CHECK(fd_crc32("123456789", 9) == 0xCBF43926u); /* the CRC-32 check value */
}

static void test_bus_off(void)
{
    setup(1);
    fd_sil_inject(&sil, 0, 96, 17, 0, 0);
    period();
    float v = 0.0f;
    CHECK(fd_core_param_read(&core, FD_PRM_CAN_TEC, &v) == FD_PA_OK && v == 96.0f);
    core.next_status_k = core.k;
    period();
    uint32_t id, len, fdf;
    uint8_t b[64];
    int rec = -1;
    while (fd_sil_tx_pop(&sil, &id, b, &len, &fdf)) {
        struct fd_can_status_t st;
        if (id == FD_CAN_STATUS_FRAME_ID && fd_can_status_unpack(&st, b, len) == 0) {
            rec = st.st_rx_errors;
        }
    }
    CHECK(rec == 17); /* the controller's REC, not 0 */
    run_armed();
    n_fault = 0;
    fd_sil_inject(&sil, 0, 255, 17, 1, 0); /* bus-off while running */
    send_duty((uint16_t)(core.k - 1u), 0.5f, 1);
    period();
    drain();
    CHECK(core.fault_code == FD_FAULT_BUS_ERROR && sil.pwm_enable == 0);
    CHECK(n_fault == 1 && last_fault.fault_detail == 255u && core.stats.can_bus_offs == 1u);
    CHECK(fd_core_background(&core) == 0u && sil.can_recoveries == 1u); /* recovery */
    CHECK(!sil.hw.can_bus_off);
    CHECK(fd_core_param_read(&core, FD_PRM_CAN_BUS_OFFS, &v) == FD_PA_OK && v == 1.0f);
    fd_core_background(&core);
    CHECK(sil.can_recoveries == 1u); /* once per event */
}

int main(void)
{
    test_arm_key();
    test_watchdog();
    test_fault_latch_reset();
    test_decimation_average();
    test_bus_voltage();
    test_params();
    test_reference_timeout();
    test_host_heartbeat();
    test_fault_injection();
    test_board_caps();
    test_nan_bus();
    test_heartbeat_from_arming();
    test_reference_from_arming();
    test_max_duty();
    test_bootstrap();
    test_reference_age();
    test_seq_wrap();
    test_period_wrap();
    test_calibration();
    test_bounded_interrupt();
    test_command_ring();
    test_reference_handover_interleaved();
    test_reentry();
    test_fault_log();
    test_param_storage();
    test_bus_off();
    if (failures) {
        fprintf(stderr, "fd_core_test: %d check(s) failed\n", failures);
        return 1;
    }
    printf("fd_core_test: all checks passed\n");
    return 0;
}
