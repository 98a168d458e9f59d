/* The per-particle loops of a UMLS-MPM step, compiled: the kernel weights of
 * datagen.mpm.kernels.umls_kernel, the P2G / G2P sums over kernel slots of
 * datagen.mpm.transfers, and the guessed-cell test of datagen.mpm.locate.locate.
 *
 * Built on first use by datagen/mpm/native.py (cc -O3 -march=native -fopenmp -shared) and called
 * through ctypes; the torch code stays the reference (tests compare the two) and the fallback.
 * Arrays are C-contiguous float64 / int64 in the layouts of KernelResult (slot weights, gradients
 * and offsets, stress coefficients and node-sum copies in `real`, below): slot fields (P, K),
 * per-axis slot fields (d, P, K), -1 marking an empty slot. Every loop runs over particles
 * (OpenMP, static schedule); P2G sums into copies of the nodes over fixed particle blocks, added
 * in a fixed order, so that results do not depend on the number of threads.
 */
#include <math.h>
#include <stdint.h>
#include <tgmath.h>

/* `real`: the precision of the kernel's slots (weights, gradients), the stress coefficients, the
 * node sums' block copies and the G2P fields, and of the arithmetic over them -- double by default,
 * float where compiled with -DBSMS_REAL=float (datagen/mpm/fused.py's float32 build). Particle
 * positions, velocities, deformation gradients, the mesh and the node velocities stay double. */
#ifndef BSMS_REAL
#define BSMS_REAL double
#endif
typedef BSMS_REAL real;
#define RC(c) ((real)(c))  /* a constant in `real`, so float arithmetic is not widened to double */

#define AHEAD 4  /* particles ahead whose cell tables are prefetched */

/* Inverse of the d x d matrix q by the adjugate (as datagen.mpm.linalg.inv). */
static inline __attribute__((always_inline)) void inverse(int d, const double q[3][3], double out[3][3]) {
    if (d == 1) { out[0][0] = 1.0 / q[0][0]; return; }
    if (d == 2) {
        double det = q[0][0] * q[1][1] - q[0][1] * q[1][0];
        out[0][0] = q[1][1] / det; out[0][1] = -q[0][1] / det;
        out[1][0] = -q[1][0] / det; out[1][1] = q[0][0] / det;
        return;
    }
    double adj[3][3];
    for (int k = 0; k < 3; k++) {  /* column k of the adjugate: row k+1 x row k+2 */
        const double *a = q[(k + 1) % 3], *b = q[(k + 2) % 3];
        adj[0][k] = a[1] * b[2] - a[2] * b[1];
        adj[1][k] = a[2] * b[0] - a[0] * b[2];
        adj[2][k] = a[0] * b[1] - a[1] * b[0];
    }
    double det = q[0][0] * adj[0][0] + q[0][1] * adj[1][0] + q[0][2] * adj[2][0];
    for (int a = 0; a < 3; a++)
        for (int b = 0; b < 3; b++) out[a][b] = adj[a][b] / det;
}

/* The kernel of particle p (see bsms_umls_weights); r, s: scratch of K doubles per axis / one.
 * Writes p's slots of index, weight and grad; returns the number of slots used (0: no kernel)
 * and sets *neg when an MLS weight is negative. */
