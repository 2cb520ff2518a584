/* The temporal ops (backends.base.AccumulateOp, ChangeOp, HistoryOp).
 * Compiled as part of native.c (one translation unit: see there). */
#include "common.h"

/* ---------------------------------------------------------------- temporal accumulation
 * One frame of torchgi.temporal's reprojection and accumulation (backends.base.AccumulateOp; the
 * same maths as torch_code.accumulation, tap by tap in the same order): the history's four
 * bilinear taps at pixel + motion (tested without branches: a tap that does not count weighs 0),
 * each counted where it is inside the image, of the same kind
 * (surface / background) and, on surfaces, within the normal and depth tolerances; then the
 * exponential averages of the light x, scaled down to `bound` where its channel maximum exceeds
 * it (fireflies). out: 13 planes (light 3, output history 3, moments 2, length, history length,
 * variance, frames, the clamped light's luminance). */
typedef struct {
    const float *x, *bound, *motion, *normal, *depth;
    const uint8_t *surface;
    const float *light, *output, *moments, *length, *pn, *pd, *ps;
    int H, W;
    float alpha, cap, ntol, dtol;
    float *out;
} accum_t;

static void accumulate_rows(const accum_t *A, int y0, int y1) {
    const int H = A->H, W = A->W;
    const size_t HW = (size_t)H * W;
    const float *hist[9] = {A->light, A->light + HW, A->light + 2 * HW, A->output, A->output + HW,
                            A->output + 2 * HW, A->moments, A->moments + HW, A->length};
    for (int y = y0; y < y1; ++y) {
        for (int x = 0; x < W; ++x) {
            const size_t i = (size_t)y * W + x;
            const float px = (float)x + A->motion[i], py = (float)y + A->motion[HW + i];
            const float fx0 = floorf(px), fy0 = floorf(py), fx = px - fx0, fy = py - fy0;
            const int surf = A->surface[i] != 0;
            const float n0 = A->normal[i], n1 = A->normal[HW + i], n2 = A->normal[2 * HW + i], d = A->depth[i];
            float acc[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0}, total = 0, w[4];
            size_t t[4];
            for (int k = 0; k < 4; ++k) { /* each tap's weight, 0 where it does not count (no branches) */
                const int dx = k & 1, dy = k >> 1;
                const float tx = fx0 + dx, ty = fy0 + dy;
                const int inside = tx >= 0 && tx <= W - 1 && ty >= 0 && ty <= H - 1;
                const size_t j = inside ? (size_t)ty * W + (size_t)tx : i;
                const float dot = A->pn[j] * n0 + A->pn[HW + j] * n1 + A->pn[2 * HW + j] * n2;
                const int close = dot >= A->ntol && fabsf(A->pd[j] - d) <= A->dtol * fabsf(d);
                const int ok = inside & ((A->ps[j] > 0.5f) == surf) & (close | !surf);
                w[k] = ok ? (dx ? fx : 1 - fx) * (dy ? fy : 1 - fy) : 0.0f;
                t[k] = j;
            }
            for (int k = 0; k < 4; ++k) {
                for (int c = 0; c < 9; ++c) acc[c] += w[k] > 0 ? w[k] * hist[c][t[k]] : 0.0f;
                total += w[k];
            }
            const int found = total > 1e-3f;
            float h[9];
            for (int c = 0; c < 9; ++c) h[c] = found ? acc[c] / total : 0.0f;
            const float hl = found ? rintf(h[8]) : 0.0f;
            const float len = hl > 0 ? MINF(hl + 1, A->cap) : 1.0f;
            const float a = MAXF(1.0f / len, A->alpha);
            float *o = A->out + i;
            float x0 = A->x[i], x1 = A->x[HW + i], x2 = A->x[2 * HW + i];
            const float peak = MAXF(MAXF(x0, x1), x2), bound = A->bound[i];
            if (peak > bound) {
                const float k = bound / peak;
                x0 *= k, x1 *= k, x2 *= k;
            }
            o[0] = h[0] + a * (x0 - h[0]);
            o[HW] = h[1] + a * (x1 - h[1]);
            o[2 * HW] = h[2] + a * (x2 - h[2]);
            o[3 * HW] = h[3], o[4 * HW] = h[4], o[5 * HW] = h[5];
            const float lum = 0.2126f * x0 + 0.7152f * x1 + 0.0722f * x2;
            const float m1 = h[6] + a * (lum - h[6]), m2 = h[7] + a * (lum * lum - h[7]);
            o[6 * HW] = m1, o[7 * HW] = m2, o[8 * HW] = len, o[9 * HW] = hl;
            o[10 * HW] = MAXF(m2 - m1 * m1, 0.0f);
            o[11 * HW] = MINF(len, (2 - a) / a);
            o[12 * HW] = lum;
        }
    }
}


