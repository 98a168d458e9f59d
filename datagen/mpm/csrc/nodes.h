/* The nodal side of the compiled substeps (datagen/mpm/csrc/substeps.c, which includes this file
 * after umls.c): the plan's layout, the materials' stress, the colliders, the node conditions, a
 * substep's scratch, G2P over kernel slots and the nodal update. Shared by the eulerian substeps and
 * the A-ULMPM reference-mode substeps (reference.h). */
#include <stdlib.h>
#include <string.h>

enum { STICKY = 0, SLIP = 1, SEPARATING = 2, MIRROR = 3, COLLIDERS = 4 };
enum { DONE = 0, LOST = 1, NONFINITE = 3, NOMEM = 4, BADSHAPE = 5, STALE_STRAIN = 6, STALE_CONTACT = 7 };
enum { LINEAR = 0, NEO_HOOKEAN = 1, FIXED_COROTATED = 2 };
enum { DISK = 0, BOX = 1, WEDGE = 2 };
/* The row stride of the node-sum block copies and the G2P fields, in reals: a node's 1+2d <= 7
 * values padded to 8 and the arrays 64-byte aligned, so that a slot's scatter or gather touches one
 * cache line. */
#define ROW 8

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

/* ----------------------------------------------------------------------------- stress */
static inline __attribute__((always_inline)) double det3(int64_t d, const double *F) {
    if (d == 1) return F[0];
    if (d == 2) return F[0] * F[3] - F[1] * F[2];
    return F[0] * (F[4] * F[8] - F[5] * F[7]) + F[1] * (F[5] * F[6] - F[3] * F[8]) + F[2] * (F[3] * F[7] - F[4] * F[6]);
}

/* The inverse of the d x d matrix a (row-major) by umls.c's adjugate inverse, as datagen.mpm.linalg.inv. */
static inline void inverse_flat(int64_t d, const double *a, double *out) {
    double q[3][3], o[3][3];
    for (int r = 0; r < d; r++)
        for (int c = 0; c < d; c++) q[r][c] = a[r * d + c];
    inverse((int)d, q, o);
    for (int r = 0; r < d; r++)
        for (int c = 0; c < d; c++) out[r * d + c] = o[r][c];
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
        const double g = pow(fabs(det3(3, A)), -1.0 / 3.0);
        double inv[9];
        inverse_flat(3, A, inv);
        for (int a = 0; a < 3; a++)
            for (int b = 0; b < 3; b++) A[a * 3 + b] = 0.5 * (g * A[a * 3 + b] + inv[b * 3 + a] / g);
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
    real *weight, *grad, *coef, *scratch, *fields; /* slots, -V^0 stress, node-sum copies, G2P fields */
    double *bary, *sums, *v, *v_new, *xn, *vn, *Fn, *patch, *node, *jac;
    int8_t *status;
    uint8_t *negative, *active;
} Scratch;

/* malloc of `bytes` on a 64-byte boundary (a cache line). */
static void *aligned(size_t bytes) {
    return aligned_alloc(64, (bytes + 63) / 64 * 64);
}

/* Allocate a substep's scratch for P particles of K slots and N nodes (kernel: the eulerian step's
 * kernel slots and cell search too); 0 where memory runs out (scratch_free releases what was got). */
static int scratch_alloc(Scratch *W, int64_t P, int64_t K, int64_t d, int64_t N, int kernel) {
    const int64_t rows = 1 + 2 * d;
    memset(W, 0, sizeof *W);
    W->coef = malloc(sizeof(real) * P * d * d);
    W->sums = malloc(sizeof(double) * rows * N);
    W->scratch = aligned(sizeof(real) * BLOCKS * ROW * N);
    W->v = malloc(sizeof(double) * d * N);
    W->v_new = malloc(sizeof(double) * d * N);
    W->fields = aligned(sizeof(real) * ROW * N);
    W->xn = malloc(sizeof(double) * P * d);
    W->vn = malloc(sizeof(double) * P * d);
    W->Fn = malloc(sizeof(double) * P * d * d);
    W->patch = malloc(sizeof(double) * (BLOCKS * 2 * N + P));
    W->node = malloc(sizeof(double) * N);
    W->jac = malloc(sizeof(double) * P);
    W->active = malloc(N);
    int ok = W->coef && W->sums && W->scratch && W->v && W->v_new && W->fields && W->xn && W->vn && W->Fn &&
             W->patch && W->node && W->jac && W->active;
    if (kernel) {
        W->index = malloc(sizeof(int64_t) * P * K);
        W->cell = malloc(sizeof(int64_t) * P);
        W->weight = malloc(sizeof(real) * P * K);
        W->grad = malloc(sizeof(real) * d * P * K);
        W->bary = malloc(sizeof(double) * P * (d + 1));
        W->status = malloc(P);
        W->negative = malloc(P);
        ok = ok && W->index && W->cell && W->weight && W->grad && W->bary && W->status && W->negative;
    }
    return ok;
}