static inline __attribute__((always_inline)) int64_t kernel_one(int64_t p, int64_t P, int64_t K, int64_t d, int64_t use_eta, double inv_h,
                                 const double *restrict x, const int64_t *restrict cell,
                                 const int8_t *restrict status, const double *restrict bary,
                                 const int64_t *restrict ring, const uint8_t *restrict adjacency,
                                 const double *restrict nodes, int64_t *restrict index, real *restrict weight,
                                 real *restrict grad, real (*restrict r)[K], real *restrict s, uint8_t *neg) {
    const int64_t PK = P * K;
    if (p + AHEAD < P && status[p + AHEAD] == 0) {  /* cells are scattered in memory: fetch early */
        const int64_t next = cell[p + AHEAD];
        for (int64_t b = 0; b < K * 8; b += 64) __builtin_prefetch((const char *)(ring + next * K) + b);
        for (int64_t b = 0; b < (d + 1) * K; b += 64)
            __builtin_prefetch((const char *)(adjacency + next * (d + 1) * K) + b);
    }
    const int64_t c = status[p] == 0 ? cell[p] : -1;
    int64_t used = 0;  /* rings are left-packed: the first -1 ends the ring */
    if (c >= 0)
        while (used < K && ring[c * K + used] >= 0) used++;
    const int64_t *ring_c = ring + (c >= 0 ? c : 0) * K;
    const uint8_t *adj_c = adjacency + (c >= 0 ? c : 0) * (d + 1) * K;
    const double *xp = x + p * d, *bp = bary + p * (d + 1);
    int64_t *ip = index + p * K;
    real *wp = weight + p * K;
    for (int64_t k = 0; k < used; k++) ip[k] = ring_c[k];
    for (int64_t k = used; k < K; k++) ip[k] = -1;
    for (int64_t k = 0; k < used; k++) {  /* the offsets: differences of doubles, rounded once */
        const double *node = nodes + ring_c[k] * d;
        for (int a = 0; a < d; a++) r[a][k] = (real)(node[a] - xp[a]);
    }
    /* d_i = N(|r| / h) eta_i (UMLS eq. 32), written without inner loops or branches so that it
     * vectorises over the slots; the same operations in the same order as the Python kernel */
    const real ih = (real)inv_h, b0 = (real)bp[0], b1 = (real)bp[1], b2 = d > 1 ? (real)bp[2] : RC(0),
               b3 = d > 2 ? (real)bp[3] : RC(0);
    const uint8_t *e0 = adj_c, *e1 = adj_c + K, *e2 = d > 1 ? adj_c + 2 * K : adj_c,
                  *e3 = d > 2 ? adj_c + 3 * K : adj_c;
    real total = 0;
#pragma omp simd reduction(+:total)
    for (int64_t k = 0; k < used; k++) {
        real q2 = r[0][k] * r[0][k];
        if (d > 1) q2 += r[1][k] * r[1][k];
        if (d > 2) q2 += r[2][k] * r[2][k];
        const real q = sqrt(q2) * ih, t = RC(1.5) - q;
        real w = q < RC(0.5) ? RC(0.75) - q * q : RC(0.5) * t * t;
        w = q < RC(1.5) ? w : RC(0);
        real eta = b0 * (real)e0[k] + b1 * (real)e1[k];  /* read always: a branch would stop vectorising */
        if (d > 1) eta += b2 * (real)e2[k];
        if (d > 2) eta += b3 * (real)e3[k];
        w = use_eta ? w * eta : w;
        s[k] = w;
        total += w;
    }
    *neg = 0;
    if (!(total > 0)) {  /* lost particle: zero kernel */
        for (int64_t k = 0; k < K; k++) wp[k] = 0;
        for (int a = 0; a < d; a++)
            for (int64_t k = 0; k < K; k++) grad[a * PK + p * K + k] = 0;
        return 0;
    }
    const real inv_total = RC(1) / total;
    real m0 = 0, m1 = 0, m2 = 0;  /* mean offset (UMLS eqs. 22-29, block form) */
#pragma omp simd reduction(+:m0, m1, m2)
    for (int64_t k = 0; k < used; k++) {
        s[k] *= inv_total;  /* d_i / S */
        m0 += s[k] * r[0][k];
        if (d > 1) m1 += s[k] * r[1][k];
        if (d > 2) m2 += s[k] * r[2][k];
    }
    const real m[3] = {m0, m1, m2};
    real q00 = 0, q01 = 0, q02 = 0, q11 = 0, q12 = 0, q22 = 0;  /* covariance Q */
#pragma omp simd reduction(+:q00, q01, q02, q11, q12, q22)
    for (int64_t k = 0; k < used; k++) {
        const real a0 = r[0][k] - m0, a1 = d > 1 ? r[1][k] - m1 : RC(0), a2 = d > 2 ? r[2][k] - m2 : RC(0);
        r[0][k] = a0; r[1][k] = a1; r[2][k] = a2;
        q00 += s[k] * a0 * a0; q01 += s[k] * a0 * a1; q02 += s[k] * a0 * a2;
        q11 += s[k] * a1 * a1; q12 += s[k] * a1 * a2; q22 += s[k] * a2 * a2;
    }
    const double q[3][3] = {{q00, q01, q02}, {q01, q11, q12}, {q02, q12, q22}};  /* inverted in double */
    double qd[3][3] = {{0.0}};
    inverse((int)d, q, qd);
    real qi[3][3];
    for (int a = 0; a < 3; a++)
        for (int b = 0; b < 3; b++) qi[a][b] = (real)qd[a][b];
    uint8_t negative = 0;
    real *g0 = grad + p * K, *g1 = grad + PK + p * K, *g2 = grad + 2 * PK + p * K;
    for (int64_t k = 0; k < used; k++) {  /* grad w_i = d_i/S Q^-1 (r_i - m), w_i = d_i/S - m . grad w_i */
        real w = s[k];
        real ga[3] = {0, 0, 0};
        for (int a = 0; a < d; a++) {
            real g = 0;
            for (int b = 0; b < d; b++) g += qi[a][b] * r[b][k];
            ga[a] = g * s[k];
            w -= ga[a] * m[a];
        }
        g0[k] = ga[0];
        if (d > 1) g1[k] = ga[1];
        if (d > 2) g2[k] = ga[2];
        wp[k] = w;
        negative |= w < 0;
    }
    for (int64_t k = used; k < K; k++) wp[k] = 0;
    for (int a = 0; a < d; a++)
        for (int64_t k = used; k < K; k++) grad[a * PK + p * K + k] = 0;
    *neg = negative;
    return used;
}

