/* The temporal ops (backends.base.AccumulateOp, ChangeOp, HistoryOp).
 * Compiled as part of native.c (one translation unit: see there). */
#include "common.h"

/* ---------------------------------------------------------------- temporal accumulation
 * One frame of torchgi.temporal's reprojection and accumulation (backends.base.AccumulateOp; the
 * same maths as torch_code.accumulation, tap by tap in the same order): the history's four
 * bilinear taps at pixel + motion (a tap that does not count weighs 0),
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

#define TBLOCK 256 /* pixels of a row the walks below take at a time: one short loop per plane, in L1 */

/* on = the surface byte mask of n pixels as floats (so that the loops reading it vectorise) */
INLINE void float_mask(const uint8_t *surface, float *on, int n) {
    for (int j = 0; j < n; ++j) on[j] = surface[j] ? 1.0f : 0.0f;
}

/* floorf(v) for |v| < 2^31; elsewhere (NaN included) a value at least 2^31 from the image (the
 * conversion's out-of-range result): a tap there is outside the image either way. With floorf
 * GCC (12, -O3 -march=native) left the loop scalar ("function is not vectorizable"). */
INLINE float floor_small(float v) {
    const float f = (float)(int)v;
    return f > v ? f - 1.0f : f;
}


/* The walk over blocks of a row, in loops free of control flow (so that the compiler vectorises
 * them, the taps as gathers), each reading or writing a few planes only: the planes lie a multiple
 * of 4 KB apart at many sizes, and a loop over more of them than the L1 cache has ways evicts its
 * own lines. The taps' positions and bilinear weights; their tests against the previous frame's
 * kind and depth, then its normal; the nine history planes' weighted sums, one plane at a time;
 * the averages; the outputs, a few planes per loop. */
