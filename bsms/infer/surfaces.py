"""A part given as its closed surface (STL, OBJ, ...) to a 3D run: tetrahedralised at the model's spacing.

The family places every body scaled to its own bodies' size (:func:`datagen.families.place`);
a surface file is meshed at the resolution of the family's bodies, from the placed scene's
parameters, else the run's dataset config's, else the family's scene's defaults: where they give
``body_size`` (an edge length, as the balls and 2D press scenes do), so that once scaled its
tetrahedra have that edge length (in the file's own units: that spacing divided by the scale);
where they give ``nodes`` instead (a scene meshing each body to about that many nodes), to about
that many nodes. The tetrahedral mesh is written next to the outputs (``<name>_tetrahedra.vtu``)
and placed like any mesh file; meshing is reported apart from the learned side's setup and from
the solver's time (``meshing_s``): both start from the tetrahedral mesh.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from datagen.families import get_family, place
from datagen.mesh import Mesh, MeshError
from datagen.scenes import get_scene
from datagen.surface import ClosedSurface, tetrahedralise

__all__ = ["Tetrahedralised", "body_resolution", "placed_sizes", "tetrahedralise_parts", "with_nodes"]

NODES_PER_VOLUME = 2.0
"""Nodes of a gmsh tetrahedral mesh per cubed mean edge length of its volume (measured on boxes and
balls 7-15 edges across: 2.0-2.3): the first guess of :func:`with_nodes`."""

_PROBE = Mesh(np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), np.array([[0, 1, 2, 3]]))


@dataclass(frozen=True)
class Tetrahedralised:
    """A surface file meshed for a run: the ``mesh`` written to ``file`` at edge length ``size``
    (the file's units; ``spacing`` once the family scales it), in ``seconds``."""

    surface: Path
    file: Path
    mesh: Mesh
    size: float
    spacing: float
    seconds: float

    def record(self) -> dict:
        """Its entry in summary.json."""
        return {"surface": str(self.surface), "mesh": str(self.file), "size": self.size, "spacing": self.spacing,
                "nodes": self.mesh.n_nodes, "cells": self.mesh.n_cells, "seconds": self.seconds}


def placed_sizes(dconfig: dict, overrides: dict | None, n: int) -> tuple[list[float | None], dict]:
    """The size (largest bounding-box extent) the run's family scales each of ``n`` bodies placed
    together to (None: kept as given), and the scene parameters of that placement: found by placing
    ``n`` unit tetrahedra."""
    params = place(dconfig["family"], [_PROBE] * n, dconfig, overrides or {})["params"]
    if params.get("sizes") is not None:
        return [None if s is None else float(s) for s in params["sizes"]], params
    if params.get("size") is not None:
        return [float(params["size"])] * n, params
    return [None] * n, params


def body_resolution(dconfig: dict, params: dict) -> dict:
    """How the family's bodies are meshed: ``{"spacing": body_size}`` (an edge length) or
    ``{"nodes": nodes}`` (a node count), from the placed scene's ``params``, else the dataset
    config's, else the family's scene's defaults; {} where none says."""
    scene = get_scene(get_family(dconfig["family"]).SCENE)
    for source in (params, dconfig.get("params") or {}, getattr(scene, "DEFAULTS", {})):
        if source.get("body_size") is not None:
            return {"spacing": float(source["body_size"])}
        if source.get("nodes") is not None:
            return {"nodes": int(source["nodes"])}
    return {}


def with_nodes(surface: ClosedSurface, nodes: int) -> tuple[Mesh, float]:
    """The tetrahedral mesh of ``surface`` with about ``nodes`` nodes and the edge length it was asked
    for: a first guess from the enclosed volume (:data:`NODES_PER_VOLUME`), corrected once by the
    cube root of the count it gave; the nearer of the two."""
    first = (NODES_PER_VOLUME * surface.volume / max(int(nodes), 8)) ** (1 / 3)
    mesh = tetrahedralise(surface, first)
    second = first * (mesh.n_nodes / nodes) ** (1 / 3)
    other = tetrahedralise(surface, second)
    return (mesh, first) if abs(mesh.n_nodes - nodes) <= abs(other.n_nodes - nodes) else (other, second)


def tetrahedralise_parts(parts: dict, groups: list[list[Path]], dconfig: dict, overrides: dict | None,
                         files: dict[Path, Path]) -> dict[Path, Tetrahedralised]:
    """Each :class:`ClosedSurface` among ``parts`` (path -> Mesh or ClosedSurface) tetrahedralised at
    the run's spacing for where it is placed (with the other meshes of its group), written to
    ``files[path]``. ``ValueError`` (MeshError, ConfigError) naming the file where it cannot be."""
    out = {}
    for group in groups:
        surfaces = [k for k, p in enumerate(group) if isinstance(parts[p], ClosedSurface)]
        if not surfaces:
            continue
        sizes, params = placed_sizes(dconfig, overrides, len(group))
        resolution = body_resolution(dconfig, params)
        if not resolution:
            raise MeshError(f"family {dconfig['family']!r} names neither body_size nor nodes for its bodies, so "
                            f"surface file {group[surfaces[0]]} cannot be meshed at the model's resolution; give a "
                            "tetrahedral mesh (.msh, .vtu)")
        for k in surfaces:
            path, surface = group[k], parts[group[k]]
            scale = 1.0 if sizes[k] is None else sizes[k] / surface.extent
            start = time.perf_counter()
            if "spacing" in resolution:
                size = resolution["spacing"] / scale
                mesh = tetrahedralise(surface, size)
            else:
                mesh, size = with_nodes(surface, resolution["nodes"])
            mesh.write(files[path])
            out[path] = Tetrahedralised(path, files[path], mesh, size, size * scale, time.perf_counter() - start)
    return out