/* Kernel: x (P, d); cell (P); status (P) int8, 0 = inside; bary (P, d+1); ring (C, K), left-packed;
 * adjacency (C, d+1, K) uint8; nodes (N, d) -> index (P, K), weight (P, K), grad (d, P, K),
 * negative (P) uint8: the particles with a negative MLS weight. The offsets x_i - x_p are not
 * written: only APIC reads them, and KernelResult computes them on first use. */
int bsms_umls_weights(int64_t P, int64_t K, int64_t d, int64_t use_eta, double inv_h,
                      const double *restrict x, const int64_t *restrict cell, const int8_t *restrict status,
                      const double *restrict bary, const int64_t *restrict ring,
                      const uint8_t *restrict adjacency, const double *restrict nodes,
                      int64_t *restrict index, real *restrict weight, real *restrict grad,
                      uint8_t *restrict negative, int64_t threads) {
    if (d < 1 || d > 3) return 1;
#pragma omp parallel num_threads(threads)
    {
        real r[3][K], s[K];  /* this particle's offsets x_i - x_p and sample weights d_i */
#pragma omp for schedule(static)
        for (int64_t p = 0; p < P; p++)
            kernel_one(p, P, K, d, use_eta, inv_h, x, cell, status, bary, ring, adjacency, nodes, index,
                       weight, grad, r, s, negative + p);
    }
    return 0;
}

/* P2G over kernel slots (datagen.mpm.transfers._p2g): sums (1+2d, N) += per slot
 *   [w m_p, w m_p (v_p + C_p r), coef_p grad w]   with coef = -V_p^0 stress (P, d, d) row-major,
 * C (P, d, d) the APIC matrix or NULL, r the slot offsets (d, P, K) (read only with C).
 * Empty slots (index < 0) are skipped. The particles are cut into BLOCKS fixed ranges, each
 * summed in particle order into its own node-major copy of the nodes (scratch: BLOCKS x N x
 * (1+2d) reals; one slot touches one or two cache lines), and the copies are added in block
 * order: the result does not depend on the number of threads. */
