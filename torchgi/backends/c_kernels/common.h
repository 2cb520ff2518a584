/* What every CPU kernel of torchgi shares: includes, the fast exp(-d) (scalar and vector), the
 * VL-wide vector types, the unrolling macros and OVER_BANDS, the band loop of every entry point.
 *
 * Planes are contiguous H x W float32; a multi-channel buffer is its planes back to back. The
 * maths of each kernel is exactly that of the torch code (backends/torch_code); only the order
 * of the sums differs (box sums accumulate in double here, so they are more accurate).
 */
#ifndef TORCHGI_COMMON_H
#define TORCHGI_COMMON_H

#include <float.h>
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
#define MINF(a, b) ((a) < (b) ? (a) : (b))


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


/* ------------------------------------------------------------------------------------------
 * Entry points: rows [0, H) in nt bands, one per thread. Built with -fopenmp the bands run on
 * OpenMP threads — the libgomp that torch has loaded, so torch's own worker threads (which spin
 * for a while after each torch op) take the bands instead of competing with them for the cores.
 * nt = 1 (or a build without OpenMP) runs the bands on the calling thread and never enters
 * OpenMP, so a forked child with one torch thread is safe. scratch: nt blocks of stride bytes.
 */
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


#endif /* TORCHGI_COMMON_H */
