"""Pictures and files a person looks at: rollout GIFs, error curves, training curves, the
speed-accuracy chart, and XDMF time series for ParaView.

Every function writes one file (atomically) and returns its path; matplotlib runs headless.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from bsms.graph.obstacles import facet_edges
from datagen.atomic import atomic_path
from datagen.export import write_series as write_xdmf

__all__ = ["training_curve", "error_curves", "speed_accuracy_chart", "rollout_gif", "write_xdmf"]


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path) -> Path:
    path = Path(path)
    with atomic_path(path, suffix=path.suffix) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
    _pyplot().close(fig)
    return path


def training_curve(metrics_csv, path) -> Path:
    """Training loss (and validation one-step RMSE, right axis) against step."""
    plt = _pyplot()
    with open(metrics_csv, newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        raise ValueError(f"{metrics_csv} holds no logged steps yet; train longer than train.log_every steps")
    step = np.array([int(r["step"]) for r in rows])
    loss = np.array([float(r["loss"]) for r in rows])
    fig, ax = plt.subplots(figsize=(6, 3.6))
    ax.semilogy(step, loss, color="tab:blue", label="training loss (normalised)")
    ax.set_xlabel("step")
    ax.set_ylabel("training loss", color="tab:blue")
    valid = [(int(r["step"]), float(r["valid_rmse"])) for r in rows if r.get("valid_rmse")]
    if valid:
        right = ax.twinx()
        right.semilogy(*zip(*valid, strict=True), "o-", color="tab:red", label="validation one-step RMSE")
        right.set_ylabel("validation one-step RMSE (m)", color="tab:red")
    ax.set_title("training curve")
    ax.grid(alpha=0.3)
    return _save(fig, path)


def error_curves(curves: dict[str, list[np.ndarray]], frame_dt: float, path, bound: float | None = None) -> Path:
    """Per-step rollout RMSE against simulated time: the mean (line) and the range over
    trajectories (band) for each label; ``bound`` draws the instability threshold."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.6))
    for label, items in curves.items():
        length = max(len(c) for c in items)
        stacked = np.full((len(items), length), np.nan)
        for k, c in enumerate(items):
            stacked[k, : len(c)] = np.where(np.isfinite(c), c, np.nan)
        t = frame_dt * np.arange(1, length + 1)
        line = ax.semilogy(t, np.nanmean(stacked, axis=0), label=label)[0]
        ax.fill_between(t, np.nanmin(stacked, axis=0), np.nanmax(stacked, axis=0), color=line.get_color(), alpha=0.2)
    if bound is not None:
        ax.axhline(bound, color="k", ls="--", lw=0.8, label="instability bound")
    values = [np.asarray(line.get_ydata(), dtype=float) for line in ax.get_lines()]
    top = max((v[np.isfinite(v)].max() for v in values if np.isfinite(v).any()), default=1.0)
    ax.set_ylim(bottom=max(ax.get_ylim()[0], 1e-6 * top))  # ranges that touch 0 (exact early frames) stay readable
    ax.set_xlabel("simulated time (s)")
    ax.set_ylabel("position RMSE (m)")
    ax.set_title("rollout error")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    return _save(fig, path)


