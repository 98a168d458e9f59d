"""Several learned simulators answering as one: the mean of their outputs, frame by frame.

Runs of one recipe that differ only in their seed (or their share of the data) err on different
bodies (docs/press.md at 8757482, "Sixteen shapes of no split"): the mean of their outputs errs less than
each, and how far they disagree marks where none of them is to be trusted. The members read one
graph (:mod:`bsms.ensemble` checks that their graph options are equal), so a frame builds its
graph once and runs each member's network on it: the graph's cost is shared, the network's is
paid once per member.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from bsms.data import LevelGraph
from bsms.models.simulator import LearnedSimulator

__all__ = ["Ensemble"]


class Ensemble(nn.Module):
    """The members' :meth:`~bsms.models.simulator.LearnedSimulator.velocity_change`, averaged.

    Every member must learn the same fields in the same dimension (``spec``, ``dim``,
    ``contact``); a member is trained on its own (``python train.py CONFIG``): an ensemble only
    infers.
    """

    def __init__(self, members: list[LearnedSimulator]):
        super().__init__()
        if not members:
            raise ValueError("an ensemble needs at least one member")
        first = members[0]
        for k, member in enumerate(members[1:], start=1):
            for name in ("dim", "spec", "contact", "frame_stride"):
                if getattr(member, name, 1) != getattr(first, name, 1):
                    raise ValueError(f"ensemble member {k} has {name} {getattr(member, name, 1)!r}, member 0 "
                                     f"{getattr(first, name, 1)!r}: every member must learn the same fields "
                                     "with the same step")
        self.members = nn.ModuleList(members)
        self.dim, self.spec, self.contact = first.dim, first.spec, first.contact
        self.frame_stride = getattr(first, "frame_stride", 1)
        self.n_levels = max(member.n_levels for member in members)
        self.latent = max(member.latent for member in members)

    def forward(self, graph: LevelGraph, *args, **kwargs) -> Tensor:
        raise TypeError("an ensemble is not trained as one: train each member with python train.py CONFIG "
                        "and join them with python -m bsms.pretrained RUN RUN ... OUT")

    @torch.no_grad()
    def member_changes(self, graph: LevelGraph, precision: str = "f32") -> Tensor:
        """(K, N, node_out): each member's velocity change on ``graph``, physical units."""
        return torch.stack([member.velocity_change(graph, precision=precision) for member in self.members])

    @torch.no_grad()
    def velocity_change(self, graph: LevelGraph, precision: str = "f32") -> Tensor:
        """(N, node_out) the mean of the members' velocity changes (zero on non-free nodes)."""
        return self.member_changes(graph, precision).mean(dim=0)

    output = velocity_change
