/* Software-in-the-loop implementation of fd_hal.h: raw readings and PWM in memory, CAN as
 * two bounded queues (see fd_sil.h). */
#include <string.h>

#include "fd_sil.h"

size_t fd_sil_sizeof(void) { return sizeof(fd_sil_t); }
size_t fd_core_sizeof(void) { return sizeof(fd_core_t); }

void fd_sil_init(fd_sil_t *s) { memset(s, 0, sizeof(*s)); }

void fd_sil_set_inputs(fd_sil_t *s, const int32_t current_counts[3], int32_t vdc_counts,
                       const int32_t high_ticks[3], int32_t period_ticks, int32_t encoder_counts,
                       int32_t temp_c, uint32_t time_us)
{
    for (int j = 0; j < 3; ++j) {
        s->adc.current_counts[j] = current_counts[j];
        s->cap.high_ticks[j] = high_ticks[j];
    }
    s->adc.vdc_counts = vdc_counts;
    s->adc.temp_c = temp_c;
    s->cap.period_ticks = period_ticks;
    s->cap.encoder_counts = encoder_counts;
    s->time_us = time_us;
    if (s->break_counts > 0) { /* the comparator trips as the reading crosses: instant */
        for (int j = 0; j < 3; ++j) {
            int32_t x = current_counts[j] - s->break_mid;
            if (x >= s->break_counts || x <= -s->break_counts) {
                s->break_latched = 1;
                s->hw.break_event = 1;
            }
        }
    }
}

static uint8_t sat8(int32_t x) { return (uint8_t)(x < 0 ? 0 : (x > 255 ? 255 : x)); }

void fd_sil_inject(fd_sil_t *s, int32_t gate_fault, int32_t can_tec, int32_t can_rec,
                   int32_t can_bus_off, int32_t overrun)
{
    s->hw.gate_fault = (uint8_t)(gate_fault != 0);
    s->hw.can_tec = sat8(can_tec);
    s->hw.can_rec = sat8(can_rec);
    s->hw.can_bus_off = (uint8_t)(can_bus_off != 0);
    s->overrun_next = overrun != 0;
}

void fd_sil_set_break(fd_sil_t *s, int32_t mid_counts, int32_t threshold_counts)
{
    s->break_mid = mid_counts;
    s->break_counts = threshold_counts;
}

void fd_sil_set_time(fd_sil_t *s, uint32_t time_us) { s->time_us = time_us; }

void fd_sil_get_pwm(const fd_sil_t *s, uint32_t compare[3], int32_t *enable)
{
    for (int j = 0; j < 3; ++j) {
        compare[j] = s->pwm_compare[j];
    }
    *enable = s->pwm_enable;
}

int fd_sil_rx_push(fd_sil_t *s, uint32_t id, const uint8_t *data, uint32_t len, uint32_t fd)
{
    if (s->rx_head - s->rx_tail >= FD_SIL_QUEUE || len > 64u) {
        return 0;
    }
    fd_can_frame_t *f = &s->rx[s->rx_head % FD_SIL_QUEUE];
    f->id = id;
    f->len = (uint8_t)len;
    f->fd = (uint8_t)(fd != 0u);
    memset(f->data, 0, sizeof(f->data));
    memcpy(f->data, data, len);
    s->rx_head++;
    return 1;
}

int fd_sil_tx_pop(fd_sil_t *s, uint32_t *id, uint8_t data[64], uint32_t *len, uint32_t *fd)
{
    if (s->tx_head == s->tx_tail) {
        return 0;
    }
    const fd_can_frame_t *f = &s->tx[s->tx_tail % FD_SIL_QUEUE];
    *id = f->id;
    *len = f->len;
    *fd = f->fd;
    memcpy(data, f->data, f->len);
    s->tx_tail++;
    return 1;
}

uint32_t fd_core_flags(const fd_core_t *c)
{
    return (uint32_t)c->armed | ((uint32_t)c->pwm_enabled << 1) |
           ((uint32_t)c->fault_latched << 2) | ((uint32_t)c->split << 3) |
           ((uint32_t)c->fault_code << 8) | ((uint32_t)(c->mode & 0xFu) << 16);
}

const fd_stats_t *fd_core_stats(const fd_core_t *c) { return &c->stats; }

uint32_t fd_core_period_index(const fd_core_t *c) { return c->k; }

void fd_sil_restart_period_index(fd_core_t *c)
{
    uint32_t k = c->k; /* unsigned: the scheduled periods keep their distance to k */
    c->k = 0u;
    c->next_status_k -= k;
    c->next_fault_k -= k;
    c->last_cmd_k -= k;
    c->last_ref_k -= k;
    c->ran_first = 0; /* the run's first boundary answers no sample before it */
}

/* ---- fd_hal.h */

void fd_hal_adc_read(void *hal, fd_adc_raw_t *out) { *out = ((fd_sil_t *)hal)->adc; }

void fd_hal_capture_read(void *hal, fd_capture_raw_t *out) { *out = ((fd_sil_t *)hal)->cap; }

void fd_hal_status_read(void *hal, fd_hal_status_t *out)
{
    fd_sil_t *s = (fd_sil_t *)hal;
    *out = s->hw;
    s->hw.break_event = 0; /* an event flag: cleared by reading (BKIF) */
}

void fd_hal_pwm_write(void *hal, const uint32_t compare[3], bool enable)
{
    fd_sil_t *s = (fd_sil_t *)hal;
    for (int j = 0; j < 3; ++j) {
        s->pwm_compare[j] = compare[j];
    }
    if (!enable) {
        s->break_latched = 0; /* the core has seen it: the next enable sets MOE again */
    }
    s->pwm_enable = enable && !s->break_latched ? 1 : 0;
}

void fd_hal_can_recover(void *hal)
{
    fd_sil_t *s = (fd_sil_t *)hal;
    s->can_recoveries++;
    s->hw.can_bus_off = 0;
    s->hw.can_tec = 0;
}

bool fd_hal_storage_read(void *hal, void *buf, uint32_t len)
{
    fd_sil_t *s = (fd_sil_t *)hal;
    if (s->store_len == 0u || len > s->store_len) {
        return false;
    }
    memcpy(buf, s->store, len);
    return true;
}

bool fd_hal_storage_write(void *hal, const void *buf, uint32_t len)
{
    fd_sil_t *s = (fd_sil_t *)hal;
    if (s->store_fail || len > sizeof(s->store)) {
        return false;
    }
    memcpy(s->store, buf, len);
    s->store_len = len;
    return true;
}

/* one thread calls both contexts in turn: nothing to lock */
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

bool fd_hal_period_overrun(void *hal)
{
    fd_sil_t *s = (fd_sil_t *)hal;
    bool late = s->overrun_next != 0;
    s->overrun_next = 0;
    return late;
}

bool fd_hal_can_tx(void *hal, const fd_can_frame_t *frame)
{
    fd_sil_t *s = (fd_sil_t *)hal;
    if (s->tx_head - s->tx_tail >= FD_SIL_QUEUE) {
        return false;
    }
    s->tx[s->tx_head % FD_SIL_QUEUE] = *frame;
    s->tx_head++;
    return true;
}

bool fd_hal_can_rx(void *hal, fd_can_frame_t *frame)
{
    fd_sil_t *s = (fd_sil_t *)hal;
    if (s->rx_head == s->rx_tail) {
        return false;
    }
    *frame = s->rx[s->rx_tail % FD_SIL_QUEUE];
    s->rx_tail++;
    return true;
}

uint32_t fd_hal_time_us(void *hal) { return ((fd_sil_t *)hal)->time_us; }
