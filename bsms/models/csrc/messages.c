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

#define EDGE_LOOP(H)                                                                       \
    for (int64_t k = 0; k < n_edges; ++k) {                                                \
        const float *pr = products + receivers[k] * 2 * (H);                               \
        const float *ps = products + senders[k] * 2 * (H) + (H);                           \
        const float *f = features + k * n_features;                                        \
        float h[H];                                                                        \
        for (int64_t j = 0; j < (H); ++j) h[j] = pr[j] + ps[j];                            \
        for (int64_t c = 0; c < n_features; ++c) {                                         \
            const float x = f[c];                                                          \
            const float *w = weight_t + c * (H);                                           \
            for (int64_t j = 0; j < (H); ++j) h[j] += x * w[j];                            \
        }                                                                                  \
        float *o = out + receivers[k] * (H);                                               \
        for (int64_t j = 0; j < (H); ++j) o[j] += h[j] > 0.0f ? h[j] : 0.0f;               \
    }

/* One function per width: a width known at compile time unrolls and vectorises the inner loops
 * (32, 64, 128, the widths bsms trains); any other width runs the same loop on a variable-length row. */
#define SUMS(NAME, H)                                                                                       \
    static void NAME(int64_t hidden, int64_t n_edges, int64_t n_features, const int64_t *senders,           \
                     const int64_t *receivers, const float *products, const float *features,              \
                     const float *weight_t, float *out) {                                                 \
        (void)hidden;                                                                                     \
        EDGE_LOOP(H)                                                                                      \
    }
SUMS(sums_32, 32)
SUMS(sums_64, 64)
SUMS(sums_128, 128)
SUMS(sums_any, hidden)

/* hidden: H, at most 1024. Returns 0, or 1 for a width it does not take. */
int bsms_edge_sums(int64_t n_edges, int64_t hidden, int64_t n_features, const int64_t *senders,
                   const int64_t *receivers, const float *products, const float *features,
                   const float *weight_t, float *out) {
    if (hidden < 1 || hidden > 1024) return 1;
    void (*sums)(int64_t, int64_t, int64_t, const int64_t *, const int64_t *, const float *, const float *,
                 const float *, float *) = hidden == 32    ? sums_32
                                           : hidden == 64  ? sums_64
                                           : hidden == 128 ? sums_128
                                                           : sums_any;
    sums(hidden, n_edges, n_features, senders, receivers, products, features, weight_t, out);
    return 0;
}

/* Normalised edge offsets, for inference: for every edge k = (s, r) and each of the node's
 * n_groups points of dimension dim (e.g. rest and world position), the offset x_r - x_s and
 * its length, laid out group by group as [offset, length], then (value - mean) / std per column.
 * points: (N, n_groups * dim); out: (E, n_groups * (dim + 1)). Returns 0, or 1 for dim > 3. */
int bsms_edge_offsets(int64_t n_edges, int64_t n_groups, int64_t dim, const float *points, const int64_t *senders,
                      const int64_t *receivers, const float *mean, const float *std, float *out) {
    if (dim < 1 || dim > 3) return 1;
    const int64_t width = n_groups * dim, columns = n_groups * (dim + 1);
    for (int64_t k = 0; k < n_edges; ++k) {
        const float *pr = points + receivers[k] * width, *ps = points + senders[k] * width;
        float *o = out + k * columns;
        for (int64_t g = 0; g < n_groups; ++g) {
            float squares = 0.0f;
            for (int64_t c = 0; c < dim; ++c) {
                const float delta = pr[g * dim + c] - ps[g * dim + c];
                o[g * (dim + 1) + c] = delta;
                squares += delta * delta;
            }
            o[g * (dim + 1) + dim] = sqrtf(squares);
        }
        for (int64_t c = 0; c < columns; ++c) o[c] = (o[c] - mean[c]) / std[c];
    }
    return 0;
}