def speed_accuracy_chart(points: list[dict], path, ylabel: str = "rollout RMSE / body size",
                         rest: float | None = None) -> Path:
    """Wall seconds per simulated second (x) against rollout error (y), one labelled point per method,
    with the Pareto front (:mod:`bsms.evaluate.pareto`) as a step line.

    points: dicts with ``label``, ``kind`` ("learned", "solver", or "ground_truth": the solver
    at the data's own settings, zero error, drawn as a vertical line at its cost),
    ``seconds_per_sim_second``, ``error`` (inf or nan when unstable or failed), ``unstable``
    (count), and optionally ``front`` (on the Pareto front) and ``dominated`` (bool). ``rest``:
    the error of predicting no motion at all, drawn as a dotted horizontal line.
    Dominated points are hollow; unstable ones sit at the top edge, hollow. The step line is
    the lowest error reachable at each cost: it steps down at every front point (to the
    bottom edge at the ground truth's cost when the ground truth is on the front).
    """
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    finite = [p["error"] for p in points
              if p["kind"] != "ground_truth" and math.isfinite(p["error"]) and p["error"] > 0]
    if rest is not None and math.isfinite(rest) and rest > 0:
        finite.append(rest)
        ax.axhline(rest, color="0.4", linestyle=":", linewidth=1.2, label="body at rest (no motion predicted)")
    ceiling = 3 * max(finite) if finite else 1.0
    floor = min(finite) / 3 if finite else 1e-6
    notes = [_chart_point(ax, p, floor, ceiling) for p in points]
    xs = [p["seconds_per_sim_second"] for p in points if 0 < p["seconds_per_sim_second"] < math.inf]
    right = max(xs) * 3 if xs else 1.0
    _front_line(ax, points, floor, right)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_ylim(floor, ceiling * 2)
    if xs:
        ax.set_xlim(min(xs) / 2, right)
    ax.set_xlabel("wall seconds per simulated second (lower is faster)")
    ax.set_ylabel(ylabel)
    ax.set_title("speed against accuracy (ground truth: the solver at the data's own settings)", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    _chart_legend(ax, points)
    _place_labels(fig, ax, [n for n in notes if n is not None])
    return _save(fig, path)


# marker and colour of each kind of method on the speed-accuracy chart
_STYLES = {"learned": ("o", "tab:red"), "solver": ("s", "tab:blue"), "physics": ("^", "tab:green")}


def _chart_legend(ax, points: list[dict]) -> None:
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], color="k", lw=1, alpha=0.6, label="Pareto front")] if any(
        p.get("front") for p in points) else []
    kinds = {p["kind"] for p in points}
    handles += [Line2D([], [], marker=marker, ls="", color=colour, label=kind)
                for kind, (marker, colour) in _STYLES.items() if kind in kinds]
    if any(p.get("dominated") or not math.isfinite(p["error"]) for p in points if p["kind"] != "ground_truth"):
        handles.append(Line2D([], [], marker="s", ls="", markerfacecolor="none", markeredgecolor="gray",
                              label="hollow: dominated or unstable"))
    handles += [h for h in ax.get_lines() if h.get_label() == "body at rest (no motion predicted)"]
    ax.legend(handles=handles, fontsize=7, loc="lower left")


def _chart_point(ax, p: dict, floor: float, ceiling: float) -> tuple[str, float, float] | None:
    """One method on the speed-accuracy chart: its marker (filled unless dominated or unstable; an
    exact one, zero error, on the bottom edge) and its label to place, (text, x, y)."""
    x = p["seconds_per_sim_second"]
    if p["kind"] == "ground_truth":
        ax.axvline(x, color="tab:blue", ls="--", lw=1)
        ax.annotate(p["label"], (x, ceiling), fontsize=8, color="tab:blue", xytext=(-4, 0),
                    textcoords="offset points", ha="right", va="top")
        return None
    stable = math.isfinite(p["error"])
    y = (p["error"] if p["error"] > 0 else floor) if stable else ceiling
    style = _STYLES.get(p["kind"], ("v", "tab:gray"))
    filled = stable and not p.get("dominated", False)
    ax.scatter(x, y, marker=style[0], s=50, edgecolors=style[1], facecolors=style[1] if filled else "none",
               linewidths=1.2, zorder=3)
    notes = [n for n, on in (("unstable", not stable), ("dominated", p.get("dominated", False))) if on]
    return p["label"] + (f" ({', '.join(notes)})" if notes else ""), x, y


def _place_labels(fig, ax, notes: list[tuple[str, float, float]]) -> None:
    """Label every point, highest first, each moved down (a few lines at most) until it overlaps
    no label placed before it."""
    renderer = fig.canvas.get_renderer()
    boxes = []
    for text, x, y in sorted(notes, key=lambda n: -n[2]):
        note = ax.annotate(text, (x, y), textcoords="offset points", xytext=(6, 4), fontsize=7)
        for shift in range(1, 6):
            box = note.get_window_extent(renderer)
            if not any(box.overlaps(other) for other in boxes):
                break
            note.xyann = (6, 4 - 9 * shift)
        boxes.append(note.get_window_extent(renderer))


