"""The evaluation's report: the metrics table (report.md, speed_accuracy.md and .csv), the
at-rest baseline and the skill of every learned model per trajectory (:mod:`bsms.rollouts.motion`)."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import torch

from bsms.evaluate import pareto
from bsms.rollouts.motion import SKILL_KEYS
from bsms.rollouts.solver_runs import SOLVER_SETTINGS
from datagen.atomic import atomic_path
from datagen.compiled import cpu_summary

__all__ = ["COLUMNS", "GROUND_TRUTH", "fmt", "columns", "table", "field_table", "write_tables", "heading", "stability",
           "rest", "rest_lines", "skill_table", "skill_lines", "write_report", "ground_truth_row"]

GROUND_TRUTH = SOLVER_SETTINGS["ground_truth"]


def ground_truth_row(rows: list[dict]) -> dict | None:
    """The row of the solver at the data's settings, if it ran."""
    return next((r for r in rows if r["label"] == GROUND_TRUTH), None)


def fmt(value, digits: int = 3) -> str:
    if value is None:
        return "-"
    if isinstance(value, list):  # labels (dominated by)
        return "; ".join(str(v) for v in value) or "none"
    if isinstance(value, float):
        if math.isnan(value):
            return "-"
        if math.isinf(value):
            return "inf"
        return f"{value:.{digits}g}"
    return str(value)


# (row key, column title) of the metrics table in report.md, speed_accuracy.md and .csv
COLUMNS = [
    ("label", "method"), ("kind", "kind"), ("rmse_1", "RMSE@1 (m)"), ("rmse_50", "RMSE@50 (m)"),
    ("rmse_all", "RMSE all (m)"), ("rmse_all_std", "± std"), ("rel_all", "RMSE all / body size"),
    ("vs_rest", "vs at rest"), ("rigid_rel_all", "rigid part / body size"),
    ("deform_rel_all", "deformation part / body size"),
    ("unstable", "unstable rollouts"), ("first_unstable_step", "first unstable step"),
    ("setup_s", "setup per mesh (s)"), ("seconds", "s end to end"),
    ("seconds_per_sim_second", "s per simulated s (end to end)"), ("speedup", "speed-up end to end"),
    ("speedup_throughput", "speed-up, throughput"), ("latency_ms", "latency (ms per frame)"),
    ("peak_memory_mb", "peak memory (MB)"), ("dominated_by", "dominated by"),
]


def columns(spec) -> list[tuple[str, str]]:
    """The table's columns; Eulerian data: errors of the first output field, relative to its scale."""
    if spec.is_lagrangian:
        return COLUMNS
    main = spec.outputs[0].name
    return [(key, title.replace("(m)", f"({main})").replace("body size", f"{main} scale")) for key, title in COLUMNS
            if key not in SKILL_KEYS]


def table(rows: list[dict], columns=COLUMNS) -> str:
    lines = ["| " + " | ".join(title for _, title in columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(fmt(row.get(key)) for key, _ in columns) + " |" for row in rows]
    return "\n".join(lines)


def field_table(rows: list[dict]) -> str:
    """RMSE per field of every learned row (Eulerian data) as one table."""
    columns = [("label", "method"), ("field", "field"), ("rmse_1", "RMSE@1"), ("rmse_50", "RMSE@50"),
               ("rmse_all", "RMSE all"), ("scale", "field scale (RMS)"), ("rel_all", "RMSE all / scale"),
               ("unstable", "unstable rollouts")]
    flat = [{**metrics, "label": row["label"], "field": name}
            for row in rows if "fields" in row for name, metrics in row["fields"].items()]
    return table(flat, columns)


def write_tables(out: Path, rows: list[dict], columns=COLUMNS) -> None:
    with atomic_path(out / "speed_accuracy.csv") as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, [key for key, _ in COLUMNS], extrasaction="ignore")
        writer.writeheader()
        writer.writerows({k: fmt(v) if isinstance(v, list) else v for k, v in row.items()} for row in rows)
    with atomic_path(out / "speed_accuracy.md") as tmp:
        tmp.write_text(table(rows, columns) + "\n")


