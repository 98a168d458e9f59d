/* Summed messages of one message pass, for inference (bsms/models/native.py).
 *
 * For every edge k = (s, r): h_k = relu(P[r, :H] + P[s, H:] + W_e f_k), and out[r] += h_k,
 * where P = [W_r v + b | W_s v] holds the node products of the edge MLP's first layer (the
 * caller computes them, one matrix product over the nodes) and W_e its edge-feature columns.
 * One pass over the edges, with no (E, H) array: the torch path writes and reads such an array
 * four times (gathered products, edge features added, ReLU, scatter to the receivers), and on
 * the narrow latents of a lean network memory traffic is what those passes cost.
 * Edges are taken in order, so each receiver's sum adds its edges in the order index_add_ does.
 */
#include <math.h>
#include <stdint.h>

/* An edge's two node indices, each checked against [0, n_nodes) before it is used: an edge out
 * of range stops the loop (the caller gets its number back, nothing outside ``out`` is written). */
#define CHECKED_ENDS(k)                                                                    \
    const int64_t r = receivers[k], s = senders[k];                                       \
    if ((uint64_t)r >= (uint64_t)n_nodes || (uint64_t)s >= (uint64_t)n_nodes) return (k) + 1;

/* How many edges ahead the loop prefetches the rows it will gather and add to: the rows of P and
 * out are scattered over arrays larger than the caches, and the loads of one edge are too few to
 * hide their latency (about a quarter of the loop's time on the press's finest level). */
#define AHEAD 16

/* Prefetch the ``n`` floats from ``p`` (one request per 64-byte line; never faults). */
#define PREFETCH_ROW(p, n, write)                                                          \
    for (int64_t q = 0; q < (n); q += 16) __builtin_prefetch((p) + q, (write));

/* ``groups`` G copies of the graph's latents share its edges (a frame and its mirror image): node
 * r's copy g is row r G + g of P and of out, and edge k's features for copy g are row k G + g of
 * the features. P's rows start stride floats apart (stride >= 2H: P may be the first 2H columns
 * of a wider product); out's rows are H wide, or H + 1 with ``counts``, whose last column then
 * counts each receiver's edges (what the edge MLP's last bias is multiplied by). NF: the number
 * of edge features, a constant where the function is specialised for it. */
#define EDGE_LOOP(H, NF)                                                                   \
    const int64_t width = (H) + (counts ? 1 : 0);                                          \
    for (int64_t k = 0; k < n_edges; ++k) {                                                \
        CHECKED_ENDS(k)                                                                    \
        if (k + AHEAD < n_edges) {                                                         \
            const uint64_t ra = (uint64_t)receivers[k + AHEAD], sa = (uint64_t)senders[k + AHEAD]; \
            if (ra < (uint64_t)n_nodes && sa < (uint64_t)n_nodes) {                        \
                for (int64_t g = 0; g < groups; ++g) {                                     \
                    PREFETCH_ROW(products + (ra * groups + g) * stride, (H), 0)            \
                    PREFETCH_ROW(products + (sa * groups + g) * stride + (H), (H), 0)      \
                }                                                                          \
                PREFETCH_ROW(out + ra * groups * width, groups * width, 1)                 \
            }                                                                              \
        }                                                                                  \
        for (int64_t g = 0; g < groups; ++g) {                                             \
            const float *pr = products + (r * groups + g) * stride;                        \
            const float *ps = products + (s * groups + g) * stride + (H);                  \
            const float *f = features + (k * groups + g) * (NF);                           \
            float h[H];                                                                    \
            for (int64_t j = 0; j < (H); ++j) h[j] = pr[j] + ps[j];                        \
            for (int64_t c = 0; c < (NF); ++c) {                                           \
                const float x = f[c];                                                      \
                const float *w = weight_t + c * (H);                                       \
                for (int64_t j = 0; j < (H); ++j) h[j] += x * w[j];                        \
            }                                                                              \
            float *o = out + (r * groups + g) * width;                                     \
            for (int64_t j = 0; j < (H); ++j) o[j] += h[j] > 0.0f ? h[j] : 0.0f;           \
            if (counts) o[H] += 1.0f;                                                      \
        }                                                                                  \
    }                                                                                      \
    return 0;

typedef int64_t (*sums_fn)(int64_t, int64_t, int64_t, int64_t, int64_t, int64_t, int, const int64_t *,
                           const int64_t *, const float *, const float *, const float *, float *);

/* One function per width and feature count: constants known at compile time unroll the inner
 * loops and keep h in registers (widths 32, 64, 128, the ones bsms trains, each with 3, 4, 6 or 8
 * features: contact and mesh edges in 2D and 3D); any other width or count runs the same loop
 * with the unknown one variable. */
#define SUMS(NAME, H, NF)                                                                                   \
    static int64_t NAME(int64_t n_nodes, int64_t n_edges, int64_t groups, int64_t hidden, int64_t n_features, \
                        int64_t stride, int counts, const int64_t *senders, const int64_t *receivers,      \
                        const float *products, const float *features, const float *weight_t, float *out) { \
        (void)hidden;                                                                                     \
        (void)n_features;                                                                                 \
        EDGE_LOOP(H, NF)                                                                                  \
    }
