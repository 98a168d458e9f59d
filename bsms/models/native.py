"""Compiled message sums for inference (``csrc/messages.c``), built on first use.

On the narrow latents of a lean network (the press recipe: latent 32, one hidden layer, no
LayerNorm) a message pass costs what its (E, H) per-edge arrays cost to write and read: the
torch path gathers the node products per edge, adds the edge features' product, applies the
ReLU and scatters to the receivers, four passes over such an array. :func:`edge_sums` does all
of it in one pass over the edges and never builds the array; :func:`edge_offsets` computes a
level's normalised edge inputs (offsets and lengths) in one pass too. It serves inference only (no
gradients) in float32 on a CPU; :func:`bsms.models.blocks.summed_messages` takes the torch path
everywhere else, and where no C compiler is found or ``BSMS_NATIVE=0``. Built by
:func:`datagen.compiled.build`.
"""

from __future__ import annotations

import ctypes
import functools
from pathlib import Path

import torch
from torch import Tensor

from datagen import compiled

__all__ = ["library", "edge_sums", "edge_offsets"]

SOURCE = Path(__file__).with_name("csrc") / "messages.c"


@functools.cache
def library() -> ctypes.CDLL | None:
    """The compiled library, or None where it cannot be built (torch sums the messages instead)."""
    lib = compiled.build(SOURCE, "compiled message sums", "messages are summed in torch, about twice as slowly")
    if lib is None:
        return None
    i64, ptr = ctypes.c_int64, ctypes.c_void_p
    lib.bsms_edge_sums.argtypes = [i64] * 6 + [ctypes.c_int] + [ptr] * 6
    lib.bsms_edge_sums.restype = i64
    lib.bsms_edge_offsets.argtypes = [i64] * 4 + [ctypes.c_int] + [ptr] * 6
    lib.bsms_edge_offsets.restype = i64
    return lib


def edge_sums(products: Tensor, features: Tensor, edge_weight: Tensor, index: Tensor,
              counts: bool = False, groups: int = 1) -> Tensor | None:
    """(N, H) per receiver the sum over its edges of relu(P[r, :H] + P[s, H:] + edge_weight f_k),
    or None where the compiled code cannot run (no library, or not float32 CPU tensors).

    products: (N, 2H) float32 node products [W_r v + b | W_s v], contiguous rows or columns of a
    wider product (a view with unit column stride is read in place); features: (E, F) float32;
    edge_weight: (H, F) the first layer's edge-feature columns; index: (2, E) int64 (senders,
    receivers), every entry in [0, N) (checked as the edges are read: an index out of range
    raises IndexError). ``counts``: (N, H + 1), the last column each receiver's edge count.
    ``groups`` G > 1: G copies of the nodes share the edges (a frame and its mirror image), node
    r's copy g in row r G + g of products (N G, 2H) and of the result, edge k's features for copy
    g in columns g F to (g + 1) F of features (E, G F)."""
    lib = library()
    tensors = (products, features, edge_weight)
    if lib is None or any(t.dtype != torch.float32 or t.device.type != "cpu" for t in tensors) \
            or index.dtype != torch.int64 or index.device.type != "cpu":
        return None
    hidden, n_edges = products.shape[1] // 2, features.shape[0]
    n_nodes, n_features = products.shape[0] // groups, features.shape[1] // groups
    if products.shape[0] != n_nodes * groups or features.shape[1] != n_features * groups:
        raise ValueError(f"edge_sums: products of {products.shape[0]} rows and features of {features.shape[1]} "
                         f"columns are not {groups} groups of nodes and of features")
    if edge_weight.shape != (hidden, n_features):
        raise ValueError(f"edge_sums: edge weight of shape {tuple(edge_weight.shape)}, expected ({hidden}, "
                         f"{n_features}) for products of width {2 * hidden} and {n_features} features")
    if index.shape != (2, n_edges):
        raise ValueError(f"edge_sums: index of shape {tuple(index.shape)}, expected (2, {n_edges})")
    if products.stride(1) != 1 or products.stride(0) < 2 * hidden:
        products = products.contiguous()
    out = torch.zeros(n_nodes * groups, hidden + int(counts))
    senders, receivers = index[0].contiguous(), index[1].contiguous()
    features = features.contiguous()
    weight_t = edge_weight.t().contiguous()
    status = lib.bsms_edge_sums(n_nodes, n_edges, groups, hidden, n_features, products.stride(0), int(counts),
                                senders.data_ptr(), receivers.data_ptr(), products.data_ptr(), features.data_ptr(),
                                weight_t.data_ptr(), out.data_ptr())
    if status > 0:
        _index_error(index, n_nodes, "edge_sums")
    return None if status else out


def _index_error(index: Tensor, n_nodes: int, what: str) -> None:
    """Raise the IndexError of an ``index`` with an entry outside [0, n_nodes) (the compiled loop found one)."""
    low, high = (int(x) for x in torch.aminmax(index))
    raise IndexError(f"{what}: node index {low if low < 0 else high} out of range for {n_nodes} nodes")


def edge_offsets(points: Tensor, index: Tensor, dim: int, mean: Tensor, std: Tensor,
                 reflect: bool = False) -> Tensor | None:
    """:func:`bsms.models.simulator._offsets` normalised by ``(x - mean) / std``, (E, k (d + 1)),
    or None where the compiled code cannot run (no library, not float32 CPU tensors, d > 3).

    points: (N, k d) k points of dimension d per node; index: (2, E) int64 (senders, receivers);
    mean, std: (k (d + 1),) the normaliser's statistics. ``reflect``: (E, 2 k (d + 1)), each edge's
    inputs followed by those of the mirror image (x -> -x), as the reflected points give them."""
    lib = library()
    if lib is None or not 1 <= dim <= 3 or points.dtype != torch.float32 or points.device.type != "cpu" \
            or index.dtype != torch.int64 or index.device.type != "cpu":
        return None
    n_groups = points.shape[1] // dim
    columns = n_groups * (dim + 1)
    if not n_groups or points.shape[1] != n_groups * dim or mean.shape != (columns,) or std.shape != (columns,):
        raise ValueError(f"edge_offsets: points of width {points.shape[1]} in dimension {dim} and statistics of "
                         f"shapes {tuple(mean.shape)}, {tuple(std.shape)} do not match")
    n_nodes, n_edges = points.shape[0], index.shape[1]
    if index.shape != (2, n_edges):
        raise ValueError(f"edge_offsets: index of shape {tuple(index.shape)}, expected (2, {n_edges})")
    out = torch.empty(n_edges, columns * (2 if reflect else 1))
    senders, receivers = index[0].contiguous(), index[1].contiguous()
    points = points.contiguous()
    mean, std = mean.to(torch.float32).contiguous(), std.to(torch.float32).contiguous()
    status = lib.bsms_edge_offsets(n_nodes, n_edges, n_groups, dim, int(reflect), points.data_ptr(),
                                   senders.data_ptr(), receivers.data_ptr(), mean.data_ptr(), std.data_ptr(),
                                   out.data_ptr())
    if status > 0:
        _index_error(index, n_nodes, "edge_offsets")
    return None if status else out