#define BLOCKS 4

/* P2G of particle p's first `slots` slots into the node-major block copy `out` (N rows of `stride`
 * >= 1+2d reals). */
static inline __attribute__((always_inline)) void p2g_particle(int64_t p, int64_t slots, int64_t K, int64_t d, int64_t PK,
                                const int64_t *restrict index, const real *restrict weight,
                                const real *restrict grad, const real *restrict offset,
                                const double *restrict mass, const double *restrict v, const real *restrict coef,
                                const double *restrict affine, real *restrict out, int64_t stride) {
    const real *cp = coef + p * d * d, mp = (real)mass[p];
    const double *ap = affine ? affine + p * d * d : 0;
    real vp[3];
    for (int a = 0; a < d; a++) vp[a] = (real)v[p * d + a];
    for (int64_t k = 0; k < slots; k++) {
        const int64_t i = index[p * K + k];
        if (i < 0) continue;
        const int64_t s = p * K + k;
        const real wm = weight[s] * mp;
        real g[3], r[3];
        for (int b = 0; b < d; b++) {
            g[b] = grad[b * PK + s];
            r[b] = ap ? offset[b * PK + s] : 0;
        }
        real *node = out + i * stride;
        node[0] += wm;
        for (int a = 0; a < d; a++) {
            real vel = vp[a], f = 0;
            for (int b = 0; b < d; b++) {
                if (ap) vel += (real)ap[a * d + b] * r[b];
                f += cp[a * d + b] * g[b];
            }
            node[1 + a] += wm * vel;
            node[1 + d + a] += f;
        }
    }
}

/* sums (rows, N) = the BLOCKS node-major copies in scratch (rows of `stride`) added in block order.
 * Called inside a parallel region (the loop over nodes is shared among its threads). */
static void add_blocks(int64_t N, int64_t rows, int64_t stride, const real *restrict scratch,
                       double *restrict sums) {
#pragma omp for schedule(static)
    for (int64_t i = 0; i < N; i++)
        for (int64_t j = 0; j < rows; j++) {
            double total = 0.0;
            for (int64_t block = 0; block < BLOCKS; block++) total += scratch[(block * N + i) * stride + j];
            sums[j * N + i] = total;
        }
}

int bsms_p2g(int64_t P, int64_t K, int64_t d, int64_t N,
             const int64_t *restrict index, const real *restrict weight, const real *restrict grad,
             const real *restrict offset, const double *restrict mass, const double *restrict v,
             const real *restrict coef, const double *restrict affine, double *restrict sums,
             real *restrict scratch, int64_t threads) {
    if (d < 1 || d > 3) return 1;
    const int64_t PK = P * K, rows = 1 + 2 * d;
#pragma omp parallel num_threads(threads)
    {
#pragma omp for schedule(static)
        for (int64_t block = 0; block < BLOCKS; block++) {
            real *out = scratch + block * rows * N;
            for (int64_t j = 0; j < rows * N; j++) out[j] = 0;
            for (int64_t p = block * P / BLOCKS; p < (block + 1) * P / BLOCKS; p++)
                p2g_particle(p, K, K, d, PK, index, weight, grad, offset, mass, v, coef, affine, out, rows);
        }
        add_blocks(N, rows, rows, scratch, sums);
    }
    return 0;
}

/* The kernel and the FLIP/PIC P2G in one pass (bsms_umls_weights, then bsms_p2g with affine NULL):
 * each particle's slots are summed into the nodes while they are still in cache, which saves
 * P2G's pass over the slot arrays. Particles with a negative MLS weight (negative[p] = 1) are
 * left out of the sums: their kernel is replaced afterwards and the caller adds them. Same
 * fixed particle blocks and block-order reduction as bsms_p2g (thread-count invariant). */
