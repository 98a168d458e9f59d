/* Many eulerian UMLS-MPM substeps in one call: the whole of datagen.mpm.step.eulerian_step
 * (cell search, kernel, stress, P2G, mirror folds, nodal update with gravity, damping, walls,
 * clamps, colliders and mirror ghosts, FLIP/PIC G2P, F update, F-bar) for the models
 * datagen/mpm/fused.py accepts, returning to Python once per frame instead of after each of
 * a few dozen torch operators per substep.
 *
 * The torch step is the reference: every formula here is the one of the Python module named
 * beside it, in the same order of operations where that order is cheap to keep. A substep that
 * needs what is not compiled (a particle outside its cell's neighbourhood of the hash search's
 * answer is fine; a particle lost from the mesh, a kernel with negative MLS weights, a
 * non-finite result) stops the call *before* it changes the state: the caller runs that substep
 * in torch (which raises or replaces the kernel) and calls again. Node sums go through the fixed
 * particle blocks of umls.c, so results do not depend on the number of threads.
 */
#include "umls.c"

#include <stdlib.h>
#include <string.h>

enum { STICKY = 0, SLIP = 1, SEPARATING = 2, MIRROR = 3, COLLIDERS = 4 };
enum { DONE = 0, LOST = 1, NONFINITE = 3, NOMEM = 4, BADSHAPE = 5, STALE_STRAIN = 6, STALE_CONTACT = 7 };
enum { LINEAR = 0, NEO_HOOKEAN = 1, FIXED_COROTATED = 2 };
enum { DISK = 0, BOX = 1, WEDGE = 2 };

/* One boundary condition of datagen.mpm.boundary (or, kind COLLIDERS, the place of the colliders
 * in the order). Mirror: ghosts = nodes, sources (count, per) and weights; wall (wall_count) the
 * wall nodes of a folded mirror (wall_count 0: not folded). */
typedef struct {
    int64_t kind, count;
    const int64_t *nodes;
    const double *normals; /* (count, d) */
    double friction;
    int64_t per;
    const int64_t *sources;
    const double *weights;
    int64_t wall_count;
    const int64_t *wall;
} Condition;

/* A collider of datagen.mpm.colliders: shape, size, friction, reach; centre (steps + 1, d) its
 * position at each substep's start time and velocity (steps, d) its mean velocity over the substep. */
typedef struct {
    int64_t shape;
    double size[3], friction, reach;
    const double *centre, *velocity;
} Collider;

/* datagen.mpm.locate.CellLocator */
typedef struct {
    const double *origin, *corner, *to_bary;
    double spacing, tol;
    const int64_t *shape, *strides, *buckets;
    int64_t n_buckets, per_bucket;
} Locator;

typedef struct {
    int64_t P, K, d, N, transfer_pic, fbar, n_conditions, n_colliders, threads;
    double inv_h, mass_floor, damping, gravity[3];
    const int64_t *ring;
    const uint8_t *adjacency;
    const double *nodes; /* (N, d) */
    const int64_t *cells; /* (C, d + 1) */
    const double *bary_grad; /* (C, d + 1, d) */
    const double *mass, *volume0, *mu, *lam;
    const int8_t *material;
    const Condition *conditions;
    const Collider *colliders;
    Locator locator;
} Plan;

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

/* ----------------------------------------------------------------------------- stress */
static inline __attribute__((always_inline)) double det3(int64_t d, const double *F) {
    if (d == 1) return F[0];
    if (d == 2) return F[0] * F[3] - F[1] * F[2];
    return F[0] * (F[4] * F[8] - F[5] * F[7]) + F[1] * (F[5] * F[6] - F[3] * F[8]) + F[2] * (F[3] * F[7] - F[4] * F[6]);
}

/* R of the polar decomposition F = R S (datagen.mpm.materials.rotation_part). */
static void rotation(int64_t d, const double *F, double *R) {
    if (d == 1) { R[0] = F[0] > 0 ? 1.0 : (F[0] < 0 ? -1.0 : 0.0); return; }
    if (d == 2) {
        double c = F[0] + F[3], s = F[2] - F[1];
        const double norm = sqrt(c * c + s * s);
        c /= norm; s /= norm;
        R[0] = c; R[1] = -s; R[2] = s; R[3] = c;
        return;
    }
    double A[9];
    memcpy(A, F, sizeof A);
    for (int it = 0; it < 12; it++) { /* R <- (g R + R^-T / g) / 2, g = |det R|^(-1/3) */
        const double det = det3(3, A), g = pow(fabs(det), -1.0 / 3.0);
        double invT[9];
        for (int k = 0; k < 3; k++) { /* column k of the adjugate = row k of adj^T: rows k+1 x k+2 */
            const double *a = A + 3 * ((k + 1) % 3), *b = A + 3 * ((k + 2) % 3);
            invT[3 * k + 0] = (a[1] * b[2] - a[2] * b[1]) / det;
            invT[3 * k + 1] = (a[2] * b[0] - a[0] * b[2]) / det;
            invT[3 * k + 2] = (a[0] * b[1] - a[1] * b[0]) / det;
        }
        for (int k = 0; k < 9; k++) A[k] = 0.5 * (g * A[k] + invT[k] / g);
    }
    memcpy(R, A, sizeof A);
}

