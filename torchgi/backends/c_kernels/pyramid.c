/* The learned pyramid's walks (backends.base.MixHalfOp, ModelResidualOp, FineBandOp, BlockMeanOp;
 * torchgi.filters.pyramid): the candidates' coefficients mixed at half resolution, the scale-1
 * candidates mixed into the model and the residual with its 2 x 2 means, then the finest band of
 * the residual given back; the block means of its levels and views (of linear models applied). Compiled as part of
 * native.c, after pipeline.c (pool_row, pool_finish). The bilinear x2 steps are torch's
 * interpolate (scale_factor 2, align_corners=False) as in upsample_apply_rows: the row of the
 * lower level interpolated between its two rows first, then along the row. */
#include "common.h"

/* The column taps of a bilinear x2 step from w to W values. */
static void up2_columns(int W, int w, int *x0, int *x1, float *lx) {
    for (int x = 0; x < W; ++x) {
        float src = 0.5f * (x + 0.5f) - 0.5f;
        src = src < 0 ? 0 : src;
        x0[x] = (int)src;
        x1[x] = x0[x] + (x0[x] < w - 1);
        lx[x] = src - x0[x];
    }
}

/* Row y of a bilinear x2 step of the h x w plane p, before the columns: t (w values). */
static void up2_row(const float *p, int h, int w, int y, float *t) {
    float src = 0.5f * (y + 0.5f) - 0.5f;
    src = src < 0 ? 0 : src;
    const int ya = (int)src, yb = ya + (ya < h - 1);
    const float ly = src - ya, *p0 = p + (size_t)ya * w, *p1 = p + (size_t)yb * w;
    for (int i = 0; i < w; ++i) t[i] = (1.0f - ly) * p0[i] + ly * p1[i];
}

#define UP2(t, x) ((1.0f - lx[x]) * (t)[x0[x]] + lx[x] * (t)[x1[x]])

/* Rows [y0, y1) of out = up2(coarse) + Σ_j up2(wgt_j) fs_j, Q planes of h x w from h4 x w4: the
 * weights' rows brought up once per row (u, n w floats), each coarse plane's row then (uc).
 * scratch: 2 w ints, w + w4 + (n + 1) w floats. */
static void mix_half_rows(const float *coarse, const float *wgt, const float *const fs[4], int n, int Q, int h, int w,
                          int h4, int w4, float *out, void *scratch, int y0, int y1) {
    const size_t hw = (size_t)h * w, hw4 = (size_t)h4 * w4;
    int *x0 = (int *)scratch, *x1 = x0 + w;
    float *lx = (float *)(x1 + w), *t = lx + w, *u = t + w4, *uc = u + (size_t)n * w;
    up2_columns(w, w4, x0, x1, lx);
    for (int y = y0; y < y1; ++y) {
        const size_t row = (size_t)y * w;
        for (int j = 0; j < n; ++j) {
            up2_row(wgt + j * hw4, h4, w4, y, t);
            for (int i = 0; i < w; ++i) u[(size_t)j * w + i] = UP2(t, i);
        }
        for (int q = 0; q < Q; ++q) {
            up2_row(coarse + q * hw4, h4, w4, y, t);
            for (int i = 0; i < w; ++i) uc[i] = UP2(t, i);
            float *o = out + q * hw + row;
            const float *f0 = fs[0] + q * hw + row;
            for (int i = 0; i < w; ++i) o[i] = u[i] * f0[i];
            for (int j = 1; j < n; ++j) {
                const float *fj = fs[j] + q * hw + row, *uj = u + (size_t)j * w;
                for (int i = 0; i < w; ++i) o[i] += uj[i] * fj[i];
            }
            for (int i = 0; i < w; ++i) o[i] = uc[i] + o[i];
        }
    }
}

/* Low rows [ly0, ly1) (full rows 2 ly, 2 ly + 1): model += Σ_j up2(wgt_j) ys_j (in place), res =
 * x - model, low = the 2 x 2 means of res. scratch: 2 W ints, W + n w floats. */
