/* Compiled loops of the bi-stride hierarchy (bsms/graph/native.py): the pooled adjacency of a
 * coarse level, bit-parallel breadth-first distance sums, and contact edges carried one level
 * down. Each produces exactly what the scipy/csgraph/numpy code produces (bsms/graph/pooling.py,
 * bsms/graph/seeding.py, bsms/graph/contact.py); the tests compare.
 *
 * Graphs are CSR arrays with int64 row pointers and column indices. */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

typedef int64_t i64;
typedef int32_t i32;
typedef uint64_t u64;

/* The pooled adjacency of a coarse level: row r holds the kept nodes within two hops of kept
 * node r, its own bit cleared. closed (K x N, c_ptr/c_idx): rows of A + I at the kept nodes;
 * reach (N x K, r_ptr/r_idx): for each node v the kept nodes in N[v] (A + I), as kept indices.
 * Row r is the union of reach[v] over v in closed[r]. */

static int by_value(const void *a, const void *b) {
    i64 x = *(const i64 *)a, y = *(const i64 *)b;
    return (x > y) - (x < y);
}

/* Sparse levels: row r's kept indices into list (sorted), returning how many, with a bitset of
 * `words` words (all clear on entry and on return) to drop repeats. */
static i64 sparse_row(i64 r, const i64 *c_ptr, const i64 *c_idx, const i64 *r_ptr, const i64 *r_idx, u64 *seen,
                      i64 *list) {
    i64 n = 0;
    seen[r >> 6] |= (u64)1 << (r & 63); /* no diagonal */
    for (i64 a = c_ptr[r]; a < c_ptr[r + 1]; a++)
        for (i64 b = r_ptr[c_idx[a]]; b < r_ptr[c_idx[a] + 1]; b++) {
            i64 j = r_idx[b];
            u64 bit = (u64)1 << (j & 63);
            if (seen[j >> 6] & bit) continue;
            seen[j >> 6] |= bit;
            list[n++] = j;
        }
    seen[r >> 6] = 0;
    for (i64 i = 0; i < n; i++) seen[list[i] >> 6] = 0;
    if (n < 32) {
        for (i64 i = 1; i < n; i++) {
            i64 value = list[i], at = i;
            for (; at > 0 && list[at - 1] > value; at--) list[at] = list[at - 1];
            list[at] = value;
        }
    } else {
        qsort(list, (size_t)n, sizeof(i64), by_value);
    }
    return n;
}

static i64 row_count(const u64 *row, i64 words) {
    i64 total = 0;
    for (i64 w = 0; w < words; w++) total += __builtin_popcountll(row[w]);
    return total;
}

/* Sparse levels, two passes that build every row again: counts (K,) in pass 1 (out_ptr,
 * out_idx NULL); pass 2 (counts NULL) writes row r's sorted kept indices at out_idx[out_ptr[r]].
 * Returns 0, or 1 when memory runs out. */
int bsms_pooled_sparse(i64 n_kept, const i64 *c_ptr, const i64 *c_idx, const i64 *r_ptr, const i64 *r_idx,
                       i64 *counts, const i64 *out_ptr, i32 *out_idx) {
    i64 words = (n_kept + 63) / 64, longest = 0;
    for (i64 r = 0; r < n_kept; r++) {
        i64 total = 0;
        for (i64 a = c_ptr[r]; a < c_ptr[r + 1]; a++) total += r_ptr[c_idx[a] + 1] - r_ptr[c_idx[a]];
        longest = total > longest ? total : longest;
    }
    longest = longest < n_kept ? longest : n_kept;
    int failed = 0;
#pragma omp parallel reduction(| : failed)
    {
        u64 *seen = calloc((size_t)words, sizeof(u64));
        i64 *list = malloc((size_t)(longest + 1) * sizeof(i64));
        failed = !seen || !list;
#pragma omp for schedule(dynamic, 64)
        for (i64 r = 0; r < n_kept; r++) {
            if (!seen || !list) continue;
            i64 n = sparse_row(r, c_ptr, c_idx, r_ptr, r_idx, seen, list);
            if (counts) counts[r] = n;
            else
                for (i64 i = 0; i < n; i++) out_idx[out_ptr[r] + i] = (i32)list[i];
        }
        free(seen);
        free(list);
    }
    return failed;
}

