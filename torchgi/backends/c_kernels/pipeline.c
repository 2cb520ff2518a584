/* The Denoiser's guided pipeline (backends.base.RestoreOp, GuideStatsOp, EdgeShareOp):
 * guide statistics, the light-source mask, demodulation, firefly clamp, remodulation.
 * Compiled as part of native.c (one translation unit: see there). */
#include "common.h"

/* ------------------------------------------------------------------------------------------
 * The Denoiser's pipeline around the guided filter (torchgi.denoise, torch_code.restore), fused into
 * a few walks over the image: guide statistics, the light-source mask, the demodulated light with
 * its capped peak, the firefly clamp (with the s x s means of the clamped light and of the guide
 * at half resolution), and the remodulation inside the filter's last pass. Row bands as
 * everywhere; per-band partial results (sums, counts) go to the first doubles of each band's
 * scratch block and are added up by the caller, float scratch rows follow them. `hit` is NULL
 * (surfaces: the pixels of non-zero albedo) or a bool plane (torch's bytes, non-zero: a surface).
 * The guide is read from its source planes (guide_t: normal, depth) with its scale and offset, so
 * it is never written at full resolution.
 */
INLINE int is_finite(float v) { return v - v == 0.0f; }

/* Sum of a[0 .. W) in double, in 16 float lanes (a vector, so that it does not wait on one add). */
static double row_sum(const float *a, int W) {
    vf acc = {0};
    int x = 0;
    for (; x + VL <= W; x += VL) acc += vload(a + x);
    double s = 0;
    for (int l = 0; l < VL; ++l) s += acc[l];
    for (; x < W; ++x) s += a[x];
    return s;
}

/* Count of non-finite values of a[0 .. W). */
static int row_bad(const float *a, int W) {
    int bad = 0;
    for (int x = 0; x < W; ++x) bad += !is_finite(a[x]);
    return bad;
}

/* min and max of a[0 .. W) into *lo, *hi (kept if smaller / larger). */
static void row_range(const float *a, int W, float *lo, float *hi) {
    vf l = vsplat(*lo), h = vsplat(*hi);
    int x = 0;
    for (; x + VL <= W; x += VL) {
        const vf v = vload(a + x);
        l = vselect(v < l, v, l);
        h = vselect(v > h, v, h);
    }
    float lm = *lo, hm = *hi;
    for (int q = 0; q < VL; ++q) lm = l[q] < lm ? l[q] : lm, hm = h[q] > hm ? h[q] : hm;
    for (; x < W; ++x) lm = a[x] < lm ? a[x] : lm, hm = a[x] > hm ? a[x] : hm;
    *lo = lm, *hi = hm;
}

/* part: min (4), max (4) of the normal's three channels and depth, the largest depth on hit
 * pixels (every pixel when hit is NULL; -inf: none), the non-finite values of normal and of
 * depth, the sums of the four channels: 15 doubles. */
static void guide_stats_rows(const float *normal, const float *depth, const uint8_t *hit, int H, int W, double *part,
                             int y0, int y1) {
    const size_t HW = (size_t)H * W;
    const int C = depth ? 4 : 3;
    float lo[4] = {INFINITY, INFINITY, INFINITY, INFINITY}, hi[4] = {-INFINITY, -INFINITY, -INFINITY, -INFINITY};
    float dmax = -INFINITY, dlo = INFINITY;
    double bad_n = 0, bad_d = 0, sum[4] = {0, 0, 0, 0};
    for (int y = y0; y < y1; ++y) {
        const size_t row = (size_t)y * W;
        for (int c = 0; c < C; ++c) {
            const float *a = (c < 3 ? normal + c * HW : depth) + row;
            row_range(a, W, &lo[c], &hi[c]);
            sum[c] += row_sum(a, W);
            if (c < 3) bad_n += row_bad(a, W); else bad_d += row_bad(a, W);
        }
        if (depth && hit) {
            float m = -INFINITY;
            for (int x = 0; x < W; ++x) m = hit[row + x] && depth[row + x] > m ? depth[row + x] : m;
            dmax = m > dmax ? m : dmax;
        }
    }
    if (depth && !hit) row_range(&hi[3], 1, &dlo, &dmax);
    for (int c = 0; c < 4; ++c) part[c] = lo[c], part[4 + c] = hi[c];
    part[8] = dmax, part[9] = bad_n, part[10] = bad_d;
    for (int c = 0; c < 4; ++c) part[11 + c] = sum[c];
}

