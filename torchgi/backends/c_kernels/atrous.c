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
    size_t PS, OPS;                        /* plane stride of the inputs (and var_out), of out */
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
    FOR8(k, C, vstore(out + k * L->OPS + x, vselect(ok, num[k] / safe, cp[k])));
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

/* Planes of every input and of var_out are ps floats apart, rows rs floats apart (padded
 * layouts keep the row streams of the taps out of one another's cache sets); out's planes and
 * rows are ops and ors apart; den is a plain H x W plane. scratch: (2 C + 1) (W + 16) floats. */
static void atrous_rows(const float *c, int C, const float *f, int F, const float *fs, const float *var,
                        const float *valid, const float *cs, int cs_plane, int H, int W, int rs, long long ps,
                        int step, const float *h25, float *out, int ors, long long ops, float *var_out,
                        float *den_out, int y0, int y1, float *scratch) {
    const unsigned csr = ftz_begin();
    const int G = F / 3, CS = cs == NULL ? 0 : cs_plane ? 2 : 1, V = var != NULL, SW = W + 16;
    level_t L;
    L.PS = (size_t)ps, L.OPS = (size_t)ops, L.fs = fs;
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
        float *o = out + (size_t)y * ors, *vo = V ? var_out + row : NULL, *dn = den_out + (size_t)y * W;
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
                    o[k * L.OPS + x] = ok ? num[k * SW + x] / sd : L.c[k * L.PS + x];
                    if (V) vo[k * L.PS + x] = ok ? vnum[k * SW + x] / (sd * sd) : L.var[k * L.PS + x];
                }
            for (int x = a; x < b; ++x) dn[x] = den[x];
        }
    }
    ftz_end(csr);
}

void torchgi_atrous_level(const float *c, int C, const float *f, int F, const float *fs, const float *var,
                          const float *valid, const float *cs, int cs_plane, int H, int W, int rs, long long ps,
                          int step, const float *h25, float *out, int ors, long long ops, float *var_out,
                          float *den_out, int nt, void *scratch, long long stride) {
    OVER_BANDS(H, atrous_rows(c, C, f, F, fs, var, valid, cs, cs_plane, H, W, rs, ps, step, h25, out, ors, ops, var_out,
                              den_out, y0, y1, (float *)scr));
}

/* ------------------------------------------------------------------------------------------
 * The gradients of one À-Trous level without variance or holes (backends.base.ATrousLevelGradOp;
 * torch_code.filter_atrous.level_grad is the same in torch), for rows [y0, y1) of one image.
 *
 * out_p = Σ_q w_pq c_q / D_p, w_pq = h_t exp(-(s_p |c_p - c_q|² + Σ_g fs_g |f_gp - f_gq|²)). With
 * gp = g / D (given), G_pq = Σ_k gp_pk (c_qk - out_pk) and E_pq = -w_pq G_pq:
 *   dc_p += Σ_q E_pq 2 s_p (c_p - c_q)          ds_p += Σ_q E_pq |c_p - c_q|²
 *   df_gp += Σ_q E_pq 2 fs_g (f_gp - f_gq)
 * as the centre, and as the neighbour q of p = q - o_t:
 *   dc_q += w_pq gp_p - E_pq 2 s_p (c_p - c_q)   df_gq -= E_pq 2 fs_g (f_gp - f_gq).
 * Each row gathers both (no two bands write one pixel); taps outside the image are left out as in
 * the forward. c, out and each guide f_g (G = F / 3 of them, 3 planes each) come with their own
 * row and plane strides (the forward's padded rows, or plain planes); gp, s, dc, df (F planes)
 * and ds are plain H x W planes. s: NULL (no colour weight), one value or a plane (CSM 0, 1, 2);
 * fs, df NULL when F = 0; df, ds NULL when not wanted.
 */
typedef struct {
    const float *cp, *cq, *fp[2], *fq[2], *op, *gp, *s; /* pixel x of the pair's p (or q) is [x] */
    const float *fs;                                     /* each guide's multiplier */
    size_t CPS, FPS[2], OPS, HW;                         /* plane strides of c, f_g, out, plain planes */
    float h;
} pair_t;