int bsms_umls_p2g(int64_t P, int64_t K, int64_t d, int64_t use_eta, double inv_h,
                  const double *restrict x, const int64_t *restrict cell, const int8_t *restrict status,
                  const double *restrict bary, const int64_t *restrict ring,
                  const uint8_t *restrict adjacency, const double *restrict nodes,
                  int64_t *restrict index, real *restrict weight, real *restrict grad,
                  uint8_t *restrict negative, int64_t N, const double *restrict mass, const double *restrict v,
                  const real *restrict coef, double *restrict sums, real *restrict scratch, int64_t threads) {
    if (d < 1 || d > 3) return 1;
    const int64_t PK = P * K, rows = 1 + 2 * d;
#pragma omp parallel num_threads(threads)
    {
        real r[3][K], s[K];
#pragma omp for schedule(static)
        for (int64_t block = 0; block < BLOCKS; block++) {
            real *out = scratch + block * rows * N;
            for (int64_t j = 0; j < rows * N; j++) out[j] = 0;
            for (int64_t p = block * P / BLOCKS; p < (block + 1) * P / BLOCKS; p++) {
                const int64_t used = kernel_one(p, P, K, d, use_eta, inv_h, x, cell, status, bary, ring,
                                                adjacency, nodes, index, weight, grad, r, s, negative + p);
                if (!negative[p])
                    p2g_particle(p, used, K, d, PK, index, weight, grad, 0, mass, v, coef, 0, out, rows);
            }
        }
        add_blocks(N, rows, rows, scratch, sums);
    }
    return 0;
}

/* G2P over kernel slots: for node fields stored node-major (N, c), per particle
 *   interp (P, c) = sum_k w f_i;  grad_v (P, d, d) = sum_k v_i (x) grad w  (v = the first d fields);
 *   moment (P, d, d) = sum_k w v_i (x) r  (APIC's B; skipped when moment is NULL). */
int bsms_g2p(int64_t P, int64_t K, int64_t d, int64_t N, int64_t c,
             const int64_t *restrict index, const real *restrict weight, const real *restrict grad,
             const real *restrict offset, const double *restrict field, double *restrict interp,
             double *restrict grad_v, double *restrict moment, int64_t threads) {
    if (d < 1 || d > 3 || c < d || c > 8 || N < 0) return 1;
    const int64_t PK = P * K;
#pragma omp parallel for schedule(static) num_threads(threads)
    for (int64_t p = 0; p < P; p++) {
        double acc[8] = {0.0}, gv[3][3] = {{0.0}}, bm[3][3] = {{0.0}};
        for (int64_t k = 0; k < K; k++) {
            const int64_t i = index[p * K + k];
            if (i < 0) continue;
            const int64_t s = p * K + k;
            const double w = weight[s];
            double f[8];
            for (int e = 0; e < c; e++) {
                f[e] = field[i * c + e];
                acc[e] += w * f[e];
            }
            for (int b = 0; b < d; b++) {
                const double g = grad[b * PK + s];
                for (int a = 0; a < d; a++) gv[a][b] += f[a] * g;
            }
            if (moment)
                for (int b = 0; b < d; b++) {
                    const double wr = w * offset[b * PK + s];
                    for (int a = 0; a < d; a++) bm[a][b] += f[a] * wr;
                }
        }
        for (int e = 0; e < c; e++) interp[p * c + e] = acc[e];
        for (int a = 0; a < d; a++)
            for (int b = 0; b < d; b++) {
                grad_v[(p * d + a) * d + b] = gv[a][b];
                if (moment) moment[(p * d + a) * d + b] = bm[a][b];
            }
    }
    return 0;
}

/* The guess test of datagen.mpm.locate.locate: barycentric coordinates of x (P, d) in the cells
 * guess (P) (-1: no guess) from each cell's corner (C, d) and to_bary (C, d, d) maps; a finite
 * particle whose coordinates are all >= -tol is inside: cell (P) = guess, bary (P, d+1) set,
 * else cell = -1 and bary = 0. */