/* part: the edges (horizontal neighbours on even rows differing by more than `edge` in the
 * guide) of rows [y0, y1): 1 double; d2: W floats of scratch. */
static void guide_edges_rows(const guide_t *g, int W, float edge, double *part, float *d2, int y0, int y1) {
    double count = 0;
    for (int y = y0 + (y0 & 1); y < y1; y += 2) {
        int c2 = 0;
        const size_t row = (size_t)y * W;
        memset(d2, 0, sizeof(float) * W);
        for (int k = 0; k < g->n; ++k) {
            const float *a = g->src[k] + row, sc = g->scale[k];
            for (int x = 0; x + 1 < W; ++x) {
                const float d = (a[x + 1] - a[x]) * sc;
                d2[x] += d * d;
            }
        }
        for (int x = 0; x + 1 < W; ++x) c2 += d2[x] > edge * edge;
        count += c2;
    }
    part[0] = count;
}

/* Adds the sums over s columns of a (W values) to l (ceil(W / s) values). */
static void pool_row(const float *a, int W, int s, float *l) {
    const int w = W / s;
    if (s == 2)
        for (int lx = 0; lx < w; ++lx) l[lx] += a[2 * lx] + a[2 * lx + 1];
    else
        for (int lx = 0; lx < w; ++lx)
            for (int j = 0; j < s; ++j) l[lx] += a[lx * s + j];
    for (int x = w * s; x < W; ++x) l[w] += a[x];
}

/* Divides the pooled sums of low row ly (rows [ya, yb) of the image) by their block sizes. */
static void pool_finish(float *l, int W, int s, int rows) {
    const int w = (W + s - 1) / s, full = W / s;
    const float inv = 1.0f / (float)(s * rows);
    for (int lx = 0; lx < full; ++lx) l[lx] *= inv;
    if (full < w) l[full] /= (float)((W - full * s) * rows);
}

/* For low rows [ly0, ly1) of s x s blocks: part = the sums of the guide's n channels over the
 * image rows they cover (n doubles); with low (s > 1), the channels' block means (h x w planes). */
static void guide_pool_rows(const guide_t *g, int H, int W, int s, float *low, double *part, int ly0, int ly1) {
    const int w = (W + s - 1) / s, h = (H + s - 1) / s;
    const size_t hw = (size_t)h * w;
    for (int k = 0; k < g->n; ++k) {
        double sum = 0;
        for (int ly = ly0; ly < ly1; ++ly) {
            const int ya = ly * s, yb = ya + s < H ? ya + s : H;
            float *l = low ? low + k * hw + (size_t)ly * w : NULL;
            if (l) memset(l, 0, sizeof(float) * w);
            for (int y = ya; y < yb; ++y) {
                const float *a = g->src[k] + (size_t)y * W;
                sum += row_sum(a, W);
                if (l) pool_row(a, W, s, l);
            }
            if (l) {
                pool_finish(l, W, s, yb - ya);
                for (int lx = 0; lx < w; ++lx) l[lx] = l[lx] * g->scale[k] + g->offset[k];
            }
        }
        part[k] = sum * g->scale[k] + (double)g->offset[k] * ((double)((ly1 * s < H ? ly1 * s : H) - ly0 * s) * W);
    }
}

/* Inputs of the light pipeline of one image; emission, kept, hit NULL when absent. */
struct light_s {
    const float *color, *emission, *kept, *albedo;
    const uint8_t *hit;
    float floor, ceil;
    size_t HW;
    int W;
};