/* coef = -V^0 tau (the Kirchhoff stress of datagen.mpm.materials) of particle p, row-major. */
static inline __attribute__((always_inline)) void force_coef(const Plan *S, int64_t p, const double *F, double *coef) {
    const int64_t d = S->d;
    const double mu = S->mu[p], lam = S->lam[p], v0 = -S->volume0[p];
    double tau[9];
    if (S->material[p] == NEO_HOOKEAN) { /* mu (F F^T - I) + lambda ln J I */
        const double log_j = log(det3(d, F));
        for (int a = 0; a < d; a++)
            for (int b = 0; b < d; b++) {
                double s = 0.0;
                for (int c = 0; c < d; c++) s += F[a * d + c] * F[b * d + c];
                tau[a * d + b] = a == b ? (s - 1.0) * mu + lam * log_j : s * mu;
            }
    } else if (S->material[p] == LINEAR) { /* (2 mu eps + lambda tr eps I) F^T, eps = sym F - I */
        double P[9], tr = 0.0;
        for (int a = 0; a < d; a++) tr += 0.5 * (F[a * d + a] + F[a * d + a]) - 1.0;
        for (int a = 0; a < d; a++)
            for (int b = 0; b < d; b++) {
                const double eps = 0.5 * (F[a * d + b] + F[b * d + a]) - (a == b ? 1.0 : 0.0);
                P[a * d + b] = 2.0 * mu * eps + (a == b ? lam * tr : 0.0);
            }
        for (int a = 0; a < d; a++)
            for (int b = 0; b < d; b++) {
                double s = 0.0;
                for (int c = 0; c < d; c++) s += P[a * d + c] * F[b * d + c];
                tau[a * d + b] = s;
            }
    } else { /* fixed corotated: 2 mu (F - R) F^T + lambda (J - 1) J I */
        double R[9];
        rotation(d, F, R);
        const double J = det3(d, F);
        for (int a = 0; a < d; a++)
            for (int b = 0; b < d; b++) {
                double s = 0.0;
                for (int c = 0; c < d; c++) s += (F[a * d + c] - R[a * d + c]) * F[b * d + c];
                tau[a * d + b] = 2.0 * mu * s + (a == b ? lam * (J - 1.0) * J : 0.0);
            }
    }
    for (int k = 0; k < d * d; k++) coef[k] = tau[k] * v0;
}

/* ----------------------------------------------------------------------------- colliders */
static inline __attribute__((always_inline)) double signed_distance(const Collider *c, int64_t d, const double *p, double *normal) {
    if (c->shape == DISK) {
        double r2 = 0.0;
        for (int a = 0; a < d; a++) r2 += p[a] * p[a];
        const double r = sqrt(r2);
        for (int a = 0; a < d; a++) normal[a] = r > 0 ? p[a] / r : (a == 0 ? 1.0 : 0.0);
        return r - c->size[0];
    }
    if (c->shape == BOX) {
        double sign[3], excess[3], beyond[3], out2 = 0.0, deepest = -INFINITY;
        int axis = 0;
        for (int a = 0; a < d; a++) {
            sign[a] = p[a] >= 0 ? 1.0 : -1.0;
            excess[a] = fabs(p[a]) - c->size[a];
            beyond[a] = excess[a] > 0.0 ? excess[a] : 0.0;
            out2 += beyond[a] * beyond[a];
            if (excess[a] > deepest) { deepest = excess[a]; axis = a; }
        }
        const double outside = sqrt(out2);
        for (int a = 0; a < d; a++)
            normal[a] = outside > 0 ? sign[a] * beyond[a] / outside : (a == axis ? sign[a] : 0.0);
        return outside + (deepest < 0.0 ? deepest : 0.0);
    }
    /* wedge: the convex polygon (0, 0), (hw, h), (-hw, h), counter-clockwise */
    const double corner[3][2] = {{0.0, 0.0}, {c->size[0], c->size[1]}, {-c->size[0], c->size[1]}};
    double nearest = INFINITY, highest = -INFINITY, away[2] = {0.0, 0.0}, out_j[2] = {0.0, 0.0};
    for (int k = 0; k < 3; k++) {
        const double ex = corner[(k + 1) % 3][0] - corner[k][0], ey = corner[(k + 1) % 3][1] - corner[k][1];
        const double length = sqrt(ex * ex + ey * ey), ox = ey / length, oy = -ex / length;
        const double rx = p[0] - corner[k][0], ry = p[1] - corner[k][1];
        const double height = rx * ox + ry * oy;
        double along = (rx * ex + ry * ey) / (length * length);
        along = along < 0.0 ? 0.0 : (along > 1.0 ? 1.0 : along);
        const double gx = rx - along * ex, gy = ry - along * ey, dist = sqrt(gx * gx + gy * gy);
        if (dist < nearest) { nearest = dist; away[0] = gx; away[1] = gy; }
        if (height > highest) { highest = height; out_j[0] = ox; out_j[1] = oy; }
    }
    if (highest <= 0) {
        normal[0] = out_j[0]; normal[1] = out_j[1];
        return highest;
    }
    const double scale = nearest > 0 ? nearest : 1.0;
    normal[0] = away[0] / scale; normal[1] = away[1] / scale;
    return nearest;
}

