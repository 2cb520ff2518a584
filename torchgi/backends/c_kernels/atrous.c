/* One À-Trous level (backends.base.ATrousOp).
 * Compiled as part of native.c (one translation unit: see there). */
#include "common.h"

/* ------------------------------------------------------------------------------------------
 * One À-Trous level (torch_code.filter_atrous._iteration) for rows [y0, y1) of one image.
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

void torchgi_atrous_level(const float *c, int C, const float *f, int F, const float *fs, const float *var,
                          const float *valid, const float *cs, int cs_plane, int H, int W, int rs, long long ps,
                          int step, const float *h25, float *out, float *var_out, float *den_out, int nt,
                          void *scratch, long long stride) {
    OVER_BANDS(H, atrous_rows(c, C, f, F, fs, var, valid, cs, cs_plane, H, W, rs, ps, step, h25, out, var_out, den_out,
                              y0, y1, (float *)scr));
}

/* ------------------------------------------------------------------------------------------
 * The gradients of one À-Trous level without variance or holes (backends.base.ATrousLevelGradOp;
 * torch_code.filter_atrous.level_grad is the same in torch), for rows [y0, y1) of one image.
 *
 * out_p = Σ_q w_pq c_q / D_p, w_pq = h_t exp(-(s_p |c_p - c_q|² + |f_p - f_q|²)). With gp = g / D
 * (given), G_pq = Σ_k gp_pk (c_qk - out_pk) and E_pq = -w_pq G_pq:
 *   dc_p += Σ_q E_pq 2 s_p (c_p - c_q)          ds_p += Σ_q E_pq |c_p - c_q|²
 *   df_p += Σ_q E_pq 2 (f_p - f_q)
 * as the centre, and as the neighbour q of p = q - o_t:
 *   dc_q += w_pq gp_p - E_pq 2 s_p (c_p - c_q)   df_q -= E_pq 2 (f_p - f_q).
 * Each row gathers both (no two bands write one pixel); taps outside the image are left out as in
 * the forward. Plain contiguous planes of H x W; s: NULL (no colour weight), one value or a plane
 * (CSM 0, 1, 2); f, df NULL when F = 0; df, ds NULL when not wanted.
 */
INLINE void grad_pairs(const int C, const int F, const int CSM, const float *restrict c, const float *restrict f,
                       const float *restrict s, const float *restrict out, const float *restrict gp, size_t HW,
                       float h, size_t p0, size_t q0, int xa, int xb, int centre, float *restrict dc,
                       float *restrict df, float *restrict ds) {
    int x = xa;
    for (; x + VL <= xb; x += VL) { /* VL pixels at a time, the same sums on vectors */
        const size_t p = p0 + x, q = q0 + x;
        vf dcol = vsplat(0.0f), dfe = vsplat(0.0f), u[8], v[8], G = vsplat(0.0f);
        FOR8(k, C, { u[k] = vload(c + k * HW + p) - vload(c + k * HW + q); dcol += u[k] * u[k]; });
        FOR8(k, F, { v[k] = vload(f + k * HW + p) - vload(f + k * HW + q); dfe += v[k] * v[k]; });
        const vf sp = CSM == 2 ? vload(s + p) : vsplat(CSM == 1 ? s[0] : 0.0f);
        const vf w = vsplat(h) * vexp_neg(sp * dcol + dfe);
        FOR8(k, C, G += vload(gp + k * HW + p) * (vload(c + k * HW + q) - vload(out + k * HW + p)));
        const vf E = -w * G, E2s = 2.0f * E * sp;
        if (centre) {
            FOR8(k, C, vstore(dc + k * HW + p, vload(dc + k * HW + p) + E2s * u[k]));
            if (df) FOR8(k, F, vstore(df + k * HW + p, vload(df + k * HW + p) + 2.0f * E * v[k]));
            if (CSM && ds) vstore(ds + p, vload(ds + p) + E * dcol);
        } else {
            FOR8(k, C, vstore(dc + k * HW + q, vload(dc + k * HW + q) + w * vload(gp + k * HW + p) - E2s * u[k]));
            if (df) FOR8(k, F, vstore(df + k * HW + q, vload(df + k * HW + q) - 2.0f * E * v[k]));
        }
    }
    for (; x < xb; ++x) {
        const size_t p = p0 + x, q = q0 + x;
        float dcol = 0.0f, dfe = 0.0f, u[8], v[8];
        FOR8(k, C, { u[k] = c[k * HW + p] - c[k * HW + q]; dcol += u[k] * u[k]; });
        FOR8(k, F, { v[k] = f[k * HW + p] - f[k * HW + q]; dfe += v[k] * v[k]; });
        const float sp = CSM == 2 ? s[p] : CSM == 1 ? s[0] : 0.0f;
        const float w = h * exp_neg(sp * dcol + dfe);
        float G = 0.0f;
        FOR8(k, C, G += gp[k * HW + p] * (c[k * HW + q] - out[k * HW + p]));
        const float E = -w * G, E2s = 2.0f * E * sp;
        if (centre) {
            FOR8(k, C, dc[k * HW + p] += E2s * u[k]);
            if (df) FOR8(k, F, df[k * HW + p] += 2.0f * E * v[k]);
            if (CSM && ds) ds[p] += E * dcol;
        } else {
            FOR8(k, C, dc[k * HW + q] += w * gp[k * HW + p] - E2s * u[k]);
            if (df) FOR8(k, F, df[k * HW + q] -= 2.0f * E * v[k]);
        }
    }
}