#define WIDTH(H)                              \
    SUMS(sums_##H##_3, H, 3)                  \
    SUMS(sums_##H##_4, H, 4)                  \
    SUMS(sums_##H##_6, H, 6)                  \
    SUMS(sums_##H##_8, H, 8)                  \
    SUMS(sums_##H##_any, H, n_features)       \
    static sums_fn sums_##H(int64_t n_features) { \
        return n_features == 3 ? sums_##H##_3 : n_features == 4 ? sums_##H##_4 : n_features == 6 ? sums_##H##_6 \
             : n_features == 8 ? sums_##H##_8 : sums_##H##_any; \
    }
WIDTH(32)
WIDTH(64)
WIDTH(128)
SUMS(sums_any, hidden, n_features)

/* hidden: H, at most 1024; stride >= 2H; groups >= 1. Returns 0; -1 for a width it does not take; k + 1
 * where edge k has an end outside [0, n_nodes) (out then holds the sums of the edges before it). */
int64_t bsms_edge_sums(int64_t n_nodes, int64_t n_edges, int64_t groups, int64_t hidden, int64_t n_features,
                       int64_t stride, int counts, const int64_t *senders, const int64_t *receivers,
                       const float *products, const float *features, const float *weight_t, float *out) {
    if (hidden < 1 || hidden > 1024 || stride < 2 * hidden || groups < 1) return -1;
    const sums_fn sums = hidden == 32    ? sums_32(n_features)
                       : hidden == 64  ? sums_64(n_features)
                       : hidden == 128 ? sums_128(n_features)
                                       : sums_any;
    return sums(n_nodes, n_edges, groups, hidden, n_features, stride, counts, senders, receivers, products, features,
                weight_t, out);
}

/* Normalised edge offsets, for inference: for every edge k = (s, r) and each of the node's
 * n_groups points of dimension dim (e.g. rest and world position), the offset x_r - x_s and
 * its length, laid out group by group as [offset, length], then (value - mean) / std per column.
 * One function per (dim, n_groups) of the models bsms builds (1 to 3 dimensions, one or two
 * groups: contact and mesh edges), the loops unrolled; any other group count runs the same loop
 * with it variable. */
#define OFFSETS_LOOP(DIM, GROUPS)                                                          \
    const int64_t width = (GROUPS) * (DIM), columns = (GROUPS) * ((DIM) + 1);              \
    const int64_t row = reflect ? 2 * columns : columns;                                   \
    for (int64_t k = 0; k < n_edges; ++k) {                                                \
        CHECKED_ENDS(k)                                                                    \
        const float *pr = points + r * width, *ps = points + s * width;                    \
        float *o = out + k * row;                                                          \
        float first[GROUPS];                                                               \
        for (int64_t g = 0; g < (GROUPS); ++g) {                                           \
            float squares = 0.0f;                                                          \
            for (int64_t c = 0; c < (DIM); ++c) {                                          \
                const float delta = pr[g * (DIM) + c] - ps[g * (DIM) + c];                 \
                o[g * ((DIM) + 1) + c] = delta;                                            \
                squares += delta * delta;                                                  \
            }                                                                              \
            first[g] = o[g * ((DIM) + 1)];                                                 \
            o[g * ((DIM) + 1) + (DIM)] = sqrtf(squares);                                   \
        }                                                                                  \
        for (int64_t c = 0; c < columns; ++c) o[c] = (o[c] - mean[c]) / std[c];            \
        if (reflect) {                                                                     \
            float *m = o + columns;                                                        \
            for (int64_t c = 0; c < columns; ++c) m[c] = o[c];                             \
            for (int64_t g = 0; g < (GROUPS); ++g) {                                       \
                const int64_t c = g * ((DIM) + 1);                                         \
                m[c] = (-first[g] - mean[c]) / std[c];                                     \
            }                                                                              \
        }                                                                                  \
    }                                                                                      \
    return 0;

#define OFFSETS(NAME, DIM, GROUPS)                                                                          \
    static int64_t NAME(int64_t n_nodes, int64_t n_edges, int64_t n_groups, int reflect, const float *points, \
                        const int64_t *senders, const int64_t *receivers, const float *mean, const float *std, \
                        float *out) {                                                                      \
        (void)n_groups;                                                                                    \
        OFFSETS_LOOP(DIM, GROUPS)                                                                          \
    }
typedef int64_t (*offsets_fn)(int64_t, int64_t, int64_t, int, const float *, const int64_t *, const int64_t *,
                              const float *, const float *, float *);
#define DIMENSION(D)                                  \
    OFFSETS(offsets_##D##_1, D, 1)                    \
    OFFSETS(offsets_##D##_2, D, 2)                    \
    OFFSETS(offsets_##D##_any, D, n_groups)
DIMENSION(1)
DIMENSION(2)
DIMENSION(3)

/* points: (N, n_groups * dim); out: (E, n_groups * (dim + 1)), or with ``reflect`` (E, 2 n_groups
 * (dim + 1)): each edge's inputs, then those of its mirror image (x -> -x: every offset's first
 * component negated before it is normalised, the lengths unchanged), the same values as the
 * inputs of reflected points. Returns 0; -1 for dim outside 1..3; k + 1 where edge k has an end
 * outside [0, n_nodes). */
int64_t bsms_edge_offsets(int64_t n_nodes, int64_t n_edges, int64_t n_groups, int64_t dim, int reflect,
                          const float *points, const int64_t *senders, const int64_t *receivers, const float *mean,
                          const float *std, float *out) {
    static const offsets_fn table[3][3] = {{offsets_1_1, offsets_1_2, offsets_1_any},
                                           {offsets_2_1, offsets_2_2, offsets_2_any},
                                           {offsets_3_1, offsets_3_2, offsets_3_any}};
    if (dim < 1 || dim > 3 || n_groups < 1) return -1;
    const offsets_fn offsets = table[dim - 1][n_groups == 1 ? 0 : n_groups == 2 ? 1 : 2];
    return offsets(n_nodes, n_edges, n_groups, reflect, points, senders, receivers, mean, std, out);
}
