/* fluxdrive drive firmware: the hardware abstraction layer the core calls.
 *
 * Thin on purpose: the core does every conversion to SI units and all protocol work; a
 * board port only moves raw counts and CAN frames. Every call takes the port's context
 * pointer (the `hal` given to fd_core_init), so one process can hold several drives (the
 * software-in-the-loop build does). Two contexts call it: the PWM-period interrupt
 * (fd_core_period: ADC, capture, status, PWM, CAN TX, time, overrun) and the background
 * (fd_core_background: CAN RX, CAN TX, time, the critical section). fd_hal_can_tx is called
 * from both, so a port makes it safe against the period interrupt (e.g. separate TX
 * buffers per context, or a critical section around the FIFO put). No call may block.
 *
 * Timing (docs/engine.md, timing convention): the period interrupt for sample k runs right
 * after the ADC conversion triggered at the carrier valley t_k. The capture registers then
 * hold the line-voltage high times of the period [t_(k-1), t_k] just ended.
 *
 * The timing of real timers: fd_hal_pwm_write in the interrupt of sample k writes the compare
 * values (and an output enable) into the timer's preload registers; they take effect at the
 * next update event, the carrier valley t_(k+1), and hold over [t_(k+1), t_(k+2)]. The period
 * [t_k, t_(k+1)] already running keeps what the previous interrupt wrote. A cleared enable is
 * the exception: it opens all six switches at once (main output enable off), in the running
 * period. A duty computed from sample k therefore acts one period later, the delay the loop
 * design assumes; the SIL's timer model (fluxdrive.can.firmware) does exactly this.
 */
/* Hardware over-current path (part of this contract): a comparator per phase current (or
 * on the bus shunt) at a threshold above the core's software trip drives the PWM timer's
 * break input. On a trip the timer opens all six switches in hardware (MOE cleared), with
 * no software in the path; fd_hal_status_read then reports break_event and the core
 * latches OVERCURRENT (detail FD_OC_DETAIL_BREAK). The outputs stay off until
 * fd_hal_pwm_write(..., true) after the fault was reset (the port sets MOE again there).
 * The SIL HAL models this as an instant trip: the period whose reading is beyond the
 * comparator threshold runs with the gates open. */
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

/** Power-stage and CAN-controller status, read once per period interrupt. */
typedef struct {
    uint8_t break_event; /* the timer's break input tripped since the last read (the
                          * over-current comparator cut the gates in hardware; BKIF) */
    uint8_t gate_fault;  /* the gate driver's fault output is asserted (nFAULT) */
    uint8_t can_bus_off; /* the CAN controller is bus-off */
    uint8_t can_tec;     /* transmit error counter (saturated at 255) */
    uint8_t can_rec;     /* receive error counter (saturated at 255) */
} fd_hal_status_t;

void fd_hal_adc_read(void *hal, fd_adc_raw_t *out);
void fd_hal_status_read(void *hal, fd_hal_status_t *out);
void fd_hal_capture_read(void *hal, fd_capture_raw_t *out);
/** Compare values (0..pwm period ticks, upper switch on-time per leg, centre-aligned) and
 *  the gate enable into the preload registers: in force from the next update event.
 *  enable = false opens all six switches at once. */
void fd_hal_pwm_write(void *hal, const uint32_t compare[3], bool enable);
/** Queue a frame for transmission; false if the TX queue is full (frame dropped). */
bool fd_hal_can_tx(void *hal, const fd_can_frame_t *frame);
/** Take one received frame; false if none is waiting. */
bool fd_hal_can_rx(void *hal, fd_can_frame_t *frame);
/** Free-running microsecond counter (wraps at 2^32). */
uint32_t fd_hal_time_us(void *hal);
/** A critical section against the period interrupt (on a Cortex-M: raise BASEPRI to its
 *  priority, or PRIMASK), returning the state to restore; the background context holds it
 *  for a few dozen instructions (an ARM_MODE, a DRIVE_PARAM write). Never called from the
 *  period interrupt. */
uint32_t fd_hal_irq_lock(void *hal);
void fd_hal_irq_unlock(void *hal, uint32_t state);
/** The CAN controller is bus-off: start its recovery (FDCAN: clear CCCR.INIT; the
 *  controller rejoins after 128 x 11 recessive bits). Background context. */
void fd_hal_can_recover(void *hal);
/** Non-volatile parameter storage (a flash page, EEPROM emulation; RAM in the SIL),
 *  background context and fd_core_init only; may take milliseconds. read: false if
 *  nothing was ever stored; write: false if it failed. */
bool fd_hal_storage_read(void *hal, void *buf, uint32_t len);
bool fd_hal_storage_write(void *hal, const void *buf, uint32_t len);
/** Called last in the period interrupt: true if this interrupt missed its deadline (on a
 *  timer: the counter read now is past the compare-preload deadline of the running period,
 *  or the period interrupt's flag is pending again, i.e. a period was lost). */
bool fd_hal_period_overrun(void *hal);

#ifdef __cplusplus
}
#endif
#endif /* FD_HAL_H */