/* Dense levels, two passes like the sparse ones (counts, then indices): rows are built in
 * column blocks of 512 kept nodes (8 words, one cache line per node). For each block a slice
 * of reach is laid out as bitsets (N cache lines, reused from block to block, so that it stays
 * in the core's cache and nothing of the size of the matrix is allocated), and row r's part of
 * the block is the OR of the slice's lines at closed[r]. reach rows must be sorted. Returns 0,
 * or 1 when memory runs out. */
int bsms_pooled_dense(i64 n_kept, i64 n_nodes, const i64 *c_ptr, const i64 *c_idx, const i64 *r_ptr,
                      const i64 *r_idx, i64 *counts, const i64 *out_ptr, i32 *out_idx) {
    i64 words = (n_kept + 63) / 64, blocks = (words + 7) / 8;
    u64 *slice = malloc((size_t)(n_nodes * 8) * sizeof(u64));
    i64 *cursor = malloc((size_t)n_nodes * sizeof(i64)), *at = malloc((size_t)n_kept * sizeof(i64));
    if (!slice || !cursor || !at) {
        free(slice);
        free(cursor);
        free(at);
        return 1;
    }
    for (i64 v = 0; v < n_nodes; v++) cursor[v] = r_ptr[v];
    for (i64 r = 0; r < n_kept; r++) {
        at[r] = counts ? 0 : out_ptr[r];
        if (counts) counts[r] = 0;
    }
    for (i64 block = 0; block < blocks; block++) {
        i64 end = (block + 1) * 512;
        memset(slice, 0, (size_t)(n_nodes * 8) * sizeof(u64));
        for (i64 v = 0; v < n_nodes; v++)
            for (; cursor[v] < r_ptr[v + 1] && r_idx[cursor[v]] < end; cursor[v]++) {
                i64 j = r_idx[cursor[v]] - block * 512;
                slice[v * 8 + (j >> 6)] |= (u64)1 << (j & 63);
            }
#pragma omp parallel for schedule(static)
        for (i64 r = 0; r < n_kept; r++) {
            u64 acc[8] = {0};
            for (i64 a = c_ptr[r]; a < c_ptr[r + 1]; a++) {
                const u64 *line = slice + c_idx[a] * 8;
                for (int j = 0; j < 8; j++) acc[j] |= line[j];
            }
            if (r >= block * 512 && r < end) acc[(r - block * 512) >> 6] &= ~((u64)1 << (r & 63));
            if (counts) {
                counts[r] += row_count(acc, 8);
            } else {
                for (int w = 0; w < 8; w++)
                    for (u64 bits = acc[w]; bits; bits &= bits - 1)
                        out_idx[at[r]++] = (i32)(block * 512 + w * 64 + __builtin_ctzll(bits));
            }
        }
    }
    free(slice);
    free(cursor);
    free(at);
    return 0;
}

/* Breadth-first search from up to 64 sources at once on a connected graph (n nodes, symmetric
 * CSR): bit s of reached[v] says that source s is within k hops of v after sweep k, so the sweep
 * in which the bit appears is the hop distance d(s, v). Adds d(s, v) summed over the sources to
 * node_sums[v] (if not NULL) and summed over the nodes to source_sums[s]. A sweep passes on only
 * the bits that arrived in the previous one: pushed from the nodes they arrived at while those
 * nodes' edges are under a quarter of the graph's, else pulled by every node from its
 * neighbours (direction-optimising BFS). One source costs about one pass over the adjacency;
 * 64 sources at most one pass per hop of the largest eccentricity. Returns 0, or 1 when memory
 * runs out. */
