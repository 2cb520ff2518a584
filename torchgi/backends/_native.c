/* CPU kernels of the two hot filters and of the sampling importance, float32, one image per call.
 *
 * Compiled at first use by torchgi/backends/c_kernels.py (gcc/cc, -O3 -march=native, -fopenmp where
 * the compiler has it) and called through ctypes, which releases the GIL; each entry point runs
 * its rows in bands, one per thread (OVER_BANDS, at the end). The maths
 * is exactly that of the torch code paths (torch_code._iteration, torch_code.solve); only the order
 * of the sums differs (box sums accumulate in double here, so they are more accurate).
 *
 * Planes are contiguous H x W float32; a multi-channel buffer is its planes back to back.
 */
#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#if defined(__SSE__)
#include <xmmintrin.h>
#endif
#if defined(_OPENMP)
#include <omp.h>
#endif

#define INLINE static inline __attribute__((always_inline))
#define MAXF(a, b) ((a) > (b) ? (a) : (b))


/* v = 0 .. N-1 for a compile-time N <= 8, written out so that the loops fold into straight code */
#define FOR8(v, N, ...) \
    do { if (0 < (N)) { const int v = 0; __VA_ARGS__; } if (1 < (N)) { const int v = 1; __VA_ARGS__; } \
         if (2 < (N)) { const int v = 2; __VA_ARGS__; } if (3 < (N)) { const int v = 3; __VA_ARGS__; } \
         if (4 < (N)) { const int v = 4; __VA_ARGS__; } if (5 < (N)) { const int v = 5; __VA_ARGS__; } \
         if (6 < (N)) { const int v = 6; __VA_ARGS__; } if (7 < (N)) { const int v = 7; __VA_ARGS__; } } while (0)


/* Flush denormals to zero for the duration of a call (weights far below 1e-38 would otherwise
 * take the slow microcode path); the caller's mode is restored on return. */
INLINE unsigned ftz_begin(void) {
#if defined(__SSE__)
    unsigned csr = _mm_getcsr();
    _mm_setcsr(csr | 0x8040);
    return csr;
#else
    return 0;
#endif
}

INLINE void ftz_end(unsigned csr) {
#if defined(__SSE__)
    _mm_setcsr(csr);
#else
    (void)csr;
#endif
}

/* exp(-d) for d >= 0 (Cephes expf: Cody-Waite reduction, degree-6 polynomial, ~1 ulp), written
 * branch-free so that loops around it vectorise; 0 where exp(-d) < 1.2e-38 (d > 87.3). One
 * scalar form for the loops the compiler vectorises, one on explicit vectors (below). */
#define EXP_LO (-87.3f)
#define EXP_LOG2E 1.44269504088896341f
#define EXP_ROUND 12582912.0f /* 1.5 * 2^23: adding and removing it rounds to an integer */
#define EXP_C1 0.693359375f
#define EXP_C2 (-2.12194440e-4f)
#define EXP_POLY(y, x)                                                                        \
    y = x * 0.0f + 1.9875691500e-4f;                                                          \
    y = y * x + 1.3981999507e-3f;                                                             \
    y = y * x + 8.3334519073e-3f;                                                             \
    y = y * x + 4.1665795894e-2f;                                                             \
    y = y * x + 1.6666665459e-1f;                                                             \
    y = y * x + 5.0000001201e-1f

/* exp(x) of x in [EXP_LO, 0] as y * 2^n, for a float or a vector of floats T: n = round(x / ln 2),
 * x reduced by n ln 2 in two parts, then the polynomial */
#define EXP_CORE(T, n, y, x)                                                                  \
    const T n = (x * EXP_LOG2E + EXP_ROUND) - EXP_ROUND;                                      \
    x = x - n * EXP_C1;                                                                       \
    x = x - n * EXP_C2;                                                                       \
    T y;                                                                                      \
    EXP_POLY(y, x);                                                                           \
    y = y * (x * x) + x + 1.0f

INLINE float exp_neg(float d) {
    float x = -d;
    const int under = x < EXP_LO;
    x = under ? EXP_LO : x;
    EXP_CORE(float, n, y, x);
    union { int32_t i; float f; } s;
    s.i = ((int32_t)n + 127) << 23;
    return under ? 0.0f : y * s.f;
}

/* 16 floats (one AVX-512 register; compilers split it where vectors are narrower); unaligned
 * loads and stores go through memcpy */
#define VL 16
typedef float vf __attribute__((vector_size(4 * VL)));
typedef int32_t vi __attribute__((vector_size(4 * VL)));

INLINE vf vload(const float *p) {
    vf v;
    memcpy(&v, p, sizeof v);
    return v;
}

INLINE void vstore(float *p, vf v) { memcpy(p, &v, sizeof v); }

INLINE vf vsplat(float a) { return a - (vf){0}; }

INLINE vf vselect(vi mask, vf a, vf b) { return (vf)(((vi)a & mask) | ((vi)b & ~mask)); }