/* The demodulator of row y (3 x W floats): the albedo (in [floor, ceil]) on surfaces, 1 elsewhere. */
static void demod_row(const light_t *L, int y, float *ad) {
    const size_t HW = L->HW, row = (size_t)y * L->W;
    const float *a0 = L->albedo + row, *a1 = a0 + HW, *a2 = a1 + HW, f = L->floor, c_ = L->ceil;
    const int W = L->W;
    for (int c = 0; c < 3; ++c) {
        const float *a = L->albedo + c * HW + row;
        float *d = ad + (size_t)c * W;
        if (L->hit) {
            const uint8_t *h = L->hit + row;
            for (int x = 0; x < W; ++x) d[x] = h[x] ? MINF(MAXF(a[x], f), c_) : 1.0f;
        } else {
            for (int x = 0; x < W; ++x) d[x] = (a0[x] > 0.0f) | (a1[x] > 0.0f) | (a2[x] > 0.0f) ? MINF(MAXF(a[x], f), c_) : 1.0f;
        }
    }
}

/* Bright pixels of row y (bytes): the emission's channel maximum above thr, or without an emission
 * input the demodulated light's (ad: 3 x W scratch floats). */
static void bright_row(const light_t *L, int y, float thr, uint8_t *out, float *ad) {
    const size_t HW = L->HW, row = (size_t)y * L->W;
    const int W = L->W;
    if (L->emission) {
        const float *e0 = L->emission + row, *e1 = e0 + HW, *e2 = e1 + HW;
        for (int x = 0; x < W; ++x) out[x] = MAXF(MAXF(e0[x], e1[x]), e2[x]) > thr;
        return;
    }
    demod_row(L, y, ad);
    for (int x = 0; x < W; ++x) out[x] = 0;
    for (int c = 0; c < 3; ++c) {
        const float *col = L->color + c * HW + row, *k = L->kept ? L->kept + c * HW + row : NULL;
        const float *d = ad + (size_t)c * W;
        if (k) for (int x = 0; x < W; ++x) out[x] |= (col[x] - k[x]) / d[x] > thr;
        else for (int x = 0; x < W; ++x) out[x] |= col[x] / d[x] > thr;
    }
}

/* out[x] = AND (erode) or OR of in[x - r .. x + r] clipped to the row. */
static void hwindow(const uint8_t *in, int W, int r, int erode, uint8_t *out) {
    memcpy(out, in, (size_t)W);
    for (int dx = -r; dx <= r; ++dx) {
        if (!dx) continue;
        const int x0 = dx < 0 ? -dx : 0, x1 = dx > 0 ? W - dx : W;
        if (erode) for (int x = x0; x < x1; ++x) out[x] &= in[x + dx];
        else for (int x = x0; x < x1; ++x) out[x] |= in[x + dx];
    }
}

/* The light-source mask of rows [y0, y1): pixels brighter than thr inside a (2r+1)² square of
 * such pixels (an opening: erosion, then dilation, windows clipped at the image borders as the
 * count-normalised box of the torch code does). part: 1 double, the bright pixels of the band;
 * then scratch bytes: 3 (y1 - y0 + 4r) W + W, and 3 W floats. */
static void lights_rows(const light_t *L, int H, float thr, int r, uint8_t *mask, void *scratch, double *part, int y0,
                        int y1) {
    const int W = L->W;
    const int b0 = y0 - 2 * r > 0 ? y0 - 2 * r : 0, b1 = y1 + 2 * r < H ? y1 + 2 * r : H;
    const int e0 = y0 - r > 0 ? y0 - r : 0, e1 = y1 + r < H ? y1 + r : H;
    float *ad = (float *)scratch;
    uint8_t *bright = (uint8_t *)(ad + 3 * (size_t)W), *hb = bright + (size_t)(b1 - b0) * W;
    uint8_t *hc = hb + (size_t)(b1 - b0) * W, *v = hc + (size_t)(e1 - e0) * W;
    double seen = 0;
    for (int y = b0; y < b1; ++y) {
        uint8_t *b = bright + (size_t)(y - b0) * W;
        bright_row(L, y, thr, b, ad);
        if (y >= y0 && y < y1) {
            int n = 0;
            for (int x = 0; x < W; ++x) n += b[x];
            seen += n;
        }
        hwindow(b, W, r, 1, hb + (size_t)(y - b0) * W);
    }
    for (int y = e0; y < e1; ++y) { /* erosion: every in-image row of the window, then OR along the row */
        memset(v, 1, (size_t)W);
        for (int yy = y - r; yy <= y + r; ++yy)
            if (yy >= 0 && yy < H)
                for (int x = 0; x < W; ++x) v[x] &= hb[(size_t)(yy - b0) * W + x];
        hwindow(v, W, r, 0, hc + (size_t)(y - e0) * W);
    }
    for (int y = y0; y < y1; ++y) { /* dilation: OR over the window's rows, on bright pixels */
        uint8_t *m = mask + (size_t)y * W;
        const uint8_t *b = bright + (size_t)(y - b0) * W;
        memset(m, 0, (size_t)W);
        for (int yy = y - r; yy <= y + r; ++yy)
            if (yy >= 0 && yy < H)
                for (int x = 0; x < W; ++x) m[x] |= hc[(size_t)(yy - e0) * W + x];
        for (int x = 0; x < W; ++x) m[x] &= b[x];
    }
    part[0] = seen;
}

