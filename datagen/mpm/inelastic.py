"""Material post-processing after G2P's F update (UMLS Algorithm 1's last line): the F-bar
treatment against volumetric locking and the plastic return map.

**F-bar** (``Model.fbar``; after Zhao, Jiang and Choo 2023, who project J through the grid).
A particle's volume ratio J_p = det F_p is replaced by its average over the particle's nodal
patch, and F_p <- (J_bar_p / J_p)^(1/d) F_p (the deviatoric part is kept). The average is a
projection onto the background nodes and back, weighted by the reference volumes V_p^0 (so that a
node's value is its patch's current volume over its reference volume) with the kernel's weights
clipped at zero (the UMLS weights may be slightly negative, which could make a node's average
leave the range of the values averaged):

    J_i = sum_p w+_ip V_p^0 J_p / sum_p w+_ip V_p^0,    J_bar_p = sum_i w+_ip J_i / sum_i w+_ip,

two convex combinations, so J_bar stays between the smallest and largest J. The total J is
averaged, not the step's increment dJ = J^{n+1} / J^n: averaging increments (J_bar^{n+1} =
J_p^n dJ_bar) lets each particle's J drift away from its patch's, and on the B-spline grid the
drift fed an instability -- the sensitive-clay slope at 0.2 m cells gained total energy (+14% by
1 s at CFL 0.2, +1700% by 1.2 s at 0.5) and sprayed particles, where averaging J keeps the energy falling.
Why nodes and not background cells: on a simplex mesh there are several cells per node (about 2
triangles or 5-6 tetrahedra), so one volume constraint per cell is still more constraints than
the d velocity unknowns per node can meet (the reason linear simplices lock in the first place);
one per node is fewer than d per node, as in averaged-nodal-pressure simplices. The nodal patch
also needs nothing but the kernel, so the B-spline grid solver uses the same code.

**Plasticity** (a material with ``plastic = True``, :class:`~datagen.mpm.plasticity.J2Softening`).
F from G2P (after F-bar) is the trial elastic F^e; the return map gives the new F^e, equivalent
plastic strain and (2D) out-of-plane elastic log strain, kept in the :class:`State`.

In the A-ULMPM total/adaptive modes F = F^{sn} F^{0s}: F-bar scales F^{sn} and the return map
sets F^{0s} <- (F^{sn})^-1 F^e, so that F = F^{sn} F^{0s} stays the (new) F.
"""

from __future__ import annotations

from dataclasses import replace

import torch

from . import linalg, native
from .kernels import KernelResult
from .model import Model
from .state import State

__all__ = ["post_process", "patch_average", "initial_fields"]


def initial_fields(model: Model, n: int, *, device, dtype) -> dict:
    """The State fields a model's plastic materials need at rest (empty if none is plastic)."""
    if not model.plastic:
        return {}
    zeros = torch.zeros(n, dtype=dtype, device=device)
    return {"plastic_strain": zeros, "out_of_plane": zeros.clone() if model.dim == 2 else None}


def patch_average(k: KernelResult, value: torch.Tensor, volume: torch.Tensor, n_nodes: int) -> torch.Tensor:
    """(P,) the volume-weighted average of a particle field ``value`` (P,) over each particle's nodal
    patch: P2G to the nodes and G2P back with the positive part of the weights (module docstring)."""
    compiled = native.patch_average(k, value, volume, n_nodes)
    if compiled is not None:
        return compiled
    w = k.weight.clamp(min=0.0) * (k.index >= 0)
    wv = w * volume[:, None]
    flat = k.index.clamp(min=0).reshape(-1)
    num = value.new_zeros(n_nodes).index_add_(0, flat, (wv * value[:, None]).reshape(-1))
    den = value.new_zeros(n_nodes).index_add_(0, flat, wv.reshape(-1))
    node = num / torch.where(den > 0, den, torch.ones_like(den))
    return (w * node[flat].view(w.shape)).sum(1) / w.sum(1)


def _fbar_scale(model: Model, new: State, k: KernelResult) -> torch.Tensor:
    """(P,) the F-bar factor (J_bar / J)^(1/d) of the state ``new`` (module docstring)."""
    J = linalg.det(new.F)
    return (patch_average(k, J, new.volume0, model.n_nodes) / J).pow(1.0 / model.dim)


def _return_map(model: Model, new: State, F: torch.Tensor) -> tuple[torch.Tensor, dict]:
    """F^e and the plastic fields after every plastic material's return map (F: the trial F^e)."""
    eps_q, out = new.plastic_strain.clone(), None if new.out_of_plane is None else new.out_of_plane.clone()
    F = F.clone()
    for material, ids in model.materials:
        if not getattr(material, "plastic", False):
            continue
        sel = slice(None) if ids is None else ids
        Fe, q, o = material.return_map(F[sel], eps_q[sel], None if out is None else out[sel])
        F[sel], eps_q[sel] = Fe, q
        if out is not None:
            out[sel] = o
    return F, {"plastic_strain": eps_q, "out_of_plane": out}


def post_process(model: Model, old: State, new: State, k: KernelResult) -> State:
    """F-bar and the return map on the state a step produced from ``old`` with kernel ``k``.
    Returns ``new`` itself when the model asks for neither (elastic runs stay bit-identical)."""
    if not (model.fbar or model.plastic):
        return new
    scale = _fbar_scale(model, new, k)[:, None, None] if model.fbar else None
    F = new.F if scale is None else scale * new.F
    fields = {}
    if model.plastic:
        F, fields = _return_map(model, new, F)
    ref = new.reference
    if ref is not None:
        Fsn = ref.Fsn if scale is None else _like(ref.Fsn, scale * ref.Fsn)
        F0s = _like(ref.F0s, linalg.inv(Fsn) @ F) if model.plastic else ref.F0s
        fields["reference"] = replace(ref, Fsn=Fsn, F0s=F0s)
        F = _like(new.F, F)
    return replace(new, F=F, **fields)


def _like(template: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """``a`` (P, d, d) in the memory layout of ``template`` (the reference step keeps F by component)."""
    if template.dim() == 3 and template.shape[0] > 1 and template.stride(0) == 1:
        return linalg.matrices(linalg.components(a).contiguous())
    return a.contiguous()
