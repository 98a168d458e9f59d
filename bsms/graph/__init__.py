"""Graph structure for BSMS-GNN: bi-stride levels, their transitions, and contact edges."""

from bsms.graph.contact import coarsen_contacts, contact_edges
from bsms.graph.hierarchy import DEFAULT_MIN_NODES, BistrideLevel, Hierarchy, bistride_levels
from bsms.graph.seeding import SEEDINGS
from bsms.graph.transitions import Transition

__all__ = [
    "bistride_levels", "Hierarchy", "BistrideLevel", "Transition", "SEEDINGS", "DEFAULT_MIN_NODES",
    "contact_edges", "coarsen_contacts",
]
