/* The A-ULMPM total and adaptive modes' substeps between updates of the reference configuration
 * (datagen.mpm.reference.reference_step without a rebuild); part of substeps.c, after nodes.h. */

/* ----------------------------------------------------------------------------- A-ULMPM reference steps */
/* The reference configuration of datagen.mpm.reference between updates: its kernel (slots in the
 * layout of KernelResult), the wall planes (Model._walls) acting on the moved node positions, the
 * adaptive mode's triggers. Particle matrices F, F^{sn}, F^{0s} are stored by component (d, d, P). */
typedef struct {
    const int64_t *index;
    const real *weight, *grad;   /* (P, K), (P, K), (d, P, K) */
    const uint8_t *support;      /* (N) the nodes in the kernel's support (Reference.active) */
    const double *rest;          /* (N, d) the background's nodes (q at s) */
    double wall_gap, epsilon, fraction, contact; /* contact: contact_margin h, < 0: no trigger */
    int64_t adaptive, n_planes, n_clusters, planes_due;
    const int64_t *plane_kind, *cluster; /* plane_kind: 0 sticky, 1 slip, 2 separating; cluster (N) */
    const double *plane_friction, *normal, *offset, *low, *high, *tangents, *lower, *upper, *gaps;
} Reference;

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

/* One reference-mode substep (datagen.mpm.reference.reference_step without a rebuild) from
 * x, v (P, d), F, Fsn, F0s (by component) and the moved nodes q (N, d) into W->xn, W->vn, W->Fn
 * (P, d, d row-major) and fsn_new (by component). */
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
        inverse_flat(d, Sp, Si);
        for (int a = 0; a < d; a++)
            for (int b = 0; b < d; b++) {
                double sum = 0.0;
                for (int c = 0; c < d; c++) sum += tau[a * d + c] * Si[b * d + c];
                W->coef[p * dd + a * d + b] = (real)sum;
            }
    }
#pragma omp parallel num_threads(S->threads)
    {
#pragma omp for schedule(static)
        for (int64_t block = 0; block < BLOCKS; block++) {
            real *out = W->scratch + block * ROW * N;
            for (int64_t j = 0; j < ROW * N; j++) out[j] = 0;
            for (int64_t p = block * P / BLOCKS; p < (block + 1) * P / BLOCKS; p++)
                p2g_particle(p, K, K, d, PK, R->index, R->weight, R->grad, 0, S->mass, v, W->coef, 0, out, ROW);
        }
        add_blocks(N, rows, ROW, W->scratch, W->sums);
    }
    nodal_velocities(S, W, dt);
    apply_planes(S, R, q, W->v_new); /* walls on the moved node positions, first (datagen.mpm.nodal.constrain) */
    nodal_constrain(S, W, step, q);
    const int64_t c = S->transfer_pic ? d : 2 * d;
    g2p_fields(S, W, c);
#pragma omp parallel for schedule(static) num_threads(S->threads)
    for (int64_t p = 0; p < P; p++) { /* G2P, F^{sn} += dt grad_s v, F = F^{sn} F^{0s} */
        real gv[3][3];
        double Sn[9], Z[9];
        g2p_particle(W, R->index, R->weight, R->grad, p, K, PK, dt, x, v, gv, c, d);
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
    const int64_t P = S->P, K = S->K, d = S->d, N = S->N, dd = d * d;
    *done_out = 0;
    if (d < 2 || d > 3 || K < 1) return BADSHAPE;
    Scratch W;
    double *fsn_new = malloc(sizeof(double) * P * dd), *qn = malloc(sizeof(double) * N * d);
    int code = scratch_alloc(&W, P, K, d, N, 0) && fsn_new && qn ? DONE : NOMEM;
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
    scratch_free(&W);
    free(fsn_new);
    free(qn);
    return code;
}
