/* Float32 math of the period interrupt, inline: what newlib would do in a library call
 * (sinf/cosf with a Payne-Hanek reduction, roundf, fminf/fmaxf, floorf: several hundred
 * cycles per interrupt on a Cortex-M4F, docs/firmware.md) done in a few instructions.
 *
 * fd_sincosf: Cody-Waite reduction by pi/2 in three parts with fused multiply-adds (one
 * VFMA each on the FPv4; exactly rounded on any host), then the minimax polynomials of
 * Cephes' sinf/cosf on [-pi/4, pi/4]. Absolute error against the exact sine/cosine at most
 * FD_SINCOS_ERR_MAX for |x| <= FD_SINCOS_X_MAX (tests/test_firmware_math.py measures it
 * against libm in double precision over that range); beyond it (and for NaN/Inf) the
 * library sinf/cosf answer, outside the interrupt's range (its angles are wrapped to
 * [-pi, pi) plus an advance of at most a few radians). */
#ifndef FD_MATH_H
#define FD_MATH_H

#include <math.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define FD_SINCOS_X_MAX 8192.0f
#define FD_SINCOS_ERR_MAX 1.2e-7f

/* pi/2 = P1 + P2 + P3, each a float; 2/pi */
#define FD_PIO2_1 1.5707963705062866e+00f
#define FD_PIO2_2 -4.3711388286737929e-08f
#define FD_PIO2_3 -1.7151245100059474e-15f
#define FD_2_PI 0.63661977236758134f

static inline float fd_fminf(float a, float b) { return b < a ? b : a; }
static inline float fd_fmaxf(float a, float b) { return b > a ? b : a; }

/* round half away from zero (roundf) for |x| < 2^23 (larger: x itself, already an
 * integer; NaN: NaN) without a library call */
static inline float fd_roundf(float x)
{
    float ax = fabsf(x);
    if (!(ax < 8388608.0f)) {
        return x;
    }
    float t = (float)(int32_t)ax; /* truncation, exact below 2^23 */
    if (ax - t >= 0.5f) {
        t += 1.0f;
    }
    return x < 0.0f ? -t : t;
}

/* floorf for |x| < 2^23 (larger, NaN: x) */
static inline float fd_floorf(float x)
{
    if (!(fabsf(x) < 8388608.0f)) {
        return x;
    }
    float t = (float)(int32_t)x; /* towards zero */
    return t > x ? t - 1.0f : t;
}

/* sin and cos of x [rad] at once (see the file comment for the accuracy) */
static inline void fd_sincosf(float x, float *s, float *c)
{
    if (!(fabsf(x) <= FD_SINCOS_X_MAX)) {
        *s = sinf(x);
        *c = cosf(x);
        return;
    }
    float kf = fd_roundf(x * FD_2_PI);
    float r = fmaf(-kf, FD_PIO2_1, x);
    r = fmaf(-kf, FD_PIO2_2, r);
    r = fmaf(-kf, FD_PIO2_3, r);
    float z = r * r;
    float sp = r + r * z * (-1.6666654611e-1f + z * (8.3321608736e-3f + z * -1.9515295891e-4f));
    float cp = 1.0f - 0.5f * z +
               z * z * (4.166664568298827e-2f + z * (-1.388731625493765e-3f +
                                                     z * 2.443315711809948e-5f));
    switch ((uint32_t)(int32_t)kf & 3u) {
    case 0u:
        *s = sp;
        *c = cp;
        break;
    case 1u:
        *s = cp;
        *c = -sp;
        break;
    case 2u:
        *s = -sp;
        *c = -cp;
        break;
    default:
        *s = -cp;
        *c = sp;
        break;
    }
}

/** fd_sincosf as a linked function (the host tests measure its accuracy through it). */
void fd_sincos(float x, float *s, float *c);

#ifdef __cplusplus
}
#endif
#endif /* FD_MATH_H */