/* Collider.apply on the active nodes: separating contact with Coulomb friction. */
static inline __attribute__((always_inline)) void apply_collider(const Plan *S, const Collider *c, int64_t step,
                                                                 const double *nodes, double *v,
                                                                 const uint8_t *active) {
    const int64_t d = S->d, N = S->N;
    const double *centre = c->centre + step * d, *u = c->velocity + step * d;
    const double reach = c->reach * (1 + 1e-9);
    for (int64_t i = 0; i < N; i++) {
        if (!active[i]) continue;
        double p[3], r2 = 0.0, n[3];
        for (int a = 0; a < d; a++) {
            p[a] = nodes[i * d + a] - centre[a];
            r2 += p[a] * p[a];
        }
        if (!(sqrt(r2) <= reach)) continue;
        if (!(signed_distance(c, d, p, n) <= 0)) continue;
        double w[3], wn = 0.0, t[3], speed2 = 0.0;
        for (int a = 0; a < d; a++) {
            w[a] = v[a * N + i] - u[a];
            wn += w[a] * n[a];
        }
        for (int a = 0; a < d; a++) {
            t[a] = w[a] - wn * n[a];
            speed2 += t[a] * t[a];
        }
        const double speed = sqrt(speed2);
        double scale = 1.0 + c->friction * wn / (speed > 0 ? speed : 1.0);
        scale = scale > 0.0 ? scale : 0.0;
        for (int a = 0; a < d; a++) v[a * N + i] = u[a] + (wn < 0 ? scale * t[a] : w[a]);
    }
}

/* ----------------------------------------------------------------------------- node conditions */
static inline __attribute__((always_inline)) void apply_mirror(const Condition *m, int64_t d, int64_t N, double *v) {
    for (int64_t g = 0; g < m->count; g++)
        for (int a = 0; a < d; a++) {
            double s = 0.0;
            for (int64_t k = 0; k < m->per; k++) s += v[a * N + m->sources[g * m->per + k]] * m->weights[g * m->per + k];
            v[a * N + m->nodes[g]] = -s;
        }
}

static inline __attribute__((always_inline)) void apply_condition(const Condition *c, int64_t d, int64_t N, double *v) {
    if (c->kind == MIRROR) { apply_mirror(c, d, N, v); return; }
    for (int64_t j = 0; j < c->count; j++) {
        const int64_t i = c->nodes[j];
        if (c->kind == STICKY) {
            for (int a = 0; a < d; a++) v[a * N + i] = 0.0;
            continue;
        }
        const double *n = c->normals + j * d;
        double vn = 0.0, t[3], speed2 = 0.0;
        for (int a = 0; a < d; a++) vn += v[a * N + i] * n[a];
        for (int a = 0; a < d; a++) {
            t[a] = v[a * N + i] - vn * n[a];
            speed2 += t[a] * t[a];
        }
        if (c->kind == SLIP) {
            for (int a = 0; a < d; a++) v[a * N + i] = t[a];
            continue;
        }
        if (!(vn > 0)) continue; /* separating: only motion into the wall is stopped */
        const double speed = sqrt(speed2);
        double scale = 1.0 - c->friction * vn / (speed > 1e-300 ? speed : 1e-300);
        scale = scale > 0.0 ? scale : 0.0;
        for (int a = 0; a < d; a++) v[a * N + i] = scale * t[a];
    }
}

/* ----------------------------------------------------------------------------- one substep */
typedef struct {
    int64_t *index, *cell;
    double *weight, *grad, *bary, *coef, *sums, *scratch, *v, *v_new, *fields, *xn, *vn, *Fn, *patch, *node, *jac;
    int8_t *status;
    uint8_t *negative, *active;
} Scratch;

/* The per-particle work of the three particle loops of a substep. Each is always inlined and
 * called with a literal dimension (DIMS below), so that OpenMP's outlined loops still see
 * constant trip counts over axes, which the compiler unrolls and vectorises. */
#define DIMS(d, call) do { if ((d) == 2) { call(2); } else { call(3); } } while (0)

