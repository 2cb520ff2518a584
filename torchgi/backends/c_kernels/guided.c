/* The guided filter and its box sums (backends.base.GuidedOp, BoxOp).
 * Compiled as part of native.c (one translation unit: see there). */
#include "common.h"

/* ------------------------------------------------------------------------------------------
 * Guided filter (torch_code.filter_guided.solve / apply_coefficients) on centred planes, in two passes over bands of
 * rows: pass 1 box-means the products and solves for the coefficients of every pixel; pass 2
 * box-means the coefficients and applies them (or returns their box means). Box sums slide
 * down the rows (double accumulators, one row in and one out per output row) and are prefix-
 * summed along the row, so the cost does not depend on r; borders are count-normalised.
 */

/* Row strides of the column sums (doubles) and of the box means (floats): padded so that the
 * rows read side by side do not share cache sets. */
#define ACC_STRIDE(W) ((W) + 8)
#define MEAN_STRIDE(W) ((W) + 16)

/* The guide's channel k: plane `src[k]` times scale[k] plus offset[k]. */
typedef struct {
    int n;
    const float *src[4];
    float scale[4], offset[4];
} guide_t;

/* The guide's channel k at x of row `row`, centred: src * scale + (offset - mean) */
#define GUIDE(G, k, row, x, centre) ((G)->src[k][(row) + (x)] * (G)->scale[k] + (centre)[k])

/* n contiguous planes of H x W (scale 1, offset 0) as a guide */
static guide_t planes_guide(const float *I, int n, size_t HW) {
    guide_t g = {n, {NULL, NULL, NULL, NULL}, {1, 1, 1, 1}, {0, 0, 0, 0}};
    for (int k = 0; k < n; ++k) g.src[k] = I + k * HW;
    return g;
}

/* offset - mean of each guide channel (what GUIDE adds) */
static void guide_centres(const guide_t *g, const float *meanI, float *centre) {
    for (int k = 0; k < 4; ++k) centre[k] = k < g->n ? g->offset[k] - meanI[k] : 0.0f;
}

/* The column sums slide down one row: acc[k][x] += value_k(yin, x) - value_k(yout, x) for the K
 * planes the layout below describes, in one pass over acc; a row < 0 is left out. */
typedef struct {
    int n, Cs, K;
    const guide_t *G;     /* guide (n channels) */
    const float *p;       /* source (Cs planes) */
    float cI[4];          /* the guide's offset minus its per-image mean, added before any sum (design.md, Numerics) */
    const float *mp;      /* the source's per-image means, subtracted before any sum */
    size_t HW;
    int W;
} products_t;

/* s[x] += E(rin) - E(rout) over the row, or ± E of the one row given (E a macro of the row's
 * offset, reading x) */
#define SLIDE(s, W, rin, rout, E)                                                      \
    do {                                                                               \
        if ((rin) != (size_t)-1 && (rout) != (size_t)-1) {                             \
            for (int x = 0; x < (W); ++x) (s)[x] += (double)E(rin) - (double)E(rout);  \
        } else {                                                                       \
            const size_t r1_ = (rin) != (size_t)-1 ? (rin) : (rout);                   \
            const double sign_ = (rin) != (size_t)-1 ? 1.0 : -1.0;                     \
            for (int x = 0; x < (W); ++x) (s)[x] += sign_ * E(r1_);                    \
        }                                                                              \
    } while (0)

/* value k of a row, centred: I_i (k < n), p_c, I_i I_j (j <= i), I_i p_c */
static void add_products(const products_t *P, int yin, int yout, double *acc) {
    const int n = P->n, Cs = P->Cs, W = P->W;
    const size_t rin = yin >= 0 ? (size_t)yin * W : (size_t)-1, rout = yout >= 0 ? (size_t)yout * W : (size_t)-1;
    const guide_t *G = P->G;
    int k = 0;
    for (int i = 0; i < n; ++i, ++k) {
        double *s = acc + (size_t)k * ACC_STRIDE(W);
#define E_I(row) GUIDE(G, i, row, x, P->cI)
        SLIDE(s, W, rin, rout, E_I);
    }
    for (int c = 0; c < Cs; ++c, ++k) {
        const float *a = P->p + c * P->HW, ma = P->mp[c];
        double *s = acc + (size_t)k * ACC_STRIDE(W);
#define E_P(row) (a[(row) + x] - ma)
        SLIDE(s, W, rin, rout, E_P);
    }
    for (int i = 0; i < n; ++i)
        for (int j = 0; j <= i; ++j, ++k) {
            double *s = acc + (size_t)k * ACC_STRIDE(W);
#define E_II(row) ((double)GUIDE(G, i, row, x, P->cI) * GUIDE(G, j, row, x, P->cI))
            SLIDE(s, W, rin, rout, E_II);
        }
    for (int i = 0; i < n; ++i)
        for (int c = 0; c < Cs; ++c, ++k) {
            const float *b = P->p + c * P->HW, mb = P->mp[c];
            double *s = acc + (size_t)k * ACC_STRIDE(W);
#define E_IP(row) ((double)GUIDE(G, i, row, x, P->cI) * (b[(row) + x] - mb))
            SLIDE(s, W, rin, rout, E_IP);
        }
}