INLINE vf vexp_neg(vf d) {
    vf x = -d;
    const vi under = x < vsplat(EXP_LO);
    x = vselect(under, vsplat(EXP_LO), x);
    EXP_CORE(vf, n, y, x);
    const vf s = (vf)((__builtin_convertvector(n, vi) + 127) << 23);
    return (vf)((vi)(y * s) & ~under);
}

int torchgi_native_version(void) { return 8; }

float torchgi_exp_neg(float d) { return exp_neg(d); }

/* ------------------------------------------------------------------------------------------
 * Sampling importance (torch_code._core) for rows [y0, y1) of one image:
 *
 *   out = clamp(1 - Σ_q v_q exp(-d(p,q)) / max(Σ_q v_q, 1), 0, 1) · v_p,
 *   d(p,q) = sn · |n_p - n_q|² + sx · |x_p - x_q|²
 *
 * over the taps q = p + (oy, ox), lo <= oy, ox <= hi, inside the image. n, x: the normal and
 * position, 3 plain H x W planes each (no centring needed: the differences of nearby float32
 * positions are exact); sn, sx: 1 / σ_n, 1 / σ_x; hit: an H x W plane of 0/1 (floats: GCC
 * turns a vector conversion from bytes into scalar code), or NULL for all 1; out: an H x W
 * plane. Pixels whose taps all lie inside the row go VL at a time, the edges one by one.
 */

INLINE float importance_of(float total, float count, float v) {
    const float q = 1.0f - total / (count > 1.0f ? count : 1.0f);
    return (q < 0.0f ? 0.0f : q > 1.0f ? 1.0f : q) * v;
}

static void importance_rows(const float *n, const float *x, float sn, float sx, const float *hit, int H, int W,
                            int lo, int hi, float *out, int y0, int y1) {
    const unsigned csr = ftz_begin();
    const size_t HW = (size_t)H * W;
    const int xl = -lo < W ? -lo : W;
    const int xv = xl + (W - hi > xl ? (W - hi - xl) / VL * VL : 0);
    const vf one = vsplat(1.0f), zero = vsplat(0.0f), vsn = vsplat(sn), vsx = vsplat(sx);
    for (int y = y0; y < y1; ++y) {
        const int ya = y + lo < 0 ? -y : lo, yb = y + hi >= H ? H - 1 - y : hi; /* rows inside */
        const size_t row = (size_t)y * W;
        const float *nr = n + row, *xr = x + row;
        const float *hr = hit ? hit + row : NULL;
        float *o = out + row;
        for (int i = xl; i < xv; i += VL) {
            vf np[3], xp[3], total = zero, count = zero;
            FOR8(k, 3, { np[k] = vload(nr + k * HW + i); xp[k] = vload(xr + k * HW + i); });
            for (int oy = ya; oy <= yb; ++oy)
                for (int ox = lo; ox <= hi; ++ox) {
                    const ptrdiff_t off = (ptrdiff_t)oy * W + ox + i;
                    if (oy == 0 && ox == 0) { /* the pixel itself: weight exp(0) = 1 */
                        const vf v = hr ? vload(hr + i) : one;
                        total += v;
                        count += v;
                        continue;
                    }
                    vf dn = zero, dx = zero;
                    FOR8(k, 3, {
                        const vf u = np[k] - vload(nr + k * HW + off), v = xp[k] - vload(xr + k * HW + off);
                        dn += u * u;
                        dx += v * v;
                    });
                    const vf w = vexp_neg(dn * vsn + dx * vsx);
                    if (hr) {
                        const vf v = vload(hr + off);
                        total += v * w;
                        count += v;
                    } else {
                        total += w;
                        count += one;
                    }
                }
            vf r = one - total / vselect(count > one, count, one);
            r = vselect(r < zero, zero, vselect(r > one, one, r));
            vstore(o + i, hr ? r * vload(hr + i) : r);
        }
        const int spans[2][2] = {{0, xl}, {xv, W}};
        for (int e = 0; e < 2; ++e)
            for (int i = spans[e][0]; i < spans[e][1]; ++i) {
                float total = 0.0f, count = 0.0f;
                for (int oy = ya; oy <= yb; ++oy)
                    for (int ox = lo; ox <= hi; ++ox) {
                        if (i + ox < 0 || i + ox >= W) continue;
                        const ptrdiff_t off = (ptrdiff_t)oy * W + ox + i;
                        float dn = 0.0f, dx = 0.0f;
                        for (int k = 0; k < 3; ++k) {
                            const float u = nr[k * HW + i] - nr[k * HW + off], v = xr[k * HW + i] - xr[k * HW + off];
                            dn += u * u;
                            dx += v * v;
                        }
                        const float v = hr ? hr[off] : 1.0f;
                        total += v * exp_neg(dn * sn + dx * sx);
                        count += v;
                    }
                o[i] = importance_of(total, count, hr ? hr[i] : 1.0f);
            }
    }
    ftz_end(csr);
}