/* Demodulated light x (3 planes) and its channel maximum capped at cap (1 plane) of rows [y0,
 * y1): light sources (mask, NULL: none) keep their emission out of x, or without an emission
 * input enter it at `level`. part: the non-finite values of colour, emission, albedo, kept (4
 * doubles); then 5 W floats of scratch. */
static void prepare_rows(const light_t *L, const uint8_t *mask, float level, float cap, float *xo, float *peak,
                         double *part, float *scratch, int y0, int y1) {
    const size_t HW = L->HW;
    const int W = L->W;
    float *ad = scratch, *zero = scratch + 3 * (size_t)W;
    uint8_t *none = (uint8_t *)(zero + W);
    memset(zero, 0, sizeof(float) * W);
    memset(none, 0, (size_t)W);
    double bad[4] = {0, 0, 0, 0};
    for (int y = y0; y < y1; ++y) {
        const size_t row = (size_t)y * W;
        const uint8_t *m = mask ? mask + row : none;
        float *pk = peak + row;
        demod_row(L, y, ad);
        for (int c = 0; c < 3; ++c) {
            const float *col = L->color + c * HW + row, *a = L->albedo + c * HW + row;
            const float *k = L->kept ? L->kept + c * HW + row : zero, *e = L->emission ? L->emission + c * HW + row : zero;
            const float *d = ad + (size_t)c * W;
            float *o = xo + c * HW + row;
            bad[0] += row_bad(col, W), bad[2] += row_bad(a, W);
            if (L->emission) bad[1] += row_bad(e, W);
            if (L->kept) bad[3] += row_bad(k, W);
            if (L->emission)
                for (int x = 0; x < W; ++x) o[x] = (col[x] - k[x] - (m[x] ? e[x] : 0.0f)) / d[x];
            else
                for (int x = 0; x < W; ++x) o[x] = m[x] ? level : (col[x] - k[x]) / d[x];
        }
        const float *o0 = xo + row, *o1 = o0 + HW, *o2 = o1 + HW;
        for (int x = 0; x < W; ++x) {
            const float v = MAXF(MAXF(o0[x], o1[x]), o2[x]);
            pk[x] = v < cap ? v : cap;
        }
    }
    for (int c = 0; c < 4; ++c) part[c] = bad[c];
}

/* The firefly clamp of low rows [ly0, ly1) (s x s blocks): where x's channel maximum exceeds
 * bound = k max(mean, 0) (mean: the box mean of the capped peak) x is scaled down to it, in place
 * for s = 1, else its block means go to low (h x w planes); part: the channel sums of the clamped
 * x (3 doubles); then W floats of scratch. */
