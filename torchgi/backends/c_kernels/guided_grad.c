/* The guided filter's gradients (backends.kernel_ops.GuidedGradOp): the adjoint of
 * torch_code.filter_guided's forward, given its inputs and the output's gradient g. Compiled as
 * part of native.c, after guided.c and pipeline.c (it uses their row routines and PART_BYTES).
 *
 * With centred I (n planes), p (Cs planes), N the pixels of a window and box^T(v) = Σ_window v / N
 * the box mean's transpose, the output q_c = Σ_i ā_ic I_i + b̄_c gives
 *   dI_i  = Σ_c g_c ā_ic + (the terms through the box means of I, I Iᵀ and I p, below),
 *   da_ic = box^T(g_c I_i),  db_c = box^T(g_c),
 * then per pixel the solve's adjoint (z = A^-1 (da - db mIᵀ), A symmetric, the LDLᵀ of the
 * forward) gives the gradients of the box means mI, mp, mII, mIp and ε, and one more box^T of
 * those K planes brings them back to I and p.
 *
 * Each band of output rows [y0, y1) streams two walks: the first slides the box sums of the
 * products and of g I / N, g / N over rows [y0 - r, y1 + r), solves for the coefficients as the
 * forward does (solve_row) and writes them and the K planes of the solve's adjoint (divided by N)
 * into rings of 2 r + 2 rows; the second, r rows behind, slides the sums of both rings (the
 * coefficients' for ā) and writes dI, dp. Nothing of image size is held. ε's gradient is summed
 * per band (doubles at the start of each band's scratch, PART_BYTES).
 */

typedef struct {
    int n, Cs, K, Q, H, W, r;
    const float *I, *p, *g;        /* centred guide (n planes), centred source (Cs), dL/dq (Cs) */
    const float *eps;              /* n values, > 0 */
    float unit;                    /* the variance rounding level (solve_row's) */
    float *dI, *dp;                /* n and Cs planes, each may be NULL */
    size_t HW;
} guided_grad_t;

/* The column sums of g_c I_i / N (k = i Cs + c) and g_c / N (k = n Cs + c) slide: + row yin, - row yout (< 0: none) */
static void add_adjoint(const guided_grad_t *T, int yin, int yout, const double *inv_cx, double *acc) {
    const int n = T->n, Cs = T->Cs, W = T->W;
    const int ys[2] = {yin, yout};
    for (int side = 0; side < 2; ++side) {
        const int y = ys[side];
        if (y < 0) continue;
        const double w = (side ? -1.0 : 1.0) / window_rows(y, T->r, T->H);
        const size_t row = (size_t)y * W;
        for (int i = 0; i <= n; ++i)
            for (int c = 0; c < Cs; ++c) {
                double *s = acc + (size_t)(i * Cs + c) * ACC_STRIDE(W);
                const float *gc = T->g + c * T->HW + row, *Ii = i < n ? T->I + i * T->HW + row : NULL;
                if (Ii)
                    for (int x = 0; x < W; ++x) s[x] += (double)gc[x] * Ii[x] * (inv_cx[x] * w);
                else
                    for (int x = 0; x < W; ++x) s[x] += (double)gc[x] * (inv_cx[x] * w);
            }
    }
}

/* The first walk at one row: from the product means m (K planes, add_products' order), the means
 * of g I / N and g / N (adj, Q planes) and the coefficients a of the row (planes HW apart), the
 * gradients of the K box means divided by N, into st (K planes of W floats), and ε's per pixel
 * into de (n rows of W). */