/* ------------------------------------------------------------------------------------------
 * One À-Trous level (torch_code._iteration) for rows [y0, y1) of one image.
 *
 * c: C planes; f: F = 3 G feature planes (G groups of 3: normal, position), each group's squared
 * distance times fs[g]; var: C planes or NULL; valid: one plane (0/1) or NULL; cs: colour scale,
 * NULL (no colour weight), one value (cs_plane = 0) or a plane (cs_plane = 1); h: the 25 tap
 * weights, row major over (dy, dx) in -2..2; step: the dilation. Writes out (C planes), var_out
 * (C planes, when var) and den (one plane).
 *
 * Pixels whose 25 taps all lie inside the row are filtered VL at a time with the sums in
 * registers (tap_block); the 2 step columns at either edge tap by tap over the row (tap_row).
 */
typedef struct {
    const float *c, *f, *var, *valid, *cs; /* row y of plane 0 (cs: row y, or the one value) */
    const float *fs;                       /* scale of each feature group */
    size_t PS;                             /* plane stride of the inputs and outputs */
    ptrdiff_t off[25];                     /* offset of each tap's neighbour; skip[t]: row outside */
    int skip[25];
    float h[25];
} level_t;

/* Pixels [x, x + VL) of one row, all taps inside the row: the weighted sums stay in registers. */
INLINE void tap_block(const int C, const int G, const int CS, const int V, const level_t *L, int x, float *out,
                      float *var_out, float *den_out) {
    const size_t PS = L->PS;
    const float *c = L->c + x, *f = L->f + x;
    vf cp[8], fp[8], num[8], vnum[8], den = vsplat(0.0f), fs[2];
    FOR8(k, C, cp[k] = vload(c + k * PS); num[k] = vsplat(0.0f); vnum[k] = vsplat(0.0f));
    FOR8(k, 3 * G, fp[k] = vload(f + k * PS));
    FOR8(g, G, fs[g] = vsplat(L->fs[g]));
    const vf cs = CS == 2 ? vload(L->cs + x) : vsplat(CS ? L->cs[0] : 0.0f);
    for (int t = 0; t < 25; ++t) {
        if (L->skip[t]) continue;
        const ptrdiff_t o = L->off[t];
        vf cq[8], d = vsplat(0.0f);
        FOR8(k, C, cq[k] = vload(c + k * PS + o));
        if (CS) {
            vf dc = vsplat(0.0f);
            FOR8(k, C, { const vf u = cp[k] - cq[k]; dc += u * u; });
            d = dc * cs;
        }
        FOR8(g, G, {
            vf dg = vsplat(0.0f);
            FOR8(k, 3, { const vf u = fp[3 * g + k] - vload(f + (3 * g + k) * PS + o); dg += u * u; });
            d += dg * fs[g];
        });
        vf w = vsplat(L->h[t]) * vexp_neg(d);
        if (L->valid) w *= vload(L->valid + x + o);
        FOR8(k, C, num[k] += w * cq[k]);
        den += w;
        if (V) FOR8(k, C, vnum[k] += w * w * vload(L->var + x + k * PS + o));
    }
    /* no weight at all keeps the centre pixel (and its variance) */
    const vi ok = den > vsplat(0.0f);
    const vf safe = vselect(ok, den, vsplat(1.0f));
    FOR8(k, C, vstore(out + k * PS + x, vselect(ok, num[k] / safe, cp[k])));
    if (V) FOR8(k, C, vstore(var_out + k * PS + x, vselect(ok, vnum[k] / (safe * safe), vload(L->var + x + k * PS))));
    vstore(den_out + x, den);
}

/* Taps one at a time over pixels [xa, xb) of one row (C, G run-time when not constant). */
INLINE void tap_row(const int C, const int G, const int CS, const int V, const level_t *L, int t, int xa, int xb,
                    float *num, float *vnum, float *den, int SW) {
    const size_t PS = L->PS;
    const ptrdiff_t o = L->off[t];
    const float h = L->h[t], *c = L->c, *f = L->f, *valid = L->valid, *var = L->var, *cs = L->cs;
    for (int x = xa; x < xb; ++x) {
        float d = 0.0f;
        if (CS) {
            float dc = 0.0f;
            for (int k = 0; k < C; ++k) {
                const float u = c[k * PS + x] - c[k * PS + x + o];
                dc += u * u;
            }
            d = dc * (CS == 2 ? cs[x] : cs[0]);
        }
        for (int g = 0; g < G; ++g) {
            float dg = 0.0f;
            for (int k = 3 * g; k < 3 * g + 3; ++k) {
                const float u = f[k * PS + x] - f[k * PS + x + o];
                dg += u * u;
            }
            d += dg * L->fs[g];
        }
        float w = h * exp_neg(d);
        if (valid) w *= valid[x + o];
        for (int k = 0; k < C; ++k) num[k * SW + x] += w * c[k * PS + x + o];
        den[x] += w;
        if (V)
            for (int k = 0; k < C; ++k) vnum[k * SW + x] += w * w * var[k * PS + x + o];
    }
}