static void scratch_free(Scratch *W) {
    free(W->index); free(W->cell); free(W->weight); free(W->grad); free(W->bary); free(W->coef); free(W->sums);
    free(W->scratch); free(W->v); free(W->v_new); free(W->fields); free(W->xn); free(W->vn); free(W->Fn);
    free(W->patch); free(W->node); free(W->jac); free(W->status); free(W->negative); free(W->active);
}

/* G2P of particle p over its kernel slots (index, weight, grad in KernelResult's layout) from the
 * node-major fields W->fields, [v_new, v_new - v] (c = 2d; PIC: [v_new], c = d): x and v into
 * W->xn, W->vn (datagen.mpm.transfers.g2p_flip / g2p_pic), gv = sum v_new grad w^T. */
static inline __attribute__((always_inline)) void g2p_particle(const Scratch *W, const int64_t *index,
                                                               const real *weight, const real *grad,
                                                               int64_t p, int64_t K, int64_t PK, double dt,
                                                               const double *x, const double *v, real gv[3][3],
                                                               const int64_t c, const int64_t d) {
    real acc[6] = {0};
    for (int a = 0; a < 3; a++)
        for (int b = 0; b < 3; b++) gv[a][b] = 0;
    for (int64_t k = 0; k < K; k++) {
        const int64_t i = index[p * K + k];
        if (i < 0) continue;
        const real w = weight[p * K + k];
        const real *f = W->fields + i * ROW;
        for (int e = 0; e < c; e++) acc[e] += w * f[e];
        for (int b = 0; b < d; b++) {
            const real g = grad[b * PK + p * K + k];
            for (int a = 0; a < d; a++) gv[a][b] += f[a] * g;
        }
    }
    for (int a = 0; a < d; a++) {
        W->xn[p * d + a] = x[p * d + a] + dt * acc[a];
        W->vn[p * d + a] = c == d ? acc[a] : v[p * d + a] + acc[d + a];
    }
}

/* The node-major G2P fields [v_new, v_new - v] (PIC: [v_new]) of the nodal update's velocities. */
static void g2p_fields(const Plan *S, Scratch *W, int64_t c) {
    const int64_t d = S->d, N = S->N;
    for (int64_t i = 0; i < N; i++)
        for (int a = 0; a < d; a++) {
            W->fields[i * ROW + a] = (real)W->v_new[a * N + i];
            if (c > d) W->fields[i * ROW + d + a] = (real)(W->v_new[a * N + i] - W->v[a * N + i]);
        }
}

/* The nodal update (datagen.mpm.nodal.nodal_update) on the P2G sums W->sums, in two parts:
 * nodal_velocities folds the mirror ghosts' sums and gives the velocities before (W->v) and after
 * (W->v_new) the update, unconstrained; nodal_constrain applies the conditions to W->v_new in
 * constrain's order, the colliders at the node positions given. The A-ULMPM step applies its
 * wall planes between the two (reference.h). */
static void nodal_velocities(const Plan *S, Scratch *W, double dt) {
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
}

static void nodal_constrain(const Plan *S, Scratch *W, int64_t step, const double *positions) {
    const int64_t d = S->d, N = S->N;
    double *va = W->v_new;
    for (int64_t j = 0; j < S->n_conditions; j++) {
        const Condition *c = S->conditions + j;
        if (c->kind == COLLIDERS)
            for (int64_t k = 0; k < S->n_colliders; k++)
                apply_collider(S, S->colliders + k, step, positions, va, W->active);
        else
            apply_condition(c, d, N, va);
    }
}