static void model_residual_rows(float *model, const float *const ys[4], int n, const float *wgt, const float *x,
                                int C, int H, int W, float *res, float *low, void *scratch, int ly0, int ly1) {
    const int h = (H + 1) / 2, w = (W + 1) / 2;
    const size_t HW = (size_t)H * W, hw = (size_t)h * w;
    int *x0 = (int *)scratch, *x1 = x0 + W;
    float *lx = (float *)(x1 + W), *t = lx + W;
    up2_columns(W, w, x0, x1, lx);
    for (int ly = ly0; ly < ly1; ++ly) {
        const int ya = 2 * ly, yb = ya + 2 < H ? ya + 2 : H;
        for (int c = 0; c < C; ++c) memset(low + c * hw + (size_t)ly * w, 0, sizeof(float) * w);
        for (int y = ya; y < yb; ++y) {
            const size_t row = (size_t)y * W;
            for (int j = 0; j < n; ++j) up2_row(wgt + j * hw, h, w, y, t + (size_t)j * w);
            for (int c = 0; c < C; ++c) {
                float *m = model + c * HW + row, *r = res + c * HW + row;
                const float *xi = x + c * HW + row;
                for (int i = 0; i < W; ++i) {
                    float mix = UP2(t, i) * ys[0][c * HW + row + i];
                    for (int j = 1; j < n; ++j) mix += UP2(t + (size_t)j * w, i) * ys[j][c * HW + row + i];
                    m[i] += mix;
                    r[i] = xi[i] - m[i];
                }
                pool_row(r, W, 2, low + c * hw + (size_t)ly * w);
            }
        }
        for (int c = 0; c < C; ++c) pool_finish(low + c * hw + (size_t)ly * w, W, 2, yb - ya);
    }
}

/* Rows [y0, y1): out = model + (up2(band) + up2(gain) (res - up2(low))). scratch: 2 W ints,
 * W + (2 C + 1) w floats. */
static void fine_band_rows(const float *model, const float *res, const float *low, const float *band, const float *gain,
                           int C, int H, int W, float *out, void *scratch, int y0, int y1) {
    const int h = (H + 1) / 2, w = (W + 1) / 2;
    const size_t HW = (size_t)H * W, hw = (size_t)h * w;
    int *x0 = (int *)scratch, *x1 = x0 + W;
    float *lx = (float *)(x1 + W), *tg = lx + W, *tb = tg + w, *tl = tb + w;
    up2_columns(W, w, x0, x1, lx);
    for (int y = y0; y < y1; ++y) {
        const size_t row = (size_t)y * W;
        up2_row(gain, h, w, y, tg);
        for (int c = 0; c < C; ++c) {
            up2_row(band + c * hw, h, w, y, tb);
            up2_row(low + c * hw, h, w, y, tl);
            const float *m = model + c * HW + row, *r = res + c * HW + row;
            float *o = out + c * HW + row;
            for (int i = 0; i < W; ++i) o[i] = m[i] + (UP2(tb, i) + UP2(tg, i) * (r[i] - UP2(tl, i)));
        }
    }
}

#undef UP2

/* l[lx] = the means of the s-column blocks of t (the sums of `rows` image rows, W values), a last
 * partial block averaged over the columns it has. */
static void pool_columns(const float *t, int W, int s, int rows, float *l) {
    const int full = W / s;
    const float inv = 1.0f / (float)(s * rows);
    if (s == 2)
        for (int lx = 0; lx < full; ++lx) l[lx] = (t[2 * lx] + t[2 * lx + 1]) * inv;
    else if (s == 4)
        for (int lx = 0; lx < full; ++lx) l[lx] = ((t[4 * lx] + t[4 * lx + 1]) + (t[4 * lx + 2] + t[4 * lx + 3])) * inv;
    else
        for (int lx = 0; lx < full; ++lx) {
            float v = 0.0f;
            for (int j = 0; j < s; ++j) v += t[lx * s + j];
            l[lx] = v * inv;
        }
    if (full * s < W) {
        float v = 0.0f;
        for (int i = full * s; i < W; ++i) v += t[i];
        l[full] = v / (float)((W - full * s) * rows);
    }
}

/* Low rows [ly0, ly1) of the s x s block means of P planes of H x W into out (P planes of h x w),
 * a last partial block averaged over the pixels it has: the block's rows summed into t (W
 * floats of scratch), then its columns. */