void torchgi_accumulate(const float *x, const float *bound, const float *motion, const float *normal, const float *depth,
                        const uint8_t *surface, const float *light, const float *output, const float *moments,
                        const float *length, const float *pn, const float *pd, const float *ps, int H, int W,
                        float alpha, float cap, float ntol, float dtol, float *out, int nt, void *scratch,
                        long long stride) {
    const accum_t A = {x, bound, motion, normal, depth, surface, light, output, moments, length, pn, pd, ps,
                       H, W, alpha, cap, ntol, dtol, out};
    OVER_BANDS(H, accumulate_rows(&A, y0, y1));
}

/* ---------------------------------------------------------------- after the accumulation
 * backends.base.ChangeOp: the change test's drop from the box means `near` and `wide` (3 planes
 * each: this frame's luminance, the accumulated light's, the spatial variance; NULL: no test) at
 * radii r0 and r1, the history moved back toward this frame by it, the variance chosen and the
 * spatial filter's colour input remodulated. step: AccumulateOp's 13 planes. out: 11 planes
 * (light 3, moments 2, length, frames, variance / frames, colour 3). */
typedef struct {
    const float *x, *bound, *step, *svar, *near, *wide, *albedo, *emission;
    const uint8_t *surface;
    int H, W, r0, r1;
    float thr, vh, floor, ceil;
    float *out;
} change_t;

/* the pixels a window of radius r covers along an axis of n at i (clipped at the edges) */
INLINE float extent(int i, int n, int r) { return (float)(MINF(i + r, n - 1) - MAXF(i - r, 0) + 1); }

/* the demodulator: the albedo a in [floor, ceil] on surfaces (on > 0), 1 elsewhere */
INLINE float demodulator(float on, float a, float floor, float ceil) { return on > 0 ? MINF(MAXF(a, floor), ceil) : 1.0f; }

/* on = the surface byte mask of n pixels as floats (so that the loops reading it vectorise) */
INLINE void float_mask(const uint8_t *surface, float *on, int n) {
    for (int j = 0; j < n; ++j) on[j] = surface[j] ? 1.0f : 0.0f;
}

/* dst = v x the demodulator + e, n values */
INLINE void remodulate(const float *restrict v, const float *restrict a, const float *restrict e,
                       const float *restrict on, float floor, float ceil, float *restrict dst, int n) {
    for (int j = 0; j < n; ++j) dst[j] = v[j] * demodulator(on[j], a[j], floor, ceil) + e[j];
}

#define TBLOCK 256 /* pixels of a row the walks below take at a time: one short loop per plane, in L1 */

static void change_rows(const change_t *C, int y0, int y1) {
    const int H = C->H, W = C->W;
    const size_t HW = (size_t)H * W;
    const float *s = C->step;
    float drop[TBLOCK], scale[TBLOCK], on[TBLOCK];
    for (int y = y0; y < y1; ++y) {
        const float ey0 = extent(y, H, C->r0), ey1 = extent(y, H, C->r1);
        for (int x0 = 0; x0 < W; x0 += TBLOCK) {
            const int n = MINF(TBLOCK, W - x0);
            const size_t i0 = (size_t)y * W + x0;
            float *o = C->out + i0;
            const float *st = s + i0;
            if (C->near) {
                #pragma GCC ivdep
                for (int j = 0; j < n; ++j) drop[j] = 0.0f;
                for (int k = 0; k < 2; ++k) {
                    const float *b = (k ? C->wide : C->near) + i0, ey = k ? ey1 : ey0;
                    const int r = k ? C->r1 : C->r0;
                    #pragma GCC ivdep
                    for (int j = 0; j < n; ++j) {
                        const float sigma = sqrtf(MAXF(b[2 * HW + j], 0.0f) / (ey * extent(x0 + j, W, r)));
                        const float beyond = (fabsf(b[j] - b[HW + j]) - C->thr * sigma) / MAXF(sigma, FLT_MIN);
                        drop[j] = MAXF(drop[j], MINF(MAXF(beyond, 0.0f), 1.0f));
                    }
                }
                const float *xs = C->x + i0, *bound = C->bound + i0;
                #pragma GCC ivdep
                for (int j = 0; j < n; ++j) {
                    if (!(st[9 * HW + j] > 0)) drop[j] = 0.0f;
                    const float peak = MAXF(MAXF(xs[j], xs[HW + j]), xs[2 * HW + j]);
                    scale[j] = peak > bound[j] ? bound[j] / peak : 1.0f;
                }
                for (int c = 0; c < 3; ++c)
                    #pragma GCC ivdep
                    for (int j = 0; j < n; ++j)
                        o[c * HW + j] = st[c * HW + j] + drop[j] * (xs[c * HW + j] * scale[j] - st[c * HW + j]);
                #pragma GCC ivdep
                for (int j = 0; j < n; ++j) {
                    const float lum = st[12 * HW + j];
                    const float m1 = st[6 * HW + j] + drop[j] * (lum - st[6 * HW + j]);
                    const float m2 = st[7 * HW + j] + drop[j] * (lum * lum - st[7 * HW + j]);
                    const float len = st[8 * HW + j] + drop[j] * (1 - st[8 * HW + j]);
                    const float fr = st[11 * HW + j] + drop[j] * (1 - st[11 * HW + j]);
                    const float var = len >= C->vh ? MAXF(m2 - m1 * m1, 0.0f) : C->svar[i0 + j];
                    o[3 * HW + j] = m1, o[4 * HW + j] = m2, o[5 * HW + j] = len, o[6 * HW + j] = fr;
                    o[7 * HW + j] = var / fr;
                }
            } else {
                for (int c = 0; c < 3; ++c) memcpy(o + c * HW, st + c * HW, n * sizeof(float));
                #pragma GCC ivdep
                for (int j = 0; j < n; ++j) {
                    const float len = st[8 * HW + j], fr = st[11 * HW + j];
                    const float var = len >= C->vh ? st[10 * HW + j] : C->svar[i0 + j];
                    o[3 * HW + j] = st[6 * HW + j], o[4 * HW + j] = st[7 * HW + j], o[5 * HW + j] = len;
                    o[6 * HW + j] = fr, o[7 * HW + j] = var / fr;
                }
            }
            float_mask(C->surface + i0, on, n);
            for (int c = 0; c < 3; ++c)
                remodulate(o + c * HW, C->albedo + c * HW + i0, C->emission + c * HW + i0, on, C->floor, C->ceil,
                           o + (8 + c) * HW, n);
        }
    }
}

