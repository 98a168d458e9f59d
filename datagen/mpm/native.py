"""Compiled UMLS-MPM kernels: C with OpenMP (``csrc/umls.c``), built on first use, torch fallback.

The UMLS kernel's per-particle work (1-ring offsets, B-spline sample weights times eta, the
MLS moment matrix and its inverse, weights and gradients) is dozens of small elementwise torch
operations over (P, K) slot arrays; written as one loop per particle it reads each slot once.
:func:`umls_weights` runs it when a compiled library is available and the tensors are float64
on the CPU; :func:`~datagen.mpm.kernels.umls_kernel` falls back to its torch code otherwise
(the torch code is the reference the tests compare against).

The library is compiled once per source, compiler and CPU by :func:`datagen.compiled.build`
(``CC``, ``$BSMS_CACHE/native``, ``BSMS_NATIVE=0`` to turn it off). Without a working compiler
the solver warns once and runs in torch.
"""

from __future__ import annotations

import ctypes
import functools
from pathlib import Path

import torch

from datagen import compiled
from datagen.compiled import cache_dir

__all__ = ["library", "available", "umls_weights", "p2g", "g2p", "locate_guess", "patch_average", "cache_dir"]

SOURCE = Path(__file__).with_name("csrc") / "umls.c"
BLOCKS = 4  # particle blocks of the node sums (csrc/umls.c): results do not depend on the thread count


@functools.cache
def library() -> ctypes.CDLL | None:
    """The compiled library (built into :func:`cache_dir` on first use), or None where it cannot be."""
    lib = compiled.build(SOURCE, "compiled UMLS kernel", "it runs in torch, several times slower")
    if lib is None:
        return None
    i64, ptr, f64 = ctypes.c_int64, ctypes.c_void_p, ctypes.c_double
    lib.bsms_umls_weights.argtypes = [i64, i64, i64, i64, f64] + [ptr] * 11 + [i64]
    lib.bsms_umls_weights.restype = ctypes.c_int
    lib.bsms_umls_p2g.argtypes = [i64, i64, i64, i64, f64] + [ptr] * 11 + [i64] + [ptr] * 5 + [i64]
    lib.bsms_umls_p2g.restype = ctypes.c_int
    lib.bsms_p2g.argtypes = [i64] * 4 + [ptr] * 10 + [i64]
    lib.bsms_p2g.restype = ctypes.c_int
    lib.bsms_g2p.argtypes = [i64] * 5 + [ptr] * 8 + [i64]
    lib.bsms_g2p.restype = ctypes.c_int
    lib.bsms_locate_guess.argtypes = [i64, i64, f64] + [ptr] * 6 + [i64]
    lib.bsms_locate_guess.restype = ctypes.c_int
    lib.bsms_patch_average.argtypes = [i64] * 3 + [ptr] * 7 + [i64]
    lib.bsms_patch_average.restype = ctypes.c_int
    return lib


def available() -> bool:
    """Whether the compiled kernels can be used (built, or buildable, here)."""
    return library() is not None


def _ptr(t: torch.Tensor) -> int:
    """The address of t's data: bind t to a name first, so that it outlives the call."""
    return t.data_ptr()


def _maybe(t: torch.Tensor | None) -> int | None:
    return None if t is None else t.data_ptr()


def _check(code: int, what: str) -> None:
    if code != 0:
        raise ValueError(f"compiled {what}: unsupported shapes (dimension 1 to 3, at most 8 node fields)")


def umls_weights(tables, x: torch.Tensor, location, eta: bool, p2g: tuple | None = None):
    """The UMLS kernel's slots by the compiled loop, or None where it does not apply (no library,
    not float64 on the CPU): index (P, K), weight (P, K), grad (d, P, K) and
    negative (P,) bool, the particles whose MLS weights are not all >= 0.

    p2g: (mass (P,), v (P, d), coef (P, d, d), n_nodes) to sum FLIP/PIC P2G (as :func:`p2g` with no
    affine) in the same pass; the sums (1+2d, N) are then returned fifth. They leave out the
    particles marked negative, whose kernel the caller replaces and whose share it adds."""
    if x.device.type != "cpu" or x.dtype != torch.float64 or tables.nodes.dtype != torch.float64:
        return None
    if p2g is not None and not _applies(*p2g[:3]):
        return None
    lib = library()
    if lib is None:
        return None
    x = x.contiguous()
    n, (_, k), d = x.shape[0], tables.ring.shape, tables.dim
    index = torch.empty((n, k), dtype=torch.int64)
    weight = torch.empty((n, k), dtype=torch.float64)
    grad = torch.empty((d, n, k), dtype=torch.float64)
    negative = torch.empty(n, dtype=torch.bool)
    cell = location.cell.contiguous()
    status = location.status.contiguous()
    bary = location.bary.contiguous()
    common = (n, k, d, int(eta), 1.0 / tables.h, _ptr(x), _ptr(cell), _ptr(status), _ptr(bary), _ptr(tables.ring),
              _ptr(tables.ring_adjacency), _ptr(tables.nodes), _ptr(index), _ptr(weight), _ptr(grad),
              _ptr(negative))
    if p2g is None:
        _check(lib.bsms_umls_weights(*common, torch.get_num_threads()), "UMLS kernel")
        return index, weight, grad, negative
    mass, v, coef = (t.contiguous() for t in p2g[:3])
    n_nodes = p2g[3]
    sums = torch.empty((1 + 2 * d, n_nodes), dtype=torch.float64)
    scratch = torch.empty((BLOCKS, n_nodes, 1 + 2 * d), dtype=torch.float64)
    _check(lib.bsms_umls_p2g(*common, n_nodes, _ptr(mass), _ptr(v), _ptr(coef), _ptr(sums), _ptr(scratch),
                             torch.get_num_threads()), "UMLS kernel and P2G")
    return index, weight, grad, negative, sums