int bsms_locate_guess(int64_t P, int64_t d, double tol, const double *restrict x, const int64_t *restrict guess,
                      const double *restrict corner, const double *restrict to_bary, int64_t *restrict cell,
                      double *restrict bary, int64_t threads) {
    if (d < 1 || d > 3) return 1;
#pragma omp parallel for schedule(static) num_threads(threads)
    for (int64_t p = 0; p < P; p++) {
        if (p + AHEAD < P && guess[p + AHEAD] >= 0) {  /* cells are scattered in memory: fetch early */
            __builtin_prefetch(to_bary + guess[p + AHEAD] * d * d);
            __builtin_prefetch(corner + guess[p + AHEAD] * d);
        }
        const int64_t c = guess[p];
        double b[4] = {1.0, 0.0, 0.0, 0.0}, lowest = INFINITY;
        int finite = 1;
        for (int a = 0; a < d; a++) finite &= isfinite(x[p * d + a]);
        if (c >= 0 && finite) {
            double rel[3];
            for (int a = 0; a < d; a++) rel[a] = x[p * d + a] - corner[c * d + a];
            double rest = 0.0;
            for (int a = 0; a < d; a++) {
                double s = 0.0;
                for (int e = 0; e < d; e++) s += to_bary[(c * d + a) * d + e] * rel[e];
                b[1 + a] = s;
                rest += s;
            }
            b[0] = 1.0 - rest;
            for (int a = 0; a <= d; a++) lowest = b[a] < lowest ? b[a] : lowest;
        }
        const int hit = c >= 0 && finite && lowest >= -tol;
        cell[p] = hit ? c : -1;
        for (int a = 0; a <= d; a++) bary[p * (d + 1) + a] = hit ? b[a] : 0.0;
    }
    return 0;
}

/* F-bar's patch average (datagen.mpm.inelastic.patch_average): with w+ the positive part of the
 * weights, node value u_i = sum w+ V_p f_p / sum w+ V_p (0 where nothing maps), and per particle
 * out_p = sum w+ u_i / sum w+. Node sums by fixed particle blocks as in P2G (scratch: BLOCKS x N
 * x 2 doubles); node: N doubles. */
int bsms_patch_average(int64_t P, int64_t K, int64_t N, const int64_t *restrict index,
                       const real *restrict weight, const double *restrict value, const double *restrict volume,
                       double *restrict scratch, double *restrict node, double *restrict out, int64_t threads) {
#pragma omp parallel num_threads(threads)
    {
#pragma omp for schedule(static)
        for (int64_t block = 0; block < BLOCKS; block++) {
            double *mine = scratch + block * 2 * N;
            for (int64_t j = 0; j < 2 * N; j++) mine[j] = 0.0;
            for (int64_t p = block * P / BLOCKS; p < (block + 1) * P / BLOCKS; p++)
                for (int64_t k = 0; k < K; k++) {
                    const int64_t i = index[p * K + k];
                    const double w = weight[p * K + k];
                    if (i < 0 || !(w > 0.0)) continue;
                    const double wv = w * volume[p];
                    mine[2 * i] += wv * value[p];
                    mine[2 * i + 1] += wv;
                }
        }
#pragma omp for schedule(static)
        for (int64_t i = 0; i < N; i++) {
            double num = 0.0, den = 0.0;
            for (int64_t block = 0; block < BLOCKS; block++) {
                num += scratch[block * 2 * N + 2 * i];
                den += scratch[block * 2 * N + 2 * i + 1];
            }
            node[i] = den > 0.0 ? num / den : 0.0;
        }
#pragma omp for schedule(static)
        for (int64_t p = 0; p < P; p++) {
            double num = 0.0, den = 0.0;
            for (int64_t k = 0; k < K; k++) {
                const int64_t i = index[p * K + k];
                const double w = weight[p * K + k];
                if (i < 0 || !(w > 0.0)) continue;
                num += w * node[i];
                den += w;
            }
            out[p] = num / den;
        }
    }
    return 0;
}