typedef void (*pairs_fn)(const float *, const float *, const float *, const float *, const float *, size_t, float,
                         size_t, size_t, int, int, int, float *, float *, float *);
#define PAIRS(C, F, CSM)                                                                                     \
    static void pairs_##C##_##F##_##CSM(const float *c, const float *f, const float *s, const float *out,   \
                                        const float *gp, size_t HW, float h, size_t p0, size_t q0, int xa,   \
                                        int xb, int centre, float *dc, float *df, float *ds) {               \
        grad_pairs(C, F, CSM, c, f, s, out, gp, HW, h, p0, q0, xa, xb, centre, dc, df, ds);                  \
    }
#define PAIRS_C(C) PAIRS(C, 0, 0) PAIRS(C, 0, 1) PAIRS(C, 0, 2) PAIRS(C, 3, 0) PAIRS(C, 3, 1) PAIRS(C, 3, 2) \
    PAIRS(C, 6, 0) PAIRS(C, 6, 1) PAIRS(C, 6, 2)
PAIRS_C(1) PAIRS_C(3)

static pairs_fn pick_pairs(int C, int F, int CSM) {
#define PICKP(c, fe) \
    if (C == c && F == fe) return CSM == 0 ? pairs_##c##_##fe##_0 : CSM == 1 ? pairs_##c##_##fe##_1 : pairs_##c##_##fe##_2;
    PICKP(1, 0) PICKP(1, 3) PICKP(1, 6) PICKP(3, 0) PICKP(3, 3) PICKP(3, 6)
#undef PICKP
    return NULL;
}

static void atrous_grad_rows(const float *c, int C, const float *f, int F, const float *s, int CSM, const float *out,
                             const float *gp, int H, int W, int step, const float *h25, float *dc, float *df,
                             float *ds, int y0, int y1) {
    const unsigned csr = ftz_begin();
    const size_t HW = (size_t)H * W;
    const pairs_fn pairs = pick_pairs(C, F, CSM);
    for (int y = y0; y < y1; ++y) {
        const size_t row = (size_t)y * W;
        for (int k = 0; k < C; ++k) memset(dc + k * HW + row, 0, sizeof(float) * W);
        for (int k = 0; k < F && df; ++k) memset(df + k * HW + row, 0, sizeof(float) * W);
        if (ds) memset(ds + row, 0, sizeof(float) * W);
        for (int t = 0; t < 25; ++t) {
            const int oy = (t / 5 - 2) * step, ox = (t % 5 - 2) * step;
            for (int centre = 1; centre >= 0; --centre) {
                const int yo = centre ? y + oy : y - oy; /* the other pixel's row */
                if (yo < 0 || yo >= H) continue;
                const int sx = centre ? ox : -ox;        /* the other pixel's column offset */
                const int xa = sx < 0 ? -sx : 0, xb = sx > 0 ? W - sx : W;
                if (xa >= xb) continue;
                /* p: the centre of the pair, q: its neighbour */
                const size_t p0 = centre ? row : (size_t)yo * W - ox, q0 = centre ? (size_t)yo * W + ox : row;
                pairs(c, f, s, out, gp, HW, h25[t], p0, q0, xa, xb, centre, dc, df, ds);
            }
        }
    }
    ftz_end(csr);
}

void torchgi_atrous_level_grad(const float *c, int C, const float *f, int F, const float *s, int CSM,
                               const float *out, const float *gp, int H, int W, int step, const float *h25,
                               float *dc, float *df, float *ds, int nt, void *scratch, long long stride) {
    OVER_BANDS(H, atrous_grad_rows(c, C, f, F, s, CSM, out, gp, H, W, step, h25, dc, df, ds, y0, y1));
}
