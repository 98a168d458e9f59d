/* Compiled loops of the bi-stride hierarchy (bsms/graph/native.py): the pooled adjacency of a
 * coarse level and bit-parallel breadth-first distance sums. Both produce exactly what the
 * scipy/csgraph code produces (bsms/graph/pooling.py, bsms/graph/seeding.py); the tests compare.
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
