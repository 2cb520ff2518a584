/* Per-pixel kernels applied to an image and their gradients (backends.kernel_ops.ApplyKernelsOp,
 * ApplyKernelsGradOp; torchgi.filters.apply_kernels). Compiled as part of native.c.
 *
 * Tap t = i k + j of a k x k kernel reads x at (y + (i - k/2) d, x + (j - k/2) d); taps outside
 * the image are left out (of the sum and, normalised, of the weight sum). Every loop runs along a
 * row over the x range where the tap is inside, so the inner loops have no branches. */
#include "common.h"

/* [lo, hi): the x where x + off lies in [0, W) */
INLINE void tap_span(int W, int off, int *lo, int *hi) {
    *lo = off < 0 ? -off : 0;
    *hi = off > 0 ? W - off : W;
    if (*hi < *lo) *hi = *lo;
}

/* Rows [y0, y1) of out = Σ_t w_t x(· + o_t) (C planes), and with den != NULL den = Σ_t w_t over
 * the taps inside and out divided by it. */
static void apply_kernels_rows(const float *x, const float *w, int C, int H, int W, int k, int d, float *out,
                               float *den, int y0, int y1) {
    const size_t HW = (size_t)H * W;
    const int h = k / 2;
    for (int y = y0; y < y1; ++y) {
        const size_t row = (size_t)y * W;
        for (int c = 0; c < C; ++c) memset(out + c * HW + row, 0, sizeof(float) * W);
        if (den) memset(den + row, 0, sizeof(float) * W);
        for (int i = 0; i < k; ++i) {
            const int ys = y + (i - h) * d;
            if (ys < 0 || ys >= H) continue;
            for (int j = 0; j < k; ++j) {
                const int off = (j - h) * d;
                int lo, hi;
                tap_span(W, off, &lo, &hi);
                const float *wt = w + (size_t)(i * k + j) * HW + row;
                for (int c = 0; c < C; ++c) {
                    const float *xs = x + c * HW + (size_t)ys * W + off;
                    float *o = out + c * HW + row;
                    for (int q = lo; q < hi; ++q) o[q] += wt[q] * xs[q];
                }
                if (den)
                    for (int q = lo; q < hi; ++q) den[row + q] += wt[q];
            }
        }
        if (den)
            for (int c = 0; c < C; ++c) {
                float *o = out + c * HW + row;
                for (int q = 0; q < W; ++q) o[q] /= den[row + q];
            }
    }
}

/* Rows [y0, y1) of the gradients, given gp = g (or g / den, normalised) and out (read only when
 * normalised): dw_t = Σ_c gp_c (x_c(· + o_t) - out_c) over the taps inside (0 outside; without
 * normalising, out is not subtracted), dx_c = Σ_t (w_t gp_c)(· - o_t). Either may be NULL. */
static void apply_kernels_grad_rows(const float *x, const float *w, const float *out, const float *gp, int C, int H,
                                    int W, int k, int d, int normalize, float *dx, float *dw, int y0, int y1) {
    const size_t HW = (size_t)H * W;
    const int h = k / 2;
    for (int y = y0; y < y1; ++y) {
        const size_t row = (size_t)y * W;
        if (dw)
            for (int t = 0; t < k * k; ++t) memset(dw + (size_t)t * HW + row, 0, sizeof(float) * W);
        if (dx)
            for (int c = 0; c < C; ++c) memset(dx + c * HW + row, 0, sizeof(float) * W);
        for (int i = 0; i < k; ++i) {
            const int dy = (i - h) * d;
            for (int j = 0; j < k; ++j) {
                const int off = (j - h) * d;
                const size_t t = (size_t)(i * k + j) * HW;
                int lo, hi;
                if (dw && y + dy >= 0 && y + dy < H) {
                    tap_span(W, off, &lo, &hi);
                    float *dwt = dw + t + row;
                    for (int c = 0; c < C; ++c) {
                        const float *xs = x + c * HW + (size_t)(y + dy) * W + off, *g = gp + c * HW + row;
                        if (normalize) {
                            const float *o = out + c * HW + row;
                            for (int q = lo; q < hi; ++q) dwt[q] += g[q] * (xs[q] - o[q]);
                        } else {
                            for (int q = lo; q < hi; ++q) dwt[q] += g[q] * xs[q];
                        }
                    }
                }
                /* dx at (y, q) from the pixel p = (y - dy, q - off) whose tap t reads it */
                if (dx && y - dy >= 0 && y - dy < H) {
                    tap_span(W, -off, &lo, &hi);
                    const float *wt = w + t + (size_t)(y - dy) * W - off;
                    for (int c = 0; c < C; ++c) {
                        const float *g = gp + c * HW + (size_t)(y - dy) * W - off;
                        float *o = dx + c * HW + row;
                        for (int q = lo; q < hi; ++q) o[q] += wt[q] * g[q];
                    }
                }
            }
        }
    }
}

void torchgi_apply_kernels(const float *x, const float *w, int C, int H, int W, int k, int d, float *out, float *den,
                           int nt, void *scratch, long long stride) {
    OVER_BANDS(H, apply_kernels_rows(x, w, C, H, W, k, d, out, den, y0, y1));
}

void torchgi_apply_kernels_grad(const float *x, const float *w, const float *out, const float *gp, int C, int H, int W,
                                int k, int d, int normalize, float *dx, float *dw, int nt, void *scratch,
                                long long stride) {
    OVER_BANDS(H, apply_kernels_grad_rows(x, w, out, gp, C, H, W, k, d, normalize, dx, dw, y0, y1));
}