static void clamp_rows(float *x, const float *mean, float k, int H, int W, int s, float *low, double *part,
                       float *scratch, int ly0, int ly1) {
    const size_t HW = (size_t)H * W;
    const int w = (W + s - 1) / s, h = (H + s - 1) / s;
    const size_t hw = (size_t)h * w;
    float *f = scratch, *v = low ? scratch + W : NULL;
    double sum[3] = {0, 0, 0};
    for (int ly = ly0; ly < ly1; ++ly) {
        const int ya = ly * s, yb = ya + s < H ? ya + s : H;
        if (low)
            for (int c = 0; c < 3; ++c) memset(low + c * hw + (size_t)ly * w, 0, sizeof(float) * w);
        for (int y = ya; y < yb; ++y) {
            const size_t row = (size_t)y * W;
            const float *x0 = x + row, *x1 = x0 + HW, *x2 = x1 + HW, *mn = mean + row;
            for (int i = 0; i < W; ++i) {
                const float m = MAXF(MAXF(x0[i], x1[i]), x2[i]), bound = k * MAXF(mn[i], 0.0f);
                f[i] = m > bound ? bound / m : 1.0f;
            }
            for (int c = 0; c < 3; ++c) {
                float *a = x + c * HW + row, *o = low ? v : a;
                for (int i = 0; i < W; ++i) o[i] = f[i] < 1.0f ? a[i] * f[i] : a[i];
                sum[c] += row_sum(o, W);
                if (low) pool_row(o, W, s, low + c * hw + (size_t)ly * w);
            }
        }
        if (low)
            for (int c = 0; c < 3; ++c) pool_finish(low + c * hw + (size_t)ly * w, W, s, yb - ya);
    }
    for (int c = 0; c < 3; ++c) part[c] = sum[c];
}

/* The remodulation of the filtered light of row y, channel c (o: W values, in place):
 * max(o, 0) times the demodulator (ad, this row's, from demod_row), plus the light sources'
 * emission and kept light; without an emission input a light source's pixels are its colour. */
static void finish_row(const light_t *L, const uint8_t *mask, int c, int y, const float *ad, float *o) {
    const size_t row = (size_t)y * L->W, j = c * L->HW + row;
    const float *d = ad + (size_t)c * L->W, *e = L->emission ? L->emission + j : NULL;
    const float *k = L->kept ? L->kept + j : NULL, *col = L->color + j;
    const uint8_t *m = mask ? mask + row : NULL;
    const int W = L->W;
    for (int x = 0; x < W; ++x) o[x] = MAXF(o[x], 0.0f) * d[x];
    if (k) for (int x = 0; x < W; ++x) o[x] += k[x];
    if (m && e) for (int x = 0; x < W; ++x) o[x] += m[x] ? e[x] : 0.0f;
    if (m && !e) for (int x = 0; x < W; ++x) o[x] = m[x] ? col[x] : o[x];
}

/* The pipeline's entry points (see the section above). */
static light_t make_light(const float *color, const float *emission, const float *kept, const float *albedo,
                          const uint8_t *hit, float floor, float ceil, int H, int W) {
    const light_t L = {color, emission, kept, albedo, hit, floor, ceil, (size_t)H * W, W};
    return L;
}

static guide_t make_guide(int n, const float *g0, const float *g1, const float *g2, const float *g3,
                          const float *scale, const float *offset) {
    guide_t g = {n, {g0, g1, g2, g3}, {1, 1, 1, 1}, {0, 0, 0, 0}};
    for (int k = 0; k < n; ++k) g.scale[k] = scale[k], g.offset[k] = offset ? offset[k] : 0.0f;
    return g;
}

#define PART_BYTES 64 /* the partial results at the start of each band's scratch block */
void torchgi_guide_stats(const float *normal, const float *depth, const uint8_t *hit, int H, int W, int nt,
                         void *scratch, long long stride) {
    OVER_BANDS(H, guide_stats_rows(normal, depth, hit, H, W, (double *)scr, y0, y1));
}

void torchgi_guide_edges(int n, const float *g0, const float *g1, const float *g2, const float *g3,
                         const float *scale, int H, int W, float edge, int nt, void *scratch, long long stride) {
    const guide_t g = make_guide(n, g0, g1, g2, g3, scale, NULL);
    OVER_BANDS(H, guide_edges_rows(&g, W, edge, (double *)scr, (float *)((char *)scr + PART_BYTES), y0, y1));
}

