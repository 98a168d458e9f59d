/* Many UMLS-MPM substeps in one call, returning to Python once per frame instead of after each
 * of about two hundred torch operators per substep (datagen/mpm/fused.py calls it):
 * - bsms_substeps: the whole of datagen.mpm.step.eulerian_step -- cell search, kernel (with the
 *   closest non-negative kernel where MLS weights go negative), stress, P2G, mirror folds, the
 *   nodal update with gravity, damping, walls, clamps, colliders and mirror ghosts, FLIP/PIC G2P,
 *   the F update, F-bar;
 * - bsms_reference_substeps (reference.h): the A-ULMPM total and adaptive modes between updates
 *   of the reference configuration.
 * The nodal side both share is nodes.h. The Python step is the reference: every formula here is
 * the one of the Python module named beside it, in the same order of operations where that order
 * is cheap to keep. A substep that needs Python (a particle lost from the mesh, a non-finite
 * result) stops the call *before* it changes the state, and the caller runs it in Python (which
 * raises with its advice). Node sums go through the fixed particle blocks of umls.c, so results
 * do not depend on the number of threads.
 */
#include "umls.c"
#include "nodes.h"

/* ----------------------------------------------------------------------------- cell search */
static inline __attribute__((always_inline)) double bary_in(const Locator *L, int64_t d, int64_t c, const double *x, double b[4]) {
    double rel[3], rest = 0.0, lowest;
    for (int a = 0; a < d; a++) rel[a] = x[a] - L->corner[c * d + a];
    for (int a = 0; a < d; a++) {
        double s = 0.0;
        for (int e = 0; e < d; e++) s += L->to_bary[(c * d + a) * d + e] * rel[e];
        b[1 + a] = s;
        rest += s;
    }
    b[0] = 1.0 - rest;
    lowest = b[0];
    for (int a = 1; a <= d; a++) lowest = b[a] < lowest ? b[a] : lowest;
    return lowest;
}

/* locate() of datagen.mpm.locate for one particle: its guessed cell, else the hash bucket's
 * candidate where it lies deepest. Returns the cell, or -1 (outside or not finite). */
static inline __attribute__((always_inline)) int64_t locate_one(const Locator *L, int64_t d, const double *x, int64_t guess, double *bary) {
    for (int a = 0; a < d; a++)
        if (!isfinite(x[a])) return -1;
    double b[4];
    if (guess >= 0 && bary_in(L, d, guess, x, b) >= -L->tol) {
        for (int a = 0; a <= d; a++) bary[a] = b[a];
        return guess;
    }
    int64_t key = 0;
    for (int a = 0; a < d; a++) {
        const int64_t i = (int64_t)floor((x[a] - L->origin[a]) / L->spacing);
        if (i < 0 || i >= L->shape[a]) return -1;
        key += i * L->strides[a];
    }
    if (key > L->n_buckets - 1) key = L->n_buckets - 1;
    int64_t best = -1;
    double deepest = -INFINITY, kept[4] = {0.0, 0.0, 0.0, 0.0};
    for (int64_t j = 0; j < L->per_bucket; j++) {
        const int64_t c = L->buckets[key * L->per_bucket + j];
        if (c < 0) continue;
        const double depth = bary_in(L, d, c, x, b);
        if (best < 0 || depth > deepest) {
            best = c;
            deepest = depth;
            for (int a = 0; a <= d; a++) kept[a] = b[a];
        }
    }
    if (best < 0 || !(deepest >= -L->tol)) return -1;
    for (int a = 0; a <= d; a++) bary[a] = kept[a];
    return best;
}

/* The per-particle work of the three particle loops of a substep. Each is always inlined and
 * called with a literal dimension (DIMS below), so that OpenMP's outlined loops still see
 * constant trip counts over axes, which the compiler unrolls and vectorises. */
#define DIMS(d, call) do { if ((d) == 2) { call(2); } else { call(3); } } while (0)

