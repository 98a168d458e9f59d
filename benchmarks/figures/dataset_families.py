"""Draw the first and last frame of one trajectory per dataset family: docs/images/family_<name>.png.

Each picture has two panels (first frame, last frame): the body mesh coloured by body, and
the obstacle geometry (walls, container, clamp) in black. The trajectory is train index 0
of ``configs/datasets/<family>.yaml`` (the default sizes; ``--quick`` uses the quick variant).

Run: python benchmarks/figures/dataset_families.py [--families disks glyphs] [--quick] [--output DIR]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402

from datagen.dataset_config import load_dataset_config, trajectory_config  # noqa: E402
from datagen.families import FAMILIES  # noqa: E402
from datagen.simulation import simulate  # noqa: E402

CONFIGS = Path(__file__).resolve().parents[2] / "configs" / "datasets"
OUTPUT = Path("docs/images")


def draw_frame(axis, traj, frame: int) -> None:
    """Body triangles at ``frame`` (coloured by body id) and the obstacle facets.

    3D trajectories are seen from the front (x right, y up): the body's surface triangles and
    the outline of the container.
    """
    x = traj.positions[frame]
    body = np.zeros(len(x), int) if traj.body_id is None else traj.body_id
    triangles = traj.mesh.boundary_facets if traj.mesh.dim == 3 else traj.mesh.cells
    for k in np.unique(body):
        cells = triangles[body[triangles[:, 0]] == k]
        axis.triplot(x[:, 0], x[:, 1], cells, color=plt.get_cmap("tab10")(k % 10), linewidth=0.3)
    if traj.obstacle_nodes is not None and len(traj.obstacle_facets) and traj.mesh.dim == 3:
        (x0, y0), (x1, y1) = traj.obstacle_nodes[:, :2].min(0), traj.obstacle_nodes[:, :2].max(0)
        axis.plot([x0, x1, x1, x0, x0], [y0, y0, y1, y1, y0], color="k", linewidth=1.2)
    elif traj.obstacle_nodes is not None and len(traj.obstacle_facets):
        axis.add_collection(LineCollection(traj.obstacle_nodes[traj.obstacle_facets], colors="k", linewidths=1.2))
    axis.set_title(f"t = {traj.times[frame]:.2f} s", fontsize=9)
    axis.set_aspect("equal")
    axis.axis("off")


def draw_family(family: str, quick: bool, output: Path) -> Path:
    name = f"{family}_quick" if quick else family
    dconfig = load_dataset_config(CONFIGS / f"{name}.yaml")
    traj = simulate(trajectory_config(dconfig, "train", 0))
    figure, axes = plt.subplots(1, 2, figsize=(6, 3.4) if family != "wavy_channel" else (4, 5), dpi=110)
    for axis, frame in zip(axes, (0, len(traj.times) - 1), strict=True):
        draw_frame(axis, traj, frame)
        if traj.obstacle_nodes is not None and len(traj.obstacle_nodes):
            lo, hi = traj.obstacle_nodes.min(0), traj.obstacle_nodes.max(0)
            lo, hi = np.minimum(lo, traj.positions.min((0, 1))), np.maximum(hi, traj.positions.max((0, 1)))
            pad = 0.03 * (hi - lo).max()
            axis.set_xlim(lo[0] - pad, hi[0] + pad)
            axis.set_ylim(lo[1] - pad, hi[1] + pad)
    figure.suptitle(f"{family}: {traj.mesh.n_nodes} nodes, {len(traj.times) - 1} frames", fontsize=10)
    figure.tight_layout()
    path = output / f"family_{family}.png"
    figure.savefig(path)
    plt.close(figure)
    return path


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--families", nargs="+", default=sorted(FAMILIES), choices=sorted(FAMILIES))
    parser.add_argument("--quick", action="store_true", help="use the quick variants (seconds)")
    parser.add_argument("--output", type=Path, default=OUTPUT)
    args = parser.parse_args(argv)
    args.output.mkdir(parents=True, exist_ok=True)
    for family in args.families:
        path = draw_family(family, args.quick, args.output)
        print(f"{path} ({path.stat().st_size / 1024:.0f} kB)")


if __name__ == "__main__":
    main()