typedef void (*block_fn)(const level_t *, int, float *, float *, float *);
#define BLOCK(C, G, CS, V) \
    static void block_##C##_##G##_##CS##_##V(const level_t *L, int x, float *o, float *vo, float *d) { \
        tap_block(C, G, CS, V, L, x, o, vo, d); }
#define BLOCKS_CG(C, G) BLOCK(C, G, 0, 0) BLOCK(C, G, 0, 1) BLOCK(C, G, 1, 0) BLOCK(C, G, 1, 1) \
    BLOCK(C, G, 2, 0) BLOCK(C, G, 2, 1)
BLOCKS_CG(1, 0) BLOCKS_CG(1, 1) BLOCKS_CG(1, 2) BLOCKS_CG(3, 0) BLOCKS_CG(3, 1) BLOCKS_CG(3, 2)

static block_fn pick_block(int C, int G, int CS, int V) {
#define PICK(c, g)                                                                             \
    if (C == c && G == g)                                                                      \
        return CS == 0 ? (V ? block_##c##_##g##_0_1 : block_##c##_##g##_0_0)                   \
             : CS == 1 ? (V ? block_##c##_##g##_1_1 : block_##c##_##g##_1_0)                   \
                       : (V ? block_##c##_##g##_2_1 : block_##c##_##g##_2_0);
    PICK(1, 0) PICK(1, 1) PICK(1, 2) PICK(3, 0) PICK(3, 1) PICK(3, 2)
#undef PICK
    return NULL;
}

/* Planes of every input and of out / var_out are ps floats apart, rows rs floats apart (padded
 * layouts keep the row streams of the taps out of one another's cache sets); den is a plain
 * H x W plane. scratch: (2 C + 1) (W + 16) floats. */
static void atrous_rows(const float *c, int C, const float *f, int F, const float *fs, const float *var,
                        const float *valid, const float *cs, int cs_plane, int H, int W, int rs, long long ps,
                        int step, const float *h25, float *out, float *var_out, float *den_out, int y0, int y1,
                        float *scratch) {
    const unsigned csr = ftz_begin();
    const int G = F / 3, CS = cs == NULL ? 0 : cs_plane ? 2 : 1, V = var != NULL, SW = W + 16;
    level_t L;
    L.PS = (size_t)ps, L.fs = fs;
    float *num = scratch, *vnum = scratch + (size_t)C * SW, *den = scratch + (size_t)2 * C * SW;
    const block_fn block = pick_block(C, G, CS, V);
    /* the vector blocks cover [xl, xv); the edges [0, xl) and [xv, W) go tap by tap */
    const int reach = 2 * step;
    const int xl = block && reach < W ? reach : W;
    const int xv = xl + (W - reach > xl ? (W - reach - xl) / VL * VL : 0);
    for (int y = y0; y < y1; ++y) {
        const size_t row = (size_t)y * rs;
        L.c = c + row, L.f = F ? f + row : NULL, L.var = V ? var + row : NULL;
        L.valid = valid ? valid + row : NULL, L.cs = CS == 2 ? cs + row : cs;
        for (int t = 0; t < 25; ++t) {
            const int oy = (t / 5 - 2) * step, ox = (t % 5 - 2) * step;
            L.skip[t] = y + oy < 0 || y + oy >= H;
            L.off[t] = (ptrdiff_t)oy * rs + ox;
            L.h[t] = h25[t];
        }
        float *o = out + row, *vo = V ? var_out + row : NULL, *dn = den_out + (size_t)y * W;
        for (int x = xl; x < xv; x += VL) block(&L, x, o, vo, dn);
        const int spans[2][2] = {{0, xl}, {xv, W}};
        for (int e = 0; e < 2; ++e) {
            const int a = spans[e][0], b = spans[e][1];
            if (a >= b) continue;
            for (int k = 0; k < C; ++k) {
                memset(num + k * SW + a, 0, sizeof(float) * (b - a));
                memset(vnum + k * SW + a, 0, sizeof(float) * (b - a));
            }
            memset(den + a, 0, sizeof(float) * (b - a));
            for (int t = 0; t < 25; ++t) {
                if (L.skip[t]) continue;
                const int ox = (t % 5 - 2) * step;
                const int xa = a > -ox ? a : -ox, xb = b < W - ox ? b : W - ox;
                if (xa >= xb) continue;
                if (C == 3 && G == 2)
                    tap_row(3, 2, CS, V, &L, t, xa, xb, num, vnum, den, SW);
                else
                    tap_row(C, G, CS, V, &L, t, xa, xb, num, vnum, den, SW);
            }
            for (int k = 0; k < C; ++k)
                for (int x = a; x < b; ++x) {
                    const int ok = den[x] > 0.0f;
                    const float sd = ok ? den[x] : 1.0f;
                    o[k * L.PS + x] = ok ? num[k * SW + x] / sd : L.c[k * L.PS + x];
                    if (V) vo[k * L.PS + x] = ok ? vnum[k * SW + x] / (sd * sd) : L.var[k * L.PS + x];
                }
            for (int x = a; x < b; ++x) dn[x] = den[x];
        }
    }
    ftz_end(csr);
}

/* ------------------------------------------------------------------------------------------
 * Guided filter (torch_code.solve / apply_coefficients) on centred planes, in two passes over bands of
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

/* Row sums of the vertical window: acc[k][x] += sign * value_k(yy, x) for the K planes the
 * callback-free layout below describes. */
typedef struct {
    int n, Cs, K;
    const guide_t *G;     /* guide (n channels) */
    const float *p;       /* source (Cs planes) */
    float cI[4];          /* the guide's offset minus its per-image mean, added before any sum (DESIGN §5) */
    const float *mp;      /* the source's per-image means, subtracted before any sum */
    size_t HW;
    int W;
} products_t;

/* value k of row yy, centred: I_i (k < n), p_c, I_i I_j (j <= i), I_i p_c */
static void add_products(const products_t *P, int yy, double sign, double *acc) {
    const int n = P->n, Cs = P->Cs, W = P->W;
    const size_t row = (size_t)yy * W;
    const guide_t *G = P->G;
    int k = 0;
    for (int i = 0; i < n; ++i, ++k) {
        double *s = acc + (size_t)k * ACC_STRIDE(W);
        for (int x = 0; x < W; ++x) s[x] += sign * GUIDE(G, i, row, x, P->cI);
    }
    for (int c = 0; c < Cs; ++c, ++k) {
        const float *a = P->p + c * P->HW + row, ma = P->mp[c];
        double *s = acc + (size_t)k * ACC_STRIDE(W);
        for (int x = 0; x < W; ++x) s[x] += sign * (a[x] - ma);
    }
    for (int i = 0; i < n; ++i)
        for (int j = 0; j <= i; ++j, ++k) {
            double *s = acc + (size_t)k * ACC_STRIDE(W);
            for (int x = 0; x < W; ++x)
                s[x] += sign * ((double)GUIDE(G, i, row, x, P->cI) * GUIDE(G, j, row, x, P->cI));
        }
    for (int i = 0; i < n; ++i)
        for (int c = 0; c < Cs; ++c, ++k) {
            const float *b = P->p + c * P->HW + row, mb = P->mp[c];
            double *s = acc + (size_t)k * ACC_STRIDE(W);
            for (int x = 0; x < W; ++x) s[x] += sign * ((double)GUIDE(G, i, row, x, P->cI) * (b[x] - mb));
        }
}

static void add_planes(const float *planes, int K, size_t HW, int W, int yy, double sign, double *acc) {
    for (int k = 0; k < K; ++k) {
        const float *a = planes + k * HW + (size_t)yy * W;
        double *s = acc + (size_t)k * ACC_STRIDE(W);
        for (int x = 0; x < W; ++x) s[x] += sign * a[x];
    }
}

/* 8 doubles, for the prefix sums along a row */
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

/* Box means along the row of K rows of column sums (acc) that cover cy image rows: mean[k][x]
 * = (sum of acc[k] over the window at x) / (pixels in the window), from prefix sums pre (W + 1
 * doubles) computed eight at a time. */
static void row_means(const double *acc, int K, int W, int r, int cy, const double *inv_cx, double *pre,
                      float *mean) {
    const double inv_cy = 1.0 / cy;
    /* x in [mid0, mid1) has the whole window inside the row: there hi = x + r + 1, lo = x - r */
    const int mid0 = r < W ? r : W, mid1 = W - r - 1 > mid0 ? W - r - 1 : mid0;
    for (int k = 0; k < K; ++k) {
        const double *a = acc + (size_t)k * ACC_STRIDE(W);
        float *m = mean + (size_t)k * MEAN_STRIDE(W);
        vd carry = {0};
        int x = 0;
        pre[0] = 0.0;
        for (; x + 8 <= W; x += 8) {
            vd v;
            memcpy(&v, a + x, sizeof v);
            v = vd_scan(v) + carry;
            memcpy(pre + x + 1, &v, sizeof v);
            carry = __builtin_shuffle(v, (vl){7, 7, 7, 7, 7, 7, 7, 7});
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

/* Solve one row for source channels [c0, c0 + G): means in m (K x W, the order of
 * add_products), write a_0..a_{n-1}, b (each Cs planes) into coef at row y. LDLᵀ as in
 * torch_code.solve: eps_i raised to unit · E[I_i²] per pixel, variances clamped at 0, pivots at eps. */
INLINE void solve_row(const int n, const int G, int c0, int Cs, const float *m, int W, const float *eps, float unit,
                      float *coef, size_t HW, int y) {
    const int MW = MEAN_STRIDE(W);
    const float *mI = m, *mp = m + (size_t)n * MW, *mII = m + (size_t)(n + Cs) * MW;
    const float *mIp = mII + (size_t)(n * (n + 1) / 2) * MW;
    float *row = coef + (size_t)y * W;
#pragma GCC ivdep
    for (int x = 0; x < W; ++x) {
        float A[4][4], L[4][4], E[4][4], D[4], e[4];
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
    for (int yy = y0 - r - 1 > 0 ? y0 - r - 1 : 0; yy <= y0 + r - 1 && yy < H; ++yy) add_products(&P, yy, 1.0, acc);
    for (int y = y0; y < y1; ++y) {
        /* the window's rows are [y - r, y + r] clipped to the image */
        if (y + r < H) add_products(&P, y + r, 1.0, acc);
        if (y - r - 1 >= 0) add_products(&P, y - r - 1, -1.0, acc);
        const int cy = (y + r < H ? y + r : H - 1) - (y - r > 0 ? y - r : 0) + 1;
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
        add_planes(coef, Q, HW, W, yy, 1.0, acc);
    for (int y = y0; y < y1; ++y) {
        if (y + r < H) add_planes(coef, Q, HW, W, y + r, 1.0, acc);
        if (y - r - 1 >= 0) add_planes(coef, Q, HW, W, y - r - 1, -1.0, acc);
        const int cy = (y + r < H ? y + r : H - 1) - (y - r > 0 ? y - r : 0) + 1;
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
    float floor;
    size_t HW;
    int W;
};

/* The demodulator of row y (3 x W floats): the albedo (at least floor) on surfaces, 1 elsewhere. */
static void demod_row(const light_t *L, int y, float *ad) {
    const size_t HW = L->HW, row = (size_t)y * L->W;
    const float *a0 = L->albedo + row, *a1 = a0 + HW, *a2 = a1 + HW, f = L->floor;
    const int W = L->W;
    for (int c = 0; c < 3; ++c) {
        const float *a = L->albedo + c * HW + row;
        float *d = ad + (size_t)c * W;
        if (L->hit) {
            const uint8_t *h = L->hit + row;
            for (int x = 0; x < W; ++x) d[x] = h[x] ? MAXF(a[x], f) : 1.0f;
        } else {
            for (int x = 0; x < W; ++x) d[x] = (a0[x] > 0.0f) | (a1[x] > 0.0f) | (a2[x] > 0.0f) ? MAXF(a[x], f) : 1.0f;
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

/* The guided filter's output rows [y0, y1) from the Q = (n + 1) Cs box-filtered coefficient
 * planes at s x s lower resolution (h x w), upsampled bilinearly by the factor s (torch's
 * interpolate, align_corners=False: rows first, then along the row) and applied to the full-resolution guide:
 * out_c = b_c + Σ_i a_ic (I_i - meanI_i) + offset_c; then remodulated by finish_row when L is
 * not NULL. scratch: 2 W ints, W + w floats, 3 W floats. */
static void upsample_apply_rows(const float *coef, int n, int Cs, int s, int h, int w, const guide_t *G, const float *meanI,
                                const float *offset, int H, int W, float *out, const light_t *L, const uint8_t *mask,
                                void *scratch, int y0, int y1) {
    const size_t HW = (size_t)H * W, hw = (size_t)h * w;
    int *x0 = (int *)scratch, *x1 = x0 + W;
    float *lx = (float *)(x1 + W), *t = lx + W, *ad = t + w;
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
                if (k == n) {
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

/* ------------------------------------------------------------------------------------------
 * Sample allocation (sampling.allocate) of one image: n_p = floor(q_p / Q · spare) plus one for
 * the `left` largest remainders (ties to the lowest index), plus min_samples; 0 off `eligible`
 * (NULL: every pixel). q: float32, or float64 with q_double. The torch code's double
 * arithmetic; Q is summed in CHUNKS fixed chunks of 8 interleaved partial sums, so the result
 * does not depend on the thread count. The remainders r in [0, 1) are ranked by the bucket
 * floor(r · 2^16) (exact and monotonic), then, within the one bucket that holds the cut, by
 * sorting its few members. Scratch: bucket, N uint16; hist, nt x 65536 uint32. Passes run on
 * nt OpenMP threads (see OVER_BANDS); with nt = 1 their `if` clauses keep them on the calling
 * thread (a forked one-thread child runs this: tests/test_native.py). Returns 0, or -1 when
 * memory runs out.
 */
#define BUCKETS 65536
#define CHUNKS 64

typedef struct {
    double r;
    int32_t p;
} ranked_t;

static int by_remainder_then_index(const void *a, const void *b) {
    const ranked_t *x = a, *y = b;
    return x->r != y->r ? (x->r < y->r ? 1 : -1) : (x->p > y->p) - (x->p < y->p);
}

typedef struct {
    const float *qf;
    const double *qd;
    const uint8_t *eligible;
    double Q, uniform, spare;
} alloc_t;

/* q_p, or -1 off eligible */
INLINE double q_at(const alloc_t *A, long long p) {
    if (A->eligible && !A->eligible[p]) return -1.0;
    return A->qd ? A->qd[p] : (double)A->qf[p];
}

/* the exact share q_p / Q · spare (uniform when Q = 0) of an eligible pixel */
INLINE double exact_at(const alloc_t *A, double q) { return (A->Q > 0.0 ? q / A->Q : A->uniform) * A->spare; }

int torchgi_allocate(const void *q, int q_double, const uint8_t *eligible, long long N, long long n_eligible,
                     long long spare, int min_samples, int64_t *counts, uint16_t *bucket, uint32_t *hist, int nt) {
    alloc_t A = {q_double ? NULL : (const float *)q, q_double ? (const double *)q : NULL, eligible, 0.0,
                 n_eligible > 0 ? 1.0 / (double)n_eligible : 0.0, (double)spare};
    double chunk_q[CHUNKS];
    long long chunk_total[CHUNKS];
#define CHUNK_RANGE(c) const long long pa = N * (c) / CHUNKS, pb = N * ((c) + 1) / CHUNKS
#pragma omp parallel for num_threads(nt) schedule(static) if (nt > 1)
    for (int c = 0; c < CHUNKS; ++c) {
        CHUNK_RANGE(c);
        double lane[8] = {0};
        for (long long p = pa; p < pb; ++p) {
            const double v = q_at(&A, p);
            lane[(p - pa) & 7] += v > 0.0 ? v : 0.0;
        }
        chunk_q[c] = ((lane[0] + lane[1]) + (lane[2] + lane[3])) + ((lane[4] + lane[5]) + (lane[6] + lane[7]));
    }
    for (int c = 0; c < CHUNKS; ++c) A.Q += chunk_q[c];
    /* floor of each share (-1 marks pixels off eligible), its remainder's bucket, histograms */
#pragma omp parallel num_threads(nt) if (nt > 1)
    {
#if defined(_OPENMP)
        uint32_t *h = hist + (size_t)omp_get_thread_num() * BUCKETS;
#else
        uint32_t *h = hist;
#endif
        memset(h, 0, sizeof(uint32_t) * BUCKETS);
#pragma omp for schedule(static)
        for (int c = 0; c < CHUNKS; ++c) {
            CHUNK_RANGE(c);
            long long total = 0;
            for (long long p = pa; p < pb; ++p) {
                const double v = q_at(&A, p);
                if (v < 0.0) {
                    counts[p] = -1;
                    continue;
                }
                const double e = exact_at(&A, v), whole = floor(e);
                const int b = (int)((e - whole) * BUCKETS);
                counts[p] = (int64_t)whole;
                bucket[p] = (uint16_t)b;
                ++h[b];
                total += (long long)whole;
            }
            chunk_total[c] = total;
        }
    }
    long long need = spare; /* remainders to hand out, fewer than the eligible pixels */
    for (int c = 0; c < CHUNKS; ++c) need -= chunk_total[c];
    int cut = BUCKETS; /* buckets above the cut get one more, and `need` members of the cut's */
    if (need > 0) {
        for (int t = 1; t < nt; ++t)
            for (int b = 0; b < BUCKETS; ++b) hist[b] += hist[(size_t)t * BUCKETS + b];
        for (cut = BUCKETS - 1; cut > 0 && hist[cut] < need; --cut) need -= hist[cut];
    }
#pragma omp parallel for num_threads(nt) schedule(static) if (nt > 1)
    for (int c = 0; c < CHUNKS; ++c) {
        CHUNK_RANGE(c);
        for (long long p = pa; p < pb; ++p)
            counts[p] = counts[p] < 0 ? 0 : counts[p] + min_samples + (cut < BUCKETS && bucket[p] > cut);
    }
    if (cut < BUCKETS) { /* the cut's bucket, sorted by remainder then index */
        ranked_t *tie = malloc(sizeof(ranked_t) * (hist[cut] + 1));
        if (!tie) return -1;
        long long m = 0;
        for (long long p = 0; p < N; ++p)
            if (bucket[p] == cut && q_at(&A, p) >= 0.0) {
                const double e = exact_at(&A, q_at(&A, p));
                tie[m].r = e - floor(e), tie[m++].p = (int32_t)p;
            }
        qsort(tie, (size_t)m, sizeof(ranked_t), by_remainder_then_index);
        for (long long i = 0; i < need; ++i) ++counts[tie[i].p];
        free(tie);
    }
#undef CHUNK_RANGE
    return 0;
}

/* ------------------------------------------------------------------------------------------
 * Entry points: rows [0, H) in nt bands, one per thread. Built with -fopenmp the bands run on
 * OpenMP threads — the libgomp that torch has loaded, so torch's own worker threads (which spin
 * for a while after each torch op) take the bands instead of competing with them for the cores.
 * nt = 1 (or a build without OpenMP) runs the bands on the calling thread and never enters
 * OpenMP, so a forked child with one torch thread is safe. scratch: nt blocks of stride bytes.
 */
/* ---------------------------------------------------------------- temporal accumulation
 * One frame of torchgi.temporal's reprojection and accumulation (backends.base.AccumulateOp; the
 * same maths as torch_code.accumulate, tap by tap in the same order): the history's four
 * bilinear taps at pixel + motion, each counted where it is inside the image, of the same kind
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
            float acc[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0}, total = 0;
            for (int k = 0; k < 4; ++k) {
                const int dx = k & 1, dy = k >> 1;
                const float tx = fx0 + dx, ty = fy0 + dy;
                if (!(tx >= 0 && tx <= W - 1 && ty >= 0 && ty <= H - 1)) continue;
                const size_t j = (size_t)ty * W + (size_t)tx;
                if ((A->ps[j] > 0.5f) != surf) continue;
                if (surf) {
                    const float dot = A->pn[j] * n0 + A->pn[HW + j] * n1 + A->pn[2 * HW + j] * n2;
                    if (!(dot >= A->ntol && fabsf(A->pd[j] - d) <= A->dtol * fabsf(d))) continue;
                }
                const float w = (dx ? fx : 1 - fx) * (dy ? fy : 1 - fy);
                for (int c = 0; c < 9; ++c) acc[c] += w * hist[c][j];
                total += w;
            }
            const int found = total > 1e-3f;
            float h[9];
            for (int c = 0; c < 9; ++c) h[c] = found ? acc[c] / total : 0.0f;
            const float hl = found ? rintf(h[8]) : 0.0f;
            const float len = hl > 0 ? fminf(hl + 1, A->cap) : 1.0f;
            const float a = fmaxf(1.0f / len, A->alpha);
            float *o = A->out + i;
            float x0 = A->x[i], x1 = A->x[HW + i], x2 = A->x[2 * HW + i];
            const float peak = fmaxf(fmaxf(x0, x1), x2), bound = A->bound[i];
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
            o[10 * HW] = fmaxf(m2 - m1 * m1, 0.0f);
            o[11 * HW] = fminf(len, (2 - a) / a);
            o[12 * HW] = lum;
        }
    }
}

#define OVER_BANDS(H, CALL)                                                                     \
    do {                                                                                        \
        if (nt > 1) {                                                                           \
            _Pragma("omp parallel for num_threads(nt) schedule(static, 1)")                     \
            for (int band = 0; band < nt; ++band) {                                             \
                const int y0 = (int)((long long)(H) * band / nt);                               \
                const int y1 = (int)((long long)(H) * (band + 1) / nt);                         \
                void *scr = scratch ? (char *)scratch + (size_t)band * (size_t)stride : NULL;   \
                CALL;                                                                           \
            }                                                                                   \
        } else {                                                                                \
            const int y0 = 0, y1 = (H);                                                         \
            void *scr = scratch;                                                                \
            CALL;                                                                               \
        }                                                                                       \
    } while (0)

int torchgi_openmp(void) {
#if defined(_OPENMP)
    return 1;
#else
    return 0;
#endif
}

void torchgi_importance(const float *n, const float *x, float sn, float sx, const float *hit, int H, int W, int lo,
                        int hi, float *out, int nt, void *scratch, long long stride) {
    OVER_BANDS(H, ((void)scr, importance_rows(n, x, sn, sx, hit, H, W, lo, hi, out, y0, y1)));
}

void torchgi_atrous_level(const float *c, int C, const float *f, int F, const float *fs, const float *var,
                          const float *valid, const float *cs, int cs_plane, int H, int W, int rs, long long ps,
                          int step, const float *h25, float *out, float *var_out, float *den_out, int nt,
                          void *scratch, long long stride) {
    OVER_BANDS(H, atrous_rows(c, C, f, F, fs, var, valid, cs, cs_plane, H, W, rs, ps, step, h25, out, var_out, den_out,
                              y0, y1, (float *)scr));
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

/* The pipeline's entry points (see the section above). */
static light_t make_light(const float *color, const float *emission, const float *kept, const float *albedo,
                          const uint8_t *hit, float floor, int H, int W) {
    const light_t L = {color, emission, kept, albedo, hit, floor, (size_t)H * W, W};
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
                    const uint8_t *hit, float floor, int H, int W, float thr, int r, uint8_t *mask, int nt,
                    void *scratch, long long stride) {
    const light_t L = make_light(color, emission, kept, albedo, hit, floor, H, W);
    OVER_BANDS(H, lights_rows(&L, H, thr, r, mask, (char *)scr + PART_BYTES, (double *)scr, y0, y1));
}

void torchgi_prepare(const float *color, const float *emission, const float *kept, const float *albedo,
                     const uint8_t *hit, float floor, int H, int W, const uint8_t *mask, float level, float cap,
                     float *x, float *peak, int nt, void *scratch, long long stride) {
    const light_t L = make_light(color, emission, kept, albedo, hit, floor, H, W);
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
                           float floor, const uint8_t *mask, int nt, void *scratch, long long stride) {
    const light_t L = make_light(color, emission, kept, albedo, hit, floor, H, W);
    const guide_t G = make_guide(n, g0, g1, g2, g3, scale, goffset);
    if (s == 1) {
        OVER_BANDS(H, apply_rows(coef, n, Cs, &G, meanI, offset, H, W, r, out, &L, mask, y0, y1, scr));
    } else {
        const int h = (H + s - 1) / s, w = (W + s - 1) / s;
        OVER_BANDS(H, upsample_apply_rows(coef, n, Cs, s, h, w, &G, meanI, offset, H, W, out, &L, mask, scr, y0, y1));
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