int bsms_multi_bfs(i64 n, const i64 *ptr, const i64 *idx, i64 n_sources, const i64 *sources, i64 *node_sums,
                   i64 *source_sums) {
    u64 *reached = calloc((size_t)n, sizeof(u64)), *fresh = calloc((size_t)n, sizeof(u64));
    u64 *arriving = calloc((size_t)n, sizeof(u64));
    i64 *front = malloc((size_t)n * sizeof(i64)), *touched = malloc((size_t)n * sizeof(i64));
    int failed = !reached || !fresh || !arriving || !front || !touched;
    i64 n_front = 0;
    for (i64 s = 0; s < n_sources && !failed; s++) {
        i64 v = sources[s];
        if (!fresh[v]) front[n_front++] = v;
        reached[v] |= (u64)1 << s;
        fresh[v] |= (u64)1 << s;
        source_sums[s] = 0;
    }
    for (i64 k = 1; n_front && !failed; k++) {
        i64 work = 0, n_touched = 0;
        for (i64 f = 0; f < n_front; f++) work += ptr[front[f] + 1] - ptr[front[f]];
        int pull = 4 * work > ptr[n];  /* a large front: read every node's neighbours instead */
        if (pull) {
            for (i64 v = 0; v < n; v++) {
                u64 bits = 0;
                for (i64 a = ptr[v]; a < ptr[v + 1]; a++) bits |= fresh[idx[a]];
                arriving[v] = bits;
            }
        } else {
            for (i64 f = 0; f < n_front; f++) {
                i64 w = front[f];
                u64 bits = fresh[w];
                for (i64 a = ptr[w]; a < ptr[w + 1]; a++) {
                    i64 v = idx[a];
                    if (!arriving[v]) touched[n_touched++] = v;
                    arriving[v] |= bits;
                }
            }
        }
        for (i64 f = 0; f < n_front; f++) fresh[front[f]] = 0;
        n_front = 0;
        for (i64 t = 0; t < (pull ? n : n_touched); t++) {
            i64 v = pull ? t : touched[t];
            u64 bits = arriving[v] & ~reached[v];
            arriving[v] = 0;
            if (!bits) continue;
            reached[v] |= bits;
            fresh[v] = bits;
            front[n_front++] = v;
            if (node_sums) node_sums[v] += k * __builtin_popcountll(bits);
            for (; bits; bits &= bits - 1) source_sums[__builtin_ctzll(bits)] += k;
        }
    }
    free(reached);
    free(fresh);
    free(arriving);
    free(front);
    free(touched);
    return failed;
}

/* Contact edges one level down (thesis eq. 4.1; bsms.graph.contact.coarse_images): for every
 * pair (i, j) with i < j of `rows`/`cols`, every (a, b) with a in reach[i], b in reach[j], a != b,
 * in both directions; written once each, sorted by (row, col), into out_rows/out_cols (room for
 * `capacity` entries). reach (n_fine x n_coarse): indptr/indices, the coarse nodes each fine node
 * reaches. The pairs of one fine node i (consecutive where the pairs are sorted by row, as
 * contact edges are) share their images: the union U of reach[j] over them is taken first (a
 * stamp per coarse node), then reach[i] x U; what remains repeated is ordered by two counting
 * sorts over the coarse nodes (by column, then stably by row) and dropped as it is written.
 * Returns the count written; -1 when memory runs out; -2 - n when the output needs room for n. */

/* The n pairs (a, b) reordered stably by key[k] (in [0, n_keys)) into (a_out, b_out); count:
 * room for n_keys + 1 entries. */