static void add_planes(const float *planes, int K, size_t HW, int W, int yin, int yout, double *acc) {
    const size_t rin = yin >= 0 ? (size_t)yin * W : (size_t)-1, rout = yout >= 0 ? (size_t)yout * W : (size_t)-1;
    for (int k = 0; k < K; ++k) {
        const float *a = planes + k * HW;
        double *s = acc + (size_t)k * ACC_STRIDE(W);
#define E_A(row) a[(row) + x]
        SLIDE(s, W, rin, rout, E_A);
    }
}
#undef E_I
#undef E_P
#undef E_II
#undef E_IP
#undef E_A

/* VD doubles, for the prefix sums along a row: one register's width (8 with AVX-512; 4 else,
 * where wider vectors' shuffles would be emulated lane by lane) */
#if defined(__AVX512F__)
#define VD 8
typedef double vd __attribute__((vector_size(64)));
typedef int64_t vl __attribute__((vector_size(64)));

/* Inclusive prefix sum within one vector (three shift-and-add steps). */
INLINE vd vd_scan(vd v) {
    const vd z = {0};
    v += __builtin_shuffle(z, v, (vl){0, 8, 9, 10, 11, 12, 13, 14});
    v += __builtin_shuffle(z, v, (vl){0, 1, 8, 9, 10, 11, 12, 13});
    v += __builtin_shuffle(z, v, (vl){0, 1, 2, 3, 8, 9, 10, 11});
    return v;
}
#define VD_LAST ((vl){7, 7, 7, 7, 7, 7, 7, 7})
#else
#define VD 4
typedef double vd __attribute__((vector_size(32)));
typedef int64_t vl __attribute__((vector_size(32)));

/* Inclusive prefix sum within one vector (two shift-and-add steps). */
INLINE vd vd_scan(vd v) {
    const vd z = {0};
    v += __builtin_shuffle(z, v, (vl){0, 4, 5, 6});
    v += __builtin_shuffle(z, v, (vl){0, 1, 4, 5});
    return v;
}
#define VD_LAST ((vl){3, 3, 3, 3})
#endif

/* Interior box means of a small constant radius R: m[x] = Σ_{|d| <= R} a[x + d] · inv for x in
 * [x0, x1), the window inside the row (a direct sum: fewer operations than the prefix sums for
 * the radii the pipelines use most, and each sum exact up to one rounding per term). */
INLINE void row_means_direct(const double *a, const int R, int x0, int x1, double inv, float *m) {
#pragma GCC ivdep
    for (int x = x0; x < x1; ++x) {
        double s = a[x - R];
        FOR8(d, 2 * R, s += a[x - R + 1 + d]);
        m[x] = (float)(s * inv);
    }
}

/* Box means at x in [x0, x1) of windows clipped to the row (the borders). */
static void row_means_clipped(const double *a, int W, int r, int x0, int x1, const double *inv_cx, double inv_cy,
                              float *m) {
    for (int x = x0; x < x1; ++x) {
        const int hi = x + r < W ? x + r : W - 1, lo = x - r > 0 ? x - r : 0;
        double s = 0.0;
        for (int q = lo; q <= hi; ++q) s += a[q];
        m[x] = (float)(s * (inv_cx[x] * inv_cy));
    }
}

/* Box means along the row of K rows of column sums (acc) that cover cy image rows: mean[k][x]
 * = (sum of acc[k] over the window at x) / (pixels in the window): direct sums for r <= 4, else
 * from prefix sums pre (W + 1 doubles) computed VD at a time. */