static void accumulate_rows(const accum_t *A, int y0, int y1) {
    const int H = A->H, W = A->W;
    const size_t HW = (size_t)H * W;
    const float *hist[9] = {A->light, A->light + HW, A->light + 2 * HW, A->output, A->output + HW,
                            A->output + 2 * HW, A->moments, A->moments + HW, A->length};
    const float *pn0 = A->pn, *pn1 = A->pn + HW, *pn2 = A->pn + 2 * HW, *pd = A->pd, *ps = A->ps;
    const float ntol = A->ntol, dtol = A->dtol, cap = A->cap, alpha = A->alpha, xmax = (float)(W - 1), ymax = (float)(H - 1);
    float w[4][TBLOCK], h[9][TBLOCK], total[TBLOCK], sf[TBLOCK], a[TBLOCK], len[TBLOCK], hl[TBLOCK],
          cx[3][TBLOCK], lum[TBLOCK];
    int t[4][TBLOCK];
    for (int y = y0; y < y1; ++y) {
        for (int x0 = 0; x0 < W; x0 += TBLOCK) {
            const int n = MINF(TBLOCK, W - x0);
            const size_t i0 = (size_t)y * W + x0;
            const float *mx = A->motion + i0, *my = A->motion + HW + i0;
            float_mask(A->surface + i0, sf, n);
            #pragma GCC ivdep
            for (int j = 0; j < n; ++j) { /* each tap's index and bilinear weight, 0 outside the image */
                const float px = (float)(x0 + j) + mx[j], py = (float)y + my[j];
                const float fx0 = floor_small(px), fy0 = floor_small(py), fx = px - fx0, fy = py - fy0;
                FOR8(k, 4, {
                    const float tx = fx0 + (k & 1), ty = fy0 + (k >> 1);
                    const int inside = (tx >= 0) & (tx <= xmax) & (ty >= 0) & (ty <= ymax);
                    t[k][j] = (int)MINF(MAXF(ty, 0.0f), ymax) * W + (int)MINF(MAXF(tx, 0.0f), xmax);
                    w[k][j] = inside ? ((k & 1) ? fx : 1 - fx) * ((k >> 1) ? fy : 1 - fy) : 0.0f;
                });
            }
            const float *dp = A->depth + i0;
            #pragma GCC ivdep
            for (int j = 0; j < n; ++j) { /* of the same kind; on surfaces, within the depth tolerance */
                const int surf = sf[j] > 0;
                FOR8(k, 4, {
                    const int at = t[k][j];
                    const int ok = ((ps[at] > 0.5f) == surf) & ((fabsf(pd[at] - dp[j]) <= dtol * fabsf(dp[j])) | !surf);
                    w[k][j] = ok ? w[k][j] : 0.0f;
                });
            }
            const float *nx = A->normal + i0, *ny = A->normal + HW + i0, *nz = A->normal + 2 * HW + i0;
            #pragma GCC ivdep
            for (int j = 0; j < n; ++j) { /* on surfaces, within the normal tolerance */
                const int surf = sf[j] > 0;
                FOR8(k, 4, {
                    const int at = t[k][j];
                    const float dot = pn0[at] * nx[j] + pn1[at] * ny[j] + pn2[at] * nz[j];
                    w[k][j] = (dot >= ntol) | !surf ? w[k][j] : 0.0f;
                });
                total[j] = ((w[0][j] + w[1][j]) + w[2][j]) + w[3][j];
            }
            for (int c = 0; c < 9; ++c) {
                const float *hc = hist[c];
                #pragma GCC ivdep
                for (int j = 0; j < n; ++j) {
                    float s = 0.0f;
                    FOR8(k, 4, {
                        const float v = hc[t[k][j]];
                        s += w[k][j] > 0 ? w[k][j] * v : 0.0f;
                    });
                    h[c][j] = total[j] > 1e-3f ? s / total[j] : 0.0f;
                }
            }
            const float *x0p = A->x + i0, *x1p = A->x + HW + i0, *x2p = A->x + 2 * HW + i0, *bp = A->bound + i0;
            #pragma GCC ivdep
            for (int j = 0; j < n; ++j) { /* the weights of this frame, its light clamped to the bound */
                hl[j] = total[j] > 1e-3f ? rintf(h[8][j]) : 0.0f;
                len[j] = hl[j] > 0 ? MINF(hl[j] + 1, cap) : 1.0f;
                a[j] = MAXF(1.0f / len[j], alpha);
                const float peak = MAXF(MAXF(x0p[j], x1p[j]), x2p[j]), bound = bp[j];
                const float k = peak > bound ? bound / peak : 1.0f;
                cx[0][j] = peak > bound ? x0p[j] * k : x0p[j];
                cx[1][j] = peak > bound ? x1p[j] * k : x1p[j];
                cx[2][j] = peak > bound ? x2p[j] * k : x2p[j];
                lum[j] = 0.2126f * cx[0][j] + 0.7152f * cx[1][j] + 0.0722f * cx[2][j];
            }
            float *o = A->out + i0;
            for (int c = 0; c < 3; ++c) {
                float *oc = o + c * HW, *oh = o + (3 + c) * HW;
                #pragma GCC ivdep
                for (int j = 0; j < n; ++j) oc[j] = h[c][j] + a[j] * (cx[c][j] - h[c][j]), oh[j] = h[3 + c][j];
            }
            float *m1p = o + 6 * HW, *m2p = o + 7 * HW, *vp = o + 10 * HW;
            #pragma GCC ivdep
            for (int j = 0; j < n; ++j) {
                const float m1 = h[6][j] + a[j] * (lum[j] - h[6][j]), m2 = h[7][j] + a[j] * (lum[j] * lum[j] - h[7][j]);
                m1p[j] = m1, m2p[j] = m2, vp[j] = MAXF(m2 - m1 * m1, 0.0f);
            }
            float *lp = o + 8 * HW, *hp = o + 9 * HW, *fp = o + 11 * HW, *up = o + 12 * HW;
            #pragma GCC ivdep
            for (int j = 0; j < n; ++j)
                lp[j] = len[j], hp[j] = hl[j], fp[j] = MINF(len[j], (2 - a[j]) / a[j]), up[j] = lum[j];
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
 * radii r0 and r1, below it the history scaled toward this frame's window means (gain d² / (d² +
 * (follow sigma)²), 0: not), the history moved back toward this frame by the drop, the variance chosen and the
 * spatial filter's colour input remodulated. step: AccumulateOp's 13 planes. out: 11 planes
 * (light 3, moments 2, length, frames, variance / frames, colour 3). */
typedef struct {
    const float *x, *bound, *step, *svar, *near, *wide, *albedo, *emission;
    const uint8_t *surface;
    int H, W, r0, r1;
    float thr, follow, vh, floor, ceil;
    float *out;
} change_t;

/* the pixels a window of radius r covers along an axis of n at i (clipped at the edges) */
INLINE float extent(int i, int n, int r) { return (float)(MINF(i + r, n - 1) - MAXF(i - r, 0) + 1); }

/* the demodulator: the albedo a in [floor, ceil] on surfaces (on > 0), 1 elsewhere */
INLINE float demodulator(float on, float a, float floor, float ceil) { return on > 0 ? MINF(MAXF(a, floor), ceil) : 1.0f; }

/* dst = v x the demodulator + e, n values */
INLINE void remodulate(const float *restrict v, const float *restrict a, const float *restrict e,
                       const float *restrict on, float floor, float ceil, float *restrict dst, int n) {
    for (int j = 0; j < n; ++j) dst[j] = v[j] * demodulator(on[j], a[j], floor, ceil) + e[j];
}

static void change_rows(const change_t *C, int y0, int y1) {
    const int H = C->H, W = C->W;
    const size_t HW = (size_t)H * W;
    const float *s = C->step;
    float drop[TBLOCK], follow[TBLOCK], scale[TBLOCK], on[TBLOCK];
    for (int y = y0; y < y1; ++y) {
        const float ey0 = extent(y, H, C->r0), ey1 = extent(y, H, C->r1);
        for (int x0 = 0; x0 < W; x0 += TBLOCK) {
            const int n = MINF(TBLOCK, W - x0);
            const size_t i0 = (size_t)y * W + x0;
            float *o = C->out + i0;
            const float *st = s + i0;
            if (C->near) {
                #pragma GCC ivdep
                for (int j = 0; j < n; ++j) drop[j] = 0.0f, follow[j] = 1.0f;
                for (int k = 0; k < 2; ++k) {
                    const float *b = (k ? C->wide : C->near) + i0, ey = k ? ey1 : ey0;
                    const int r = k ? C->r1 : C->r0;
                    #pragma GCC ivdep
                    for (int j = 0; j < n; ++j) {
                        const float sigma = sqrtf(MAXF(b[2 * HW + j], 0.0f) / (ey * extent(x0 + j, W, r)));
                        const float beyond = (fabsf(b[j] - b[HW + j]) - C->thr * sigma) / MAXF(sigma, FLT_MIN);
                        drop[j] = MAXF(drop[j], MINF(MAXF(beyond, 0.0f), 1.0f));
                    }
                    if (C->follow > 0) {  /* the history's window mean toward this frame's, by the gain */
                        const float f2 = C->follow * C->follow;
                        #pragma GCC ivdep
                        for (int j = 0; j < n; ++j) {
                            const float s2 = MAXF(b[2 * HW + j], 0.0f) / (ey * extent(x0 + j, W, r));
                            const float before = b[HW + j], d = b[j] - before;
                            const float gain = d * d / MAXF(d * d + f2 * s2, FLT_MIN);
                            const float f = before > 0 ? 1 + gain * d / (before > 0 ? before : 1.0f) : 1.0f;
                            follow[j] *= MINF(MAXF(f, 0.0f), 4.0f);
                        }
                    }
                }
                const float *xs = C->x + i0, *bound = C->bound + i0;
                #pragma GCC ivdep
                for (int j = 0; j < n; ++j) {
                    const int old = st[9 * HW + j] > 0;
                    drop[j] = old ? drop[j] : 0.0f, follow[j] = old ? follow[j] : 1.0f;
                    const float peak = MAXF(MAXF(xs[j], xs[HW + j]), xs[2 * HW + j]);
                    scale[j] = peak > bound[j] ? bound[j] / peak : 1.0f;
                }
                for (int c = 0; c < 3; ++c)
                    #pragma GCC ivdep
                    for (int j = 0; j < n; ++j) {
                        const float h = st[c * HW + j] * follow[j];
                        o[c * HW + j] = (1 - drop[j]) * h + drop[j] * (xs[c * HW + j] * scale[j]);
                    }
                #pragma GCC ivdep
                for (int j = 0; j < n; ++j) {
                    const float lum = st[12 * HW + j], h1 = st[6 * HW + j] * follow[j], keep = 1 - drop[j];
                    const float h2 = st[7 * HW + j] * (follow[j] * follow[j]);
                    const float m1 = keep * h1 + drop[j] * lum;
                    const float m2 = keep * h2 + drop[j] * (lum * lum);
                    const float len = keep * st[8 * HW + j] + drop[j];
                    const float fr = keep * st[11 * HW + j] + drop[j];
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
                    int r0, int r1, float thr, float follow, float vh, float floor, float ceil, float *out, int nt,
                    void *scratch, long long stride) {
    const change_t C = {x, bound, step, svar, near, wide, albedo, emission, surface, H, W, r0, r1, thr, follow, vh, floor,
                        ceil, out};
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
