/* fluxdrive drive firmware: the hardware abstraction layer the core calls.
 *
 * Thin on purpose: the core does every conversion to SI units and all protocol work; a
 * board port only moves raw counts and CAN frames. Every call takes the port's context
 * pointer (the `hal` given to fd_core_init), so one process can hold several drives (the
 * software-in-the-loop build does). All calls are made from the PWM-period interrupt
 * (fd_core_period), never re-entered. No call may block.
 *
 * Timing (docs/engine.md, timing convention): the period interrupt for sample k runs right
 * after the ADC conversion triggered at the carrier valley t_k. The capture registers then
 * hold the line-voltage high times of the period [t_(k-1), t_k] just ended. fd_hal_pwm_write
 * sets the compare values and the output enable for the period [t_k, t_(k+1)] now running.
 */
#ifndef FD_HAL_H
#define FD_HAL_H

#include <stdbool.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/** Raw ADC readings of one sample instant t_k. */
typedef struct {
    int32_t current_counts[3]; /* phase a, b, c current ADC results (mid-scale = 0 A) */
    int32_t vdc_counts;        /* DC-bus ADC result */
    int32_t temp_c;            /* power-stage temperature [degC] (STATUS only) */
} fd_adc_raw_t;

/** Line-voltage capture of the period just ended: signed high time of each line-to-line
 *  voltage (v_ab, v_bc, v_ca) in timer ticks (positive pulses minus negative pulses, one
 *  comparator pair per line as in the paper's Fig. 10), the ticks of one period, and the
 *  encoder timer (a reference sensor; the control never uses it). */
typedef struct {
    int32_t high_ticks[3];
    int32_t period_ticks;
    int32_t encoder_counts; /* encoder timer at t_k (lines x 4, wraps) */
} fd_capture_raw_t;

/** One CAN (FD) frame, 11-bit identifier. */
typedef struct {
    uint32_t id;
    uint8_t len;      /* payload bytes, 0..64 */
    uint8_t fd;       /* 1: CAN FD frame with bit-rate switch */
    uint8_t data[64];
} fd_can_frame_t;

void fd_hal_adc_read(void *hal, fd_adc_raw_t *out);
void fd_hal_capture_read(void *hal, fd_capture_raw_t *out);
/** Compare values (0..pwm period ticks, upper switch on-time per leg, centre-aligned) and
 *  the gate enable for the period now starting. enable = false opens all six switches. */
void fd_hal_pwm_write(void *hal, const uint32_t compare[3], bool enable);
/** Queue a frame for transmission; false if the TX queue is full (frame dropped). */
bool fd_hal_can_tx(void *hal, const fd_can_frame_t *frame);
/** Take one received frame; false if none is waiting. */
bool fd_hal_can_rx(void *hal, fd_can_frame_t *frame);
/** Free-running microsecond counter (wraps at 2^32). */
uint32_t fd_hal_time_us(void *hal);

#ifdef __cplusplus
}
#endif
#endif /* FD_HAL_H */
