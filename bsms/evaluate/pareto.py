"""The Pareto front of the speed-accuracy chart: which methods no other method beats on both counts.

A point is (wall seconds per simulated second, relative RMSE over the whole rollout); lower is
better in both. ``a`` *dominates* ``b`` when ``a`` is at least as fast and at least as accurate
and strictly better in one of the two. The rules, chosen for a reader who asks "is there a
solver setting that is both faster and more accurate than this model?":

- The ground truth (the solver at the data's own settings) is the reference: its error is zero
  by definition (its re-run's difference from the stored data is reported apart) and it takes
  part like every other point. So a learned model slower than the solver it imitates is
  dominated by it, and nothing but an exact tie can dominate the ground truth.
- A method with an unstable rollout or a failed solver run on any trajectory has infinite
  error (a user cannot tell in advance which trajectory will blow up). An infinitely
  inaccurate point is no alternative to anything, so it dominates nothing -- not even
  another failed point -- and is never on the front; any point at least as fast dominates it.
- A missing or non-finite time counts as infinitely slow.
- Equal points do not dominate each other (neither is strictly better): both stay on the front.

The front is the points with finite error that nothing dominates, fastest first; along it the
error falls as the cost grows (a step line on the chart).
"""

from __future__ import annotations

import math

__all__ = ["dominates", "dominated_by", "pareto_front", "row_point", "mark_rows", "front_lines"]


def _clean(point) -> tuple[float, float]:
    """(time, error) with None and NaN read as infinity."""
    return tuple(math.inf if v is None or math.isnan(float(v)) else float(v) for v in point)


def dominates(a, b) -> bool:
    """Whether point ``a`` = (time, error) dominates ``b``: at least as fast and as accurate,
    strictly better in one; a point of infinite error dominates nothing."""
    (ta, ea), (tb, eb) = _clean(a), _clean(b)
    if math.isinf(ea):
        return False
    return ta <= tb and ea <= eb and (ta < tb or ea < eb)


def dominated_by(points) -> list[list[int]]:
    """For each (time, error) point, the indices of the points that dominate it (in order)."""
    return [[j for j, other in enumerate(points) if j != i and dominates(other, point)]
            for i, point in enumerate(points)]


def pareto_front(points) -> list[int]:
    """Indices of the points on the front (finite error, dominated by none), fastest first
    (ties in time: the more accurate first; exact ties: in the given order)."""
    clean = [_clean(p) for p in points]
    front = [i for i, by in enumerate(dominated_by(clean)) if not by and math.isfinite(clean[i][1])]
    return sorted(front, key=lambda i: (clean[i][0], clean[i][1], i))


def row_point(row: dict, reference: str | None = None) -> tuple[float, float]:
    """(seconds per simulated second, relative RMSE all) of a summary row of :mod:`bsms.evaluate`;
    the row labelled ``reference`` (the ground truth) has error 0, a row with unstable rollouts
    or a failed run infinite error."""
    seconds = row.get("seconds_per_sim_second")
    if reference is not None and row.get("label") == reference:
        return _clean((seconds, 0.0))
    if row.get("unstable") or row.get("failed"):
        return _clean((seconds, math.inf))
    return _clean((seconds, row.get("rel_all")))


def mark_rows(rows: list[dict], reference: str | None = None) -> list[int]:
    """Set ``dominated_by`` (labels of the rows that dominate it, [] when none) and
    ``pareto_front`` (bool) on every row; return the front's row indices, fastest first."""
    points = [row_point(row, reference) for row in rows]
    front = pareto_front(points)
    for k, (row, by) in enumerate(zip(rows, dominated_by(points), strict=True)):
        row["dominated_by"] = [rows[j]["label"] for j in by]
        row["pareto_front"] = k in front
    return front


def front_lines(rows: list[dict], reference: str | None = None) -> list[str]:
    """Report sentences about rows marked by :func:`mark_rows`: the front, and for every learned
    model whether a solver setting is both at least as fast and at least as accurate."""
    front = pareto_front([row_point(row, reference) for row in rows])
    names = "; ".join(f"{rows[i]['label']}" for i in front) or "none"
    lines = [f"Pareto front (the step line; hollow points are dominated), fastest first: {names}. A method's "
             "'dominated by' lists the methods at least as fast and at least as accurate (relative RMSE over the "
             "whole rollout), strictly better in one; the ground truth counts with zero error, and a method with an "
             "unstable or failed run counts as infinitely inaccurate (it dominates nothing).", ""]
    kinds = {row["label"]: row["kind"] for row in rows}
    if all(kind == "learned" for kind in kinds.values()):  # no solver ran: nothing to say about it
        return lines
    for row in rows:
        if row["kind"] != "learned":
            continue
        solvers = [label for label in row["dominated_by"] if kinds.get(label) != "learned"]
        if math.isinf(row_point(row, reference)[1]):
            lines.append(f"- {row['label']}: unstable on {row.get('unstable')} rollout(s), so counted as infinitely "
                         "inaccurate" + (f"; dominated by the solver ({'; '.join(solvers)})." if solvers else "."))
        elif solvers:
            lines.append(f"- {row['label']}: dominated by the solver ({'; '.join(solvers)}).")
        else:
            lines.append(f"- {row['label']}: no solver setting is both at least as fast and at least as accurate.")
    return lines
