/* Bench implementation of fd_hal.h for the target images (see fd_hal_bench.h). */
#include "fd_hal_bench.h"

#include "fd_can_words.h"

int fd_bench_rx_push(fd_bench_hal_t *h, const fd_can_frame_t *f)
{
    if (h->rx_head - h->rx_tail >= FD_BENCH_QUEUE) {
        return 0;
    }
    h->rx[h->rx_head % FD_BENCH_QUEUE] = *f;
    h->rx_head++;
    return 1;
}

void fd_hal_adc_read(void *hal, fd_adc_raw_t *out) { *out = ((fd_bench_hal_t *)hal)->adc; }

void fd_hal_capture_read(void *hal, fd_capture_raw_t *out) { *out = ((fd_bench_hal_t *)hal)->cap; }

void fd_hal_pwm_write(void *hal, const uint32_t compare[3], bool enable)
{
    fd_bench_hal_t *h = (fd_bench_hal_t *)hal;
    for (int j = 0; j < 3; ++j) {
        h->pwm_compare[j] = compare[j];
    }
    h->pwm_enable = enable ? 1u : 0u;
}

bool fd_hal_can_tx(void *hal, const fd_can_frame_t *frame)
{
    fd_bench_hal_t *h = (fd_bench_hal_t *)hal;
    fd_can_copy(&h->tx[h->tx_head % FD_BENCH_QUEUE], frame);
    h->tx_head++;
    return true;
}

bool fd_hal_can_rx(void *hal, fd_can_frame_t *frame)
{
    fd_bench_hal_t *h = (fd_bench_hal_t *)hal;
    if (h->rx_head == h->rx_tail) {
        return false;
    }
    fd_can_copy(frame, &h->rx[h->rx_tail % FD_BENCH_QUEUE]);
    h->rx_tail++;
    return true;
}

uint32_t fd_hal_time_us(void *hal) { return ((fd_bench_hal_t *)hal)->time_us; }

void fd_hal_status_read(void *hal, fd_hal_status_t *out) { *out = ((fd_bench_hal_t *)hal)->hw; }

void fd_hal_can_recover(void *hal) { (void)hal; }

/* no storage on the bench: the defaults at boot, a save fails */
bool fd_hal_storage_read(void *hal, void *buf, uint32_t len)
{
    (void)hal;
    (void)buf;
    (void)len;
    return false;
}

bool fd_hal_storage_write(void *hal, const void *buf, uint32_t len)
{
    (void)hal;
    (void)buf;
    (void)len;
    return false;
}

/* the bench calls the background between interrupts, never inside one */
uint32_t fd_hal_irq_lock(void *hal)
{
    (void)hal;
    return 0u;
}

void fd_hal_irq_unlock(void *hal, uint32_t state)
{
    (void)hal;
    (void)state;
}

bool fd_hal_period_overrun(void *hal) { return ((fd_bench_hal_t *)hal)->overrun != 0u; }
