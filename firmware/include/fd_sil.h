/* fluxdrive firmware: the software-in-the-loop HAL (fd_hal.h over plain memory).
 *
 * A driver (the Python binding python/fluxdrive/can/firmware.py, or a C test) writes the
 * raw readings of sample k with fd_sil_set_inputs, pushes received CAN frames, calls
 * fd_core_period, then reads the PWM compare values/enable and pops the frames the core
 * sent. No heap: the caller owns fd_sil_t (fd_sil_sizeof bytes) like fd_core_t. */
#ifndef FD_SIL_H
#define FD_SIL_H

#include <stddef.h>
#include <stdint.h>

#include "fd_core.h"

#ifdef __cplusplus
extern "C" {
#endif

#define FD_SIL_QUEUE 64u

typedef struct {
    fd_adc_raw_t adc;
    fd_capture_raw_t cap;
    uint32_t time_us;
    uint32_t pwm_compare[3];
    int32_t pwm_enable;
    fd_can_frame_t rx[FD_SIL_QUEUE];
    uint32_t rx_head, rx_tail;
    fd_can_frame_t tx[FD_SIL_QUEUE];
    uint32_t tx_head, tx_tail;
    /* injected power-stage / CAN status (fd_sil_inject) and the hardware over-current
     * comparator: |count - break_mid| >= break_counts on any phase trips the break
     * (break_counts 0: no comparator) */
    fd_hal_status_t hw;
    int32_t break_mid, break_counts;
    int32_t break_latched; /* gates held open by the break until the core writes PWM off */
    int32_t overrun_next;  /* the next fd_hal_period_overrun answers true (once) */
    uint32_t can_recoveries; /* fd_hal_can_recover calls (each ends the bus-off) */
    /* the parameter storage: RAM standing in for a flash page */
    uint8_t store[sizeof(fd_param_record_t)];
    uint32_t store_len;   /* bytes stored, 0: nothing */
    int32_t store_fail;   /* 1: writes fail */
} fd_sil_t;

size_t fd_sil_sizeof(void);
size_t fd_core_sizeof(void);
void fd_sil_init(fd_sil_t *s);
void fd_sil_set_inputs(fd_sil_t *s, const int32_t current_counts[3], int32_t vdc_counts,
                       const int32_t high_ticks[3], int32_t period_ticks, int32_t encoder_counts,
                       int32_t temp_c, uint32_t time_us);
void fd_sil_set_time(fd_sil_t *s, uint32_t time_us);
/** Fault injection: the gate driver's fault input, the CAN controller's error state, and
 *  a missed deadline reported at the end of the next period interrupt. */
void fd_sil_inject(fd_sil_t *s, int32_t gate_fault, int32_t can_tec, int32_t can_rec,
                   int32_t can_bus_off, int32_t overrun);
/** The hardware over-current comparator on the current ADC counts (0: none). */
void fd_sil_set_break(fd_sil_t *s, int32_t mid_counts, int32_t threshold_counts);
/** PWM of the period now starting: compare values and enable. */
void fd_sil_get_pwm(const fd_sil_t *s, uint32_t compare[3], int32_t *enable);
/** Queue a received frame for the core; 0 if the queue is full. */
int fd_sil_rx_push(fd_sil_t *s, uint32_t id, const uint8_t *data, uint32_t len, uint32_t fd);
/** Take a frame the core sent; 0 if none. */
int fd_sil_tx_pop(fd_sil_t *s, uint32_t *id, uint8_t data[64], uint32_t *len, uint32_t *fd);

/** State flags of the core for the binding: bit 0 armed, 1 pwm_enabled, 2 fault_latched,
 *  3 split, bits 8-15 fault_code, 16-19 mode. */
uint32_t fd_core_flags(const fd_core_t *c);
const fd_stats_t *fd_core_stats(const fd_core_t *c);
uint32_t fd_core_period_index(const fd_core_t *c);
/** The lockstep bench's run origin: the period counter back to 0 and every period it
 *  schedules from (STATUS, FAULT repeats, the command and reference ages) moved with it,
 *  the next boundary the first again, after the periods a drive ran disarmed before the
 *  run (its offset calibration). */
void fd_sil_restart_period_index(fd_core_t *c);
/** 1 if the host's answer to sample `seq` is waiting: taken in by the core
 *  (fd_core_has_answer) or still in the RX queue (lockstep drivers wait for it). */
int fd_sil_has_answer(const fd_sil_t *s, const fd_core_t *c, uint16_t seq);
/** Test hook: decode a host->drive frame (ARM_MODE, DUTY_CMD, HOST_REF, DRIVE_PARAM,
 *  HOST_HEARTBEAT) with the generated codec into SI values in the DBC's signal order;
 *  returns how many, < 0 if malformed or not a host frame. */
int fd_sil_decode_host(uint32_t id, const uint8_t *data, uint32_t len, float out[10]);

#ifdef __cplusplus
}
#endif
#endif /* FD_SIL_H */
