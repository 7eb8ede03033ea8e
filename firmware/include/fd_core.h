/* fluxdrive drive firmware core: the drive side of config/can/fluxdrive.dbc.
 *
 * C11, no heap, no OS, float32 arithmetic. One fd_core_t per drive, owned by the caller
 * (static storage on a target). fd_core_period() is the whole per-PWM-period interrupt:
 *
 *   sample    raw ADC/capture (HAL) -> SI units (calibration in fd_config_t)
 *   window    per-period accumulation; every D-th period a sample (SAMPLE_FD or the four
 *             SAMPLE_C_* frames) with line voltages and duties averaged over the window
 *   protect   timer break and gate-driver inputs, ADC saturation, over-current
 *             (instantaneous), I2t, DC-bus over/under-voltage (engine codes), temperature;
 *             thresholds: the stricter of the board's (fd_config_t) and the DRIVE_PARAM
 *   protocol  STATUS and latched-FAULT repeats at 10 Hz; received ARM_MODE, DUTY_CMD,
 *             HOST_REF, DRIVE_PARAM (answered by DRIVE_PARAM_ACK), HOST_HEARTBEAT
 *   command   host mode: the DUTY_CMD answering sample k-D at each sample boundary, duty
 *             watchdog; split mode: the newest HOST_REF, reference timeout, and the dq
 *             current loop on the extrapolated angle (fd_current_loop)
 *   output    modulation guards (finite, MAX_DUTY, bootstrap charge after arming), PWM
 *             compare values + enable (HAL); then the HAL's overrun check
 *
 * The Python emulator's MCU logic (python/fluxdrive/can/emulator.py) is the reference for
 * host mode; the engine's _current_loops / _protect (python/fluxdrive/drive/control/kernel.py) for
 * the current loop and the protections. docs/firmware.md describes the whole.
 */
#ifndef FD_CORE_H
#define FD_CORE_H

#include <stdatomic.h>
#include <stdbool.h>
#include <stdint.h>

#include "fd_hal.h"
#include "fd_protocol.h"