INLINE void adjoint_row(const int n, const int Cs, const float *m, const float *adj, const float *cx, float cy,
                        const float *coef, size_t HW, int W, const float *eps, float unit, float *st, float *de) {
    const int MW = MEAN_STRIDE(W), NP = n * (n + 1) / 2;
    const float *mI = m, *mp = m + (size_t)n * MW, *mII = m + (size_t)(n + Cs) * MW;
    float *sI = st, *sp = st + (size_t)n * W, *sII = sp + (size_t)Cs * W, *sIp = sII + (size_t)NP * W;
#pragma GCC ivdep
    for (int x = 0; x < W; ++x) {
        float L[4][4], D[4], e[4], mi[4], a[4][3], z[4][3], db[3], dmp[3], dmI[4];
        const float N = cx[x] * cy, invN = 1.0f / N;
        FOR8(i, n, mi[i] = mI[(size_t)i * MW + x]);
        ldl_factor(n, mI, mII, MW, x, eps, unit, L, D, e); /* the forward's (solve_row) */
        FOR8(i, n, FOR8(c, Cs, a[i][c] = coef[((size_t)i * Cs + c) * HW + x]));
        FOR8(c, Cs, { db[c] = adj[((size_t)n * Cs + c) * MW + x] * N; dmp[c] = db[c]; });
        /* b = mp - Σ_i a_i mI_i */
        FOR8(i, n, { float v = 0.0f; FOR8(c, Cs, v -= db[c] * a[i][c]); dmI[i] = v; });
        /* a = A^-1 (mIp - mI mp): z = A^-1 (da - db mI) */
        FOR8(c, Cs, {
            float yv[4];
            FOR8(i, n, {
                float v = adj[((size_t)i * Cs + c) * MW + x] * N - db[c] * mi[i];
                FOR8(q, i, v -= L[i][q] * yv[q]);
                yv[i] = v;
            });
            FOR8(ri, n, {
                const int i = n - 1 - ri;
                float v = yv[i] / D[i];
                FOR8(q, n, if (q > i) v -= L[q][i] * z[q][c]);
                z[i][c] = v;
            });
        });
        FOR8(i, n, FOR8(c, Cs, {
            const float mpc = mp[(size_t)c * MW + x];
            dmI[i] -= z[i][c] * mpc;
            dmp[c] -= z[i][c] * mi[i];
            sIp[((size_t)i * Cs + c) * W + x] = z[i][c] * invN;
        }));
        /* A = mII - mI mIᵀ + diag(ε_eff): dA = -z aᵀ, symmetrised below the diagonal */
        FOR8(i, n, FOR8(j, i + 1, {
            float dA = 0.0f;
            if (i != j) {
                FOR8(c, Cs, dA -= z[i][c] * a[j][c] + z[j][c] * a[i][c]);
                dmI[i] -= dA * mi[j];
                dmI[j] -= dA * mi[i];
                sII[(size_t)TRI(i, j) * W + x] = dA * invN;
            } else {
                FOR8(c, Cs, dA -= z[i][c] * a[i][c]);
                const float mii = mII[(size_t)TRI(i, i) * MW + x];
                const float raw = mii - mi[i] * mi[i] >= 0.0f ? 1.0f : 0.0f;
                const float from_eps = eps[i] >= mii * unit ? 1.0f : 0.0f;
                const float dvar = raw * dA;
                dmI[i] -= 2.0f * mi[i] * dvar;
                sII[(size_t)TRI(i, i) * W + x] = (dvar + (1.0f - from_eps) * dA * unit) * invN;
                de[(size_t)i * W + x] = from_eps * dA;
            }
        }));
        FOR8(i, n, sI[(size_t)i * W + x] = dmI[i] * invN);
        FOR8(c, Cs, sp[(size_t)c * W + x] = dmp[c] * invN);
    }
}

#define ADJOINT_NC(N, C)                                                                                      \
    static void adjoint_##N##_##C(const float *m, const float *adj, const float *cx, float cy, const float *coef, \
                                  size_t HW, int W, const float *eps, float unit, float *st, float *de) {     \
        adjoint_row(N, C, m, adj, cx, cy, coef, HW, W, eps, unit, st, de);                                    \
    }
#define ADJOINT_N(N) ADJOINT_NC(N, 1) ADJOINT_NC(N, 2) ADJOINT_NC(N, 3)
ADJOINT_N(1) ADJOINT_N(2) ADJOINT_N(3) ADJOINT_N(4)
typedef void (*adjoint_fn)(const float *, const float *, const float *, float, const float *, size_t, int,
                           const float *, float, float *, float *);
static const adjoint_fn ADJOINTS[4][3] = {{adjoint_1_1, adjoint_1_2, adjoint_1_3}, {adjoint_2_1, adjoint_2_2, adjoint_2_3},
                                          {adjoint_3_1, adjoint_3_2, adjoint_3_3}, {adjoint_4_1, adjoint_4_2, adjoint_4_3}};

/* A ring's column sums slide: + ring row yin, - ring row yout (< 0: none); the ring's rows hold
 * S planes of W, the first K slide */
