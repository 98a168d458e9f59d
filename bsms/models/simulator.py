"""The learned simulator: physics-aware features around a physics-free core network.

What it reads and writes is the data's :class:`~bsms.fields.FieldSpec` (thesis Table 4.2).
Lagrangian (the default, every MPM dataset): inputs per node velocity and one-hot node type
(+ per-node scene constants); edge features per level: material-space and world-space offsets
x_i - x_j (receiver minus sender) and their norms on mesh edges, world-space offset and norm
on contact edges; output the per-node velocity change over one frame. Eulerian: inputs the
node fields of the spec (velocity, density, ...), mesh edges with material-space offsets
only, outputs the spec's changes and values. Everything is normalised by running statistics
stored in the module; the core predicts the normalised outputs.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from bsms.augment import reflected
from bsms.data import LevelGraph, NodeType
from bsms.fields import FieldSpec
from bsms.models import native
from bsms.models.blocks import EdgeSet
from bsms.models.body_motion import rigid_part, rigid_step
from bsms.models.bsms_gnn import BSMSGNN
from bsms.models.inputs import Context, Level
from bsms.models.meshgraphnets import MeshGraphNets
from bsms.models.normalize import Normalizer
from bsms.models.precision import network_autocast, network_dtype

CORES = ("bsms_gnn", "meshgraphnets", "ms_gnn_grid", "graph_unets")
# cores that read only the mesh (level 0) of the bi-stride hierarchy
SINGLE_LEVEL = ("meshgraphnets", "ms_gnn_grid", "graph_unets")


def build_core(core: str, node_in: int, node_out: int, edge_dims: list[int], *, n_levels: int, latent: int,
               n_passes: int, hidden_layers: int, options: dict) -> nn.Module:
    """The core network ``core`` (one of :data:`CORES`); ``options``: its own keyword options."""
    common = {"latent": latent, "hidden": latent, "hidden_layers": hidden_layers, **options}
    if core == "bsms_gnn":
        return BSMSGNN(node_in, node_out, edge_dims, n_levels, **common)
    if core == "meshgraphnets":
        return MeshGraphNets(node_in, node_out, edge_dims, n_passes=n_passes, **common)
    if core == "ms_gnn_grid":
        from bsms.models.ms_gnn_grid import MSGNNGrid
        return MSGNNGrid(node_in, node_out, edge_dims, **common)
    if core == "graph_unets":  # as many levels as BSMS-GNN would use
        from bsms.models.graph_unets import GraphUNets
        return GraphUNets(node_in, node_out, edge_dims, n_levels, **common)
    raise ValueError(f"unknown model {core!r}; choose one of {', '.join(CORES)}")


def _offsets(points: Tensor, edge_index: Tensor, dim: int) -> Tensor:
    """points: (n, k d), k points of dimension d per node -> (E, k (d + 1)): for each of the k,
    x_receiver - x_sender and its norm."""
    delta = points.index_select(0, edge_index[1]) - points.index_select(0, edge_index[0])
    delta = delta.view(delta.shape[0], points.shape[1] // dim, dim)
    return torch.cat([delta, delta.norm(dim=-1, keepdim=True)], dim=-1).flatten(1)


class LearnedSimulator(nn.Module):
    """A core network (``bsms_gnn`` or ``meshgraphnets``) with its features and normalisers.

    Args:
        core: name of the core network.
        dim: spatial dimension d.
        n_levels: levels the core uses (1 for meshgraphnets).
        contact: whether graphs carry contact edges.
        n_constants: per-node scene constants appended to the node inputs.
        penetration: the graphs carry ``penetration`` (N, d), appended to the node inputs
            (``graph.penetration``, :mod:`bsms.physics.penetration`).
        clearance: the graphs carry ``clearance`` (N, d), appended after it (``graph.clearance``).
        elastic: the graphs carry ``elastic`` (N, d), the body's linear-elastic answer to the
            penetration loads, appended last (``graph.elastic``, :mod:`bsms.physics.elastic`).
        latent: width of the latents.
        n_passes: message passes of meshgraphnets.
        hidden_layers: hidden layers of every MLP.
        max_accumulations: batches after which the normalisers freeze.
        core_options: options of the core beyond these (``transition`` of bsms_gnn, ...).
        fields: the data's field spec (default: Lagrangian of dimension ``dim``).
        edge_velocity: mesh edges also carry v_receiver - v_sender and its norm (Lagrangian data with
            material and world positions of one dimension): a rigid turn's rate is then on every edge,
            Delta v = omega x Delta x, instead of something messages must compare node by node.
        mirror_average: :meth:`velocity_change` (inference) is the mean of the answer and the
            reflection of the answer to the reflected graph (x -> -x, :func:`bsms.augment.reflected`):
            exactly mirror-equivariant, the network run on both images (in one pass where the core
            can: :meth:`_paired`). Lagrangian data only.
        rigid_part: the output is the velocity change's rigid-motion part over each body's free nodes
            (its best 2D similarity, 3D affine field: :mod:`bsms.models.body_motion`) and the rest,
            each from its own channels of the core (2 d outputs) with its own normaliser, both fitted
            as parts of the one answer: a stiff body's rest is small, so are its errors (Lagrangian
            data with material and world positions of one dimension).
        rigid_step: at inference (every rollout) the next velocity's affine part over each body's free
            nodes is made a rigid motion, the rotation nearest it (:func:`~bsms.models.body_motion.rigid_step`):
            a stiff body keeps its size and shape however the answer's affine part errs. For stiff bodies
            (whose affine strain the frames do not show); same data as rigid_part.
    """

    def __init__(self, core: str, dim: int, n_levels: int = 1, contact: bool = False, n_constants: int = 0,
                 latent: int = 128, n_passes: int = 15, hidden_layers: int = 2, max_accumulations: int = 1_000_000,
                 core_options: dict | None = None, fields: FieldSpec | None = None, penetration: bool = False,
                 clearance: bool = False, elastic: bool = False,
                 mirror_average: bool = False, edge_velocity: bool = False, rigid_part: bool = False,
                 rigid_step: bool = False):
        super().__init__()
        if core not in CORES:
            raise ValueError(f"unknown model {core!r}; choose one of {', '.join(CORES)}")
        spec = FieldSpec.lagrangian(dim) if fields is None else fields
        if spec.dim != dim or (contact and spec.contact_edge_dim is None):
            raise ValueError(f"the field spec ({spec.describe()}) does not fit dim={dim}, contact={contact}")
        if mirror_average and not spec.is_lagrangian:
            raise ValueError(f"mirror_average reflects positions and velocities; this data has {spec.describe()}: "
                             "leave it off")
        if edge_velocity and not (spec.is_lagrangian and spec.material_dim == dim):
            raise ValueError(f"edge_velocity differences node velocities along mesh edges; this data has "
                             f"{spec.describe()}: leave it off")
        if (rigid_part or rigid_step) and not (spec.is_lagrangian and spec.material_dim == dim and dim in (2, 3)):
            raise ValueError(f"rigid_part and rigid_step split a body's velocity into its rigid-motion part and "
                             f"the rest; this data has {spec.describe()}: leave them off")
        self.dim, self.contact, self.spec, self.latent = dim, contact, spec, latent
        self.mirror_average, self.edge_velocity, self.rigid_part = mirror_average, edge_velocity, rigid_part
        self.rigid_step = rigid_step
        self.n_levels = 1 if core in SINGLE_LEVEL else n_levels
        self.penetration, self.clearance, self.elastic = penetration, clearance, elastic
        node_in = spec.node_in + spec.n_types + n_constants + dim * (int(penetration) + int(clearance) + int(elastic))
        edge_dims = [spec.mesh_edge_dim + (dim + 1) * int(edge_velocity)] + ([spec.contact_edge_dim] if contact else [])
        node_out = spec.node_out * (2 if rigid_part else 1)
        self.core = build_core(core, node_in, node_out, edge_dims, n_levels=n_levels, latent=latent,
                               n_passes=n_passes, hidden_layers=hidden_layers, options=dict(core_options or {}))
        if getattr(self.core, "needs_context", False) and spec.material_dim != dim:
            raise ValueError(f"model {core} reads material and world positions of one dimension; this data has "
                             f"{dim}D positions on a {spec.material_dim}D mesh: use bsms_gnn or meshgraphnets")
        self.node_normalizer = Normalizer(node_in, max_accumulations)
        self.output_normalizer = Normalizer(spec.node_out, max_accumulations)  # rigid_part: of the rigid-motion part
        if rigid_part:  # of the rest
            self.residual_normalizer = Normalizer(spec.node_out, max_accumulations)
        self.edge_normalizers = nn.ModuleList(
            nn.ModuleList(Normalizer(size, max_accumulations) for size in edge_dims) for _ in range(self.n_levels)
        )

    def node_features(self, graph: LevelGraph) -> Tensor:
        """(N, node_in) raw node inputs."""
        spec = self.spec
        for name, needed in (("fields", not spec.is_lagrangian), ("type_code", bool(spec.types))):
            if needed and name not in graph:
                raise ValueError(f"the model learned {spec.describe()} and reads '{name}' of its graphs, which this "
                                 "graph lacks; build scenarios from the data's trajectories (Scenario.from_trajectory)")
        state = graph.velocity if spec.is_lagrangian else graph.fields
        codes = graph.type_code if spec.types else graph.node_type
        parts = [state, nn.functional.one_hot(codes, spec.n_types).to(state.dtype)]
        if "constants" in graph:
            parts.append(graph.constants)
        for name, used, what in (("penetration", self.penetration, "how far obstacles reach into the body"),
                                 ("clearance", self.clearance, "where the container's walls are")):
            if used:
                if name not in graph:
                    raise ValueError(f"the model reads {what} ('{name}', graph.{name}), which this graph lacks; "
                                     f"build it with graph.{name}: true")
                parts.append(graph[name])
        if self.elastic:
            if "elastic" not in graph:
                raise ValueError("the model reads the body's elastic answer to the push ('elastic', graph.elastic), "
                                 "which this graph lacks; build it with graph.elastic: true")
            parts.append(graph.elastic)
        return torch.cat(parts, dim=-1)

    def _level(self, graph: LevelGraph, l: int, accumulate: bool, reflect: bool = False) -> Level:
        """Level ``l`` of ``graph`` as the core reads it; ``reflect`` (inference, Lagrangian data
        with material and world positions of one dimension): each edge set's features followed by
        those of the mirror image, (E, 2 F), as :meth:`_paired` runs them."""
        nodes, edge_index = graph[f"nodes_{l}"], graph[f"edge_index_{l}"]
        if l < getattr(self.core, "first_level", 0) and l + 1 < self.n_levels:  # a level that passes no messages
            return Level([], graph.transition("down", l), graph.transition("up", l), nodes)
        spec = self.spec
        normalizers = self.edge_normalizers[l]
        if spec.is_lagrangian and spec.material_dim == self.dim:
            parts = [graph.rest_pos, graph.pos] + ([graph.velocity] if self.edge_velocity else [])
            rest_and_pos = torch.cat(parts, dim=-1).index_select(0, nodes)
            world = rest_and_pos[:, self.dim: 2 * self.dim]
            edge_sets = [EdgeSet(edge_index, self._edge_inputs(normalizers[0], rest_and_pos, edge_index, accumulate,
                                                               reflect))]
        elif reflect:
            raise ValueError("reflected edge inputs need Lagrangian data with material and world positions of one "
                             f"dimension; this data has {spec.describe()}")
        else:  # Eulerian: material offsets only; cloth: material and world offsets of different dimensions
            parts = [_offsets(graph.rest_pos.index_select(0, nodes), edge_index, spec.material_dim)]
            world = graph.pos.index_select(0, nodes)
            if spec.is_lagrangian:
                parts.append(_offsets(world, edge_index, self.dim))
            raw = torch.cat(parts, dim=-1)
            if accumulate:
                normalizers[0].accumulate(raw)
            edge_sets = [EdgeSet(edge_index, normalizers[0](raw))]
        if self.contact:
            contact_index = graph[f"contact_index_{l}"]
            contact_inputs = self._edge_inputs(normalizers[1], world, contact_index, accumulate, reflect)
            edge_sets.append(EdgeSet(contact_index, contact_inputs))
        if l + 1 == self.n_levels:
            return Level(edge_sets, None, None, nodes)
        return Level(edge_sets, graph.transition("down", l), graph.transition("up", l), nodes)

    def _edge_inputs(self, normalizer: Normalizer, points: Tensor, index: Tensor, accumulate: bool,
                     reflect: bool = False) -> Tensor:
        """The normalised offsets and lengths of ``index``'s edges between ``points`` (N, k d): at
        inference in one compiled pass where it runs (:func:`bsms.models.native.edge_offsets`).
        ``reflect``: (E, 2 k (d + 1)), followed by those of the mirror image (x -> -x)."""
        if not accumulate and not torch.is_grad_enabled():
            inputs = native.edge_offsets(points, index, self.dim, normalizer.mean, normalizer.std, reflect)
            if inputs is not None:
                return inputs
        raw = _offsets(points, index, self.dim)
        if accumulate:
            normalizer.accumulate(raw)
        if not reflect:
            return normalizer(raw)
        flip = torch.ones(raw.shape[1], dtype=raw.dtype, device=raw.device)
        flip[:: self.dim + 1] = -1.0  # the first component of each offset; lengths stay
        return torch.cat([normalizer(raw), normalizer(raw * flip)], dim=1)

    @staticmethod
    def _graph_ids(graph: LevelGraph) -> tuple[Tensor, int]:
        """((N,) the graph of each node of a batch, the number of graphs)."""
        counts = graph["n_nodes_0"]
        if torch.is_tensor(counts):  # a batch: one count per graph
            ids = torch.arange(len(counts), device=graph.pos.device)
            return ids.repeat_interleave(counts.to(graph.pos.device)), len(counts)
        return torch.zeros(graph.pos.shape[0], dtype=torch.long, device=graph.pos.device), 1

    def _context(self, graph: LevelGraph, accumulate: bool) -> Context:
        graph_ids, n_graphs = self._graph_ids(graph)
        return Context(torch.cat([graph.rest_pos, graph.pos], dim=-1), graph_ids, n_graphs, self.dim, accumulate)

    def _rigid(self, field: Tensor, graph: LevelGraph) -> Tensor:
        """``field``'s rigid-motion part per body (:func:`~bsms.models.body_motion.rigid_part`; one body per
        graph, fitted over its free nodes)."""
        ids, n = self._graph_ids(graph)
        return rigid_part(field, graph.pos.to(field.dtype), ids, n, graph.node_type == NodeType.FREE)

    def _channels(self, prediction: Tensor) -> tuple[Tensor, Tensor]:
        """rigid_part: the normalised ``prediction`` (N, 2 d)'s two sets of channels in physical units,
        before their fits (the rigid part's field, the rest's)."""
        d = self.spec.node_out
        return (self.output_normalizer.inverse(prediction[:, :d]),
                prediction[:, d:] * self.residual_normalizer.std.to(prediction.dtype))

    def _rigid_step(self, change: Tensor, graph: LevelGraph) -> Tensor:
        """``change`` with the next velocity's affine part per body a rigid motion (rigid_step)."""
        ids, n = self._graph_ids(graph)
        velocity = graph.velocity.double()
        coming = rigid_step(velocity + change.double(), graph.pos.double(), ids, n, graph.node_type == NodeType.FREE,
                            graph.frame_dt)
        return (coming - velocity).to(change.dtype)

    def accumulate_outputs(self, graph: LevelGraph) -> None:
        """Feed the output normalisers ``graph``'s targets on its ``loss_mask`` nodes (rigid_part: the
        rigid-motion part to the output normaliser, the rest to the residual one)."""
        if not self.rigid_part:
            self.output_normalizer.accumulate(graph.target[graph.loss_mask])
            return
        rigid = self._rigid(graph.target, graph)
        self.output_normalizer.accumulate(rigid[graph.loss_mask])
        self.residual_normalizer.accumulate((graph.target - rigid)[graph.loss_mask])

    def forward(self, graph: LevelGraph, accumulate: bool = False, precision: str = "f32") -> Tensor:
        """Normalised velocity change per node, (N, d) float32 (rigid_part: (N, 2 d), the rigid part's
        channels then the rest's, :meth:`physical` joins them). ``accumulate`` feeds the normalisers;
        ``precision`` (``auto``, ``bf16``, ``f32``: :mod:`bsms.models.precision`) is the core
        network's number format; features and normalisers are float32 in every precision."""
        if graph.n_levels < self.n_levels:
            raise ValueError(f"the graph has {graph.n_levels} levels but the model needs {self.n_levels}")
        dtype = network_dtype(precision, graph.pos.device, self.latent)
        raw = self.node_features(graph)
        if accumulate:
            self.node_normalizer.accumulate(raw)
        levels = [self._level(graph, l, accumulate) for l in range(self.n_levels)]
        inputs = self.node_normalizer(raw)
        context = self._context(graph, accumulate) if getattr(self.core, "needs_context", False) else None
        with network_autocast(dtype, graph.pos.device):
            return self.core(inputs, levels, context).float()

    def loss(self, graph: LevelGraph, accumulate: bool = False, reduction: str = "mean",
             precision: str = "f32") -> Tensor:
        """Squared error on the normalised target, summed over dimensions, over ``loss_mask`` nodes.

        reduction: ``"mean"`` over those nodes, or ``"sum"`` (a trainer that splits a batch
        over processes divides the sum by the node count of the whole batch); precision: as in
        :meth:`forward`.
        """
        if accumulate:
            self.accumulate_outputs(graph)
        return self.prediction_loss(self(graph, accumulate, precision), graph, reduction)

    def prediction_loss(self, prediction: Tensor, graph: LevelGraph, reduction: str = "mean") -> Tensor:
        """The loss of :meth:`loss` of a ``prediction`` (N, node_out) already made of ``graph``
        (multi-step training, :mod:`bsms.training.unroll`, goes on from the prediction it scores)."""
        if self.rigid_part:  # each part's error in its own normaliser's units (the fits are linear)
            field, rest = self._channels(prediction)
            rigid_error = self._rigid(field - graph.target, graph)
            rest_error = rest - graph.target
            rest_error = rest_error - self._rigid(rest_error, graph)
            error = ((rigid_error / self.output_normalizer.std.to(field.dtype)).square().sum(-1)
                     + (rest_error / self.residual_normalizer.std.to(rest.dtype)).square().sum(-1))
        else:
            error = (prediction - self.output_normalizer(graph.target)).square().sum(dim=-1)
        if "loss_weight" in graph:  # train.loss_weight (bsms.data.FrameDataset)
            error = error * graph.loss_weight
        error = error[graph.loss_mask]
        return error.sum() if reduction == "sum" else error.mean()

    def physical(self, prediction: Tensor, graph: LevelGraph | None = None) -> Tensor:
        """The network's normalised ``prediction`` of ``graph`` in physical units (non-free nodes as the
        network gives them; ``graph`` needed by rigid_part models, whose parts are fitted on it)."""
        if not self.rigid_part:
            return self.output_normalizer.inverse(prediction)
        if graph is None:
            raise ValueError("a rigid_part model's answer is fitted per body: give physical() the graph it answers")
        field, rest = self._channels(prediction)
        return self._rigid(field, graph) + rest - self._rigid(rest, graph)

    @torch.no_grad()
    def velocity_change(self, graph: LevelGraph, precision: str = "f32") -> Tensor:
        """(N, node_out) predicted outputs in physical units (zero on non-free nodes), float32:
        the velocity change of Lagrangian data, the spec's outputs of Eulerian data (the name
        predates specs); precision: as in :meth:`forward`."""
        if not self.mirror_average:
            change = self.physical(self(graph, precision=precision), graph)
        else:
            image = reflected(graph)
            paired = self._paired(graph, image, precision)
            ours, theirs = paired if paired is not None else (self(graph, precision=precision),
                                                              self(image, precision=precision))
            change = self.physical(ours, graph)
            change = 0.5 * (change + self.physical(theirs, image) * self._flip(change))
        if self.rigid_step:
            change = self._rigid_step(change, graph)
        return torch.where((graph.node_type == NodeType.FREE)[:, None], change, torch.zeros_like(change))

    def _paired(self, graph: LevelGraph, image: LevelGraph, precision: str) -> tuple[Tensor, Tensor] | None:
        """:meth:`forward` of ``graph`` and of its mirror ``image`` in one pass of the core, each node's
        two copies side by side (:meth:`bsms.models.bsms_gnn.BSMSGNN.runs_groups`: the copies share
        the edges, transitions and every Python step); None where the core cannot run them so (the
        caller then runs it twice). The same outputs as two passes to float32 round-off."""
        runs_groups = getattr(self.core, "runs_groups", None)
        if runs_groups is None or not runs_groups() or graph.pos.device.type != "cpu" \
                or self.spec.material_dim != self.dim \
                or network_dtype(precision, graph.pos.device, self.latent) != torch.float32:
            return None
        if graph.n_levels < self.n_levels:
            raise ValueError(f"the graph has {graph.n_levels} levels but the model needs {self.n_levels}")
        raw = torch.stack([self.node_features(graph), self.node_features(image)], 1)
        inputs = self.node_normalizer(raw.flatten(0, 1))
        # the image's edge inputs are the graph's with every offset's first component negated: made with them
        levels = [self._level(graph, l, False, reflect=True) for l in range(self.n_levels)]
        out = self.core(inputs, levels, None, groups=2)
        return out[0::2], out[1::2]

    def _flip(self, like: Tensor) -> Tensor:
        """(d,) the reflection x -> -x as a factor per component, of ``like``'s dtype and device."""
        flip = torch.ones(self.dim, dtype=like.dtype, device=like.device)
        flip[0] = -1.0
        return flip

    output = velocity_change
