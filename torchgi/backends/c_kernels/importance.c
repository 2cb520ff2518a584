/* The sampling importance map (backends.base.ImportanceOp).
 * Compiled as part of native.c (one translation unit: see there). */
#include "common.h"

/* ------------------------------------------------------------------------------------------
 * Sampling importance (torch_code.sampling._core) for rows [y0, y1) of one image:
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

void torchgi_importance(const float *n, const float *x, float sn, float sx, const float *hit, int H, int W, int lo,
                        int hi, float *out, int nt, void *scratch, long long stride) {
    OVER_BANDS(H, ((void)scr, importance_rows(n, x, sn, sx, hit, H, W, lo, hi, out, y0, y1)));
}