def _applies(*tensors: torch.Tensor) -> bool:
    return all(t.device.type == "cpu" and t.dtype in (torch.float64, torch.int64) for t in tensors)


def p2g(k, mass: torch.Tensor, v: torch.Tensor, coef: torch.Tensor, affine: torch.Tensor | None,
        n_nodes: int) -> torch.Tensor | None:
    """P2G sums (1+2d, N) [m, p, f_int] by the compiled loop over kernel slots, or None where it does
    not apply. mass (P,), v (P, d), coef (P, d, d) = -V^0 times the force stress, affine (P, d, d):
    the APIC C_p = B_p D_p^-1 (nodes see v_p + C_p (x_i - x_p)), or None."""
    tensors = (k.index, k.weight, k.grad_axes, mass, v, coef) + ((affine,) if affine is not None else ())
    lib = library() if _applies(*tensors) else None
    if lib is None:
        return None
    (n, kk), d = k.index.shape, v.shape[1]
    index, weight, grad = k.index.contiguous(), k.weight.contiguous(), k.grad_axes.contiguous()
    offset = k.offset_axes.contiguous() if affine is not None else None  # APIC only
    mass, v, coef = mass.contiguous(), v.contiguous(), coef.contiguous()
    affine = affine.contiguous() if affine is not None else None
    threads = torch.get_num_threads()
    sums = torch.empty((1 + 2 * d, n_nodes), dtype=torch.float64)
    scratch = torch.empty((BLOCKS, n_nodes, 1 + 2 * d), dtype=torch.float64)
    _check(lib.bsms_p2g(n, kk, d, n_nodes, _ptr(index), _ptr(weight), _ptr(grad), _maybe(offset), _ptr(mass),
                        _ptr(v), _ptr(coef), _maybe(affine), _ptr(sums), _ptr(scratch),
                        threads), "P2G")
    return sums


def g2p(k, field: torch.Tensor, moment: bool):
    """G2P sums over kernel slots by the compiled loop, or None where it does not apply: for node
    fields (c, N) (the first d of them velocities), (interp (P, c) = sum w f_i, grad_v (P, d, d) =
    sum v_i grad w^T, B (P, d, d) = sum w v_i (x_i - x_p)^T or None)."""
    lib = library() if _applies(k.index, k.weight, k.grad_axes, field) and field.shape[0] <= 8 else None
    if lib is None:
        return None
    (n, kk), d, c = k.index.shape, k.grad_axes.shape[0], field.shape[0]
    index, weight, grad = k.index.contiguous(), k.weight.contiguous(), k.grad_axes.contiguous()
    offset = k.offset_axes.contiguous() if moment else None  # APIC only
    field = field.T.contiguous()  # node-major: one line per node
    interp = torch.empty((n, c), dtype=torch.float64)
    grad_v = torch.empty((n, d, d), dtype=torch.float64)
    b = torch.empty((n, d, d), dtype=torch.float64) if moment else None
    _check(lib.bsms_g2p(n, kk, d, field.shape[0], c, _ptr(index), _ptr(weight), _ptr(grad),
                        _maybe(offset), _ptr(field), _ptr(interp), _ptr(grad_v), _maybe(b),
                        torch.get_num_threads()), "G2P")
    return interp, grad_v, b


def locate_guess(locator, x: torch.Tensor, guess: torch.Tensor, tol: float):
    """(cell (P,), bary (P, d+1)) of the particles inside their guessed cell (cell -1 and bary 0
    elsewhere, and for non-finite positions) by the compiled loop, or None where it does not apply."""
    lib = library() if _applies(x, guess, locator.corner) else None
    if lib is None:
        return None
    x, guess = x.contiguous(), guess.contiguous()
    n, d = x.shape
    cell = torch.empty(n, dtype=torch.int64)
    bary = torch.empty((n, d + 1), dtype=torch.float64)
    _check(lib.bsms_locate_guess(n, d, tol, _ptr(x), _ptr(guess), _ptr(locator.corner), _ptr(locator.to_bary),
                                 _ptr(cell), _ptr(bary), torch.get_num_threads()), "cell search")
    return cell, bary


def patch_average(k, value: torch.Tensor, volume: torch.Tensor, n_nodes: int) -> torch.Tensor | None:
    """F-bar's patch average (:func:`~datagen.mpm.inelastic.patch_average`) by the compiled loops, or
    None where it does not apply."""
    lib = library() if _applies(k.index, k.weight, value, volume) else None
    if lib is None:
        return None
    (n, kk), threads = k.index.shape, torch.get_num_threads()
    index, weight, value, volume = k.index.contiguous(), k.weight.contiguous(), value.contiguous(), volume.contiguous()
    scratch = torch.empty((BLOCKS, n_nodes, 2), dtype=torch.float64)
    node = torch.empty(n_nodes, dtype=torch.float64)
    out = torch.empty(n, dtype=torch.float64)
    _check(lib.bsms_patch_average(n, kk, n_nodes, _ptr(index), _ptr(weight), _ptr(value), _ptr(volume),
                                  _ptr(scratch), _ptr(node), _ptr(out), threads), "patch average")
    return out
