/* The temporal accumulation (backends.base.AccumulateOp).
 * Compiled as part of native.c (one translation unit: see there). */
#include "common.h"

/* ---------------------------------------------------------------- temporal accumulation
 * One frame of torchgi.temporal's reprojection and accumulation (backends.base.AccumulateOp; the
 * same maths as torch_code.accumulation, tap by tap in the same order): the history's four
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


void torchgi_accumulate(const float *x, const float *bound, const float *motion, const float *normal, const float *depth,
                        const uint8_t *surface, const float *light, const float *output, const float *moments,
                        const float *length, const float *pn, const float *pd, const float *ps, int H, int W,
                        float alpha, float cap, float ntol, float dtol, float *out, int nt, void *scratch,
                        long long stride) {
    const accum_t A = {x, bound, motion, normal, depth, surface, light, output, moments, length, pn, pd, ps,
                       H, W, alpha, cap, ntol, dtol, out};
    OVER_BANDS(H, accumulate_rows(&A, y0, y1));
}
