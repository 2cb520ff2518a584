/* The sample allocation (backends.base.AllocateOp).
 * Compiled as part of native.c (one translation unit: see there). */
#include "common.h"

/* ------------------------------------------------------------------------------------------
 * Sample allocation (sampling.allocate) of one image: n_p = floor(q_p / Q · spare) plus one for
 * the `left` largest remainders (ties to the lowest index), plus min_samples; 0 off `eligible`
 * (NULL: every pixel). q: float32, or float64 with q_double. The torch code's double
 * arithmetic; Q is summed in CHUNKS fixed chunks of 8 interleaved partial sums, so the result
 * does not depend on the thread count. The remainders r in [0, 1) are ranked by the bucket
 * floor(r · 2^16) (exact and monotonic), then, within the one bucket that holds the cut, by
 * sorting its few members. Scratch: bucket, N uint16; hist, nt x 65536 uint32. Passes run on
 * nt OpenMP threads (see OVER_BANDS); with nt = 1 their `if` clauses keep them on the calling
 * thread (a forked one-thread child runs this: tests/backends/test_native.py). Returns 0, or -1 when
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

