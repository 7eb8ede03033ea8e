/* fluxdrive firmware: the bench HAL of the target images (fd_hal.h over RAM). Readings are
 * written by the bench program between interrupts; CAN RX is a ring the program fills, TX a
 * ring it may read (older frames are overwritten: nothing drains it on the bench). It stands
 * where a board's peripheral HAL goes and costs about what register reads and a FIFO write
 * cost; it is not a port (docs/firmware.md lists what a port writes). */
#ifndef FD_HAL_BENCH_H
#define FD_HAL_BENCH_H

#include <stdint.h>

#include "fd_hal.h"

#define FD_BENCH_QUEUE 16u

typedef struct {
    fd_adc_raw_t adc;
    fd_capture_raw_t cap;
    uint32_t time_us;
    uint32_t pwm_compare[3];
    uint32_t pwm_enable;
    fd_can_frame_t rx[FD_BENCH_QUEUE];
    uint32_t rx_head, rx_tail;
    fd_can_frame_t tx[FD_BENCH_QUEUE];
    uint32_t tx_head;
    fd_hal_status_t hw;  /* power-stage / CAN status (all clear on the bench) */
    uint32_t overrun;    /* what fd_hal_period_overrun answers (0 on the bench) */
} fd_bench_hal_t;

/** Queue a frame for the core (0 if full). */
int fd_bench_rx_push(fd_bench_hal_t *h, const fd_can_frame_t *f);

#endif /* FD_HAL_BENCH_H */