INLINE void grad_pairs(const int C, const int F, const int CSM, const pair_t *P, int xa, int xb, int centre,
                       float *restrict dc, float *restrict df, float *restrict ds) {
    const float *restrict cp = P->cp, *restrict cq = P->cq, *restrict op = P->op, *restrict gp = P->gp;
    const float *restrict s = P->s;
    const size_t CPS = P->CPS, OPS = P->OPS, HW = P->HW, FPS[2] = {P->FPS[0], P->FPS[1]};
    const float *fp[2] = {P->fp[0], P->fp[1]}, *fq[2] = {P->fq[0], P->fq[1]};
    const float h = P->h;
    float fs[2] = {0.0f, 0.0f};
    FOR8(g, F / 3, fs[g] = P->fs[g]);
    int x = xa;
    for (; x + VL <= xb; x += VL) { /* VL pixels at a time, the same sums on vectors */
        vf dcol = vsplat(0.0f), dfe = vsplat(0.0f), u[8], v[8], G = vsplat(0.0f);
        FOR8(k, C, { u[k] = vload(cp + k * CPS + x) - vload(cq + k * CPS + x); dcol += u[k] * u[k]; });
        FOR8(g, F / 3, {
            vf e = vsplat(0.0f);
            FOR8(k, 3, { v[3 * g + k] = vload(fp[g] + k * FPS[g] + x) - vload(fq[g] + k * FPS[g] + x);
                         e += v[3 * g + k] * v[3 * g + k]; });
            dfe += e * vsplat(fs[g]);
        });
        const vf sp = CSM == 2 ? vload(s + x) : vsplat(CSM == 1 ? s[0] : 0.0f);
        const vf w = vsplat(h) * vexp_neg(sp * dcol + dfe);
        FOR8(k, C, G += vload(gp + k * HW + x) * (vload(cq + k * CPS + x) - vload(op + k * OPS + x)));
        const vf E = -w * G, E2s = 2.0f * E * sp;
        if (centre) {
            FOR8(k, C, vstore(dc + k * HW + x, vload(dc + k * HW + x) + E2s * u[k]));
            if (df) FOR8(k, F, vstore(df + k * HW + x, vload(df + k * HW + x) + 2.0f * E * vsplat(fs[k / 3]) * v[k]));
            if (CSM && ds) vstore(ds + x, vload(ds + x) + E * dcol);
        } else {
            FOR8(k, C, vstore(dc + k * HW + x, vload(dc + k * HW + x) + w * vload(gp + k * HW + x) - E2s * u[k]));
            if (df) FOR8(k, F, vstore(df + k * HW + x, vload(df + k * HW + x) - 2.0f * E * vsplat(fs[k / 3]) * v[k]));
        }
    }
    for (; x < xb; ++x) {
        float dcol = 0.0f, dfe = 0.0f, u[8], v[8];
        FOR8(k, C, { u[k] = cp[k * CPS + x] - cq[k * CPS + x]; dcol += u[k] * u[k]; });
        FOR8(k, F, { v[k] = fp[k / 3][k % 3 * FPS[k / 3] + x] - fq[k / 3][k % 3 * FPS[k / 3] + x];
                     dfe += fs[k / 3] * v[k] * v[k]; });
        const float sp = CSM == 2 ? s[x] : CSM == 1 ? s[0] : 0.0f;
        const float w = h * exp_neg(sp * dcol + dfe);
        float G = 0.0f;
        FOR8(k, C, G += gp[k * HW + x] * (cq[k * CPS + x] - op[k * OPS + x]));
        const float E = -w * G, E2s = 2.0f * E * sp;
        if (centre) {
            FOR8(k, C, dc[k * HW + x] += E2s * u[k]);
            if (df) FOR8(k, F, df[k * HW + x] += 2.0f * E * fs[k / 3] * v[k]);
            if (CSM && ds) ds[x] += E * dcol;
        } else {
            FOR8(k, C, dc[k * HW + x] += w * gp[k * HW + x] - E2s * u[k]);
            if (df) FOR8(k, F, df[k * HW + x] -= 2.0f * E * fs[k / 3] * v[k]);
        }
    }
}