void torchgi_guide_pool(int n, const float *g0, const float *g1, const float *g2, const float *g3,
                        const float *scale, const float *offset, int H, int W, int s, float *low, int nt,
                        void *scratch, long long stride) {
    const guide_t g = make_guide(n, g0, g1, g2, g3, scale, offset);
    OVER_BANDS((H + s - 1) / s, guide_pool_rows(&g, H, W, s, low, (double *)scr, y0, y1));
}

void torchgi_lights(const float *color, const float *emission, const float *kept, const float *albedo,
                    const uint8_t *hit, float floor, float ceil, int H, int W, float thr, int r, uint8_t *mask, int nt,
                    void *scratch, long long stride) {
    const light_t L = make_light(color, emission, kept, albedo, hit, floor, ceil, H, W);
    OVER_BANDS(H, lights_rows(&L, H, thr, r, mask, (char *)scr + PART_BYTES, (double *)scr, y0, y1));
}

void torchgi_prepare(const float *color, const float *emission, const float *kept, const float *albedo,
                     const uint8_t *hit, float floor, float ceil, int H, int W, const uint8_t *mask, float level, float cap,
                     float *x, float *peak, int nt, void *scratch, long long stride) {
    const light_t L = make_light(color, emission, kept, albedo, hit, floor, ceil, H, W);
    OVER_BANDS(H, prepare_rows(&L, mask, level, cap, x, peak, (double *)scr, (float *)((char *)scr + PART_BYTES), y0,
                               y1));
}

void torchgi_clamp(float *x, const float *mean, float k, int H, int W, int s, float *low, int nt, void *scratch,
                   long long stride) {
    OVER_BANDS((H + s - 1) / s, clamp_rows(x, mean, k, H, W, s, low, (double *)scr,
                                           (float *)((char *)scr + PART_BYTES), y0, y1));
}

void torchgi_restore_coefficients(int n, const float *g0, const float *g1, const float *g2, const float *g3,
                                  const float *scale, const float *offset, const float *meanI, const float *p,
                                  const float *meanp, int Cs, int H, int W, int r, const float *eps, float unit,
                                  float *coef, int nt, void *scratch, long long stride) {
    const guide_t G = make_guide(n, g0, g1, g2, g3, scale, offset);
    OVER_BANDS(H, coefficients_rows(&G, meanI, n, p, meanp, Cs, H, W, r, eps, unit, coef, y0, y1, scr));
}

void torchgi_guided_finish(const float *coef, int n, int Cs, const float *g0, const float *g1, const float *g2,
                           const float *g3, const float *scale, const float *goffset, const float *meanI,
                           const float *offset, int H, int W, int r, int s, float *out, const float *color,
                           const float *emission, const float *kept, const float *albedo, const uint8_t *hit,
                           float floor, float ceil, const uint8_t *mask, int nt, void *scratch, long long stride) {
    const light_t L = make_light(color, emission, kept, albedo, hit, floor, ceil, H, W);
    const guide_t G = make_guide(n, g0, g1, g2, g3, scale, goffset);
    if (s == 1) {
        OVER_BANDS(H, apply_rows(coef, n, Cs, &G, meanI, offset, H, W, r, out, &L, mask, y0, y1, scr));
    } else {
        const int h = (H + s - 1) / s, w = (W + s - 1) / s;
        OVER_BANDS(H, upsample_apply_rows(coef, n, Cs, s, h, w, &G, meanI, offset, H, W, out, &L, mask, scr, y0, y1));
    }
}

/* backends.base.LightOutOp: another filter's output o (3 planes) remodulated in place; 3 W floats of scratch. */
void torchgi_finish(float *o, const float *color, const float *emission, const float *kept, const float *albedo,
                    const uint8_t *hit, float floor, float ceil, int H, int W, const uint8_t *mask, int nt,
                    void *scratch, long long stride) {
    const light_t L = make_light(color, emission, kept, albedo, hit, floor, ceil, H, W);
    OVER_BANDS(H, for (int y = y0; y < y1; ++y) { demod_row(&L, y, (float *)scr);
        for (int c = 0; c < 3; ++c) finish_row(&L, mask, c, y, (const float *)scr, o + c * L.HW + (size_t)y * W); });
}

