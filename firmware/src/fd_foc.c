/* The dq current loop and the I2t integral: float32 ports of the engine's _current_loops,
 * _svpwm and _protect (python/fluxdrive/drive/control/kernel.py) with the same blocks
 * (core/blocks.py pi_output / pi_update, core/transforms.py clarke / park). Operation for
 * operation the same order, so a float32 result differs from the engine's float64 one only
 * by rounding and by fd_sincosf's error (tests/test_firmware.py compares them). No library
 * call and one division per step unless the hexagon limit or the deadtime feed-forward act
 * (fd_math.h; the cycle budget in docs/firmware.md). */
#include <math.h>

#include "fd_core.h"
#include "fd_math.h"

#define FD_SQRT3_2 0.8660254037844386f

static float fd_clampf(float x, float lo, float hi) { return x < lo ? lo : (x > hi ? hi : x); }

static float pi_output(float kp, float integ, float err) { return kp * err + integ; }

/* integrate and back-calculate: the integrator absorbs what the limiter cut off */
static float pi_update(float integ, float ki, float ts, float err, float out_unsat, float out_sat)
{
    return integ + ki * ts * err + (out_sat - out_unsat);
}

static void inv_clarke(float al, float be, float abc[3])
{
    float half_b = FD_SQRT3_2 * be;
    abc[0] = al;
    abc[1] = -0.5f * al + half_b;
    abc[2] = -0.5f * al - half_b;
}

/* phase voltages -> duties, min-max zero sequence, scaled into the hexagon; returns scale */
static float svpwm(float va, float vb, float vdc, float duty[3])
{
    float p[3];
    inv_clarke(va, vb, p);
    float hi = fd_fmaxf(p[0], fd_fmaxf(p[1], p[2]));
    float lo = fd_fminf(p[0], fd_fminf(p[1], p[2]));
    float span = hi - lo;
    float scale = 1.0f;
    if (span > vdc) {
        scale = vdc / span;
        p[0] *= scale;
        p[1] *= scale;
        p[2] *= scale;
        hi *= scale;
        lo *= scale;
    }
    float off = -0.5f * (hi + lo);
    float inv_vdc = 1.0f / vdc;
    for (int j = 0; j < 3; ++j) {
        duty[j] = 0.5f + (p[j] + off) * inv_vdc;
    }
    return scale;
}

void fd_current_loop(fd_cur_state_t *st, const fd_cur_params_t *p, float i_alpha, float i_beta,
                     float th, float we, float id_ref, float iq_ref, float vdc, float ts,
                     fd_cur_out_t *out)
{
    float c_t, s_t;
    fd_sincosf(th, &s_t, &c_t);
    float i_d = i_alpha * c_t + i_beta * s_t;
    float i_q = -i_alpha * s_t + i_beta * c_t;
    float lh = p->l_hat;
    float ed = id_ref - i_d;
    float eq = iq_ref - i_q;
    float dec = p->decouple;
    float vd_u = pi_output(p->kp, st->id_i, ed) - dec * we * lh * iq_ref;
    float vq_u = pi_output(p->kp, st->iq_i, eq) + dec * we * (lh * id_ref + p->lambda_hat);
    float th_adv = th + p->advance * ts * we;
    float c_a, s_a;
    fd_sincosf(th_adv, &s_a, &c_a);
    float va = vd_u * c_a - vq_u * s_a;
    float vb = vd_u * s_a + vq_u * c_a;
    float d[3];
    float scale = svpwm(va, vb, vdc, d);
    float vd_s = vd_u * scale;
    float vq_s = vq_u * scale;
    st->id_i = pi_update(st->id_i, p->ki, ts, ed, vd_u, vd_s);
    st->iq_i = pi_update(st->iq_i, p->ki, ts, eq, vq_u, vq_s);
    if (p->tdcomp_s > 0.0f) {
        /* deadtime feed-forward on the reference current's sign per phase */
        float ra = id_ref * c_a - iq_ref * s_a;
        float rb = id_ref * s_a + iq_ref * c_a;
        float x[3];
        inv_clarke(ra, rb, x);
        float dd = p->tdcomp_s / ts;
        for (int j = 0; j < 3; ++j) {
            d[j] += dd * (x[j] > 0.0f ? 1.0f : -1.0f);
        }
    }
    for (int j = 0; j < 3; ++j) {
        out->duty[j] = fd_clampf(d[j], 0.0f, 1.0f);
    }
    out->i_d = i_d;
    out->i_q = i_q;
    out->v_d = vd_s;
    out->v_q = vq_s;
}

float fd_i2t_step(float i2t, float i_alpha, float i_beta, float rated_a, float ts)
{
    /* integrate (i/I_rated)^2 - 1 while above rated (never below 0) */
    float i_pk2 = (i_alpha * i_alpha + i_beta * i_beta) / (rated_a * rated_a);
    return fd_fmaxf(i2t + (i_pk2 - 1.0f) * ts, 0.0f);
}

void fd_sincos(float x, float *s, float *c) { fd_sincosf(x, s, c); }