static void add_ring(const float *ring, int R, int S, int K, int W, int yin, int yout, double *acc) {
    const float *rin = yin >= 0 ? ring + (size_t)(yin % R) * S * W : NULL;
    const float *rout = yout >= 0 ? ring + (size_t)(yout % R) * S * W : NULL;
    for (int k = 0; k < K; ++k) {
        double *s = acc + (size_t)k * ACC_STRIDE(W);
        const float *a = rin ? rin + (size_t)k * W : NULL, *b = rout ? rout + (size_t)k * W : NULL;
        if (a && b)
            for (int x = 0; x < W; ++x) s[x] += (double)a[x] - (double)b[x];
        else if (a)
            for (int x = 0; x < W; ++x) s[x] += a[x];
        else if (b)
            for (int x = 0; x < W; ++x) s[x] -= b[x];
    }
}

/* The second walk at output row y: T (the K box^T sums, as means times N), ā (n Cs box means), into dI, dp */
static void gradient_row(const guided_grad_t *T, const float *ms, const float *mc, const float *nx, int y) {
    const int n = T->n, Cs = T->Cs, W = T->W, MW = MEAN_STRIDE(W), NP = n * (n + 1) / 2;
    const size_t row = (size_t)y * W, HW = T->HW;
    const float *tI = ms, *tp = ms + (size_t)n * MW, *tII = tp + (size_t)Cs * MW, *tIp = tII + (size_t)NP * MW;
    if (T->dp)
        for (int c = 0; c < Cs; ++c) { /* dp_c = T_p + Σ_i T_Ip I_i */
            float *o = T->dp + c * HW + row;
            const float *t = tp + (size_t)c * MW;
            for (int x = 0; x < W; ++x) o[x] = t[x] * nx[x];
            for (int i = 0; i < n; ++i) {
                const float *u = tIp + ((size_t)i * Cs + c) * MW, *Ii = T->I + i * HW + row;
                for (int x = 0; x < W; ++x) o[x] += u[x] * nx[x] * Ii[x];
            }
        }
    if (!T->dI) return;
    for (int i = 0; i < n; ++i) { /* dI_i = Σ_c g_c ā_ic + T_I + Σ_c T_Ip p_c + Σ_j T_II (2 on the diagonal) I_j */
        float *o = T->dI + i * HW + row;
        const float *t = tI + (size_t)i * MW;
        for (int x = 0; x < W; ++x) o[x] = t[x] * nx[x];
        for (int c = 0; c < Cs; ++c) {
            const float *ab = mc + ((size_t)i * Cs + c) * MW, *gc = T->g + c * HW + row;
            const float *u = tIp + ((size_t)i * Cs + c) * MW, *pc = T->p + c * HW + row;
            for (int x = 0; x < W; ++x) o[x] += gc[x] * ab[x] + u[x] * nx[x] * pc[x];
        }
        for (int j = 0; j < n; ++j) {
            const float *u = tII + (size_t)(i >= j ? TRI(i, j) : TRI(j, i)) * MW, *Ij = T->I + j * HW + row;
            const float f = i == j ? 2.0f : 1.0f;
            for (int x = 0; x < W; ++x) o[x] += f * u[x] * nx[x] * Ij[x];
        }
    }
}

/* scratch: PART_BYTES of ε's partial sums (n doubles), then doubles acc (2 K + Q + n Cs rows of
 * ACC_STRIDE(W)) + inv_cx (W) + pre (W + 8), then floats means (as many rows of MEAN_STRIDE(W)),
 * cx (W), nx (W), de (n W) and the rings ((2 r + 2) (K + Q) W). */