static void row_means(const double *acc, int K, int W, int r, int cy, const double *inv_cx, double *pre,
                      float *mean) {
    const double inv_cy = 1.0 / cy;
    /* x in [mid0, mid1) has the whole window inside the row: there hi = x + r + 1, lo = x - r */
    const int mid0 = r < W ? r : W, mid1 = W - r - 1 > mid0 ? W - r - 1 : mid0;
    for (int k = 0; k < K; ++k) {
        const double *a = acc + (size_t)k * ACC_STRIDE(W);
        float *m = mean + (size_t)k * MEAN_STRIDE(W);
        if (r <= 4) {
            const double inv = inv_cy / (2 * r + 1);
            row_means_clipped(a, W, r, 0, mid0, inv_cx, inv_cy, m);
            row_means_clipped(a, W, r, mid1, W, inv_cx, inv_cy, m);
            switch (r) { /* the interior */
                case 1: row_means_direct(a, 1, mid0, mid1, inv, m); break;
                case 2: row_means_direct(a, 2, mid0, mid1, inv, m); break;
                case 3: row_means_direct(a, 3, mid0, mid1, inv, m); break;
                case 4: row_means_direct(a, 4, mid0, mid1, inv, m); break;
                default: row_means_direct(a, 0, mid0, mid1, inv, m); break;
            }
            continue;
        }
        vd carry = {0};
        int x = 0;
        pre[0] = 0.0;
        for (; x + VD <= W; x += VD) {
            vd v;
            memcpy(&v, a + x, sizeof v);
            v = vd_scan(v) + carry;
            memcpy(pre + x + 1, &v, sizeof v);
            carry = __builtin_shuffle(v, VD_LAST);
        }
        for (; x < W; ++x) pre[x + 1] = pre[x] + a[x];
        for (x = 0; x < mid0; ++x) {
            const int hi = x + r + 1 < W ? x + r + 1 : W;
            m[x] = (float)((pre[hi] - pre[0]) * (inv_cx[x] * inv_cy));
        }
        for (x = mid0; x < mid1; ++x) m[x] = (float)((pre[x + r + 1] - pre[x - r]) * (inv_cx[x] * inv_cy));
        for (x = mid1; x < W; ++x) {
            const int lo = x - r > 0 ? x - r : 0;
            m[x] = (float)((pre[W] - pre[lo]) * (inv_cx[x] * inv_cy));
        }
    }
}

/* 1 / (columns inside the window) per x. */
static void column_counts(int W, int r, double *inv_cx) {
    for (int x = 0; x < W; ++x) {
        const int hi = x + r < W ? x + r : W - 1, lo = x - r > 0 ? x - r : 0;
        inv_cx[x] = 1.0 / (hi - lo + 1);
    }
}

#define TRI(i, j) ((i) * ((i) + 1) / 2 + (j))

/* The LDLᵀ of pixel x's Σ + diag(ε_eff) as in torch_code.filter_guided._factor, from the means
 * mI (n planes MW apart) and mII (j <= i, TRI order): L below the diagonal, the pivots D
 * (clamped at ε_eff) and ε_eff e (each ε_i raised to unit · E[I_i²]; variances clamped at 0). */
INLINE void ldl_factor(const int n, const float *mI, const float *mII, int MW, int x, const float *eps, float unit,
                       float L[4][4], float D[4], float e[4]) {
    float A[4][4], E[4][4];
    FOR8(i, n, FOR8(j, i + 1, {
        const float mij = mII[(size_t)TRI(i, j) * MW + x];
        float v = mij - mI[(size_t)i * MW + x] * mI[(size_t)j * MW + x];
        if (i == j) {
            e[i] = MAXF(mij * unit, eps[i]);
            v = MAXF(v, 0.0f) + e[i];
        }
        A[i][j] = v;
    }));
    FOR8(j, n, {
        float d = A[j][j];
        FOR8(q, j, d -= L[j][q] * E[j][q]);
        D[j] = MAXF(d, e[j]);
        FOR8(i, n, if (i > j) {
            float v = A[i][j];
            FOR8(q, j, v -= L[i][q] * E[j][q]);
            E[i][j] = v;
            L[i][j] = v / D[j];
        });
    });
}

/* The rows of the (2r+1)² window around row y, clipped to the image */
INLINE int window_rows(int y, int r, int H) { return (y + r < H ? y + r : H - 1) - (y - r > 0 ? y - r : 0) + 1; }