static inline __attribute__((always_inline)) int locate_and_stress(const Plan *S, Scratch *W, int64_t p,
                                                                   const double *x, const double *F,
                                                                   const int64_t *cell_in, const int64_t d) {
    W->cell[p] = locate_one(&S->locator, d, x + p * d, cell_in[p], W->bary + p * (d + 1));
    W->status[p] = W->cell[p] >= 0 ? 0 : 1;
    double coef[9];
    force_coef(S, p, F + p * d * d, coef);
    for (int k = 0; k < d * d; k++) W->coef[p * d * d + k] = (real)coef[k];
    return W->cell[p] < 0;
}

/* mls_linear_weights (datagen.mpm.kernels) of one particle's first `used` slots: moments from the
 * sample weights dd, the fit evaluated with e; w (K) and g (d, K), zero beyond `used`. */
static void mls_row(int64_t used, int64_t d, int64_t K, double (*r)[K], const double *dd, const double *e,
                    double *w, double (*g)[K]) {
    double total = 0.0, m[3] = {0.0, 0.0, 0.0}, q[3][3] = {{0.0}}, qi[3][3];
    for (int64_t k = 0; k < used; k++) total += dd[k];
    const int alive = total > 0;
    const double inv_total = 1.0 / (alive ? total : 1.0);
    for (int64_t k = 0; k < used; k++)
        for (int a = 0; a < d; a++) m[a] += r[a][k] * (dd[k] * inv_total);
    for (int64_t k = 0; k < used; k++) {
        const double share = dd[k] * inv_total;
        for (int a = 0; a < d; a++)
            for (int b = 0; b < d; b++) q[a][b] += (r[a][k] - m[a]) * share * (r[b][k] - m[b]);
    }
    if (!alive)
        for (int a = 0; a < d; a++)
            for (int b = 0; b < d; b++) q[a][b] = a == b;
    inverse((int)d, q, qi);
    for (int64_t k = 0; k < K; k++) {
        const double share = k < used ? e[k] * inv_total : 0.0;
        w[k] = share;
        for (int a = 0; a < d; a++) {
            double grad = 0.0;
            for (int b = 0; b < d; b++) grad += (k < used ? (r[b][k] - m[b]) * share : 0.0) * qi[a][b];
            g[a][k] = grad;
            w[k] -= grad * m[a];
        }
    }
}

/* nonnegative_mls (datagen.mpm.kernels) for particle p, whose MLS kernel from kernel_one has a
 * negative weight: the closest non-negative, linearly exact kernel by the primal active-set
 * method, started from the barycentric hat of its cell; its slots are overwritten. */