static void guided_grad_rows(const guided_grad_t *T, int y0, int y1, void *scratch) {
    const unsigned csr = ftz_begin();
    const int n = T->n, Cs = T->Cs, K = T->K, Q = T->Q, H = T->H, W = T->W, r = T->r, R = 2 * r + 2, NA = n * Cs;
    double *part = (double *)scratch;
    double *accP = (double *)((char *)scratch + PART_BYTES), *accA = accP + (size_t)K * ACC_STRIDE(W);
    double *accS = accA + (size_t)Q * ACC_STRIDE(W), *accC = accS + (size_t)K * ACC_STRIDE(W);
    double *inv_cx = accC + (size_t)NA * ACC_STRIDE(W), *pre = inv_cx + W;
    float *mP = (float *)(pre + W + 8), *mA = mP + (size_t)K * MEAN_STRIDE(W);
    float *mS = mA + (size_t)Q * MEAN_STRIDE(W), *mC = mS + (size_t)K * MEAN_STRIDE(W);
    float *cx = mC + (size_t)NA * MEAN_STRIDE(W), *nx = cx + W, *de = nx + W, *ring = de + (size_t)n * W;
    float *ringC = ring + (size_t)R * K * W; /* the coefficients a_0..a_{n-1}, b of each ring row */
    column_counts(W, r, inv_cx);
    for (int x = 0; x < W; ++x) cx[x] = (float)(1.0 / inv_cx[x]);
    const guide_t G = planes_guide(T->I, n, T->HW);
    const float zeros[64] = {0};
    products_t P = {n, Cs, K, &G, T->p, {0, 0, 0, 0}, zeros, T->HW, W};
    memset(accP, 0, sizeof(double) * (size_t)(2 * K + Q + NA) * ACC_STRIDE(W));
    const int ys = y0 - r > 0 ? y0 - r : 0, ye = y1 + r < H ? y1 + r : H; /* the first walk's rows */
    for (int yy = ys - r - 1 > 0 ? ys - r - 1 : 0; yy <= ys + r - 1 && yy < H; ++yy) {
        add_products(&P, yy, -1, accP);
        add_adjoint(T, yy, -1, inv_cx, accA);
    }
    int next = ys; /* the first walk's next row */
    for (int y = y0; y < y1; ++y) {
        for (const int last = y + r < H ? y + r : H - 1; next <= last && next < ye; ++next) {
            if (next + r < H || next - r - 1 >= 0) {
                add_products(&P, next + r < H ? next + r : -1, next - r - 1, accP);
                add_adjoint(T, next + r < H ? next + r : -1, next - r - 1, inv_cx, accA);
            }
            const int cy = window_rows(next, r, H);
            float *coef = ringC + (size_t)(next % R) * Q * W;
            row_means(accP, K, W, r, cy, inv_cx, pre, mP);
            row_means(accA, Q, W, r, cy, inv_cx, pre, mA);
            for (int c0 = 0; c0 < Cs; c0 += 3) /* the forward's coefficients (coefficients_rows) */
                SOLVERS[n - 1][(Cs - c0 < 3 ? Cs - c0 : 3) - 1](c0, Cs, mP, W, T->eps, T->unit, coef, W, 0);
            ADJOINTS[n - 1][Cs - 1](mP, mA, cx, (float)cy, coef, W, W, T->eps, T->unit,
                                    ring + (size_t)(next % R) * K * W, de);
            if (next >= y0 && next < y1)
                for (int i = 0; i < n; ++i) {
                    double s = 0.0;
                    for (int x = 0; x < W; ++x) s += de[(size_t)i * W + x];
                    part[i] += s;
                }
        }
        const int yin = y + r < H ? y + r : -1, yout = y - r - 1;
        if (y == y0) { /* the second walk's sums: rows [y - r, y + r] of the rings */
            for (int yy = ys; yy <= y + r && yy < H; ++yy) {
                add_ring(ring, R, K, K, W, yy, -1, accS);
                if (T->dI) add_ring(ringC, R, Q, NA, W, yy, -1, accC);
            }
        } else if (yin >= 0 || yout >= 0) {
            add_ring(ring, R, K, K, W, yin, yout, accS);
            if (T->dI) add_ring(ringC, R, Q, NA, W, yin, yout, accC);
        }
        const int cy = window_rows(y, r, H);
        row_means(accS, K, W, r, cy, inv_cx, pre, mS);
        if (T->dI) row_means(accC, NA, W, r, cy, inv_cx, pre, mC);
        for (int x = 0; x < W; ++x) nx[x] = cx[x] * (float)cy;
        gradient_row(T, mS, mC, nx, y);
    }
    ftz_end(csr);
}

void torchgi_guided_grad(const float *I, const float *p, const float *g, int n, int Cs, int H, int W, int r,
                         const float *eps, float unit, float *dI, float *dp, int nt, void *scratch, long long stride) {
    const guided_grad_t T = {n, Cs, n + Cs + n * (n + 1) / 2 + n * Cs, (n + 1) * Cs, H, W, r, I, p, g, eps, unit,
                             dI, dp, (size_t)H * W};
    OVER_BANDS(H, guided_grad_rows(&T, y0, y1, scr));
}
