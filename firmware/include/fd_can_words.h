/* fluxdrive firmware: a CAN frame's payload as little-endian 32-bit words, the way an FDCAN
 * message RAM or a FIFO holds it. The one frame copy of the HALs that move frames word by
 * word (the board's message RAM, the bench HAL's rings): the header and the payload's len
 * bytes, never the whole 72-byte struct (a memcpy call, byte by byte in newlib-nano). */
#ifndef FD_CAN_WORDS_H
#define FD_CAN_WORDS_H

#include <stdint.h>
#include <string.h>

#include "fd_hal.h"

/** Payload bytes [w, w+4) of `f` as one word (w a multiple of 4, below 64); bytes at or
 *  beyond f->len read as 0 (a DLC's padding). */
static inline uint32_t fd_can_word(const fd_can_frame_t *f, uint32_t w)
{
    uint32_t v = 0;
    if (w + 4u <= f->len) { /* a whole word of payload: one load (little-endian target) */
        memcpy(&v, &f->data[w], 4u);
        return v;
    }
    for (uint32_t b = 0; b < 4u; ++b) {
        uint32_t i = w + b;
        v |= (uint32_t)(i < f->len ? f->data[i] : 0u) << (8u * b);
    }
    return v;
}

/** Payload bytes [w, w+4) of `f` from one word (w a multiple of 4, below 64). */
static inline void fd_can_set_word(fd_can_frame_t *f, uint32_t w, uint32_t v)
{
    memcpy(&f->data[w], &v, 4u);
}

/** `dst` = `src`: the header and the payload's len bytes rounded up to whole words (the
 *  last word's bytes beyond len copied as they are). */
static inline void fd_can_copy(fd_can_frame_t *dst, const fd_can_frame_t *src)
{
    dst->id = src->id;
    dst->len = src->len;
    dst->fd = src->fd;
    uint32_t n = ((uint32_t)src->len + 3u) / 4u;
    if (n > 16u) {
        n = 16u;
    }
    for (uint32_t i = 0; i < n; ++i) {
        uint32_t v;
        memcpy(&v, &src->data[4u * i], 4u);
        fd_can_set_word(dst, 4u * i, v);
    }
}

#endif /* FD_CAN_WORDS_H */
