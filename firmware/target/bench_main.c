/* The target images' program: the drive core on synthetic readings, host mode then split
 * mode, each period interrupt between two marker calls (fd_mark_begin / fd_mark_end) so an
 * instruction trace can count and cost what one interrupt executes
 * (fluxdrive.can.firmware_target, docs/firmware.md).
 *
 * Worst paths on purpose: D = 1 (a SAMPLE_FD encoded every period), STATUS every 8th period
 * (a real drive: every 1000th), a DRIVE_PARAM answered in some periods, and in split mode a
 * new HOST_REF every period (integrator rotation every period) with the current loop
 * running, the voltage in the hexagon limit at times. Under QEMU (FD_BENCH_QEMU) the
 * program ends through semihosting SYS_EXIT; on the G474 image it loops. */
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "fd_can.h"
#include "fd_core.h"
#include "fd_hal_bench.h"

#define N_HOST 64u
#define N_SPLIT 64u

static fd_core_t core;
static fd_bench_hal_t hal;
volatile uint32_t fd_mark_tag;
volatile uint32_t fd_mark_done;

__attribute__((noinline)) void fd_mark_begin(uint32_t tag);
__attribute__((noinline)) void fd_mark_end(void);
void fd_mark_begin(uint32_t tag) { fd_mark_tag = tag; }
void fd_mark_end(void) { fd_mark_done = fd_mark_done + 1u; }

static void push(uint32_t id, const uint8_t *data, uint8_t len, uint8_t fd)
{
    fd_can_frame_t f;
    memset(&f, 0, sizeof(f));
    f.id = id;
    f.len = len;
    f.fd = fd;
    memcpy(f.data, data, len);
    (void)fd_bench_rx_push(&hal, &f);
}

static void arm(uint8_t split)
{
    struct fd_can_arm_mode_t m;
    uint8_t b[8];
    fd_can_arm_mode_init(&m);
    m.arm = 1u;
    m.arm_key = (uint8_t)FD_ARM_KEY;
    m.mode = (uint8_t)FD_MODE_RUN;
    m.control_split = split;
    m.decimation = 1u;
    (void)fd_can_arm_mode_pack(b, &m, 8u);
    push(FD_CAN_ARM_MODE_FRAME_ID, b, 8u, 0u);
}

static void param(uint8_t id, float value)
{
    struct fd_can_drive_param_t m;
    uint8_t b[8];
    fd_can_drive_param_init(&m);
    m.prm_id = id;
    m.prm_write = 1u;
    m.prm_value = value;
    (void)fd_can_drive_param_pack(b, &m, 8u);
    push(FD_CAN_DRIVE_PARAM_FRAME_ID, b, 8u, 0u);
}

/* synthetic sample k: a 5 A current vector turning at 50 Hz electrical, 24 V bus */
static void readings(uint32_t k)
{
    float th = 6.2831853f * 50.0f * 1.0e-4f * (float)k;
    for (int j = 0; j < 3; ++j) {
        float i = 5.0f * cosf(th - 2.0943951f * (float)j);
        hal.adc.current_counts[j] = 2048 + (int32_t)(i / (40.0f / 4096.0f));
        hal.cap.high_ticks[j] = (int32_t)(1000.0f * sinf(th - 2.0943951f * (float)j));
    }
    hal.adc.vdc_counts = 983;
    hal.adc.temp_c = 35;
    hal.cap.period_ticks = 4096;
    hal.cap.encoder_counts = (int32_t)k;
    hal.time_us = k * 100u;
}

static void run_period(uint32_t tag)
{
    while (fd_core_background(&core) > 0u) { /* the main loop between interrupts */
    }
    readings(core.k);
    fd_mark_begin(tag);
    fd_core_period(&core);
    fd_mark_end();
}

#ifdef FD_BENCH_QEMU
static void semihost_exit(void)
{
    register uint32_t r0 __asm__("r0") = 0x18u;     /* SYS_EXIT */
    register uint32_t r1 __asm__("r1") = 0x20026u; /* ADP_Stopped_ApplicationExit */
    __asm__ volatile("bkpt 0xAB" : : "r"(r0), "r"(r1) : "memory");
}
#endif

int main(void)
{
    fd_config_t cfg;
    fd_config_default(&cfg);
    cfg.status_period = 8u;
    cfg.pwm_period_ticks = 8500u; /* 170 MHz, centre-aligned 10 kHz */
    cfg.require_calibration = 0u; /* the bench counts the running interrupt, not the
                                   * calibration's (PWM off, a few additions) */
    fd_core_init(&core, &cfg, &hal);
    (void)fd_core_param_write(&core, FD_PRM_CUR_KP, 2.0f);
    (void)fd_core_param_write(&core, FD_PRM_CUR_KI, 3000.0f);
    (void)fd_core_param_write(&core, FD_PRM_L_HAT, 2.0e-3f);
    (void)fd_core_param_write(&core, FD_PRM_LAMBDA_HAT, 0.05f);
    (void)fd_core_param_write(&core, FD_PRM_DEADTIME_COMP_S, 1.0e-6f);

    /* host mode: a DUTY_CMD answering the previous sample every period */
    arm(0u);
    for (uint32_t n = 0; n < N_HOST; ++n) {
        if (core.k >= 1u) {
            struct fd_can_duty_cmd_t m;
            uint8_t b[8];
            fd_can_duty_cmd_init(&m);
            m.cmd_seq = (uint16_t)(core.k - 1u);
            m.cmd_duty_a = 12500u;
            m.cmd_duty_b = 13000u;
            m.cmd_duty_c = 12000u;
            m.cmd_enable = 1u;
            (void)fd_can_duty_cmd_pack(b, &m, 8u);
            push(FD_CAN_DUTY_CMD_FRAME_ID, b, 8u, 0u);
        }
        if (n % 16u == 5u) {
            param(FD_PRM_CUR_KP, 2.0f);
        }
        run_period(1u);
    }
    /* split mode: disarm (PWM off), switch, then a new HOST_REF every period */
    struct fd_can_duty_cmd_t off;
    uint8_t b8[8];
    fd_can_duty_cmd_init(&off);
    off.cmd_seq = (uint16_t)(core.k - 1u);
    (void)fd_can_duty_cmd_pack(b8, &off, 8u);
    push(FD_CAN_DUTY_CMD_FRAME_ID, b8, 8u, 0u);
    while (fd_core_background(&core) > 0u) {
    }
    readings(core.k);
    fd_core_period(&core);
    arm(1u);
    for (uint32_t n = 0; n < N_SPLIT; ++n) {
        struct fd_can_host_ref_t r;
        uint8_t b[12];
        fd_can_host_ref_init(&r);
        float th = 6.2831853f * 50.0f * 1.0e-4f * (float)core.k;
        r.ref_seq = (uint16_t)(core.k - 1u);
        r.ref_id = 0;
        r.ref_iq = (int16_t)(n < N_SPLIT / 2u ? 5000 : 20000); /* 5 A, then 20 A: saturates */
        r.ref_theta = (uint16_t)(fmodf(th, 6.2831853f) / 9.58737992428526e-05f);
        r.ref_omega = 314159; /* 314.159 rad/s */
        r.ref_enable = 1u;
        (void)fd_can_host_ref_pack(b, &r, 12u);
        push(FD_CAN_HOST_REF_FRAME_ID, b, 12u, 1u);
        if (n % 16u == 5u) {
            param(FD_PRM_CUR_KI, 3000.0f);
        }
        run_period(2u);
    }
#ifdef FD_BENCH_QEMU
    semihost_exit();
#endif
    for (;;) {
    }
}