def _front_line(ax, points: list[dict], floor: float, right: float) -> None:
    """The Pareto front as a step line through the front points, fastest first."""
    front = sorted((p for p in points if p.get("front")), key=lambda p: (p["seconds_per_sim_second"], p["error"]))
    if not front:
        return
    xs = [p["seconds_per_sim_second"] for p in front]
    ys = [floor if p["kind"] == "ground_truth" or p["error"] <= 0 else p["error"] for p in front]
    ax.step([*xs, max(right, xs[-1])], [*ys, ys[-1]], where="post", color="k", lw=1, alpha=0.6,
            label="Pareto front", zorder=2)


def _limits(*arrays) -> tuple[np.ndarray, np.ndarray]:
    stacked = np.concatenate([a.reshape(-1, a.shape[-1]) for a in arrays if a is not None])
    stacked = stacked[np.isfinite(stacked).all(axis=1)]
    lo, hi = stacked.min(axis=0), stacked.max(axis=0)
    pad = 0.05 * (hi - lo).max()
    return lo - pad, hi + pad


def _colouring(predicted: np.ndarray, truth: np.ndarray | None, steps: int, frame_dt: float):
    """(values (T, N) the prediction is coloured by, their label, colour-scale top)."""
    if truth is not None:
        values = np.linalg.norm(predicted[:steps] - truth[:steps], axis=-1)
        label = "position error (m)"
    else:
        values = np.zeros(predicted.shape[:2])
        values[1:] = np.linalg.norm(np.diff(predicted, axis=0), axis=-1) / frame_dt
        label = "speed (m/s)"
    top = float(np.nanmax(np.where(np.isfinite(values), values, np.nan))) if np.isfinite(values).any() else 1.0
    return values, label, top if top > 0 else 1.0


def _draw_body(ax, x: np.ndarray, cells: np.ndarray, colour, vmax: float, edges: np.ndarray | None) -> list:
    """Body positions ``x`` (N, d) on ``ax``: a 2D mesh (its ``edges`` (E, 2) as one broken line,
    the cells coloured where ``colour`` is given) or a 3D point cloud projected on x-y. Returns the
    artists drawn (the caller removes them before the next frame)."""
    if x.shape[-1] == 2:
        drawn = ax.plot(*_broken_line(x[edges]), color="0.3", lw=0.3, zorder=3)
        if colour is not None:
            drawn.append(ax.tripcolor(x[:, 0], x[:, 1], cells, colour, shading="gouraud", cmap="viridis", vmin=0,
                                      vmax=vmax))
        return drawn
    if colour is not None:
        return [ax.scatter(x[:, 0], x[:, 1], c=colour, s=4, cmap="viridis", vmin=0, vmax=vmax)]
    return [ax.scatter(x[:, 0], x[:, 1], color="0.4", s=4)]