/* Solve one row for source channels [c0, c0 + G): means in m (K x W, the order of
 * add_products), write a_0..a_{n-1}, b (each Cs planes) into coef at row y. LDLᵀ as in
 * torch_code.filter_guided.solve: eps_i raised to unit · E[I_i²] per pixel, variances clamped at 0, pivots at eps. */
INLINE void solve_row(const int n, const int G, int c0, int Cs, const float *m, int W, const float *eps, float unit,
                      float *coef, size_t HW, int y) {
    const int MW = MEAN_STRIDE(W);
    const float *mI = m, *mp = m + (size_t)n * MW, *mII = m + (size_t)(n + Cs) * MW;
    const float *mIp = mII + (size_t)(n * (n + 1) / 2) * MW;
    float *row = coef + (size_t)y * W;
#pragma GCC ivdep
    for (int x = 0; x < W; ++x) {
        float L[4][4], D[4], e[4];
        ldl_factor(n, mI, mII, MW, x, eps, unit, L, D, e);
        FOR8(g, G, {
            const int c = c0 + g;
            const float mpc = mp[(size_t)c * MW + x];
            float yv[4], a[4];
            FOR8(i, n, {
                float v = mIp[((size_t)i * Cs + c) * MW + x] - mI[(size_t)i * MW + x] * mpc;
                FOR8(q, i, v -= L[i][q] * yv[q]);
                yv[i] = v;
            });
            FOR8(ri, n, {
                const int i = n - 1 - ri;
                float v = yv[i] / D[i];
                FOR8(q, n, if (q > i) v -= L[q][i] * a[q]);
                a[i] = v;
            });
            float b = mpc;
            FOR8(i, n, {
                b -= a[i] * mI[(size_t)i * MW + x];
                row[((size_t)i * Cs + c) * HW + x] = a[i];
            });
            row[((size_t)n * Cs + c) * HW + x] = b;
        });
    }
}

#define SOLVE_NG(N, G) \
    static void solve_##N##_##G(int c0, int Cs, const float *m, int W, const float *eps, float unit, float *coef, \
                                size_t HW, int y) { solve_row(N, G, c0, Cs, m, W, eps, unit, coef, HW, y); }
#define SOLVE_N(N) SOLVE_NG(N, 1) SOLVE_NG(N, 2) SOLVE_NG(N, 3)
SOLVE_N(1) SOLVE_N(2) SOLVE_N(3) SOLVE_N(4)
typedef void (*solve_fn)(int, int, const float *, int, const float *, float, float *, size_t, int);
static const solve_fn SOLVERS[4][3] = {{solve_1_1, solve_1_2, solve_1_3}, {solve_2_1, solve_2_2, solve_2_3},
                                        {solve_3_1, solve_3_2, solve_3_3}, {solve_4_1, solve_4_2, solve_4_3}};

/* scratch: doubles acc (K ACC_STRIDE(W)) + inv_cx (W) + pre (W + 8), then floats m (K MEAN_STRIDE(W)),
 * K = n + Cs + n (n + 1) / 2 + n Cs. */
static void coefficients_rows(const guide_t *G, const float *meanI, int n, const float *p, const float *meanp, int Cs,
                              int H, int W, int r, const float *eps, float unit, float *coef, int y0, int y1,
                              void *scratch) {
    const unsigned csr = ftz_begin();
    const int K = n + Cs + n * (n + 1) / 2 + n * Cs;
    const size_t HW = (size_t)H * W;
    double *acc = (double *)scratch, *inv_cx = acc + (size_t)K * ACC_STRIDE(W), *pre = inv_cx + W;
    float *m = (float *)(pre + W + 8);
    column_counts(W, r, inv_cx);
    products_t P = {n, Cs, K, G, p, {0, 0, 0, 0}, meanp, HW, W};
    guide_centres(G, meanI, P.cI);
    memset(acc, 0, sizeof(double) * (size_t)K * ACC_STRIDE(W));
    /* before row y the sums hold rows [y - 1 - r, y - 1 + r] of the image */
    for (int yy = y0 - r - 1 > 0 ? y0 - r - 1 : 0; yy <= y0 + r - 1 && yy < H; ++yy) add_products(&P, yy, -1, acc);
    for (int y = y0; y < y1; ++y) {
        /* the window's rows are [y - r, y + r] clipped to the image */
        if (y + r < H || y - r - 1 >= 0) add_products(&P, y + r < H ? y + r : -1, y - r - 1, acc);
        const int cy = window_rows(y, r, H);
        row_means(acc, K, W, r, cy, inv_cx, pre, m);
        for (int c0 = 0; c0 < Cs; c0 += 3) /* source channels three at a time */
            SOLVERS[n - 1][(Cs - c0 < 3 ? Cs - c0 : 3) - 1](c0, Cs, m, W, eps, unit, coef, HW, y);
    }
    ftz_end(csr);
}