static void counting_sort(i64 n, i64 n_keys, const i64 *key, const i64 *a, const i64 *b, i64 *a_out, i64 *b_out,
                          i64 *count) {
    memset(count, 0, ((size_t)n_keys + 1) * sizeof(i64));
    for (i64 k = 0; k < n; k++) count[key[k] + 1]++;
    for (i64 c = 0; c < n_keys; c++) count[c + 1] += count[c];
    for (i64 k = 0; k < n; k++) {
        const i64 at = count[key[k]]++;
        a_out[at] = a[k], b_out[at] = b[k];
    }
}

/* The candidates of the run of pairs [p, q) that share row i: reach[i] x (union of reach[j]),
 * both directions, appended at a/b from k on (a == NULL: only counted). Returns the new k. */
static i64 images_of_row(i64 p, i64 q, const i64 *rows, const i64 *cols, const i64 *indptr, const i64 *indices,
                         i64 *stamp, i64 *united, i64 *a, i64 *b, i64 k) {
    const i64 i = rows[p];
    i64 n_united = 0;
    for (i64 r = p; r < q; r++) {
        const i64 j = cols[r];
        if (i >= j) continue;
        for (i64 y = indptr[j]; y < indptr[j + 1]; y++)
            if (stamp[indices[y]] != p) {
                stamp[indices[y]] = p;
                united[n_united++] = indices[y];
            }
    }
    for (i64 x = indptr[i]; x < indptr[i + 1]; x++)
        for (i64 u = 0; u < n_united; u++) {
            if (indices[x] == united[u]) continue;
            if (a) {
                a[k] = indices[x], b[k] = united[u];
                a[k + 1] = united[u], b[k + 1] = indices[x];
            }
            k += 2;
        }
    return k;
}

i64 bsms_coarse_images(i64 n_pairs, const i64 *rows, const i64 *cols, const i64 *indptr, const i64 *indices,
                       i64 n_coarse, i64 capacity, i64 *out_rows, i64 *out_cols) {
    i64 *stamp = malloc(((size_t)n_coarse + 1) * sizeof(i64)), *united = malloc(((size_t)n_coarse + 1) * sizeof(i64));
    i64 *count = malloc(((size_t)n_coarse + 1) * sizeof(i64));
    i64 *a = NULL, *b = NULL, *a2 = NULL, *b2 = NULL;
    i64 written = -1, total = 0;
    if (!stamp || !united || !count) goto done;
    for (int pass = 0; pass < 2; pass++) { /* count, then write */
        for (i64 c = 0; c < n_coarse; c++) stamp[c] = -1;
        i64 k = 0;
        for (i64 p = 0, q; p < n_pairs; p = q) {
            for (q = p + 1; q < n_pairs && rows[q] == rows[p];) q++;
            k = images_of_row(p, q, rows, cols, indptr, indices, stamp, united, pass ? a : NULL, b, k);
        }
        if (pass == 0) {
            total = k;
            const size_t room = (size_t)(total > 0 ? total : 1);
            a = malloc(room * sizeof(i64)), b = malloc(room * sizeof(i64));
            a2 = malloc(room * sizeof(i64)), b2 = malloc(room * sizeof(i64));
            if (!a || !b || !a2 || !b2) goto done;
        }
    }
    counting_sort(total, n_coarse, b, a, b, a2, b2, count);   /* by column, into a2/b2 */
    counting_sort(total, n_coarse, a2, a2, b2, a, b, count);  /* stably by row: sorted by (row, col) */
    written = 0;
    for (i64 k = 0; k < total; k++)
        if (k == 0 || a[k] != a[k - 1] || b[k] != b[k - 1]) {
            if (written == capacity) { /* no room: count the rest, say how much is needed */
                i64 needed = written;
                for (; k < total; k++) needed += (a[k] != a[k - 1] || b[k] != b[k - 1]);
                written = -2 - needed;
                goto done;
            }
            out_rows[written] = a[k];
            out_cols[written] = b[k];
            written++;
        }
done:
    free(stamp);
    free(united);
    free(count);
    free(a);
    free(b);
    free(a2);
    free(b2);
    return written;
}
