"""Graph models, all built from the same MLPs and message-passing blocks."""

from bsms.models.blocks import EdgeLatentBlock, EdgeSet, MessagePassingBlock
from bsms.models.bsms_gnn import BSMSGNN, apply_transition
from bsms.models.inputs import Context, Level
from bsms.models.meshgraphnets import MeshGraphNets
from bsms.models.mlp import mlp

MODELS = {"bsms_gnn": BSMSGNN, "meshgraphnets": MeshGraphNets}

__all__ = [
    "BSMSGNN", "MODELS", "Context", "EdgeLatentBlock", "EdgeSet", "Level", "MeshGraphNets", "MessagePassingBlock",
    "apply_transition", "mlp",
]
