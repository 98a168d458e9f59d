"""Draw the bi-stride levels of a glyph mesh: docs/images/hierarchy_levels.png (README picture).

Each panel is one level: its edges, its nodes, in orange the nodes kept for the next level
and, ringed, the BFS seeds that chose them (one per connected component).

Run: python benchmarks/figures/hierarchy_levels.py [--text BSMS] [--output PATH]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402

from bsms.graph import bistride_levels  # noqa: E402
from datagen import shapes  # noqa: E402

OUTPUT = Path("docs/images/hierarchy_levels.png")


def draw_level(axis, positions: np.ndarray, edge_index: np.ndarray, kept, seeds, title: str) -> None:
    """One panel. positions: (n, 2); edge_index: (2, E); kept, seeds: node indices or None."""
    one_way = edge_index[:, edge_index[0] < edge_index[1]]
    segments = positions[one_way.T]  # (E, 2, 2)
    width = 0.3 if one_way.shape[1] < 5000 else 0.15
    axis.add_collection(LineCollection(segments, colors="0.55", linewidths=width, zorder=1))
    dropped = np.ones(len(positions), dtype=bool)
    if kept is not None:
        dropped[kept] = False
    axis.scatter(*positions[dropped].T, s=2, color="#1f77b4", zorder=2, linewidths=0)
    axis.scatter(*positions[~dropped].T, s=5, color="#ff7f0e", zorder=3, linewidths=0)
    if seeds is not None:
        axis.scatter(*positions[seeds].T, s=40, facecolors="none", edgecolors="k", linewidths=0.8, zorder=4)
    axis.set_title(title, fontsize=9)
    axis.set_aspect("equal")
    axis.axis("off")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--text", default="BSMS")
    parser.add_argument("--size", type=float, default=0.025, help="mesh edge length (glyph height 1)")
    parser.add_argument("--levels", type=int, default=6)
    parser.add_argument("--output", type=Path, default=OUTPUT)
    args = parser.parse_args()
    mesh = shapes.glyph(args.text, args.size)
    hierarchy = bistride_levels(mesh, levels=args.levels, seeding="min_ave")
    columns = 3
    rows = -(-hierarchy.n_levels // columns)
    low, high = mesh.nodes.min(axis=0), mesh.nodes.max(axis=0)
    margin = 0.03 * (high - low).max()
    figure, axes = plt.subplots(rows, columns, figsize=(12, 1.5 * rows + 0.5),
                                subplot_kw={"xlim": (low[0] - margin, high[0] + margin),
                                            "ylim": (low[1] - margin, high[1] + margin)})
    for l, axis in enumerate(axes.ravel()):
        if l >= hierarchy.n_levels:
            axis.axis("off")
            continue
        level = hierarchy.levels[l]
        below = hierarchy.levels[l + 1] if l + 1 < hierarchy.n_levels else None
        draw_level(axis, hierarchy.select(mesh.nodes, l), level.edge_index,
                   None if below is None else below.kept, None if below is None else below.seeds,
                   f"level {l}: {level.n_nodes} nodes, {level.n_edges // 2} edges")
    title = f"Bi-stride levels of '{args.text}' (MinAve seeds ringed, kept nodes orange)"
    figure.suptitle(title, fontsize=10)
    figure.tight_layout()
    args.output.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(args.output, dpi=110)
    print(f"written {args.output} ({args.output.stat().st_size / 1024:.0f} kB)")


if __name__ == "__main__":
    main()