def _members(state: dict) -> str:
    """How many members an ensemble (:mod:`bsms.ensemble`) averages, where the model is one."""
    members = state.get("members")
    return f" (the first of an ensemble of {len(members)}, averaged frame by frame)" if members else ""


def heading(config, state, options, n_files: int, dataset_name: str, spec) -> list[str]:
    steps = "all frames" if options.steps is None else f"{options.steps} steps"
    errors = "Errors are position RMSE over free body nodes (m)" if spec.is_lagrangian else (
        f"Data: {spec.describe()}. Errors are RMSE of the `{spec.outputs[0].name}` field over free nodes (the "
        "data's units; every field under 'RMSE per field')")
    return [
        f"# Evaluation of run `{config.name}`", "",
        f"Model `{config.model.name}` after {int(state['step'])} training steps"
        f"{_members(state)}; {n_files} `{options.split}` "
        f"trajectories of dataset `{dataset_name}`; rollouts from frame 0 over {steps}. {errors}; times are wall "
        f"seconds on this machine ({cpu_summary()}), measured in this run on {torch.get_num_threads()} CPU "
        "thread(s), learned models and solver alike. Speed-ups are end to end for a new mesh: a learned model's "
        "per-mesh setup (hierarchy, factorisations, graph building) and its rollout of the mesh alone against the "
        "solver's setup and frames (its settling pre-roll apart); `speed-up, throughput` batches many meshes and "
        "frames with the setup amortised; `latency` is one frame per call.",
    ]


def stability(rows: list[dict], bound: float, size: str = "body size") -> list[str]:
    lines = []
    for row in rows:
        state = "stable on every trajectory" if not row["unstable"] else \
            f"unstable on {row['unstable']} of {row['trajectories']} (first at step {row.get('first_unstable_step')})"
        failure = f"; the solver stopped: {row['failed']}" if row.get("failed") else ""
        lines.append(f"- {row['label']}: {state} (bound {bound} x {size}){failure}")
    truth = ground_truth_row(rows)
    if truth is not None and "max_difference_from_stored" in truth:
        lines += ["", f"The solver re-run at the data's settings reproduces the stored trajectories to "
                      f"{truth['max_difference_from_stored']:.3g} m."]
    learned = [r for r in rows if r["kind"] == "learned"]
    if learned and truth is not None:
        best = min(learned, key=lambda r: r["rmse_all"])
        lines += ["", f"Fastest learned model speed-up over the ground-truth solver: "
                      f"{max(r.get('speedup', 0) for r in learned):.3g}x; most accurate: {best['label']} "
                      f"({fmt(best['rel_all'])} of the body size over the whole rollout)."]
    return lines


def rest(rows: list[dict]) -> float | None:
    """The body-at-rest error of the evaluated trajectories (every learned row holds the same)."""
    return next((r["rest_rel_all"] for r in rows if "rest_rel_all" in r), None)


def rest_lines(rows: list[dict]) -> list[str]:
    baseline = rest(rows)
    if baseline is None:
        return []
    field = next((r["field"] for r in rows if r.get("field")), None)
    if field:  # Eulerian data: the trivial answer of a fixed mesh is persistence
        return [f"Persistence (the first frame's fields held for ever): RMSE all of {field} / its scale "
                f"{fmt(baseline)} on these trajectories (dotted line on the chart); a model above it has learned less "
                "than nothing.", ""]
    return [f"Body at rest (no motion predicted, every free node kept where it is at frame 0): RMSE all / body size "
            f"{fmt(baseline)} on these trajectories (dotted line on the chart); a model above it has learned less than "
            "nothing.", ""]