static inline __attribute__((always_inline)) int locate_and_stress(const Plan *S, Scratch *W, int64_t p,
                                                                   const double *x, const double *F,
                                                                   const int64_t *cell_in, const int64_t d) {
    W->cell[p] = locate_one(&S->locator, d, x + p * d, cell_in[p], W->bary + p * (d + 1));
    W->status[p] = W->cell[p] >= 0 ? 0 : 1;
    force_coef(S, p, F + p * d * d, W->coef + p * d * d);
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
        W->weight[p * K + k] = done ? weight[k] : start[k];
        for (int a = 0; a < d; a++) W->grad[a * PK + p * K + k] = done ? grad[a][k] : sg[a][k];
    }
}

static inline __attribute__((always_inline)) void kernel_and_p2g(const Plan *S, Scratch *W, int64_t p,
                                                                 const double *x, const double *v, double *out,
                                                                 double (*r)[S->K], double *s, const int64_t d) {
    const int64_t K = S->K;
    int64_t used = kernel_one(p, S->P, K, d, 1, S->inv_h, x, W->cell, W->status, W->bary, S->ring, S->adjacency,
                              S->nodes, W->index, W->weight, W->grad, r, s, W->negative + p);
    if (W->negative[p]) {
        nonnegative_one(S, W, p, x);
        used = K;
    }
    p2g_particle(p, used, K, d, S->P * K, W->index, W->weight, W->grad, 0, S->mass, v, W->coef, 0, out);
}

/* G2P of particle p (datagen.mpm.transfers.g2p_flip / g2p_pic) from the node-major fields
 * [v_new, v_new - v] (c = 2d; PIC: [v_new], c = d), and F <- F + dt grad_v F. */
static inline __attribute__((always_inline)) void g2p_one(const Plan *S, Scratch *W, int64_t p, double dt,
                                                          const double *x, const double *v, const double *F,
                                                          const int64_t c, const int64_t d) {
    const int64_t K = S->K, PK = S->P * K;
    double acc[6] = {0.0}, gv[3][3] = {{0.0}};
    for (int64_t k = 0; k < K; k++) {
        const int64_t i = W->index[p * K + k];
        if (i < 0) continue;
        const double w = W->weight[p * K + k];
        const double *f = W->fields + i * c;
        for (int e = 0; e < c; e++) acc[e] += w * f[e];
        for (int b = 0; b < d; b++) {
            const double g = W->grad[b * PK + p * K + k];
            for (int a = 0; a < d; a++) gv[a][b] += f[a] * g;
        }
    }
    for (int a = 0; a < d; a++) {
        W->xn[p * d + a] = x[p * d + a] + dt * acc[a];
        W->vn[p * d + a] = c == d ? acc[a] : v[p * d + a] + acc[d + a];
    }
    const double *Fp = F + p * d * d;
    for (int a = 0; a < d; a++)
        for (int b = 0; b < d; b++) {
            double sum = 0.0;
            for (int e = 0; e < d; e++) sum += gv[a][e] * Fp[e * d + b];
            W->Fn[(p * d + a) * d + b] = Fp[a * d + b] + dt * sum;
        }
}

/* The nodal update (datagen.mpm.nodal.nodal_update) on the P2G sums W->sums: fold the mirror
 * ghosts' sums, velocities before (W->v) and after (W->v_new) the update, constrained. */
typedef struct Reference Reference;
static void apply_planes(const Plan *S, const Reference *R, const double *q, double *v);