void torchgi_change(const float *x, const float *bound, const float *step, const float *svar, const float *near,
                    const float *wide, const float *albedo, const uint8_t *surface, const float *emission, int H, int W,
                    int r0, int r1, float thr, float vh, float floor, float ceil, float *out, int nt, void *scratch,
                    long long stride) {
    const change_t C = {x, bound, step, svar, near, wide, albedo, emission, surface, H, W, r0, r1, thr, vh, floor, ceil,
                        out};
    OVER_BANDS(H, change_rows(&C, y0, y1));
}

/* backends.base.HistoryOp: the spatial filter's output demodulated, the output history clamped to
 * within sqrt(clamp x spread) of it and averaged in. out: the next output history (3 planes), image: the image (3). */
typedef struct {
    const float *filtered, *emission, *albedo, *spread, *hist, *kept, *hist_length;
    const uint8_t *surface;
    int H, W;
    float clamp, alpha, floor, ceil;
    float *out, *image;
} history_t;

/* one channel of n pixels of backends.base.HistoryOp: o the next output history, img the image */
INLINE void history_block(const float *restrict f, const float *restrict e, const float *restrict a,
                          const float *restrict hist, const float *restrict sigma, const float *restrict beta,
                          const float *restrict hl, const float *restrict on, float floor, float ceil,
                          float *restrict o, float *restrict img, int n) {
    for (int j = 0; j < n; ++j) {
        const float d = demodulator(on[j], a[j], floor, ceil);
        const float lit = (f[j] - e[j]) / d;
        const float h = MAXF(MINF(hist[j], lit + sigma[j]), lit - sigma[j]);
        const float v = hl[j] > 0 ? h + beta[j] * (lit - h) : lit;
        o[j] = v;
        img[j] = v * d + e[j];
    }
}

static void history_rows(const history_t *A, int y0, int y1) {
    const size_t HW = (size_t)A->H * A->W, end = (size_t)y1 * A->W;
    float sigma[TBLOCK], beta[TBLOCK], on[TBLOCK];
    for (size_t i0 = (size_t)y0 * A->W; i0 < end; i0 += TBLOCK) {
        const int n = (int)MINF((size_t)TBLOCK, end - i0);
        const float *spread = A->spread + i0, *kept = A->kept + i0, *hl = A->hist_length + i0;
        #pragma GCC ivdep
        for (int j = 0; j < n; ++j) {
            sigma[j] = sqrtf(A->clamp * MAXF(spread[j], 0.0f));
            beta[j] = MAXF(1.0f / kept[j], A->alpha);
        }
        float_mask(A->surface + i0, on, n);
        for (int c = 0; c < 3; ++c)
            history_block(A->filtered + c * HW + i0, A->emission + c * HW + i0, A->albedo + c * HW + i0,
                          A->hist + c * HW + i0, sigma, beta, hl, on, A->floor, A->ceil, A->out + c * HW + i0,
                          A->image + c * HW + i0, n);
    }
}

void torchgi_history(const float *filtered, const float *emission, const float *albedo, const uint8_t *surface,
                     const float *spread, const float *hist, const float *kept, const float *hist_length, int H, int W,
                     float clamp, float alpha, float floor, float ceil, float *out, float *image, int nt,
                     void *scratch, long long stride) {
    const history_t A = {filtered, emission, albedo, spread, hist, kept, hist_length, surface, H, W, clamp, alpha, floor,
                         ceil, out, image};
    OVER_BANDS(A.H, history_rows(&A, y0, y1));
}
