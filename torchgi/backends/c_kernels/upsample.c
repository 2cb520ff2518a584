/* The x2 (or s x s) upsampling of linear-model coefficients and their application to the guide
 * (backends.base.UpsampleApplyOp; the guided pipeline's last pass at reduced resolution,
 * backends.base.RestoreOp). Compiled as part of native.c, after guided.c (the guide, the light
 * steps' row routines declared there) and before pipeline.c, whose entry points call it. */
#include "common.h"

/* u (W values): the row t (w = ⌈W/2⌉ values) brought up x2 along the row, the bilinear taps of
 * torch's interpolate (align_corners=False) written out: x = 2k between t[k-1] and t[k] at 0.75,
 * x = 2k + 1 between t[k] and t[k+1] at 0.25, the edges clamped (the same products as the
 * index-array taps of upsample_apply_rows's general path, without the gathers). */
static void up2_along(const float *t, int w, int W, float *u) {
    u[0] = (1.0f - 0.0f) * t[0] + 0.0f * t[w > 1 ? 1 : 0];
    int k = 1;
    for (; 2 * k + 1 < W && k + 1 < w; ++k) {
        u[2 * k] = (1.0f - 0.75f) * t[k - 1] + 0.75f * t[k];
        u[2 * k + 1] = (1.0f - 0.25f) * t[k] + 0.25f * t[k + 1];
    }
    for (; 2 * k < W; ++k) { /* the last column pair: t[k + 1] clamped to t[k] */
        u[2 * k] = (1.0f - 0.75f) * t[k - 1] + 0.75f * t[k];
        if (2 * k + 1 < W) u[2 * k + 1] = (1.0f - 0.25f) * t[k] + 0.25f * t[k + (k < w - 1)];
    }
    if (W > 1) u[1] = (1.0f - 0.25f) * t[0] + 0.25f * t[w > 1 ? 1 : 0];
}

/* The guided filter's output rows [y0, y1) from the Q = (n + 1) Cs box-filtered coefficient
 * planes at s x s lower resolution (h x w), upsampled bilinearly by the factor s (torch's
 * interpolate, align_corners=False: rows first, then along the row) and applied to the full-resolution guide:
 * out_c = b_c + Σ_i a_ic (I_i - meanI_i) + offset_c; then remodulated by finish_row when L is
 * not NULL; at s = 2 each coefficient row is brought up along the row once (up2_along). scratch:
 * 2 W ints, W + w floats, 4 W floats. */
static void upsample_apply_rows(const float *coef, int n, int Cs, int s, int h, int w, const guide_t *G, const float *meanI,
                                const float *offset, int H, int W, float *out, const light_t *L, const uint8_t *mask,
                                void *scratch, int y0, int y1) {
    const size_t HW = (size_t)H * W, hw = (size_t)h * w;
    int *x0 = (int *)scratch, *x1 = x0 + W;
    float *lx = (float *)(x1 + W), *t = lx + W, *ad = t + w, *u = ad + 3 * W;
    float cI[4];
    guide_centres(G, meanI, cI);
    const float sx = 1.0f / (float)s, sy = sx; /* torch's scale_factor = s: the grid does not depend on H, W */
    for (int x = 0; x < W; ++x) {
        float src = sx * (x + 0.5f) - 0.5f;
        src = src < 0 ? 0 : src;
        x0[x] = (int)src;
        x1[x] = x0[x] + (x0[x] < w - 1);
        lx[x] = src - x0[x];
    }
    for (int y = y0; y < y1; ++y) {
        float src = sy * (y + 0.5f) - 0.5f;
        src = src < 0 ? 0 : src;
        const int ya = (int)src, yb = ya + (ya < h - 1);
        const float ly = src - ya;
        const size_t row = (size_t)y * W;
        if (L) demod_row(L, y, ad);
        for (int c = 0; c < Cs; ++c) {
            float *o = out + c * HW + row;
            for (int q = n; q >= 0; --q) { /* b first, then a_0 .. a_{n-1} */
                const int k = q == n ? n : n - 1 - q;
                const float *p0 = coef + ((size_t)k * Cs + c) * hw + (size_t)ya * w;
                const float *p1 = coef + ((size_t)k * Cs + c) * hw + (size_t)yb * w;
                for (int i = 0; i < w; ++i) t[i] = (1.0f - ly) * p0[i] + ly * p1[i];
                if (s == 2) {
                    up2_along(t, w, W, u);
                    if (k == n) {
                        const float off = offset[c];
                        for (int x = 0; x < W; ++x) o[x] = u[x] + off;
                    } else {
                        const float *g = G->src[k] + row, sc = G->scale[k], ce = cI[k];
                        for (int x = 0; x < W; ++x) o[x] += u[x] * (g[x] * sc + ce);
                    }
                } else if (k == n) {
                    const float off = offset[c];
                    for (int x = 0; x < W; ++x) o[x] = (1.0f - lx[x]) * t[x0[x]] + lx[x] * t[x1[x]] + off;
                } else {
                    const float *g = G->src[k] + row, sc = G->scale[k], ce = cI[k];
                    for (int x = 0; x < W; ++x) o[x] += ((1.0f - lx[x]) * t[x0[x]] + lx[x] * t[x1[x]]) * (g[x] * sc + ce);
                }
            }
            if (L) finish_row(L, mask, c, y, ad, o);
        }
    }
}