static void nodal(const Plan *S, Scratch *W, int64_t step, double dt, const double *positions,
                  const Reference *R) {
    const int64_t d = S->d, N = S->N, rows = 1 + 2 * d;
    double *sums = W->sums;
    for (int64_t j = 0; j < S->n_conditions; j++) {
        const Condition *m = S->conditions + j;
        if (m->kind != MIRROR || m->wall_count == 0) continue;
        for (int64_t g = 0; g < m->count; g++) {
            const int64_t ghost = m->nodes[g];
            for (int64_t row = 0; row < rows; row++) {
                const double value = sums[row * N + ghost] * (row == 0 ? 1.0 : -1.0);
                for (int64_t k = 0; k < m->per; k++)
                    sums[row * N + m->sources[g * m->per + k]] += value * m->weights[g * m->per + k];
            }
        }
        for (int64_t g = 0; g < m->count; g++)
            for (int64_t row = 0; row < rows; row++) sums[row * N + m->nodes[g]] = 0.0;
    }
    for (int64_t j = 0; j < S->n_conditions; j++) {
        const Condition *m = S->conditions + j;
        if (m->kind != MIRROR || m->wall_count == 0) continue;
        for (int64_t w = 0; w < m->wall_count; w++)
            for (int64_t row = 1; row < rows; row++) sums[row * N + m->wall[w]] = 0.0;
    }
    double *vb = W->v, *va = W->v_new;
    for (int64_t i = 0; i < N; i++) {
        const double mass = sums[i];
        W->active[i] = mass > S->mass_floor;
        const double safe = W->active[i] ? mass : 1.0;
        for (int a = 0; a < d; a++) vb[a * N + i] = W->active[i] ? sums[(1 + a) * N + i] / safe : 0.0;
    }
    for (int64_t j = 0; j < S->n_conditions; j++)
        if (S->conditions[j].kind == MIRROR && S->conditions[j].wall_count) apply_mirror(S->conditions + j, d, N, vb);
    const double damp = 1.0 + S->damping * dt;
    for (int64_t i = 0; i < N; i++) {
        const double safe = W->active[i] ? sums[i] : 1.0;
        for (int a = 0; a < d; a++) {
            const double accel = sums[(1 + d + a) * N + i] / safe + S->gravity[a];
            double value = W->active[i] ? vb[a * N + i] + dt * accel : 0.0;
            if (S->damping != 0.0) value = value / damp;
            va[a * N + i] = value;
        }
    }
    if (R) apply_planes(S, R, positions, va); /* A-ULMPM: walls on the moved node positions, first */
    for (int64_t j = 0; j < S->n_conditions; j++) {
        const Condition *c = S->conditions + j;
        if (c->kind == COLLIDERS)
            for (int64_t k = 0; k < S->n_colliders; k++)
                apply_collider(S, S->colliders + k, step, positions, va, W->active);
        else
            apply_condition(c, d, N, va);
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
        double r[3][K], s[K];
#pragma omp for schedule(static)
        for (int64_t block = 0; block < BLOCKS; block++) {
            double *out = W->scratch + block * rows * N;
            for (int64_t j = 0; j < rows * N; j++) out[j] = 0.0;
            for (int64_t p = block * P / BLOCKS; p < (block + 1) * P / BLOCKS; p++) {
#define CALL(D) kernel_and_p2g(S, W, p, x, v, out, r, s, D)
                DIMS(d, CALL);
#undef CALL
            }
        }
        add_blocks(N, rows, W->scratch, W->sums);
    }
    nodal(S, W, step, dt, S->nodes, 0);
    const int64_t c = S->transfer_pic ? d : 2 * d;
    for (int64_t i = 0; i < N; i++)
        for (int a = 0; a < d; a++) {
            W->fields[i * c + a] = W->v_new[a * N + i];
            if (c > d) W->fields[i * c + d + a] = W->v_new[a * N + i] - W->v[a * N + i];
        }
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
    const int64_t P = S->P, K = S->K, d = S->d, N = S->N, rows = 1 + 2 * d;
    *done_out = 0;
    if (d < 2 || d > 3 || K < 1) return BADSHAPE;
    Scratch W;
    memset(&W, 0, sizeof W);
    W.index = malloc(sizeof(int64_t) * P * K);
    W.cell = malloc(sizeof(int64_t) * P);
    W.weight = malloc(sizeof(double) * P * K);
    W.grad = malloc(sizeof(double) * d * P * K);
    W.bary = malloc(sizeof(double) * P * (d + 1));
    W.coef = malloc(sizeof(double) * P * d * d);
    W.sums = malloc(sizeof(double) * rows * N);
    W.scratch = malloc(sizeof(double) * BLOCKS * rows * N);
    W.v = malloc(sizeof(double) * d * N);
    W.v_new = malloc(sizeof(double) * d * N);
    W.fields = malloc(sizeof(double) * 2 * d * N);
    W.xn = malloc(sizeof(double) * P * d);
    W.vn = malloc(sizeof(double) * P * d);
    W.Fn = malloc(sizeof(double) * P * d * d);
    W.patch = malloc(sizeof(double) * (BLOCKS * 2 * N + P));
    W.node = malloc(sizeof(double) * N);
    W.jac = malloc(sizeof(double) * P);
    W.status = malloc(P);
    W.negative = malloc(P);
    W.active = malloc(N);
    int code = DONE;
    if (!(W.index && W.cell && W.weight && W.grad && W.bary && W.coef && W.sums && W.scratch && W.v && W.v_new &&
          W.fields && W.xn && W.vn && W.Fn && W.patch && W.node && W.jac && W.status && W.negative && W.active))
        code = NOMEM;
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
    free(W.index); free(W.cell); free(W.weight); free(W.grad); free(W.bary); free(W.coef); free(W.sums);
    free(W.scratch); free(W.v); free(W.v_new); free(W.fields); free(W.xn); free(W.vn); free(W.Fn); free(W.patch);
    free(W.node); free(W.jac); free(W.status); free(W.negative); free(W.active);
    return code;
}

/* ----------------------------------------------------------------------------- A-ULMPM reference steps */
/* The reference configuration of datagen.mpm.reference between updates: its kernel (slots in the
 * layout of KernelResult), the wall planes (Model._walls) acting on the moved node positions, the
 * adaptive mode's triggers. Particle matrices F, F^{sn}, F^{0s} are stored by component (d, d, P). */