/* Box means of the Q = (n + 1) Cs coefficient planes for rows [y0, y1): written to out (Q
 * planes) when I is NULL, else applied: out_c = mean(b_c) + Σ_i mean(a_ic) (I_i - meanI_i) +
 * offset_c (Cs planes), then remodulated by finish_row (below) when L is not NULL. scratch: doubles acc (Q ACC_STRIDE(W)) + inv_cx (W) + pre (W + 8), then floats m
 * (Q MEAN_STRIDE(W)). */
typedef struct light_s light_t;
static void finish_row(const light_t *L, const uint8_t *mask, int c, int y, const float *ad, float *o);
static void demod_row(const light_t *L, int y, float *ad);

static void apply_rows(const float *coef, int n, int Cs, const guide_t *G, const float *meanI, const float *offset,
                       int H, int W, int r, float *out, const light_t *L, const uint8_t *mask, int y0, int y1,
                       void *scratch) {
    const unsigned csr = ftz_begin();
    const int Q = (n + 1) * Cs;
    const size_t HW = (size_t)H * W;
    double *acc = (double *)scratch, *inv_cx = acc + (size_t)Q * ACC_STRIDE(W), *pre = inv_cx + W;
    float *m = (float *)(pre + W + 8);
    float cI[4], *ad = m + (size_t)Q * MEAN_STRIDE(W); /* 3 W floats past the means, when L */
    if (G) guide_centres(G, meanI, cI);
    column_counts(W, r, inv_cx);
    memset(acc, 0, sizeof(double) * (size_t)Q * ACC_STRIDE(W));
    for (int yy = y0 - r - 1 > 0 ? y0 - r - 1 : 0; yy <= y0 + r - 1 && yy < H; ++yy)
        add_planes(coef, Q, HW, W, yy, -1, acc);
    for (int y = y0; y < y1; ++y) {
        if (y + r < H || y - r - 1 >= 0) add_planes(coef, Q, HW, W, y + r < H ? y + r : -1, y - r - 1, acc);
        const int cy = window_rows(y, r, H);
        row_means(acc, Q, W, r, cy, inv_cx, pre, m);
        if (L) demod_row(L, y, ad);
        if (!G) {
            for (int q = 0; q < Q; ++q) memcpy(out + q * HW + (size_t)y * W, m + (size_t)q * MEAN_STRIDE(W), sizeof(float) * W);
            continue;
        }
        for (int c = 0; c < Cs; ++c) {
            float *o = out + c * HW + (size_t)y * W;
            const float *mb = m + ((size_t)n * Cs + c) * MEAN_STRIDE(W);
            const float off = offset[c];
            for (int x = 0; x < W; ++x) o[x] = mb[x] + off;
                        for (int i = 0; i < n; ++i) {
                const float *ma = m + ((size_t)i * Cs + c) * MEAN_STRIDE(W);
                const size_t row = (size_t)y * W;
                for (int x = 0; x < W; ++x) o[x] += ma[x] * GUIDE(G, i, row, x, cI);
            }
            if (L) finish_row(L, mask, c, y, ad, o);
        }
    }
    ftz_end(csr);
}

void torchgi_guided_coefficients(const float *I, const float *meanI, int n, const float *p, const float *meanp, int Cs,
                                 int H, int W, int r, const float *eps, float unit, float *coef, int nt, void *scratch,
                                 long long stride) {
    const guide_t G = planes_guide(I, n, (size_t)H * W);
    OVER_BANDS(H, coefficients_rows(&G, meanI, n, p, meanp, Cs, H, W, r, eps, unit, coef, y0, y1, scr));
}

void torchgi_guided_apply(const float *coef, int n, int Cs, const float *I, const float *meanI, const float *offset,
                          int H, int W, int r, float *out, int nt, void *scratch, long long stride) {
    const guide_t G = planes_guide(I, n, (size_t)H * W);
    OVER_BANDS(H, apply_rows(coef, n, Cs, I ? &G : NULL, meanI, offset, H, W, r, out, NULL, NULL, y0, y1, scr));
}