def write_report(run_dir: Path, heading: list[str], rows: list[dict], learned: dict[str, list[dict]],
                 pictures: list, solver_ran: bool, bound: float, training, spec) -> Path:
    """``run_dir``/report.md: the metrics table, the chart, the skill per trajectory (Lagrangian
    data), error against time, stability, training curve and rollout pictures."""
    size = "body size" if spec.is_lagrangian else f"{spec.outputs[0].name} scale"
    fields = ["## RMSE per field", "", field_table(rows), ""] if not spec.is_lagrangian else []
    lines = [
        *heading, "", "## Metrics", "", table(rows, columns(spec)), "", *fields,
        "## Speed against accuracy", "", "![speed against accuracy](evaluation/speed_accuracy.png)", "",
        "The solver at the data's settings is the ground truth (no error of its own); cheaper solver "
        "settings are the honest baseline a surrogate must beat." if solver_ran else
        "No solver ran (--no-solver, or evaluate.solver: []; converted datasets have no scene to re-run): the "
        "chart shows the learned models alone.", "", *pareto.front_lines(rows, GROUND_TRUTH), "",
        *rest_lines(rows), *skill_lines(learned),
        "## Error against time", "", "![rollout error](evaluation/error_vs_step.png)", "",
        "## Stability", "", *stability(rows, bound, size),
    ]
    if training is not None:
        lines += ["", "## Training", "", "![training curve](evaluation/training_curve.png)"]
    if pictures:
        lines += ["", "## Rollouts (solver left, learned right, coloured by error)", ""]
        lines += [f"![rollout {k}](evaluation/{Path(p).name})" for k, p in enumerate(pictures)]
        lines += ["", "ParaView: `evaluation/rollout_0.xdmf` (warp by `displacement`)."]
    path = run_dir / "report.md"
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return path


# (metric key, column title) of the per-trajectory skill table
SKILL_COLUMNS = [
    ("rel_all", "RMSE all / body size"), ("rest_rel_all", "at rest"), ("vs_rest", "vs at rest"),
    ("rigid_rel_all", "error: rigid"), ("deform_rel_all", "error: deformation"),
    ("rest_rigid_rel_all", "motion: rigid"), ("rest_deform_rel_all", "motion: deformation"),
]


def skill_table(label: str, metrics: list[dict], names: list[str] | None = None) -> str:
    """One learned model's skill per trajectory (then the mean): its error, the at-rest error,
    their ratio, and both split into rigid and deformation parts (:mod:`bsms.rollouts.motion`)."""
    names = names or [str(k) for k in range(len(metrics))]
    cols = [("trajectory", "trajectory"), *SKILL_COLUMNS]
    rows = [{"trajectory": name, **m} for name, m in zip(names, metrics, strict=True)]
    mean = {key: float(sum(m[key] for m in metrics) / len(metrics)) for key, _ in SKILL_COLUMNS
            if metrics and all(key in m for m in metrics)}
    return f"`{label}`:\n\n" + table([*rows, {"trajectory": "mean", **mean}], cols)


def skill_lines(learned: dict[str, list[dict]]) -> list[str]:
    """The report's skill section (Lagrangian data only: rows without ``vs_rest`` are skipped)."""
    tables = [skill_table(label, metrics) for label, metrics in learned.items()
              if metrics and all("vs_rest" in m for m in metrics)]
    if not tables:
        return []
    field = next((m["field"] for metrics in learned.values() for m in metrics if m.get("field")), None)
    if field:
        return ["## Skill per trajectory", "",
                f"Eulerian data: errors of {field} / its scale; `at rest` is persistence (the first frame's fields "
                "held for ever) and `vs at rest` the model's RMSE over all steps / persistence's (above 1: it has "
                "learned nothing).", "", *[line for t in tables for line in (t, "")]]
    return ["## Skill per trajectory", "",
            "`vs at rest` = the model's RMSE over all steps / that of predicting no motion (above 1: it has learned "
            "nothing). Each error, and the true motion from frame 0, is split per frame by the best rigid fit "
            "(rotation and translation): the rigid part and the deformation left over, RMS over all steps / body "
            "size.", "", *[line for t in tables for line in (t, "")]]