struct Reference {
    const int64_t *index;
    const double *weight, *grad; /* (P, K), (P, K), (d, P, K) */
    const uint8_t *support;      /* (N) the nodes in the kernel's support (Reference.active) */
    const double *rest;          /* (N, d) the background's nodes (q at s) */
    double wall_gap, epsilon, fraction, contact; /* contact: contact_margin h, < 0: no trigger */
    int64_t adaptive, n_planes, n_clusters, planes_due;
    const int64_t *plane_kind, *cluster; /* plane_kind: 0 sticky, 1 slip, 2 separating; cluster (N) */
    const double *plane_friction, *normal, *offset, *low, *high, *tangents, *lower, *upper, *gaps;
};

/* WallPlane.apply_to on the support's nodes each plane holds at their moved positions q (N, d)
 * (datagen.mpm.nodal.constrain with _wall_members), plane by plane. */
static void apply_planes(const Plan *S, const Reference *R, const double *q, double *v) {
    if (!R->planes_due) return;
    const int64_t d = S->d, N = S->N;
    for (int64_t j = 0; j < R->n_planes; j++) {
        const double *n = R->normal + j * d;
        for (int64_t i = 0; i < N; i++) {
            if (!R->support[i]) continue;
            double height = 0.0;
            for (int a = 0; a < d; a++) height += n[a] * q[i * d + a];
            height -= R->offset[j];
            if (!(height >= R->low[j] && height <= R->high[j])) continue;
            int inside = 1;
            for (int t = 0; t < d - 1; t++) {
                double along = 0.0;
                for (int a = 0; a < d; a++) along += R->tangents[(j * (d - 1) + t) * d + a] * q[i * d + a];
                inside &= along >= R->lower[j * (d - 1) + t] && along <= R->upper[j * (d - 1) + t];
            }
            if (!inside) continue;
            double vn = 0.0, tng[3], speed2 = 0.0;
            for (int a = 0; a < d; a++) vn += v[a * N + i] * n[a];
            for (int a = 0; a < d; a++) {
                tng[a] = v[a * N + i] - vn * n[a];
                speed2 += tng[a] * tng[a];
            }
            if (R->plane_kind[j] == STICKY) {
                for (int a = 0; a < d; a++) v[a * N + i] = 0.0;
            } else if (R->plane_kind[j] == SLIP) {
                for (int a = 0; a < d; a++) v[a * N + i] = tng[a];
            } else if (vn > 0) {
                const double speed = sqrt(speed2);
                double scale = 1.0 - R->plane_friction[j] * vn / (speed > 1e-300 ? speed : 1e-300);
                scale = scale > 0.0 ? scale : 0.0;
                for (int a = 0; a < d; a++) v[a * N + i] = scale * tng[a];
            }
        }
    }
}

/* inverse of the d x d matrix a (row-major) by the adjugate, as datagen.mpm.linalg.inv */
static inline void inverse_rm(int64_t d, const double *a, double *out) {
    if (d == 2) {
        const double det = a[0] * a[3] - a[1] * a[2];
        out[0] = a[3] / det; out[1] = -a[1] / det; out[2] = -a[2] / det; out[3] = a[0] / det;
        return;
    }
    const double det = det3(3, a);
    for (int k = 0; k < 3; k++) { /* column k of the adjugate: row k+1 x row k+2 */
        const double *r = a + 3 * ((k + 1) % 3), *t = a + 3 * ((k + 2) % 3);
        out[0 * 3 + k] = (r[1] * t[2] - r[2] * t[1]) / det;
        out[1 * 3 + k] = (r[2] * t[0] - r[0] * t[2]) / det;
        out[2 * 3 + k] = (r[0] * t[1] - r[1] * t[0]) / det;
    }
}

/* One reference-mode substep (datagen.mpm.reference.reference_step without a rebuild) from
 * x, v (P, d), F, Fsn, F0s (by component) and the moved nodes q (N, d) into W->xn, W->vn, Fn (P, d, d
 * row-major), Fsn_new (by component, in W->jac's neighbour buffer fsn). */