static void nonnegative_one(const Plan *S, Scratch *W, int64_t p, const double *x) {
    const int64_t K = S->K, d = S->d, PK = S->P * K, c = W->cell[p];
    const int64_t *ip = W->index + p * K;
    const double *bp = W->bary + p * (d + 1);
    double r[3][K], dd[K], start[K], sg[3][K], weight[K], grad[3][K], fit[K], fg[3][K], masked[K];
    uint8_t free_[K], candidate[K];
    int64_t used = 0;
    while (used < K && ip[used] >= 0) used++;
    for (int64_t k = 0; k < K; k++) {
        double q2 = 0.0, eta = 0.0;
        for (int a = 0; a < d; a++) {
            r[a][k] = k < used ? S->nodes[ip[k] * d + a] - x[p * d + a] : 0.0;
            q2 += r[a][k] * r[a][k];
        }
        const double q = sqrt(q2) * S->inv_h, t = 1.5 - q;
        for (int n = 0; n <= d; n++) eta += bp[n] * (double)S->adjacency[(c * (d + 1) + n) * K + k];
        dd[k] = k < used ? (q < 0.5 ? 0.75 - q * q : (q < 1.5 ? 0.5 * t * t : 0.0)) * eta : 0.0;
        start[k] = 0.0;
        for (int a = 0; a < d; a++) sg[a][k] = 0.0;
        for (int n = 0; n <= d; n++) {
            const int64_t corner = S->cells[c * (d + 1) + n];
            if (k < used && ip[k] == corner) {
                start[k] += bp[n];
                for (int a = 0; a < d; a++) sg[a][k] += S->bary_grad[(c * (d + 1) + n) * d + a];
            }
        }
        candidate[k] = dd[k] > 0;
        free_[k] = candidate[k] && (start[k] > 0 || W->weight[p * K + k] > 0);
        weight[k] = start[k];
        for (int a = 0; a < d; a++) grad[a][k] = sg[a][k];
    }
    int done = 0;
    for (int64_t iteration = 0; iteration < 4 * K && !done; iteration++) {
        for (int64_t k = 0; k < K; k++) masked[k] = dd[k] * free_[k];
        mls_row(used, d, K, r, masked, dd, fit, fg);
        double alpha = INFINITY;
        int partial = 0;
        for (int64_t k = 0; k < K; k++)
            if (free_[k] && fit[k] < 0) {
                const double ratio = weight[k] / (weight[k] - fit[k]);
                alpha = ratio < alpha ? ratio : alpha;
                partial = 1;
            }
        if (partial) { /* step towards the fit until the first weight reaches 0; that node leaves */
            alpha = alpha < 1.0 ? alpha : 1.0;
            for (int64_t k = 0; k < K; k++) {
                const double target = free_[k] ? fit[k] : 0.0;
                double stepped = (1 - alpha) * weight[k] + alpha * target;
                stepped = stepped > 0.0 ? stepped : 0.0;
                if (free_[k] && fit[k] < 0 && weight[k] / (weight[k] - fit[k]) <= alpha) {
                    stepped = 0.0;
                    free_[k] = 0;
                }
                weight[k] = stepped;
            }
            continue;
        }
        int64_t best = -1; /* the full step, then the node whose fit is most positive enters */
        for (int64_t k = 0; k < K; k++) {
            weight[k] = free_[k] ? fit[k] : 0.0;
            for (int a = 0; a < d; a++) grad[a][k] = fg[a][k] * free_[k];
            if (!free_[k] && candidate[k] && fit[k] > 1e-13 && (best < 0 || fit[k] > fit[best])) best = k;
        }
        if (best >= 0)
            free_[best] = 1;
        else
            done = 1;
    }
    for (int64_t k = 0; k < K; k++) {
        W->weight[p * K + k] = (real)(done ? weight[k] : start[k]);
        for (int a = 0; a < d; a++) W->grad[a * PK + p * K + k] = (real)(done ? grad[a][k] : sg[a][k]);
    }
}

static inline __attribute__((always_inline)) void kernel_and_p2g(const Plan *S, Scratch *W, int64_t p,
                                                                 const double *x, const double *v, real *out,
                                                                 real (*r)[S->K], real *s, const int64_t d) {
    const int64_t K = S->K;
    int64_t used = kernel_one(p, S->P, K, d, 1, S->inv_h, x, W->cell, W->status, W->bary, S->ring, S->adjacency,
                              S->nodes, W->index, W->weight, W->grad, r, s, W->negative + p);
    if (W->negative[p]) {
        nonnegative_one(S, W, p, x);
        used = K;
    }
    p2g_particle(p, used, K, d, S->P * K, W->index, W->weight, W->grad, 0, S->mass, v, W->coef, 0, out, ROW);
}

/* Eulerian G2P of particle p and F <- F + dt grad_v F (UMLS eq. 17). */
static inline __attribute__((always_inline)) void g2p_one(const Plan *S, Scratch *W, int64_t p, double dt,
                                                          const double *x, const double *v, const double *F,
                                                          const int64_t c, const int64_t d) {
    real gv[3][3];
    g2p_particle(W, W->index, W->weight, W->grad, p, S->K, S->P * S->K, dt, x, v, gv, c, d);
    const double *Fp = F + p * d * d;
    for (int a = 0; a < d; a++)
        for (int b = 0; b < d; b++) {
            double sum = 0.0;
            for (int e = 0; e < d; e++) sum += gv[a][e] * Fp[e * d + b];
            W->Fn[(p * d + a) * d + b] = Fp[a * d + b] + dt * sum;
        }
}

