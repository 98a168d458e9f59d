"""The ``model`` section of a training config: which core network, how wide, and its own options."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from bsms.config import ConfigError, at_least

__all__ = ["ModelConfig"]


@dataclass
class ModelConfig:
    """name: the core network; latent: width of latents and hidden layers; hidden_layers per
    MLP; passes: message passes of meshgraphnets (bsms_gnn makes one per level).

    transition (bsms_gnn only; thesis §4.4.4.1, Table 4.7): ``bistride`` (the weighted
    aggregation and return of §4.3.2), ``none`` (pool and unpool by index), ``graph_conv`` (one
    unweighted graph convolution), ``pos_kernel`` (inverse-distance weights, Liu et al.) or
    ``learnable`` (one message pass per transition, Fortunato et al.).
    grid_* (ms_gnn_grid; thesis §4.4.2.3, Table 4.3): levels (the mesh, then the grids), message
    passes per level (the mesh first; each level above the bottom passes on the way down and
    again on the way up), the finest grid's cell size per dimension (empty: twice the mean rest
    length of the mesh edges of each graph) and its inflation from level to level.
    pool_ratio (graph_unets): fraction of nodes top-k pooling keeps at each level.
    layer_norm (bsms_gnn only): LayerNorm on the output of the encoder's and the message passes'
    MLPs (the thesis' and MeshGraphNets' choice, default); false drops it: on one CPU thread a latent-32 press frame
    spends ~30% of its network time in LayerNorm over the edges (docs/press.md).
    first_level (bsms_gnn only): the finest level that passes messages; the levels below it only
    encode, pool, unpool (with their skip connection) and decode, so the network's edge work is
    on the coarser levels (0, the default: every level passes, the thesis' BSMS-GNN).
    mirror_average (Lagrangian data, any core): at inference -- every rollout: validation,
    evaluation, ``bsms.infer`` -- a frame's answer is the mean of the network's answer and the
    reflection of its answer to the frame reflected by x -> -x, so the model is exactly
    mirror-equivariant (a symmetric scene stays symmetric) at the price of the network run on both
    images (in one pass of about 1.7 single ones where every block runs fused, as the press
    recipe's lean network does; twice elsewhere); the graph is built once. Training's loss is the
    network's own answer, unchanged (``train.mirror`` gives it both images, and is required).
    edge_velocity (Lagrangian data): mesh edges also carry the difference of their nodes' velocities
    and its norm, so that a rigid turn's rate is an edge input (Delta v = omega x Delta x) rather than
    something the messages must work out.
    rigid_part (Lagrangian data): the output is the velocity change's rigid-motion part over each
    body's free nodes (the best 2D similarity or 3D affine field: the smallest space holding what
    rigid motion gives a velocity change over a step, :mod:`bsms.models.body_motion`) plus the rest,
    each from channels of its own with its own normaliser: a stiff body's rest is small, and so are
    the errors it lets through.
    rigid_step (Lagrangian data): at inference each step's next velocity has its affine part over each
    body's free nodes made the nearest rigid motion (polar factor, :func:`bsms.models.body_motion.rigid_step`):
    a stiff body keeps its size and shape however the answer's affine part errs. For stiff bodies.
    """

    name: Literal["bsms_gnn", "meshgraphnets", "ms_gnn_grid", "graph_unets"] = "bsms_gnn"
    latent: int = 128
    hidden_layers: int = 2
    passes: int = 15
    transition: Literal["bistride", "none", "graph_conv", "pos_kernel", "learnable"] = "bistride"
    grid_levels: int = 4
    grid_passes: list[int] = field(default_factory=lambda: [4, 2, 2, 4])
    grid_dx: list[float] = field(default_factory=list)
    grid_inflation: float = 2.0
    pool_ratio: float = 0.5
    layer_norm: bool = True
    first_level: int = 0
    mirror_average: bool = False
    edge_velocity: bool = False
    rigid_part: bool = False
    rigid_step: bool = False

    def validate(self, prefix: str) -> None:
        at_least(self, prefix, 1, ("latent", "hidden_layers", "passes", "grid_levels"))
        if self.transition != "bistride" and self.name != "bsms_gnn":
            raise ConfigError(f"config key '{prefix}.transition' applies to bsms_gnn only; {self.name} "
                              f"has its own transitions (leave it at bistride)")
        at_least(self, prefix, 0, ("first_level",))
        for key, default in (("layer_norm", True), ("first_level", 0)):
            if getattr(self, key) != default and self.name != "bsms_gnn":
                raise ConfigError(f"config key '{prefix}.{key}' applies to bsms_gnn only; leave it at "
                                  f"{str(default).lower()} for {self.name}")
        if len(self.grid_passes) != self.grid_levels or min(self.grid_passes) < 1:
            raise ConfigError(f"config key '{prefix}.grid_passes' must give one pass count >= 1 per grid level "
                              f"({self.grid_levels}, '{prefix}.grid_levels'), got {self.grid_passes}")
        if any(dx <= 0 for dx in self.grid_dx):
            raise ConfigError(f"config key '{prefix}.grid_dx' must hold positive cell sizes (one per dimension) "
                              f"or be empty (automatic), got {self.grid_dx}")
        if self.grid_inflation <= 1:
            raise ConfigError(f"config key '{prefix}.grid_inflation' must be > 1, got {self.grid_inflation}")
        if not 0 < self.pool_ratio < 1:
            raise ConfigError(f"config key '{prefix}.pool_ratio' must be between 0 and 1 (exclusive), "
                              f"got {self.pool_ratio}")

    def core_options(self, dim: int) -> dict:
        """Keyword options of the core network beyond the common ones."""
        if self.name == "bsms_gnn":
            return {"transition": self.transition, "layer_norm": self.layer_norm, "first_level": self.first_level}
        if self.name == "ms_gnn_grid":
            if self.grid_dx and len(self.grid_dx) != dim:
                raise ConfigError(f"config key 'model.grid_dx' must give one cell size per dimension ({dim}), "
                                  f"got {self.grid_dx}")
            return {"passes": list(self.grid_passes), "dx": list(self.grid_dx), "inflation": self.grid_inflation}
        if self.name == "graph_unets":
            return {"ratio": self.pool_ratio}
        return {}