static int reference_substep(const Plan *S, const Reference *R, Scratch *W, int64_t step, double dt, const double *x,
                             const double *v, const double *F, const double *Fsn, const double *F0s, const double *q,
                             double *fsn_new) {
    const int64_t P = S->P, K = S->K, d = S->d, N = S->N, rows = 1 + 2 * d, PK = P * K, dd = d * d;
    /* the force stress tau (F^{sn})^-T times -V^0 (datagen.mpm.stress.force_stress) */
#pragma omp parallel for schedule(static) num_threads(S->threads)
    for (int64_t p = 0; p < P; p++) {
        double Fp[9], Sp[9], Si[9], tau[9];
        for (int k = 0; k < dd; k++) {
            Fp[k] = F[k * P + p];
            Sp[k] = Fsn[k * P + p];
        }
        force_coef(S, p, Fp, tau); /* -V^0 tau */
        inverse_rm(d, Sp, Si);
        for (int a = 0; a < d; a++)
            for (int b = 0; b < d; b++) {
                double sum = 0.0;
                for (int c = 0; c < d; c++) sum += tau[a * d + c] * Si[b * d + c];
                W->coef[p * dd + a * d + b] = sum;
            }
    }
#pragma omp parallel num_threads(S->threads)
    {
#pragma omp for schedule(static)
        for (int64_t block = 0; block < BLOCKS; block++) {
            double *out = W->scratch + block * rows * N;
            for (int64_t j = 0; j < rows * N; j++) out[j] = 0.0;
            for (int64_t p = block * P / BLOCKS; p < (block + 1) * P / BLOCKS; p++)
                p2g_particle(p, K, K, d, PK, R->index, R->weight, R->grad, 0, S->mass, v, W->coef, 0, out);
        }
        add_blocks(N, rows, W->scratch, W->sums);
    }
    nodal(S, W, step, dt, q, R);
    const int64_t c = S->transfer_pic ? d : 2 * d;
    for (int64_t i = 0; i < N; i++)
        for (int a = 0; a < d; a++) {
            W->fields[i * c + a] = W->v_new[a * N + i];
            if (c > d) W->fields[i * c + d + a] = W->v_new[a * N + i] - W->v[a * N + i];
        }
#pragma omp parallel for schedule(static) num_threads(S->threads)
    for (int64_t p = 0; p < P; p++) { /* G2P, F^{sn} += dt grad_s v, F = F^{sn} F^{0s} */
        double acc[6] = {0.0}, gv[3][3] = {{0.0}}, Sn[9], Z[9];
        for (int64_t k = 0; k < K; k++) {
            const int64_t i = R->index[p * K + k];
            if (i < 0) continue;
            const double w = R->weight[p * K + k];
            const double *f = W->fields + i * c;
            for (int e = 0; e < c; e++) acc[e] += w * f[e];
            for (int b = 0; b < d; b++) {
                const double g = R->grad[b * PK + p * K + k];
                for (int a = 0; a < d; a++) gv[a][b] += f[a] * g;
            }
        }
        for (int a = 0; a < d; a++) {
            W->xn[p * d + a] = x[p * d + a] + dt * acc[a];
            W->vn[p * d + a] = c == d ? acc[a] : v[p * d + a] + acc[d + a];
        }
        for (int a = 0; a < d; a++)
            for (int b = 0; b < d; b++) {
                Sn[a * d + b] = Fsn[(a * d + b) * P + p] + dt * gv[a][b];
                Z[a * d + b] = F0s[(a * d + b) * P + p];
            }
        for (int a = 0; a < d; a++)
            for (int b = 0; b < d; b++) {
                double sum = Sn[a * d] * Z[b];
                for (int e = 1; e < d; e++) sum += Sn[a * d + e] * Z[e * d + b];
                W->Fn[(p * d + a) * d + b] = sum;
                fsn_new[(a * d + b) * P + p] = Sn[a * d + b];
            }
    }
    if (S->fbar) { /* F-bar scales F^{sn} and F (datagen.mpm.inelastic.post_process) */
        for (int64_t p = 0; p < P; p++) W->jac[p] = det3(d, W->Fn + p * dd);
        bsms_patch_average(P, K, N, R->index, R->weight, W->jac, S->volume0, W->patch, W->node,
                           W->patch + BLOCKS * 2 * N, S->threads);
        for (int64_t p = 0; p < P; p++) {
            const double scale = pow(W->patch[BLOCKS * 2 * N + p] / W->jac[p], 1.0 / (double)d);
            for (int k = 0; k < dd; k++) {
                W->Fn[p * dd + k] *= scale;
                fsn_new[k * P + p] *= scale;
            }
        }
    }
    int finite = 1;
    for (int64_t j = 0; j < P * d; j++) finite &= isfinite(W->xn[j]) && isfinite(W->vn[j]);
    for (int64_t j = 0; j < P * dd; j++) finite &= isfinite(W->Fn[j]);
    return finite ? DONE : NONFINITE;
}

