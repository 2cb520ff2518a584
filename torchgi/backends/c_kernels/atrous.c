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
