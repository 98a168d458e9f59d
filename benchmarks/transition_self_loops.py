"""Measure the self-loop option of the bi-stride transitions (bsms.graph.transitions).

A smooth field is sent down the hierarchy and back up; the relative L2 error of the round
trip, with and without a kept node's own value in its averages, picks the default. One
round trip through level 1 ("1 level") and through every level ("all levels").

Run: python benchmarks/transition_self_loops.py
"""

from __future__ import annotations

import numpy as np

from bsms.graph import bistride_levels
from datagen import shapes


def smooth_field(x: np.ndarray) -> np.ndarray:
    """A smooth scalar field with a few oscillations over a unit-sized shape: (N, d) -> (N,)."""
    value = np.sin(2.0 * x[:, 0]) * np.cos(3.0 * x[:, 1]) + x[:, 0] * x[:, 1]
    return value + (np.sin(2.5 * x[:, 2]) if x.shape[1] > 2 else 0.0)


def round_trip_error(hierarchy, field: np.ndarray, depth: int) -> float:
    """Relative L2 error of down through ``depth`` levels and back up."""
    values = field
    for level in hierarchy.levels[1:depth + 1]:
        values = level.down.apply(values)
    for level in reversed(hierarchy.levels[1:depth + 1]):
        values = level.up.apply(values)
    return float(np.linalg.norm(values - field) / np.linalg.norm(field))


def main() -> None:
    meshes = {
        "disk r=1, h=0.03": shapes.disk(1.0, 0.03),
        "glyph 'BSMS', h=0.02": shapes.glyph("BSMS", 0.02),
        "annulus 0.4-1, h=0.03": shapes.annulus(0.4, 1.0, 0.03),
        "box 1^3, h=0.06": shapes.box((1.0, 1.0, 1.0), 0.06),
        "sphere r=1, h=0.12": shapes.sphere(1.0, 0.12),
    }
    print(f"{'mesh':26s} {'nodes':>7s} {'depth':>10s} {'self-loop':>10s} {'no loop':>10s}")
    for name, mesh in meshes.items():
        field = smooth_field(mesh.nodes)
        with_loop = bistride_levels(mesh, levels=3, seeding="min_ave", self_loops=True)
        without = bistride_levels(mesh, levels=3, seeding="min_ave", self_loops=False)
        for depth, label in ((1, "to level 1"), (2, "to level 2")):
            errors = [round_trip_error(hierarchy, field, depth) for hierarchy in (with_loop, without)]
            print(f"{name:26s} {mesh.n_nodes:7d} {label:>10s} {errors[0]:10.4f} {errors[1]:10.4f}")


if __name__ == "__main__":
    main()