/* The adaptive mode's triggers after a step (datagen.mpm.reference._update_due). */
static int update_due(const Plan *S, const Reference *R, const double *fsn, const double *q, double drift) {
    const int64_t P = S->P, d = S->d, N = S->N;
    int64_t marked = 0;
    for (int64_t p = 0; p < P; p++) {
        double Sp[9];
        for (int k = 0; k < d * d; k++) Sp[k] = fsn[k * P + p];
        marked += fabs(det3(d, Sp) - 1.0) >= R->epsilon;
    }
    if ((double)marked / (double)P >= R->fraction) return STALE_STRAIN;
    const int64_t C = R->n_clusters;
    if (R->contact < 0 || C < 2) return DONE;
    double smallest = INFINITY;
    for (int64_t k = 0; k < C * C; k++) smallest = R->gaps[k] < smallest ? R->gaps[k] : smallest;
    if (2.0 * drift < smallest - R->contact) return DONE;
    double D[C];
    for (int64_t k = 0; k < C; k++) D[k] = 0.0;
    for (int64_t i = 0; i < N; i++) {
        if (R->cluster[i] < 0) continue;
        double r2 = 0.0;
        for (int a = 0; a < d; a++) r2 += (q[i * d + a] - R->rest[i * d + a]) * (q[i * d + a] - R->rest[i * d + a]);
        const double moved = sqrt(r2);
        D[R->cluster[i]] = moved > D[R->cluster[i]] ? moved : D[R->cluster[i]];
    }
    for (int64_t a = 0; a < C; a++)
        for (int64_t b = 0; b < C; b++)
            if (D[a] + D[b] >= R->gaps[a * C + b] - R->contact) return STALE_CONTACT;
    return DONE;
}

/* Up to `steps` reference-mode substeps on x, v (P, d), F, Fsn (by component), the moved nodes
 * q (d, N) and *drift, in place; stops after a substep that makes an update due (STALE_*), or
 * before one that is not finite. */
int bsms_reference_substeps(const Plan *S, Reference *R, int64_t steps, double dt, double *x, double *v, double *F,
                            double *Fsn, const double *F0s, double *q, double *drift, double *time,
                            int64_t *done_out) {
    const int64_t P = S->P, K = S->K, d = S->d, N = S->N, rows = 1 + 2 * d, dd = d * d;
    *done_out = 0;
    if (d < 2 || d > 3 || K < 1) return BADSHAPE;
    Scratch W;
    memset(&W, 0, sizeof W);
    W.coef = malloc(sizeof(double) * P * dd);
    W.sums = malloc(sizeof(double) * rows * N);
    W.scratch = malloc(sizeof(double) * BLOCKS * rows * N);
    W.v = malloc(sizeof(double) * d * N);
    W.v_new = malloc(sizeof(double) * d * N);
    W.fields = malloc(sizeof(double) * 2 * d * N);
    W.xn = malloc(sizeof(double) * P * d);
    W.vn = malloc(sizeof(double) * P * d);
    W.Fn = malloc(sizeof(double) * P * dd);
    W.patch = malloc(sizeof(double) * (BLOCKS * 2 * N + P));
    W.node = malloc(sizeof(double) * N);
    W.jac = malloc(sizeof(double) * P);
    W.active = malloc(N);
    double *fsn_new = malloc(sizeof(double) * P * dd), *qn = malloc(sizeof(double) * N * d);
    int code = DONE;
    if (!(W.coef && W.sums && W.scratch && W.v && W.v_new && W.fields && W.xn && W.vn && W.Fn && W.patch &&
          W.node && W.jac && W.active && fsn_new && qn))
        code = NOMEM;
    if (code == DONE)
        for (int64_t i = 0; i < N; i++)
            for (int a = 0; a < d; a++) qn[i * d + a] = q[a * N + i];
    for (int64_t n = 0; code == DONE && n < steps; n++) {
        R->planes_due = R->n_planes > 0 && *drift >= R->wall_gap;
        code = reference_substep(S, R, &W, n, dt, x, v, F, Fsn, F0s, qn, fsn_new);
        if (code != DONE) break;
        memcpy(x, W.xn, sizeof(double) * P * d);
        memcpy(v, W.vn, sizeof(double) * P * d);
        memcpy(Fsn, fsn_new, sizeof(double) * P * dd);
        for (int64_t p = 0; p < P; p++)
            for (int k = 0; k < dd; k++) F[k * P + p] = W.Fn[p * dd + k];
        double speed = 0.0; /* datagen.mpm.reference: nodes move with v_new, drift bounds how far */
        for (int64_t j = 0; j < d * N; j++) speed = fabs(W.v_new[j]) > speed ? fabs(W.v_new[j]) : speed;
        speed *= sqrt((double)d);
        for (int64_t i = 0; i < N; i++)
            for (int a = 0; a < d; a++) qn[i * d + a] += dt * W.v_new[a * N + i];
        *drift += dt * speed;
        *time += dt;
        *done_out = n + 1;
        if (R->adaptive) code = update_due(S, R, Fsn, qn, *drift);
    }
    if (code != NOMEM)
        for (int64_t i = 0; i < N; i++)
            for (int a = 0; a < d; a++) q[a * N + i] = qn[i * d + a];
    free(W.coef); free(W.sums); free(W.scratch); free(W.v); free(W.v_new); free(W.fields); free(W.xn); free(W.vn);
    free(W.Fn); free(W.patch); free(W.node); free(W.jac); free(W.active); free(fsn_new); free(qn);
    return code;
}