#ifdef __cplusplus
extern "C" {
#endif

/* Protocol constants (FD_PROTOCOL_VERSION, FD_ARM_KEY, FD_FAULT_*, FD_ST_*, FD_MODE_*,
 * FD_PRM_*, FD_PA_*) are generated from the DBC at build time into fd_protocol.h
 * (firmware/codegen.cmake): add a code to the DBC, not here. */

/* FAULT.fault_detail of OVERCURRENT: phase index in bits 0-1; 3 = the hardware path (the
 * comparator into the timer's break input; no phase known) */
#define FD_OC_DETAIL_BREAK 3u
/* FAULT.fault_detail of ADC_FAULT from a failed offset calibration: this bit, the phase in
 * bits 0-1, |offset - nominal| in counts in bits 2-14 (saturated) */
#define FD_ADC_DETAIL_CALIBRATION 0x8000u

/** Build-time configuration of a board: what a real firmware fixes at compile time. */
typedef struct {
    uint32_t period_us;          /* PWM period [us] (10 kHz: 100) */
    float ts_s;                  /* PWM period [s] */
    uint8_t decimation;          /* D, periods per sample */
    uint8_t classic_layout;      /* 0: SAMPLE_FD, 1: SAMPLE_C_CUR/VLT/DUTY/AUX */
    float current_lsb_a;         /* current ADC step [A/count] */
    int32_t current_offset_counts[3]; /* ADC result at 0 A per phase */
    int32_t current_clip_counts; /* |count - offset| at or beyond this: clipped */
    float vdc_lsb_v;             /* bus ADC step [V/count] */
    uint32_t pwm_period_ticks;   /* compare value of 100 % duty */
    uint32_t cmd_timeout_us;     /* default duty watchdog (ARM_MODE.cmd_timeout = 0) */
    uint32_t status_period;      /* periods between STATUS frames (10 Hz) */
    /* ---- board limits: what the power stage and its sensors allow; a DRIVE_PARAM can
     * only tighten them (the protections use the stricter of the two) */
    int32_t current_adc_max_counts; /* highest current ADC result (12 bit: 4095); a result
                                     * at 0 or at this is saturated: fault ADC_FAULT */
    float oc_limit_a;            /* over-current trip cap [A], below the ADC full scale */
    float vdc_max_v;             /* bus over-voltage trip [V] (the stage's rating) */
    float vdc_min_v;             /* bus under-voltage trip while armed [V] */
    float vdc_modulation_min_v;  /* below this bus no duty is computed or applied [V] */
    int32_t temp_max_c;          /* over-temperature trip [degC] */
    int32_t temp_hysteresis_c;   /* reset allowed at temp_max_c - this [degC] */
    uint32_t bootstrap_periods;  /* low sides on before the first switching period */
    uint32_t ref_max_age_periods; /* HOST_REF older than this at reception: refused */
    uint32_t ref_horizon_periods; /* extrapolation beyond this: fault STALE_INPUT */
    /* ---- offset calibration (ARM_MODE.mode CALIBRATE_ADC, PWM off) */
    uint32_t cal_periods;          /* periods averaged (at most 65536) */
    int32_t cal_max_offset_counts; /* |offset - current_offset_counts| beyond: ADC_FAULT */
    uint8_t require_calibration;   /* 1: arming an uncalibrated drive is NOT_CALIBRATED */
} fd_config_t;

/** dq current-loop state (the engine's CS_ID_I / CS_IQ_I). */
typedef struct {
    float id_i; /* d-axis PI integrator [V] */
    float iq_i; /* q-axis PI integrator [V] */
} fd_cur_state_t;

/** dq current-loop parameters (the engine's CP_* of the same names). */
typedef struct {
    float kp;         /* CP_KP_I [V/A] */
    float ki;         /* CP_KI_I [V/(A s)] */
    float l_hat;      /* CP_L [H] */
    float lambda_hat; /* CP_LAM [V s] */
    float decouple;   /* CP_DECOUPLE, 0 or 1 */
    float advance;    /* CP_ADV [periods] */
    float tdcomp_s;   /* CP_TDCOMP [s] */
} fd_cur_params_t;

/** dq current-loop output (the engine's CO_* of the same names). */
typedef struct {
    float duty[3];
    float i_d, i_q; /* measured [A] */
    float v_d, v_q; /* realised (after the hexagon limit) [V] */
} fd_cur_out_t;

/** One step of the dq current loop: exactly the engine's _current_loops in float32.
 *  i_alpha/i_beta: Clarke of the sampled currents [A]; th: angle [rad]; we: electrical
 *  speed [rad/s]; id_ref/iq_ref [A]; vdc [V]; ts [s]. */
void fd_current_loop(fd_cur_state_t *st, const fd_cur_params_t *p, float i_alpha, float i_beta,
                     float th, float we, float id_ref, float iq_ref, float vdc, float ts,
                     fd_cur_out_t *out);

/** I2t integral update: the engine's _protect formula. Returns the new integral [pu^2 s]. */
float fd_i2t_step(float i2t, float i_alpha, float i_beta, float rated_a, float ts);

#define FD_CMD_SLOTS 8u

typedef struct {
    uint16_t seq;
    uint8_t valid;
    uint8_t enable;
    float duty[3];
} fd_duty_cmd_t;

typedef struct {
    uint16_t seq;
    uint8_t valid;
    uint8_t enable;
    float id, iq, theta, omega;
} fd_host_ref_t;

/* Hand-over from the background context to the period interrupt, lock-free (one writer,
 * one reader, the reader never waits):
 * - DUTY_CMDs: a single-producer single-consumer ring; the background writes a slot, then
 *   publishes it by advancing `head` (release); the interrupt reads up to FD_CMD_RING
 *   slots between `tail` and `head` (acquire) into its own slots and advances `tail`.
 * - HOST_REF: a sequence lock; the background makes `seq` odd, writes the reference, makes
 *   it even again; the interrupt takes a reference only when `seq` is even, differs from
 *   the last one it took, and is unchanged after the copy. An interrupt that lands inside
 *   a write (seq odd) keeps the reference it has and takes the new one a period later. */
#define FD_CMD_RING 8u
typedef struct {
    fd_duty_cmd_t slot[FD_CMD_RING];
    atomic_uint head; /* written only by the background */
    atomic_uint tail; /* written only by the interrupt */
} fd_cmd_ring_t;

typedef struct {
    atomic_uint seq;  /* even: stable, odd: being written */
    fd_host_ref_t ref;
} fd_ref_box_t;

/* frames the background takes from the CAN controller per fd_core_background call */
#define FD_BG_FRAMES 16u

/* the fault log: the last FD_FAULT_LOG faults with the period counter they were raised in */
#define FD_FAULT_LOG 8u
typedef struct {
    uint8_t code;
    uint16_t detail;
    uint32_t k;
} fd_fault_entry_t;

/* DRIVE_PARAM PARAM_SOURCE: where the parameters at boot came from */
enum { FD_PRM_SOURCE_DEFAULTS = 0, FD_PRM_SOURCE_STORED = 1, FD_PRM_SOURCE_BAD_CRC = 2 };

/* the stored parameter record (fd_hal_storage_*): the writable DRIVE_PARAMs and a CRC-32
 * (IEEE 802.3, reflected, over everything before it) */
#define FD_STORE_MAGIC 0x46445031u /* "FDP1" */
typedef struct {
    uint32_t magic;
    uint32_t count; /* FD_PRM_COUNT of the firmware that wrote it */
    float prm[FD_PRM_COUNT];
    uint32_t crc;
} fd_param_record_t;

/** CRC-32 (IEEE 802.3, reflected, init and final xor 0xFFFFFFFF) of n bytes. */
uint32_t fd_crc32(const void *data, uint32_t n);

/** Counters (what the emulator's EmulatorStats counts). */
typedef struct {
    uint32_t periods;
    uint32_t samples_sent;
    uint32_t duty_rx;
    uint32_t duty_applied;
    uint32_t duty_late;
    uint32_t stale_periods;
    uint32_t ref_rx;
    uint32_t arm_rx;
    uint32_t bad_rx;
    uint32_t tx_overruns;
    uint32_t layout_mismatch;
    uint32_t disarm_rx;
    uint32_t faults;
    uint32_t param_rx;
    uint32_t refs_applied;
    uint32_t ref_old;      /* HOST_REFs refused: older than ref_max_age_periods */
    uint32_t ref_future;   /* HOST_REFs refused: numbered ahead of the drive's counter */
    uint32_t adc_clipped;  /* periods with a saturated current reading */
    uint32_t duty_limited; /* periods a duty was limited to MAX_DUTY */
    uint32_t cmd_ring_full;     /* DUTY_CMDs dropped: the hand-over ring was full */
    uint32_t ref_handover_busy; /* interrupts that met a HOST_REF half written */
    uint32_t bg_frames;         /* frames handled by the background context */
    uint32_t can_bus_offs;      /* bus-off events of the CAN controller */
    uint32_t param_saves;       /* parameter records written to storage */
} fd_stats_t;

/** The whole drive state. Fields are public for tests and the SIL binding; firmware code
 *  outside fd_core.c only reads them. */
typedef struct {
    fd_config_t cfg;
    void *hal;
    float prm[FD_PRM_COUNT]; /* DRIVE_PARAM values by prm_id */
    /* period counter and the sample of this period, SI */
    uint32_t k;
    uint32_t t_us; /* SAMPLE_FD.t_mcu of sample k [us] */
    float i_abc[3], v_ll[3], vdc;
    int32_t encoder;
    uint8_t clip;          /* a current reading saturated in this sample */
    uint16_t clip_detail;  /* its phase (bits 0-1) and raw count (bits 2-15) */
    int32_t temp_c;        /* power-stage temperature of this sample [degC] */
    /* what the PWM held over the period just ended, and what the last interrupt wrote into
     * the timer's preload registers (in force from the next update event) */
    float duty_applied[3];
    uint8_t pwm_applied;
    float duty_preload[3];
    uint8_t pwm_preload;
    /* sample window */
    float win_v[3], win_duty[3];
    uint32_t win_n;
    uint8_t win_pwm, win_flags;
    /* state machine */
    uint8_t armed, pwm_enabled, fault_latched, fault_code, fault_count, mode, split;
    uint8_t reset_prev, stale_prev, status_alive, hb_seen;
    uint8_t ran_first;          /* a sample boundary has passed (host mode's first command) */
    uint8_t temp_hot;           /* last temperature at or above cfg.temp_max_c */
    fd_hal_status_t hw;         /* power-stage and CAN controller status of this period */
    uint32_t bootstrap_left;    /* periods of low-side bootstrap charge still to run */
    /* limits in effect (board cap and DRIVE_PARAM, the stricter), updated on a write */
    float oc_trip_a, vdc_max_v, vdc_min_v, max_duty;
    float ticks_f;              /* pwm_period_ticks as float */
    /* offset calibration */
    uint8_t calibrating, cal_valid, cal_req_prev;
    uint32_t cal_n;
    int32_t cal_sum_i[3], cal_sum_cap[3];
    float cur_off[3]; /* current offsets in effect [counts] (nominal until calibrated) */
    float cap_off[3]; /* capture offsets in effect [ticks] */
    float inv_ticks;            /* 1 / pwm_period_ticks */
    uint16_t applied_seq;
    uint32_t last_cmd_k, last_ref_k;
    uint32_t next_status_k, next_fault_k;
    uint32_t cmd_timeout_us;
    uint32_t hb_last_us;
    float duty[3]; /* host mode: duties for the period now starting */
    fd_duty_cmd_t cmds[FD_CMD_SLOTS];
    /* protections */
    float i2t;
    /* split mode */
    fd_ref_box_t ref_box;     /* newest received (background -> interrupt) */
    unsigned ref_box_taken;   /* ref_box.seq of the last reference the interrupt took */
    fd_cmd_ring_t cmd_ring;   /* received DUTY_CMDs (background -> interrupt) */
    uint8_t in_isr;           /* fd_core_period running: a second entry is an overrun */
    uint8_t bus_off_prev;     /* the CAN controller was bus-off at the last period */
    uint32_t bus_off_recovered; /* stats.can_bus_offs the background has recovered */
    fd_fault_entry_t fault_log[FD_FAULT_LOG]; /* ring, newest at fault_log_n - 1 */
    uint32_t fault_log_n;     /* faults logged since boot */
    fd_host_ref_t ref;        /* in use */
    fd_cur_state_t cur;
    fd_cur_out_t cur_out;     /* output of the last current-loop step */
    float theta_used;         /* angle of the last current-loop step [rad] */
    fd_stats_t stats;
} fd_core_t;

/** Defaults of a 10 kHz board (fd_config_t) and of the DRIVE_PARAMs. */
void fd_config_default(fd_config_t *cfg);
/** Initialise (PWM off, disarmed): parameters from storage if its record's CRC holds, else
 *  the defaults (DRIVE_PARAM PARAM_SOURCE says which). Before the interrupts start. */
void fd_core_init(fd_core_t *c, const fd_config_t *cfg, void *hal);
/** The per-PWM-period interrupt body (see the file comment). Bounded: no CAN reception,
 *  at most FD_CMD_RING commands and one reference taken over, at most a sample (one
 *  SAMPLE_FD or four SAMPLE_C_*), a STATUS and a FAULT frame sent. */
void fd_core_period(fd_core_t *c);
/** The background context: the main loop (or an interrupt of lower priority than the
 *  period interrupt) calls it as often as it can. Takes up to FD_BG_FRAMES received frames
 *  from the HAL and handles each (fd_core_handle_frame); returns how many. */
unsigned fd_core_background(fd_core_t *c);
/** DRIVE_PARAM access (what a received DRIVE_PARAM does); returns a FD_PA_* status. */
int fd_core_param_write(fd_core_t *c, int prm_id, float value);
int fd_core_param_read(const fd_core_t *c, int prm_id, float *value);
/** Fault log entry i (0 = newest); 0 if there is none. */
int fd_core_fault_log(const fd_core_t *c, uint32_t i, fd_fault_entry_t *out);
/** 1 if the host's answer to sample `seq` (a DUTY_CMD in host mode, a HOST_REF in split
 *  mode) has been received and not yet taken (lockstep drivers wait for it). */
int fd_core_has_answer(const fd_core_t *c, uint16_t seq);
/** Handle one received frame in the background context (fd_core_background calls it):
 *  DUTY_CMD and HOST_REF go to the interrupt through the lock-free hand-over; ARM_MODE,
 *  DRIVE_PARAM (answered with DRIVE_PARAM_ACK from here) and HOST_HEARTBEAT change the
 *  state inside a short critical section (fd_hal_irq_lock). */
void fd_core_handle_frame(fd_core_t *c, const fd_can_frame_t *f);

/* ---- frame encoders (the DBC's scaling through the generated codec; exposed for the
 * byte-for-byte test against cantools). Each returns the payload length, < 0 on error. */
int fd_encode_fault(uint8_t out[8], uint8_t code, uint8_t latched, uint8_t active,
                    uint8_t pwm_disabled, uint16_t detail, uint16_t seq, uint8_t count);
int fd_encode_status(uint8_t out[8], uint8_t alive, uint8_t state, uint8_t armed,
                     uint8_t pwm_enabled, uint8_t fault_latched, uint8_t layout,
                     uint8_t decimation, uint16_t tx_overruns, int8_t temp_c,
                     uint8_t rx_errors);
/** SAMPLE_FD. f: i_a, i_b, i_c, v_ab, v_bc, v_ca, vdc, duty_a, duty_b, duty_c [SI];
 *  flags bit 0 pwm_enabled, 1 armed, 2 fault_active, 3 adc_clip, 4 cmd_stale,
 *  5 capture_valid, 6 control_split. */
int fd_encode_sample_fd(uint8_t out[64], uint16_t seq, const float f[10], int32_t encoder,
                        uint16_t cmd_seq_applied, uint32_t t_mcu_us, uint8_t flags, uint8_t mode,
                        uint8_t fault_code);
/** SAMPLE_C_CUR, _VLT, _DUTY, _AUX into out[4][8] (same f and flags as SAMPLE_FD). */
int fd_encode_sample_classic(uint8_t out[4][8], uint16_t seq, const float f[10], int32_t encoder,
                             uint8_t flags);
int fd_encode_param_ack(uint8_t out[8], uint8_t id, uint8_t seq, uint8_t status, float value);

#ifdef __cplusplus
}
#endif
#endif /* FD_CORE_H */