static void block_mean_rows(const float *x, int P, int H, int W, int s, float *out, float *t, int ly0, int ly1) {
    const int h = (H + s - 1) / s, w = (W + s - 1) / s;
    for (int p = 0; p < P; ++p)
        for (int ly = ly0; ly < ly1; ++ly) {
            const float *a = x + (size_t)p * H * W + (size_t)ly * s * W;
            const int rows = ly * s + s < H ? s : H - ly * s;
            memcpy(t, a, sizeof(float) * W);
            for (int y = 1; y < rows; ++y)
                for (int i = 0; i < W; ++i) t[i] += a[(size_t)y * W + i];
            pool_columns(t, W, s, rows, out + (size_t)p * h * w + (size_t)ly * w);
        }
}

/* Low rows [ly0, ly1) of the s x s block means of b + Σ_i a_i I_i (coef: the (n + 1) C planes a_0..a_{n-1},
 * b of H x W; I: n planes), C planes of h x w: each image row applied into v, the block's rows
 * summed into t, then its columns. scratch: 2 W floats. */
static void applied_means_rows(const float *coef, const float *I, int n, int C, int H, int W, int s, float *out,
                               float *scratch, int ly0, int ly1) {
    const int h = (H + s - 1) / s, w = (W + s - 1) / s;
    const size_t HW = (size_t)H * W;
    float *t = scratch, *v = t + W;
    for (int c = 0; c < C; ++c)
        for (int ly = ly0; ly < ly1; ++ly) {
            const int rows = ly * s + s < H ? s : H - ly * s;
            for (int y = 0; y < rows; ++y) {
                const size_t row = (size_t)(ly * s + y) * W;
                const float *b = coef + ((size_t)n * C + c) * HW + row;
                for (int i = 0; i < W; ++i) v[i] = b[i];
                for (int k = 0; k < n; ++k) {
                    const float *ak = coef + ((size_t)k * C + c) * HW + row, *Ik = I + k * HW + row;
                    for (int i = 0; i < W; ++i) v[i] = v[i] + ak[i] * Ik[i];
                }
                if (y == 0)
                    memcpy(t, v, sizeof(float) * W);
                else
                    for (int i = 0; i < W; ++i) t[i] += v[i];
            }
            pool_columns(t, W, s, rows, out + (size_t)c * h * w + (size_t)ly * w);
        }
}

void torchgi_mix_half(const float *coarse, const float *wgt, const float *f0, const float *f1, const float *f2,
                      const float *f3, int n, int Q, int h, int w, int h4, int w4, float *out, int nt, void *scratch,
                      long long stride) {
    const float *fs[4] = {f0, f1, f2, f3};
    OVER_BANDS(h, mix_half_rows(coarse, wgt, fs, n, Q, h, w, h4, w4, out, scr, y0, y1));
}

void torchgi_model_residual(float *model, const float *y0p, const float *y1p, const float *y2p, const float *y3p,
                            int n, const float *wgt, const float *x, int C, int H, int W, float *res, float *low, int nt,
                            void *scratch, long long stride) {
    const float *ys[4] = {y0p, y1p, y2p, y3p};
    OVER_BANDS((H + 1) / 2, model_residual_rows(model, ys, n, wgt, x, C, H, W, res, low, scr, y0, y1));
}

void torchgi_fine_band(const float *model, const float *res, const float *low, const float *coarse, const float *gain,
                       int C, int H, int W, float *out, int nt, void *scratch, long long stride) {
    /* (not `band`: OVER_BANDS's loop variable) */
    OVER_BANDS(H, fine_band_rows(model, res, low, coarse, gain, C, H, W, out, scr, y0, y1));
}

void torchgi_block_mean(const float *x, int P, int H, int W, int s, float *out, int nt, void *scratch, long long stride) {
    OVER_BANDS((H + s - 1) / s, block_mean_rows(x, P, H, W, s, out, (float *)scr, y0, y1));
}

void torchgi_applied_means(const float *coef, const float *I, int n, int C, int H, int W, int s, float *out, int nt,
                           void *scratch, long long stride) {
    OVER_BANDS((H + s - 1) / s, applied_means_rows(coef, I, n, C, H, W, s, out, (float *)scr, y0, y1));
}