def _broken_line(segments: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Polylines (S, k, 2) as one line's x and y, broken by NaN between them (one artist, one path)."""
    gap = np.full((len(segments), 1, segments.shape[-1]), np.nan)
    joined = np.concatenate([segments[..., :2], gap[..., :2]], axis=1).reshape(-1, 2)
    return joined[:, 0], joined[:, 1]


def _blit_panel(ax, x: np.ndarray, values, name: str, when: str, cells: np.ndarray, vmax: float, edges,
                obstacle) -> None:
    """Draw one panel's moving artists onto the canvas (the obstacle's closed facets ``obstacle``
    (F, k, 2) or None, the body, the title: ``name`` and ``when``) and take them off the axes again."""
    drawn = [] if obstacle is None else ax.plot(*_broken_line(obstacle), color="0.6", lw=1)
    title = f"{name}: not finite"
    if np.isfinite(x).all():
        drawn += _draw_body(ax, x, cells, values, vmax, edges)
        title = f"{name}, {when}"
    drawn.append(ax.text(0.5, 1.01, title, transform=ax.transAxes, ha="center", va="bottom", fontsize=9))
    for artist in sorted(drawn, key=lambda a: a.get_zorder()):  # mesh lines over the colours
        ax.draw_artist(artist)
        artist.remove()


def _obstacle_frames(obstacles, steps: int):
    """Obstacle nodes by frame: (T, M, d) positions as given, or static (M, d) nodes for every frame."""
    if obstacles is None:
        return None
    nodes = np.asarray(obstacles[0])
    if nodes.ndim == 2:
        return np.broadcast_to(nodes, (steps, *nodes.shape))
    if nodes.ndim != 3 or len(nodes) < steps:
        raise ValueError(f"obstacle nodes of shape {nodes.shape}: give (M, d) static nodes or (T, M, d) positions "
                         f"for each of the {steps} frames drawn")
    return nodes


def rollout_gif(cells: np.ndarray, predicted: np.ndarray, path, truth: np.ndarray | None = None,
                obstacles: tuple[np.ndarray, np.ndarray] | None = None, frame_dt: float = 1.0,
                fps: int = 10, max_frames: int = 80, colour: tuple[np.ndarray, str] | None = None) -> Path:
    """Animated rollout of the body: ground truth (left) next to the prediction coloured by its
    position error (right); without ``truth`` the prediction alone coloured by speed.

    cells: (C, d+1) body cells; predicted / truth: (T, N, d) body-node positions; obstacles:
    (nodes, facets) drawn in grey, nodes (M, d) where they stand still or (T, M, d) where they
    sit in each frame (moving obstacles; at least as many frames as are drawn). 3D bodies are
    drawn as point clouds (x-y projection).
    colour: (values (T, N), label) to colour the prediction by instead (e.g. a field's error on
    a fixed mesh).
    """
    plt = _pyplot()
    from PIL import Image

    steps = min(len(predicted), len(truth)) if truth is not None else len(predicted)
    obstacle_frames = _obstacle_frames(obstacles, steps)
    frames = np.unique(np.linspace(0, steps - 1, min(steps, max_frames)).round().astype(int))
    panels = 2 if truth is not None else 1
    fig, axes = plt.subplots(1, panels, figsize=(4.2 * panels, 4.2), squeeze=False)
    axes = axes[0]
    lo, hi = _limits(predicted[:steps], truth[:steps] if truth is not None else None,
                     obstacle_frames[:steps] if obstacle_frames is not None else None)
    if colour is None:
        colour, label, vmax = _colouring(predicted, truth, steps, frame_dt)
    else:
        colour, label = colour
        finite = colour[np.isfinite(colour)]
        vmax = float(finite.max()) if finite.size and finite.max() > 0 else 1.0
    fig.colorbar(plt.cm.ScalarMappable(cmap="viridis", norm=plt.Normalize(0, vmax)), ax=axes[-1], fraction=0.046,
                 label=label)
    for ax in axes:
        ax.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), aspect="equal", xticks=[], yticks=[])
        ax.set_title(" ", fontsize=9)  # the title's place kept in the static background
    edges = facet_edges(np.asarray(cells)) if predicted.shape[-1] == 2 else None
    outline = None
    if obstacles is not None and len(obstacles[0]):
        facets = np.asarray(obstacles[1])
        outline = np.concatenate([facets, facets[:, :1]], axis=1)  # each facet closed, drawn as one polyline
    fig.canvas.draw()
    background = fig.canvas.copy_from_bbox(fig.bbox)  # axes, colour bar: drawn once
    images = []
    # each frame: the background restored, only the moving artists drawn on it (blitting), grabbed
    for frame in frames:
        fig.canvas.restore_region(background)
        shown = [(truth[frame], None, "solver")] if truth is not None else []
        shown.append((predicted[frame], colour[frame], "learned"))
        obstacle = None if outline is None else obstacle_frames[frame][:, :2][outline]
        for ax, (x, values, name) in zip(axes, shown, strict=True):
            _blit_panel(ax, x, values, name, f"t = {frame * frame_dt:.2f} s", cells, vmax, edges, obstacle)
        rgb = Image.fromarray(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
        images.append(rgb.quantize(256, method=Image.Quantize.FASTOCTREE))  # 8x faster than the adaptive palette
    plt.close(fig)
    path = Path(path)
    with atomic_path(path, suffix=".gif") as tmp:
        images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=round(1000 / fps), loop=0)
    return path
