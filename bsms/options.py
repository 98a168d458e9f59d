"""How trajectories become samples: the graph options (``graph.*``: hierarchy, contacts,
obstacles, constants, quasi-static learning) and the training noise (``noise.*``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, ClassVar, Literal

from bsms.config import ConfigError, Retired

if TYPE_CHECKING:
    from bsms.fields import FieldSpec

__all__ = ["GraphOptions", "NoiseOptions", "saved_graph_options"]


@dataclass
class GraphOptions:
    """How a trajectory becomes graphs (the ``graph`` section of a training config).

    levels: bi-stride levels, the mesh included (every graph of a run has exactly this many,
        so that batches line up; meshgraphnets uses level 0 only).
    seeding, self_loops: options of :func:`bsms.graph.bistride_levels`.
    max_coarse_degree: null (the thesis' levels: every pair of kept nodes within two hops is
        joined), or at most this many edges per node on the coarse levels, kept from the mesh's
        topology (:mod:`bsms.graph.capping`): for tetrahedral meshes, whose coarse levels
        otherwise densify (docs/scaling.md).
    obstacles: add the wall/container geometry of the trajectory as OBSTACLE nodes (with the
        edges of its facets), so that the model can see the walls it bounces off.
    contact: add world-space contact edges per frame, carried to every level.
    contact_radius: contact distance in units of the median rest edge length of the body.
        MPM bodies feel a wall about one background cell before they reach it, so it should
        cover a background cell (the family configs use 3 body edges = ~1.5 cells).
    contact_distance: the contact distance in world units instead (null: contact_radius
        applies), as datasets give it (DeepMind's deforming plate: 0.03).
    obstacle_spacing: obstacle facets are subdivided until no obstacle edge is longer than
        this many median body edges (0: keep the geometry as stored), so that a body node
        near a wall always finds wall nodes within the contact radius (with spacing 2 and
        radius 3, any body node within 2.8 edges of a wall does).
    obstacle_margin: lean obstacles: a frame's graph holds only the obstacle nodes within
        contact_radius + obstacle_margin median body edges of a body node (and, on coarser
        levels, their parents; :mod:`bsms.graph.frames`), chosen anew every frame; walls no
        body is near cost nothing. null: every obstacle node in every frame (the graph of runs
        saved before this option; :func:`saved_graph_options`).
    self_contact: also join close nodes of the same body that are not mesh neighbours.
    constants: scene parameters (names in the trajectory's ``params``) fed to every node,
        such as ``E``; positive values spanning a decade or more are best given as ``log_E``
        (the natural log of ``E``).
    quasi_static: first-order learning for driven, slow scenes (DeepMind's DEFORMINGPLATE):
        free nodes get no velocity input (0), and the model predicts their whole velocity over
        the coming frame, x_{t+1} = x_t + dt out, so a one-step error grows a rollout's error
        linearly, not quadratically, and motion the frames cannot resolve (elastic ringing,
        contact chatter aliased by the frame interval) is neither an input nor carried over.
        Kinematic nodes keep the velocity of their coming step. Position noise is then undone
        in full by the target (``noise.gamma`` does not apply; ``noise.velocity`` must be 0).
        Lagrangian data only.
    from_rest: a learned solution operator for bodies held in place under a slow drive: free
        nodes enter every graph at their rest positions X with no velocity input, so that a
        frame's graph carries only the drive (the kinematic nodes where they are, with the
        velocity of their coming step, and their contact edges to the rest shape), and the
        model predicts each free node's displacement from rest at the next frame, as a velocity
        over one frame: x_{t+1} = X + dt out. No state passes from one frame to the next, so a
        rollout's error does not accumulate and input noise has nothing to undo. It holds where
        the body's state is a function of the drive (elastic, quasi-static: inertia, ringing
        and friction history beyond what the drive's velocity tells are not modelled).
        Lagrangian data only; excludes ``quasi_static`` and training noise.
    penetration: every node also gets, as an input, how far the moving obstacles reach into
        the body at the coming frame: for a free node inside an obstacle's closed outline (not
        the container of walls around the body) where the obstacle will be, the vector to the
        outline's nearest point, else 0 (:mod:`bsms.physics.penetration`) -- the kinematic
        boundary condition an indenter imposes, which the network would otherwise have to
        infer from offsets to the obstacle's surface nodes. 2D (segment outlines) and 3D (triangles).
    clearance: the container (the walls around the body) leaves every graph:
        no nodes of its own, no contact edges to them; each node gets instead, as an input, the
        vector from it to the container's nearest point where that is within the contact radius,
        else 0 (:class:`bsms.physics.penetration.Clearance`). What a floor's contact edges told the
        network (where the wall is) it gets per node, and a frame's graph keeps only the body and
        the other obstacles (on a press test frame the floor's contacts were a third of level 0's edges).
    elastic: every node also gets, as an input, the body's first-order answer to the push: the
        linear-elastic displacement of its rest mesh (held where it touches the container, E = 1,
        the scene's Poisson ratio ``nu``) as a frictionless contact along the penetration vectors
        gives it -- every penetrating node moved along its vector by its length, free to slide
        across it, released where the contact would pull, unscaled
        (:meth:`~bsms.physics.elastic.ElasticResponse.constrained`): how far a push moves the far
        end of a thin arm, which the network would otherwise infer from the mesh alone. Needs
        ``penetration`` (its loads) and simplex body meshes; costs a solve per penetrating node.
    """

    # options measured and not adopted (docs/experiments.md): a saved run's config that gives one at
    # what the code still does loads; any other value is an error naming it (datagen.config.without_retired)
    RETIRED: ClassVar[dict[str, Retired]] = {
        "displacement": Retired("with quasi_static, free nodes' displacement from rest as their velocity input",
                                "false", "b28cc7d", lambda value, graph: value is False),
        "drive": Retired("with from_rest, every node's displacement from rest (the drive's travel) as an input",
                         "false", "066728a", lambda value, graph: value is False),
        "elastic_residual": Retired("with elastic and from_rest, the network learning the correction to the elastic "
                                    "answer", "false", "3ed6533", lambda value, graph: value is False),
        "push": Retired("how the penetration input puts a node back: leading, through the facets that face the "
                        "obstacle's travel; collider, as the data's solver pushes", "nearest", "fc6ef27",
                        lambda value, graph: value == "nearest"),
        "elastic_load": Retired("force: the elastic input loaded by forces along the pushes, its answer scaled to "
                                "them", "contact", "4a6f103", lambda value, graph: value == "contact" or (
                                    value == "force" and not graph.get("elastic"))),  # then it did nothing
    }

    levels: int = 4
    seeding: Literal["min_ave", "close_center", "random"] = "min_ave"
    self_loops: bool = True
    max_coarse_degree: int | None = None
    obstacles: bool = True
    contact: bool = True
    contact_radius: float = 3.0
    contact_distance: float | None = None
    obstacle_spacing: float = 2.0
    obstacle_margin: float | None = 0.0
    self_contact: bool = False
    constants: list[str] = field(default_factory=list)
    quasi_static: bool = False
    from_rest: bool = False
    penetration: bool = False
    clearance: bool = False
    elastic: bool = False

    def validate(self, prefix: str = "graph") -> None:
        if self.from_rest and self.quasi_static:
            raise ConfigError(f"config key '{prefix}.from_rest' predicts every frame from the rest shape and the "
                              f"drive, '{prefix}.quasi_static' steps from the frame before; set one of them to false")
        if self.elastic and not self.penetration:
            raise ConfigError(f"config key '{prefix}.elastic' loads the body where the obstacles reach into it; set "
                              f"'{prefix}.penetration: true' too, or '{prefix}.elastic: false'")
        if self.clearance and not self.obstacles:
            raise ConfigError(f"config key '{prefix}.clearance' stands in for the container's obstacle nodes; set "
                              f"'{prefix}.obstacles: true' too, or '{prefix}.clearance: false'")
        if not 1 <= self.levels <= 16:
            raise ConfigError(f"config key '{prefix}.levels' must be from 1 to 16 (the mesh included), "
                              f"got {self.levels}")
        if self.max_coarse_degree is not None and self.max_coarse_degree < 1:
            raise ConfigError(f"config key '{prefix}.max_coarse_degree' must be an integer >= 1 (coarse edges per "
                              f"node) or null (no cap), got {self.max_coarse_degree}")
        if self.obstacle_spacing < 0:
            raise ConfigError(f"config key '{prefix}.obstacle_spacing' must be >= 0 (0 keeps the stored "
                              f"geometry), got {self.obstacle_spacing}")
        if self.obstacle_margin is not None and self.obstacle_margin < 0:
            raise ConfigError(f"config key '{prefix}.obstacle_margin' must be >= 0 (in median rest edge lengths) "
                              f"or null (every obstacle node), got {self.obstacle_margin}")
        if self.contact_distance is not None and self.contact_distance <= 0:
            raise ConfigError(f"config key '{prefix}.contact_distance' must be positive (world units) or null, "
                              f"got {self.contact_distance}")
        if self.contact_radius <= 0:
            raise ConfigError(f"config key '{prefix}.contact_radius' must be positive (in median rest edge "
                              f"lengths), got {self.contact_radius}")
        for name in self.constants:
            if not name or name == "log_":
                raise ConfigError(f"config key '{prefix}.constants' holds an empty name")


# Graph options added after runs were saved with the behaviour before them: a saved run that
# lacks one was trained with this value (the new default applies to new runs only).
_BEFORE = {"obstacle_margin": None}


def saved_graph_options(graph: dict | None) -> dict:
    """The ``graph`` section of a saved run's config, completed with the values it was trained
    with for the options it predates (lean obstacles: every obstacle node in every frame)."""
    return {**_BEFORE, **(graph or {})}


@dataclass
class NoiseOptions:
    """Training noise on the inputs of free nodes, with the target corrected (``data.noise``).

    position: std (m) added to x_t; the input velocity sees it, and the target asks for a
        fraction ``gamma`` of it to be undone in position (gamma = 0 restores the velocity only,
        1 also the position; MeshGraphNets uses 0.1 for cloth). Lagrangian data only.
    velocity: std (m/s) added to the input velocity only; the target restores the velocity.
        On Eulerian data: the std of the velocity field's noise (the target of its change
        restores it).
    fields: Eulerian data: std of the noise on other input fields by name, e.g. ``{density: 10}``
        (thesis Table 4.4); a predicted change restores it.
    rigid: the position noise is its rigid-motion part over each scene's free nodes (a random 2D
        similarity or 3D affine field of the same per-component variance, :func:`bsms.augment.position_noise`):
        for ``model.rigid_part`` models, whose rest (the deformation) then stays as small as the data's,
        while the rigid part learns to undo what it can err in. Lagrangian data only.
    """

    position: float = 0.0
    velocity: float = 0.0
    gamma: float = 0.1
    fields: dict[str, float] = field(default_factory=dict)
    rigid: bool = False

    def validate(self, prefix: str = "noise") -> None:
        for name in ("position", "velocity"):
            if getattr(self, name) < 0:
                raise ConfigError(f"config key '{prefix}.{name}' is a standard deviation and must be >= 0, "
                                  f"got {getattr(self, name)}")
        for name, std in self.fields.items():
            if std < 0 or name in ("velocity", "position"):
                raise ConfigError(f"config key '{prefix}.fields.{name}' must be a standard deviation >= 0 of a field "
                                  f"other than velocity (that is '{prefix}.velocity'), got {std}")
        if not 0.0 <= self.gamma <= 1.0:
            raise ConfigError(f"config key '{prefix}.gamma' must lie in [0, 1], got {self.gamma}")

    def field_std(self, name: str) -> float:
        """Noise std of Eulerian input field ``name``."""
        return self.velocity if name == "velocity" else float(self.fields.get(name, 0.0))

    def check(self, spec: FieldSpec, source: str, prefix: str = "noise") -> None:
        """ConfigError where the noise names what ``spec`` (the data's fields) does not have."""
        if spec.is_lagrangian and self.fields:
            raise ConfigError(f"config key '{prefix}.fields' applies to Eulerian data; {source} is Lagrangian (use "
                              f"'{prefix}.position' and '{prefix}.velocity')")
        if self.rigid and not (spec.is_lagrangian and spec.material_dim == spec.dim in (2, 3)):
            raise ConfigError(f"config key '{prefix}.rigid' draws rigid motions of 2D or 3D bodies; {source} holds "
                              f"{spec.describe()}: leave it false")
        inputs = [f.name for f in spec.inputs]
        unknown = [name for name in self.fields if name not in inputs]
        if not spec.is_lagrangian and (self.position > 0 or unknown):
            key = f"{prefix}.position" if self.position > 0 else f"{prefix}.fields.{unknown[0]}"
            raise ConfigError(f"config key '{key}' does not apply: {source} is Eulerian (a fixed mesh) with input "
                              f"fields {', '.join(inputs)}; give their noise as '{prefix}.velocity' and "
                              f"'{prefix}.fields.NAME'")