/* backends.base.UpsampleApplyOp: coefficient planes at half resolution upsampled x2 and applied
 * to n <= 4 centred guide planes, no remodulation. */
void torchgi_upsample_apply(const float *coef, int n, int Cs, const float *g0, const float *g1, const float *g2,
                            const float *g3, int H, int W, float *out, int nt, void *scratch, long long stride) {
    static const float ones[4] = {1, 1, 1, 1}, zeros[4] = {0, 0, 0, 0}, offset[64] = {0}; /* Cs <= 64: the caller */
    const guide_t G = make_guide(n, g0, g1, g2, g3, ones, zeros);
    const int h = (H + 1) / 2, w = (W + 1) / 2;
    OVER_BANDS(H, upsample_apply_rows(coef, n, Cs, 2, h, w, &G, zeros, offset, H, W, out, NULL, NULL, scr, y0, y1));
}

/* ---------------------------------------------------------------- back-off (backends.base.BackOffOp)
 * torchgi.light.back_off in two walks around the box pass: planes = (|color - out|², the summed
 * noise variance), 0 on emitting pixels; then, from their box means (sums), each pixel's weight
 * w = clamp(1 - k v / e) (an emitting pixel: 1 - k (noise / |res|² + inv_n)), 0 where the
 * denominator is at most `floor`; dst = out + w (color - out). var_c: 1 or 3 variance planes. */
static inline void backoff_pixel(const float *color, const float *out, const float *var, int var_c, size_t i,
                                 size_t HW, float res[3], float *r2, float *noise) {
    *r2 = 0.0f;
    for (int c = 0; c < 3; ++c) {
        res[c] = color[c * HW + i] - out[c * HW + i];
        *r2 += res[c] * res[c];
    }
    *noise = var_c == 3 ? var[i] + var[HW + i] + var[2 * HW + i] : 3.0f * var[i];
}

static void backoff_planes_rows(const float *color, const float *out, const float *var, int var_c,
                                const uint8_t *emit, int W, size_t HW, float *planes, int y0, int y1) {
    for (size_t i = (size_t)y0 * W; i < (size_t)y1 * W; ++i) {
        float res[3], r2, noise;
        backoff_pixel(color, out, var, var_c, i, HW, res, &r2, &noise);
        planes[i] = emit[i] ? 0.0f : r2;
        planes[HW + i] = emit[i] ? 0.0f : noise;
    }
}

static void backoff_apply_rows(const float *color, const float *out, const float *var, int var_c,
                               const uint8_t *emit, const float *sums, int W, size_t HW, float k, float inv_n,
                               float floor, float *dst, int y0, int y1) {
    for (size_t i = (size_t)y0 * W; i < (size_t)y1 * W; ++i) {
        float res[3], r2, noise, w;
        backoff_pixel(color, out, var, var_c, i, HW, res, &r2, &noise);
        if (emit[i]) {
            w = r2 > floor ? 1.0f - k * (noise / r2 + inv_n) : 0.0f;
        } else {
            const float e = sums[i], v = sums[HW + i];
            w = e > floor ? 1.0f - k * v / e : 0.0f;
        }
        w = fminf(fmaxf(w, 0.0f), 1.0f);
        for (int c = 0; c < 3; ++c) dst[c * HW + i] = out[c * HW + i] + w * res[c];
    }
}

void torchgi_backoff_planes(const float *color, const float *out, const float *var, int var_c, const uint8_t *emit,
                            int H, int W, float *planes, int nt, void *scratch, long long stride) {
    const size_t HW = (size_t)H * W;
    OVER_BANDS(H, backoff_planes_rows(color, out, var, var_c, emit, W, HW, planes, y0, y1));
}

void torchgi_backoff_apply(const float *color, const float *out, const float *var, int var_c, const uint8_t *emit,
                           const float *sums, int H, int W, float k, float inv_n, float floor, float *dst, int nt,
                           void *scratch, long long stride) {
    const size_t HW = (size_t)H * W;
    OVER_BANDS(H, backoff_apply_rows(color, out, var, var_c, emit, sums, W, HW, k, inv_n, floor, dst, y0, y1));
}

