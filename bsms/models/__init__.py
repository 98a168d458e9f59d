"""Graph models, all built from the same MLPs and message-passing blocks."""

from bsms.models.blocks import EdgeLatentBlock, EdgeSet, MessagePassingBlock
from bsms.models.bsms_gnn import BSMSGNN, apply_transition
from bsms.models.graph_unets import GraphUNets
from bsms.models.inputs import Context, Level
from bsms.models.meshgraphnets import MeshGraphNets
from bsms.models.mlp import mlp
from bsms.models.ms_gnn_grid import MSGNNGrid
from bsms.models.transition_variants import TRANSITIONS

MODELS = {"bsms_gnn": BSMSGNN, "meshgraphnets": MeshGraphNets, "ms_gnn_grid": MSGNNGrid, "graph_unets": GraphUNets}

__all__ = [
    "BSMSGNN", "MODELS", "Context", "EdgeLatentBlock", "EdgeSet", "GraphUNets", "Level", "MSGNNGrid",
    "MeshGraphNets", "MessagePassingBlock", "TRANSITIONS", "apply_transition", "mlp",
]