/* One substep from (x, v, F, cell_in) into W->xn, vn, Fn, cell; DONE or why it stopped. */
static int substep(const Plan *S, Scratch *W, int64_t step, double dt, const double *x, const double *v,
                   const double *F, const int64_t *cell_in) {
    const int64_t P = S->P, K = S->K, d = S->d, N = S->N, rows = 1 + 2 * d;
    int lost = 0;
    /* line 1: where each particle is, and the stress it carries */
#pragma omp parallel for schedule(static) num_threads(S->threads) reduction(| : lost)
    for (int64_t p = 0; p < P; p++) {
#define CALL(D) lost |= locate_and_stress(S, W, p, x, F, cell_in, D)
        DIMS(d, CALL);
#undef CALL
    }
    if (lost) return LOST;
    /* lines 1-3: the kernel and P2G [m, p, f_int] in one pass (bsms_umls_p2g's blocks) */
#pragma omp parallel num_threads(S->threads)
    {
        real r[3][K], s[K];
#pragma omp for schedule(static)
        for (int64_t block = 0; block < BLOCKS; block++) {
            real *out = W->scratch + block * ROW * N;
            for (int64_t j = 0; j < ROW * N; j++) out[j] = 0;
            for (int64_t p = block * P / BLOCKS; p < (block + 1) * P / BLOCKS; p++) {
#define CALL(D) kernel_and_p2g(S, W, p, x, v, out, r, s, D)
                DIMS(d, CALL);
#undef CALL
            }
        }
        add_blocks(N, rows, ROW, W->scratch, W->sums);
    }
    nodal_velocities(S, W, dt);
    nodal_constrain(S, W, step, S->nodes);
    const int64_t c = S->transfer_pic ? d : 2 * d;
    g2p_fields(S, W, c);
#pragma omp parallel for schedule(static) num_threads(S->threads)
    for (int64_t p = 0; p < P; p++) {
#define CALL(D) g2p_one(S, W, p, dt, x, v, F, c, D)
        DIMS(d, CALL);
#undef CALL
    }
    if (S->fbar) { /* datagen.mpm.inelastic: F <- (J_bar / J)^(1/d) F with J_bar the patch average of J */
        for (int64_t p = 0; p < P; p++) W->jac[p] = det3(d, W->Fn + p * d * d);
        bsms_patch_average(P, K, N, W->index, W->weight, W->jac, S->volume0, W->patch, W->node,
                           W->patch + BLOCKS * 2 * N, S->threads);
        for (int64_t p = 0; p < P; p++) {
            const double scale = pow(W->patch[BLOCKS * 2 * N + p] / W->jac[p], 1.0 / (double)d);
            for (int k = 0; k < d * d; k++) W->Fn[p * d * d + k] *= scale;
        }
    }
    int finite = 1;
    for (int64_t j = 0; j < P * d; j++) finite &= isfinite(W->xn[j]) && isfinite(W->vn[j]);
    for (int64_t j = 0; j < P * d * d; j++) finite &= isfinite(W->Fn[j]);
    return finite ? DONE : NONFINITE;
}

/* Run up to `steps` substeps of dt on x (P, d), v (P, d), F (P, d, d), cell (P), in place, from
 * time *time (advanced by dt per substep, as the Python step does). Returns a status (DONE, or
 * why the substep *done_out stopped before changing anything) and the substeps done. */
int bsms_substeps(const Plan *S, int64_t steps, double dt, double *x, double *v, double *F, int64_t *cell,
                  double *time, int64_t *done_out) {
    const int64_t P = S->P, K = S->K, d = S->d, N = S->N;
    *done_out = 0;
    if (d < 2 || d > 3 || K < 1) return BADSHAPE;
    Scratch W;
    int code = scratch_alloc(&W, P, K, d, N, 1) ? DONE : NOMEM;
    for (int64_t n = 0; code == DONE && n < steps; n++) {
        code = substep(S, &W, n, dt, x, v, F, cell);
        if (code != DONE) break;
        memcpy(x, W.xn, sizeof(double) * P * d);
        memcpy(v, W.vn, sizeof(double) * P * d);
        memcpy(F, W.Fn, sizeof(double) * P * d * d);
        memcpy(cell, W.cell, sizeof(int64_t) * P);
        *time += dt;
        *done_out = n + 1;
    }
    scratch_free(&W);
    return code;
}

#include "reference.h"