/* ---------------------------------------------------------------- choice among radii (backends.base.ChooseOp)
 * torchgi.light.choose in two walks around the box pass: planes = (the summed noise variance,
 * |o_k - o_0|² for k = 1..n-1), each times the relMSE weight 1 / (mean_c o_mid² + 0.01) of
 * o_mid = o[n / 2], 0 on emitting pixels; then, from their box means (sums), each output's error
 * e_0 = σ share_0, e_k = max(sums_k - σ (share_0 - share_k), 0) + σ share_k (σ = sums_0) and the
 * softmax weights of -e / max(T share_0 σ, floor), one-hot on the sharpest where σ <= floor;
 * dst = Σ w_k o_k. o: n (2..4) outputs, the unused pointers NULL. */
static void choose_planes_rows(const float *const o[4], int n, const float *var, int var_c, const uint8_t *emit,
                               int W, size_t HW, float *planes, int y0, int y1) {
    const float *mid = o[n / 2];
    for (size_t i = (size_t)y0 * W; i < (size_t)y1 * W; ++i) {
        const float m = (mid[i] * mid[i] + mid[HW + i] * mid[HW + i] + mid[2 * HW + i] * mid[2 * HW + i]) / 3.0f;
        const float w = emit[i] ? 0.0f : 1.0f / (m + 0.01f);
        const float noise = var_c == 3 ? var[i] + var[HW + i] + var[2 * HW + i] : 3.0f * var[i];
        planes[i] = noise * w;
        for (int k = 1; k < n; ++k) {
            float d2 = 0.0f;
            for (int c = 0; c < 3; ++c) {
                const float d = o[k][c * HW + i] - o[0][c * HW + i];
                d2 += d * d;
            }
            planes[k * HW + i] = d2 * w;
        }
    }
}

static void choose_apply_rows(const float *const o[4], int n, const float *sums, const float *share, float T,
                              float floor, int W, size_t HW, float *dst, int y0, int y1) {
    for (size_t i = (size_t)y0 * W; i < (size_t)y1 * W; ++i) {
        const float sigma = sums[i];
        float wk[4] = {1.0f, 0.0f, 0.0f, 0.0f};
        if (sigma > floor) {
            float e[4], lo;
            e[0] = lo = sigma * share[0];
            for (int k = 1; k < n; ++k) {
                e[k] = fmaxf(sums[k * HW + i] - sigma * (share[0] - share[k]), 0.0f) + sigma * share[k];
                lo = fminf(lo, e[k]);
            }
            const float scale = fmaxf(T * share[0] * sigma, floor);
            float total = 0.0f;
            for (int k = 0; k < n; ++k) total += wk[k] = expf(-(e[k] - lo) / scale);
            for (int k = 0; k < n; ++k) wk[k] /= total;
        }
        for (int c = 0; c < 3; ++c) {
            float acc = 0.0f;
            for (int k = 0; k < n; ++k) acc += wk[k] * o[k][c * HW + i];
            dst[c * HW + i] = acc;
        }
    }
}

void torchgi_choose_planes(const float *o0, const float *o1, const float *o2, const float *o3, int n, const float *var,
                           int var_c, const uint8_t *emit, int H, int W, float *planes, int nt, void *scratch,
                           long long stride) {
    const size_t HW = (size_t)H * W;
    const float *const o[4] = {o0, o1, o2, o3};
    OVER_BANDS(H, choose_planes_rows(o, n, var, var_c, emit, W, HW, planes, y0, y1));
}

void torchgi_choose_apply(const float *o0, const float *o1, const float *o2, const float *o3, int n, const float *sums,
                          const float *share, float T, float floor, int H, int W, float *dst, int nt, void *scratch,
                          long long stride) {
    const size_t HW = (size_t)H * W;
    const float *const o[4] = {o0, o1, o2, o3};
    OVER_BANDS(H, choose_apply_rows(o, n, sums, share, T, floor, W, HW, dst, y0, y1));
}