typedef void (*pairs_fn)(const pair_t *, int, int, int, float *, float *, float *);
#define PAIRS(C, F, CSM)                                                                                 \
    static void pairs_##C##_##F##_##CSM(const pair_t *P, int xa, int xb, int centre, float *dc, float *df, \
                                        float *ds) {                                                     \
        grad_pairs(C, F, CSM, P, xa, xb, centre, dc, df, ds);                                            \
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

/* rs (rows) and ps (planes) of c, out and the guides, in floats */
typedef struct {
    int crs, ors, frs[2];
    size_t cps, ops, fps[2];
} strides_t;

static void atrous_grad_rows(const float *c, int C, const float *const *f, int F, const float *fs, const float *s, int CSM,
                             const float *out, const float *gp, const strides_t *S, int H, int W, int step,
                             const float *h25, float *dc, float *df, float *ds, int y0, int y1) {
    const unsigned csr = ftz_begin();
    const size_t HW = (size_t)H * W;
    const pairs_fn pairs = pick_pairs(C, F, CSM);
    pair_t P;
    P.fs = fs, P.CPS = S->cps, P.OPS = S->ops, P.HW = HW;
    P.FPS[0] = S->fps[0], P.FPS[1] = S->fps[1];
    for (int y = y0; y < y1; ++y) {
        const size_t row = (size_t)y * W;
        for (int k = 0; k < C; ++k) memset(dc + k * HW + row, 0, sizeof(float) * W);
        for (int k = 0; k < F && df; ++k) memset(df + k * HW + row, 0, sizeof(float) * W);
        if (ds) memset(ds + row, 0, sizeof(float) * W);
        for (int t = 0; t < 25; ++t) {
            const int oy = (t / 5 - 2) * step, ox = (t % 5 - 2) * step;
            P.h = h25[t];
            for (int centre = 1; centre >= 0; --centre) {
                const int yo = centre ? y + oy : y - oy; /* the other pixel's row */
                if (yo < 0 || yo >= H) continue;
                const int sx = centre ? ox : -ox;        /* the other pixel's column offset */
                const int xa = sx < 0 ? -sx : 0, xb = sx > 0 ? W - sx : W;
                if (xa >= xb) continue;
                /* p: the centre of the pair, q: its neighbour; [x] indexes the pixel (y, x) */
                const ptrdiff_t yp = centre ? y : yo, yq = centre ? yo : y;
                const ptrdiff_t xp = centre ? 0 : -ox, xq = centre ? ox : 0;
                P.cp = c + yp * S->crs + xp, P.cq = c + yq * S->crs + xq;
                for (int g = 0; g < F / 3; ++g)
                    P.fp[g] = f[g] + yp * S->frs[g] + xp, P.fq[g] = f[g] + yq * S->frs[g] + xq;
                P.op = out + yp * S->ors + xp, P.gp = gp + yp * W + xp;
                P.s = CSM == 2 ? s + yp * W + xp : s;
                pairs(&P, xa, xb, centre, dc + row, df ? df + row : NULL, ds ? ds + row : NULL);
            }
        }
    }
    ftz_end(csr);
}

void torchgi_atrous_level_grad(const float *c, int crs, long long cps, int C, const float *f0, int f0rs,
                               long long f0ps, const float *f1, int f1rs, long long f1ps, int F, const float *fs,
                               const float *s, int CSM, const float *out, int ors, long long ops, const float *gp,
                               int H, int W, int step, const float *h25, float *dc, float *df, float *ds, int nt,
                               void *scratch, long long stride) {
    const strides_t S = {crs, ors, {f0rs, f1rs}, (size_t)cps, (size_t)ops, {(size_t)f0ps, (size_t)f1ps}};
    const float *const f[2] = {f0, f1};
    OVER_BANDS(H, atrous_grad_rows(c, C, f, F, fs, s, CSM, out, gp, &S, H, W, step, h25, dc, df, ds, y0, y1));
}
