"""Writes docs/results.md from bench/results/*.json: ``python bench/report.py`` (``--check`` compares instead).

Every table names the run it comes from (script, date, machine and its load, as the JSON records them);
nothing is typed by hand, so the page says what the last run of each benchmark measured. The README's
results table is `readme_table` (tests/test_report.py checks that the README holds it verbatim).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any, Callable, Iterable

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results"
OUTPUT = REPO / "docs" / "results.md"

METHOD_NAMES = {
    "mde": "MDE alone",
    "mde_scale": "MDE + global scale",
    "ip_basic": "IP-Basic (points only)",
    "gp_default": "**GP default** (`DepthGPConfig()`)",
    "gp_paper": "GP balanced (the paper, `DepthGPConfig.paper()`)",
    "gp_balanced": "GP balanced (the paper, `DepthGPConfig.paper()`)",
    "gp_residual": "GP residual (`DepthGPConfig.residual()`)",
    "gp_residual_fit": "GP residual, fitted per frame",
}
"""Row names of the methods the tables show (others, such as experimental variants, are left out)."""


# ----------------------------------------------------------------------------- formatting


def fmt(value: Any, digits: int = 3) -> str:
    """A table cell: numbers with ``digits`` significant digits (integers as they are), None/NaN as a dash."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if value != 0 and (abs(value) >= 10**digits):
            return f"{value:.0f}"
        return f"{value:.{digits}g}"
    if isinstance(value, (list, tuple)):
        return " × ".join(fmt(v, digits) for v in value) if all(isinstance(v, int) for v in value) else str(value)
    return str(value).replace("|", "\\|").replace("\n", " ")


def pct(value: Any) -> str:
    """A share as a percentage with one decimal (None as a dash)."""
    return "–" if value is None else f"{100 * float(value):.1f}%"


def table(header: list[str], rows: Iterable[list[str]]) -> str:
    """A Markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def _load_of(d: dict) -> str:
    if isinstance(d.get("machine"), dict) and "load_average_1min" in d["machine"]:
        d = d["machine"]
    for key in ("load_average_1min", "load_average_before", "load_average"):
        if key in d:
            v = d[key]
            if v is None:
                return "not recorded"
            if isinstance(v, dict):  # {"before": ..., "after": ...}
                return ", ".join(f"{k} {fmt(x, 2)}" for k, x in v.items())
            return fmt(v[0] if isinstance(v, list) else v, 2)
    rows = d.get("rows") or d.get("runs")
    if isinstance(rows, list):
        loads = [
            r.get(k) for r in rows if isinstance(r, dict) for k in ("load_average_1min", "load_average", "load_before")
        ]
        loads = [x for x in loads if isinstance(x, (int, float))]
        if loads:
            return f"{min(loads):.2f}–{max(loads):.2f}"
    return "not recorded"


def run_info(d: dict, script: str) -> str:
    """The line under a table's heading: how to rerun it, when it ran, on what machine, under what load."""
    date = d.get("date") or d.get("started") or "not recorded"
    machine = d.get("machine", "not recorded")
    if isinstance(machine, dict):
        labels = {"platform": "{}", "cpus": "{} CPUs", "note": "{}"}
        machine = ", ".join(labels[k].format(v) for k, v in machine.items() if k in labels)
    return f"*`{script}`; run {date}; machine: {machine}; load average (1 min): {_load_of(d)}.*"


# ----------------------------------------------------------------------------- sections


def _eval_rows(rows: list[dict], methods: Iterable[str]) -> list[list[str]]:
    levels = sorted({r["level"] for r in rows})
    by = {(r["method"], r["level"]): r for r in rows}
    out = []
    for m in methods:
        if not any((m, lv) in by for lv in levels):
            continue
        rmse = " / ".join(fmt(round(by[(m, lv)]["rmse"])) if (m, lv) in by else "–" for lv in levels)
        cov = " / ".join(pct(by[(m, lv)].get("coverage_2sigma")) if (m, lv) in by else "–" for lv in levels)
        out.append([METHOD_NAMES.get(m, m), rmse, cov if "%" in cov else "–"])
    return out


EVAL_METHODS = ("mde", "mde_scale", "ip_basic", "gp_balanced", "gp_default", "gp_residual", "gp_residual_fit")


def readme_table(results: Path = RESULTS) -> str:
    """The README's results table: 7-Scenes with FastDepth, RMSE and ±2σ coverage at 50 / 200 / 500 points."""
    return _uniform_table(json.loads((results / "eval_7scenes.json").read_text(encoding="utf-8")))


def _uniform_table(d: dict) -> str:
    levels = " / ".join(str(int(lv)) for lv in sorted({r["level"] for r in d["uniform"]}))
    header = ["method", f"RMSE [mm] at {levels} points", "±2σ covers"]
    return table(header, _eval_rows(d["uniform"], EVAL_METHODS))


def section_eval_7scenes(d: dict) -> str:
    parts = [
        "## Depth completion, 7-Scenes, FastDepth",
        run_info(d, "python bench/eval_7scenes.py"),
        "FastDepth (TFLite, NYU-trained) as the MDE at 320×240; uniform samples of the Kinect depth as the points; "
        "every method on the same samples; scored on the dense Kinect depth; mean over frames.",
        _uniform_table(d),
    ]
    bands = d.get("bands")
    if bands:
        parts.append("Biased points (200, only in the lower half rows / left half columns): RMSE [mm] and ±2σ.")
        rows = []
        for m in EVAL_METHODS:
            cells = []
            for protocol in ("hband", "vband"):
                r = next((x for x in bands if x["method"] == m and x["protocol"] == protocol), None)
                cov = "" if r is None or r.get("coverage_2sigma") is None else f" ({pct(r['coverage_2sigma'])})"
                cells.append("–" if r is None else f"{fmt(round(r['rmse']))}{cov}")
            if any(c != "–" for c in cells):
                rows.append([METHOD_NAMES.get(m, m), *cells])
        parts.append(table(["method", "lower half rows", "left half columns"], rows))
    return "\n\n".join(parts)


def section_default_model(d: dict) -> str:
    parts = ["## The default model against its targets", run_info(d, "python bench/default_model.py")]
    s7 = d.get("7scenes", {})
    rows = []
    for key, r in s7.items():
        if not isinstance(r, dict) or "rmse_mm" not in r:
            continue
        points, _, share = key.partition("_points_outliers_")
        rows.append(
            [
                points,
                pct(float(share)),
                fmt(round(r["rmse_mm"])),
                fmt(round(r["mde_rmse_mm"])),
                pct(r["coverage_2sigma"]),
                fmt(r["rejected_mean"]),
                fmt(1000 * r["median_seconds"], 3),
            ]
        )
    if rows:
        parts.append("7-Scenes (FastDepth, 320×240), with and without gross outliers among the points:")
        parts.append(
            table(
                [
                    "points",
                    "outliers",
                    "RMSE [mm]",
                    "MDE RMSE [mm]",
                    "±2σ covers",
                    "rejected (mean)",
                    "median time [ms]",
                ],
                rows,
            )
        )
    vio = d.get("vio_sparse")
    if vio:
        parts.append(
            f"vio_sparse (real SLAM points, {vio['held_out_points']} held out): RMSE {fmt(round(vio['rmse_mm']))} mm "
            f"(scaled MDE {fmt(round(vio['scaled_mde_rmse_mm']))} mm, MDE alone {fmt(round(vio['mde_rmse_mm']))} mm), "
            f"±2σ covers {pct(vio['coverage_2sigma'])}."
        )
    speed = d.get("speed_kitti")
    if speed:
        parts.append("Speed, KITTI frame 0 (RT-MonoDepth-S), mean + variance:")
        parts.append(
            table(
                ["case", "points", "GP [ms]", "IP-Basic [ms]"],
                [
                    [k, fmt(v["points"]), fmt(1000 * v["seconds"]), fmt(1000 * v["ip_basic_seconds"])]
                    for k, v in speed.items()
                ],
            )
        )
    return "\n\n".join(parts)


def section_kitti_paper(d: dict) -> str:
    parts = [
        "## The paper's KITTI protocol",
        run_info(d, "python bench/kitti_paper.py"),
        fmt(d.get("ground_truth", "")),
    ]
    paper = d.get("paper_rmse_mm", {})
    for name, ds in d.get("datasets", {}).items():
        rows = [r for r in ds["summary"] if r["resolution"] == "full" and r["protocol"] == "uniform"]
        labels = list(dict.fromkeys(r["label"] for r in rows))
        methods = [m for m in ("mde", "ip_basic", "gp_paper", "gp_default") if any(r["method"] == m for r in rows)]
        by = {(r["label"], r["method"]): r for r in rows}
        body = []
        for label in labels:
            cells = [label, fmt(round(next(r["n_points"] for r in rows if r["label"] == label))), fmt(paper.get(label))]
            cells += [fmt(round(by[(label, m)]["rmse"])) if (label, m) in by else "–" for m in methods]
            cells += [pct(by[(label, m)].get("coverage_2sigma")) if (label, m) in by else "–" for m in methods[2:]]
            body.append(cells)
        header = (
            ["density", "points", "paper [mm]"] + [f"{m} [mm]" for m in methods] + [f"{m} ±2σ" for m in methods[2:]]
        )
        parts.append(f"{name} ({len(ds['frames'])} frames), RMSE at full resolution, uniform densities:")
        parts.append(table(header, body))
    if d.get("paper_note"):
        parts.append(f"The paper's column: {d['paper_note']} (a reference, not the same test).")
    return "\n\n".join(parts)


def section_calibration(d: dict) -> str:
    rows = []
    for case, r in d.get("cases", {}).items():
        rows.append(
            [
                case,
                pct(r["coverage_1sigma"]),
                pct(r["coverage_2sigma"]),
                fmt(r["median_abs_z"]),
                fmt(r["ause"]),
                fmt(round(r["rmse_mm"])),
            ]
        )
    return "\n\n".join(
        [
            "## How far to trust σ",
            run_info(d, "python bench/calibration.py"),
            f"Model: `{d.get('config', 'DepthGPConfig()')}`. Coverage of the posterior intervals, median |error| / σ, "
            "and AUSE (how well σ orders the errors; 0 is perfect).",
            table(["case", "±1σ covers", "±2σ covers", "median abs z", "AUSE", "RMSE [mm]"], rows),
        ]
    )


def section_mapping(fusion: dict, mapper: dict) -> str:
    parts = ["## Mapping, 7-Scenes"]
    if fusion:
        parts.append(run_info(fusion, "python bench/fusion.py"))
        m = fusion["mesh_vs_ground_truth_mesh"]
        rows = [
            [
                name,
                fmt(v["accuracy"]),
                fmt(v["completeness"]),
                fmt(v["chamfer"]),
                fmt(v["precision"]),
                fmt(v["recall"]),
                fmt(v["fscore"]),
            ]
            for name, v in (("MDE only", m["mde"]), ("GP, variance weights", m["gp_variance"]))
        ]
        parts.append(
            f"{fusion['frames']} frames at {fmt(fusion['resolution'])}, meshes against the mesh fused from the "
            f"Kinect depth (threshold {fmt(m['mde']['threshold'])} m):"
        )
        parts.append(
            table(
                ["variant", "accuracy [m]", "completeness [m]", "Chamfer [m]", "precision", "recall", "F-score"], rows
            )
        )
        parts.append(
            f"Per-frame depth RMSE, GP / MDE: {fmt(fusion['depth_rmse_ratio_gp_over_mde'])}; triangulated "
            f"points within ±2σ of the Kinect depth: {pct(fusion['points_coverage_2sigma']['all']['within_2sigma'])}."
        )
    if mapper:
        parts.append(run_info(mapper, "python bench/mapper.py"))
        rows = [
            [stage, fmt(v["median_ms"]), fmt(v["mean_ms"]), fmt(v["p90_ms"])]
            for stage, v in mapper["add_frame_ms"].items()
        ]
        parts.append(
            f"`Mapper.add_frame` per stage over {mapper['frames']} keyframes (lag {mapper['lag']}, window "
            f"{mapper['window']}), wall time:"
        )
        parts.append(table(["stage", "median [ms]", "mean [ms]", "p90 [ms]"], rows))
    return "\n\n".join(parts)


SEQUENCE_NAMES = {"7scenes": "7-Scenes", "hololens": "HoloLens walk"}


def _pose_sources(s: dict) -> list[tuple[str, dict]]:
    """(label, run) of a sequence's run with its own poses and each ``--perturb`` run."""
    runs = [("exact", s)]
    for run in s.get("perturbed", {}).values():
        runs.append((f"perturbed {fmt(run['cm'], 1)} cm, {fmt(run['deg'], 1)}°", run))
    return runs


def readme_mapping_table(results: Path = RESULTS) -> str:
    """The README's mapping table: what the README's own ``gpdepth3d map`` lines printed (`bench/map_recipes.py`).

    Each row is one command of the README run as written, on the version it records: the F-score at
    5 cm of the map and of the MDE alone against the mesh fused from the sensor depth, as ``map`` prints them.
    """
    d = json.loads((results / "map_recipes.json").read_text(encoding="utf-8"))
    readme = README.read_text(encoding="utf-8")

    def f3(value: Any) -> str:
        return "–" if value is None else f"{value:.3f}"

    rows = [
        [
            f"{s.get('label', SEQUENCE_NAMES.get(name, name))} ({s['frames_fused']} of {s['frames']} frames)",
            "–" if s["fscore_map"] is None else f"**{f3(s['fscore_map'])}**",
            f3(s["fscore_mde_only"]),
            fmt(s["mapping_wall_s"], 0),
        ]
        for name, s in d["sequences"].items()
        if s["command"] in readme  # the README's own lines, as written
    ]
    header = ["`gpdepth3d map` on", "F, map", "F, MDE alone", "mapping [s]"]
    version = d.get("version", "not recorded")
    return (
        table(header, rows)
        + "\n\n"
        + run_info(d, "python bench/map_recipes.py").replace("; machine:", f"; gpdepth3d {version}; machine:")
    )


def _breakdown(counts: dict, skip: tuple[str, ...] = ()) -> str:
    items = sorted(((k, n) for k, n in counts.items() if k not in skip and n), key=lambda kv: (-kv[1], kv[0]))
    return ", ".join(f"{n} `{k}`" if k[0].isupper() else f"{n} {k}" for k, n in items)


def reliability_table(results: Path = RESULTS) -> str:
    """The fuzz table of docs/reliability.md: the outcome counts of the sweeps' last run (`bench/reliability.py`)."""
    d = json.loads((results / "reliability.json").read_text(encoding="utf-8"))
    sweeps = d["sweeps"]
    rows = []
    api = sweeps.get("api_cases", {})
    if api:
        rows.append(
            ["API cases of bad input (`API_CASES`)", str(sum(api.values())), f"typed errors: {_breakdown(api)}"]
        )
    cases = sweeps.get("cli_cases", {})
    if cases:
        rows.append(["CLI cases of bad input (`CLI_CASES`)", str(sum(cases.values())), _breakdown(cases)])
    sweep = sweeps.get("cli_sweep")
    if sweep:
        n = sum(v for k, v in sweep.items() if k != "leftover temporaries")
        rows.append(["CLI sweep, garbage in every option of every command", str(n), _breakdown(sweep)])
    prop = sweeps.get("property_sweep", {})
    if prop:
        text = f"{prop.get('posterior', 0)} posteriors equal to the exact engine's; typed errors: "
        rows.append(
            [
                f"property sweep against the `exact` engine ({d.get('examples')} examples)",
                str(sum(prop.values())),
                text + (_breakdown(prop, ("posterior",)) or "none"),
            ]
        )
    return table(["what", "cases", "outcome"], rows) + "\n\n" + run_info(d, "python bench/reliability.py")


RELIABILITY = Path(__file__).resolve().parents[1] / "docs" / "reliability.md"

README = Path(__file__).resolve().parents[1] / "README.md"
README_BLOCKS = {"results": readme_table, "mapping": readme_mapping_table}
"""The README's generated blocks (between ``<!-- bench/report.py: NAME -->`` and ``<!-- end -->``)."""


def render_readme(text: str, results: Path = RESULTS, blocks: dict | None = None) -> str:
    """The README ``text`` (or another page's) with every generated block replaced by its table from ``results``."""
    for name, make in (README_BLOCKS if blocks is None else blocks).items():
        start, end = f"<!-- bench/report.py: {name} -->", "<!-- end -->"
        if start not in text:
            raise SystemExit(f"no {start} block to fill")
        head, rest = text.split(start, 1)
        text = head + start + "\n" + make(results) + "\n" + end + rest.split(end, 1)[1]
    return text


def _f_and_coverage(run: dict) -> str:
    coverage = run.get("points_within_2sigma")
    return fmt(run["fscore"]) + ("" if coverage is None else f" ({pct(coverage)})")


def section_mapping_selection(d: dict) -> str:
    """Each mapping default chosen on one sequence (best F there) and its F on the other beside the other values'."""
    parts = [
        "## Mapping defaults, chosen on one sequence, confirmed on the other",
        run_info(d, "python bench/mapping_sequences.py --select ..."),
        "One `MapperConfig` field at a time, the others at their defaults; each value's F at 5 cm on both "
        "sequences (in brackets: the share of the points within ±2σ of the sensor depth). The default (**bold**) is "
        "the value of best F on the sequence it is chosen on among those whose points keep ±2σ at 90–98 % there "
        "and whose F on the other sequence is within 0.01 of the best there; when none is, the one the other "
        "sequence does best with (`choose` in the script).",
    ]
    rows = []
    for field, entry in d["fields"].items():
        on = entry.get("chosen_on", d["choose_on"])
        for value, by_seq in entry["values"].items():
            mark = "**" if value == entry["chosen"] else ""
            rows.append(
                [f"`{field}`", f"{mark}{value}{mark}", SEQUENCE_NAMES.get(on, on)]
                + [_f_and_coverage(by_seq[seq]) for seq in sorted(by_seq)]
            )
    seqs = sorted(next(iter(next(iter(d["fields"].values()))["values"].values())))
    header = ["field", "value", "chosen on", *(f"F, {SEQUENCE_NAMES.get(q, q)}" for q in seqs)]
    parts.append(table(header, rows))
    return "\n\n".join(parts)


def section_mapping_sequences(d: dict) -> str:
    """The `Mapper`'s defaults on both shared posed sequences, with its own points and with pycolmap's."""
    command = "python bench/mapping_sequences.py" + "".join(f" --perturb {p}" for p in d.get("perturb", []))
    parts = ["## Mapping two posed sequences, defaults", run_info(d, command)]
    rows = []
    for name, s in d["sequences"].items():
        for label, run in _pose_sources(s):
            rows.append(
                [
                    f"{name} ({s['frames']} frames, {fmt(s['resolution'][1])}×{fmt(s['resolution'][0])})",
                    label,
                    fmt(run["fscore"]),
                    fmt(run["metrics"]["mapper"]["precision"]),
                    fmt(run["metrics"]["mapper"]["recall"]),
                    fmt(run["fscore_mde_only"]),
                    fmt(run["points_per_frame_median"], 0),
                    pct(run["points_within_2sigma"]),
                    fmt(run.get("frames_pose_warned")),
                    fmt(run.get("frames_mde_fallback")),
                    fmt(run.get("colmap", {}).get("fscore")),
                    fmt(run["add_frame_ms"]["median"], 0),
                    fmt(run.get("mde_ms", {}).get("median"), 0),
                ]
            )
    parts.append(
        "`Mapper()` with FastDepth at a 320-px working width and its own triangulated points (no sensor depth "
        "used); meshes against the mesh fused from the sensor depth, F at 5 cm. MDE only: `MapperConfig(refine="
        "False)`, given the same poses. Perturbed: every pose given to both moved by the distance and turned by the "
        "angle shown, in random directions, independently per frame (`--perturb CM,DEG`, seeded); the reference "
        "mesh keeps the sensor's own poses. Pose warnings: frames whose tracks disagree with their pose. MDE "
        "fallbacks: frames fused as their rescaled MDE (held-out points). pycolmap: the same map with pycolmap's "
        "points (poses held fixed, σ 3 % of the distance). The MDE's own time per frame is beside `add_frame`'s "
        "(which includes it), from the same run."
    )
    parts.append(
        table(
            [
                "sequence",
                "poses",
                "F",
                "precision",
                "recall",
                "F, MDE only",
                "points / frame",
                "points within ±2σ",
                "pose warnings",
                "MDE fallbacks",
                "F, pycolmap points",
                "`add_frame` median [ms]",
                "MDE median [ms]",
            ],
            rows,
        )
    )
    return "\n\n".join(parts)


def _scalars(row: dict) -> dict:
    return {k: v for k, v in row.items() if v is None or isinstance(v, (int, float, str, bool))}


def section_rows(title: str, script: str, d: dict, note: str = "", max_columns: int = 10) -> str:
    """A benchmark whose JSON holds a list of flat ``rows``: its scalar columns, first ``max_columns``."""
    rows = [_scalars(r) for r in d.get("rows", []) if isinstance(r, dict)]
    columns: list[str] = []
    for r in rows:
        columns += [k for k in r if k not in columns and not k.startswith("load") and k != "date"]
    columns = columns[:max_columns]
    parts = [f"## {title}", run_info(d, script)]
    if note:
        parts.append(note)
    parts.append(table(columns, [[fmt(r.get(c)) for c in columns] for r in rows]))
    return "\n\n".join(parts)


def section_engines_kitti(d: dict, title: str, script: str) -> str:
    rows, kissgp_runs = [], set()
    for r in d.get("rows", []):
        cells = [r["resolution"], fmt(r["density"]), fmt(r["points"]), fmt(1000 * r["ip_basic_seconds"])]
        for model in ("default", "paper"):
            m = r.get(model)
            cells.append("–" if not m else f"{fmt(1000 * m['seconds'])} ({m.get('route', '')})")
        k = r.get("kissgp") or {}
        if "from_run" in k:
            kissgp_runs.add(k["from_run"])
        if "seconds" in k:
            cells.append(fmt(1000 * k["seconds"]))
        elif "timeout_seconds" in k:
            cells.append(f"> {fmt(1000 * k['timeout_seconds'])}")
        else:
            cells.append("not run")
        rows.append(cells)
    parts = [f"## {title}", run_info(d, script)]
    if kissgp_runs:
        parts.append(f"The KISS-GP column comes from the run of {', '.join(sorted(kissgp_runs))} on the same machine.")
    summary = d.get("targets", {}).get("summary")
    if summary:
        parts.append("; ".join(summary) + ".")
    parts.append(
        table(
            [
                "output",
                "density",
                "points",
                "IP-Basic [ms]",
                "default [ms] (route)",
                "paper [ms] (route)",
                "KISS-GP [ms]",
            ],
            rows,
        )
    )
    return "\n\n".join(parts)


def section_cuda(d: dict) -> str:
    rows = []
    for r in d.get("rows", []):
        cpu, cuda = r.get("cpu") or {}, r.get("cuda") or {}
        rows.append(
            [
                r.get("model", ""),
                r["resolution"],
                fmt(r["density"]),
                fmt(r["points"]),
                fmt(1000 * cpu["seconds"]) if cpu else "–",
                fmt(1000 * cuda["seconds"]) if cuda else "–",
            ]
        )
    return "\n\n".join(
        [
            "## CPU and CUDA",
            run_info(d, "python bench/cuda.py") + f" *GPU: {d.get('gpu', 'none')}; torch {d.get('torch', '')}.*",
            table(["model", "output", "density", "points", "CPU [ms]", "CUDA [ms]"], rows),
        ]
    )


def section_speed(d: dict) -> str:
    """The default model's warm frame on KITTI, stage by stage, beside IP-Basic (bench/speed.py)."""
    stages = ("setup", "fit", "lattice", "engine", "detail", "assemble", "calibrate")
    cuda = any("cuda" in r for r in d.get("rows", []))
    rows = []
    for r in d.get("rows", []):
        cpu = r["cpu"]
        cells = [f"{r['grid']}, {r['density']}", fmt(r["points"]), cpu.get("route", ""), fmt(cpu["median_ms"])]
        cells += [fmt(cpu["stages_median_ms"].get(k)) for k in stages] + [fmt(r.get("ip_basic_ms"))]
        if cuda:
            cells += [fmt(r["cuda"]["median_ms"]) if "cuda" in r else "–"]
        rows.append(cells)
    header = ["grid, LiDAR", "points", "route", "total [ms]", *(f"{k} [ms]" for k in stages), "IP-Basic [ms]"]
    m = d.get("machine", {})
    parts = [
        "## Speed of a warm frame (the default model, KITTI)",
        f"*`python bench/speed.py`; run {d.get('date', 'not recorded')}; machine: {m.get('cpu', '?')}, "
        f"{m.get('cpus', '?')} CPUs, numba {m.get('numba_threads', '?')} threads; load average (1 min) "
        f"{fmt(d.get('load_average_before', [None])[0], 2)} before, {fmt(d.get('load_average_after', [None])[0], 2)}"
        f" after; GPU: {d.get('gpu') or 'none'}.*",
        "Median of the calls after two warm-up calls, mean + variance; *fit* is the slope and the outlier screen, "
        "*engine* the engine's solve. A shared machine's load inflates every time: compare within one table.",
        table(header + (["CUDA total [ms]"] if cuda else []), rows),
    ]
    seq = d.get("sequence")
    if seq:
        parts.append(
            f"A sequence ({seq['frames']} kitti_tiny frames at 1/3, all LiDAR) through `DepthCompleter.map`: "
            f"{fmt(seq['serial_ms_per_frame'])} ms per frame with one worker, {fmt(seq['parallel_ms_per_frame'])} ms "
            f"with {seq['workers']} (again: {fmt(seq['serial_again_ms_per_frame'])} / "
            f"{fmt(seq['parallel_again_ms_per_frame'])}); largest difference of the posteriors "
            f"{fmt(seq['max_abs_difference'])}."
        )
    cold = d.get("cold_start")
    if cold:
        parts.append(
            f"`gpdepth3d demo` with an empty numba cache: {fmt(cold['first_run_s'])} s ({fmt(cold['first_run_cpu_s'])} "
            f"s of CPU in the command's process; a second process compiles kernels ahead on another core, "
            f"`gpdepth3d.gp.compile_ahead`); the next run, loading the compiled kernels: {fmt(cold['second_run_s'])} s "
            f"({fmt(cold['second_run_cpu_s'])} s of CPU)."
        )
    return "\n\n".join(parts)


def section_viewer(d: dict) -> str:
    med = d.get("median", {})
    return "\n\n".join(
        [
            "## Viewer start-up",
            run_info(d, "python bench/viewer_startup.py"),
            f"{fmt(d.get('what', ''))}: page {fmt(med.get('page'))} s, panel {fmt(med.get('panel'))} s, first frame "
            f"{fmt(med.get('first_frame'))} s (median of {len(d.get('runs', []))} runs).",
        ]
    )


def section_batch(d: dict) -> str:
    s = d.get("summary", {})
    note = (
        f"{d['settings']['frames']} frames, {d['settings']['resolution']}, {d['settings']['n_input']} points, "
        f"`{d['settings']['config']}`. Scaling 2 vs 1 worker: {fmt(s.get('scaling_2_vs_1'))}×; overhead "
        f"{fmt(s.get('overhead_per_frame_s'))} s per frame."
    )
    return section_rows("Datasets on Dask", "python bench/batch.py", d, note)


SEQUENCE_NAMES = {"7scenes": "7-Scenes", "hololens": "HoloLens walk"}


def section_sfm(d: dict) -> str:
    """`gpdepth3d map` without poses (pycolmap SfM) and the sigma of pycolmap's points (bench/sfm.py)."""
    runs = d.get("runs", {})
    rows = []
    for name, r in runs.items():
        first = r["pieces"][0] if r["pieces"] else {}
        scale = first.get("scale") or {}
        frames = max(r["frames"], 1)
        scored = [(p["frames_fused"], p["fscore"]) for p in r["pieces"] if p.get("fscore") is not None]
        weighted = sum(n * f for n, f in scored) / sum(n for n, _ in scored) if scored else None
        rows.append(
            [
                SEQUENCE_NAMES.get(name, name),
                f"{r['registered']} / {r['frames']} ({len(r['pieces'])})",
                f"{first.get('frames', 0)}",
                f"{fmt(scale.get('scale'), 4)} ± {fmt(scale.get('sigma'), 4)} (MAD {pct(scale.get('mad'))})",
                fmt(r.get("fscore_map")),
                fmt(weighted),
                fmt(r.get("fscore_mde_only")),
                f"{fmt(r['process_wall_s'], 0)} / {fmt(r['process_cpu_s'], 0)}",
                f"{fmt(r['process_cpu_s'] * 100 / frames, 0)}",
                f"{fmt(r['loadavg_before'][0], 1)}–{fmt(r['loadavg_after'][0], 1)}",
            ]
        )
    parts = [
        "## A map from images alone (pycolmap SfM on the CPU)",
        run_info(d, "python bench/sfm.py"),
        "`gpdepth3d map` without `--poses` as docs/mapping.md writes it: registered images (pieces), the largest "
        "piece's frames and metric scale (metres per SfM unit, ± its bootstrap sigma over frames; MAD: spread of the "
        "per-point ratios), F at 5 cm of the largest piece's map and of the MDE alone against the mesh fused from the "
        "sensor depth with the same poses (all pieces: each piece's F weighted by its frames), wall and CPU seconds of the whole process (SfM, scale, mapping, scoring) "
        "and CPU seconds per 100 frames, load average before–after.",
        table(
            [
                "sequence",
                "registered (pieces)",
                "largest piece",
                "scale",
                "F map",
                "F, all pieces",
                "F MDE only",
                "wall / CPU [s]",
                "CPU per 100 frames [s]",
                "load",
            ],
            rows,
        ),
    ]
    parts += _sfm_pieces(runs)
    sigma = d.get("sigma")
    if sigma:
        rules = list(sigma["rules"])
        header = ["sequence", "observations", "median abs. rel. error"] + [f"±2σ: {k}" for k in rules]
        srows = []
        for name, row in sigma["sequences"].items():
            srows.append(
                [SEQUENCE_NAMES.get(name, name), str(row["observations"]), pct(row["median_abs_rel_error"])]
                + [f"{pct(row[k]['coverage_2sigma'])} (σ {pct(row[k]['median_sigma_rel'])})" for k in rules]
            )
        described = "; ".join(
            f"{k}: relative {fmt(v['relative'], 4)}, geometric {fmt(v['geometric'], 2)}"
            for k, v in sigma["rules"].items()
        )
        mapped = ", ".join(
            f"{SEQUENCE_NAMES.get(n, n)} {pct(r['as mapped']['coverage_2sigma'])} "
            f"(median error {pct(r['as mapped']['median_abs_rel_error'])})"
            for n, r in sigma["sequences"].items()
        )
        errors = ", ".join(
            f"{SEQUENCE_NAMES.get(n, n)} {'+' if r['scale_error'][0] >= 0 else ''}{pct(r['scale_error'][0])}"
            for n, r in sigma["sequences"].items()
            if r.get("scale_error")
        )
        parts += [
            f"The network's scale against the one factor that fits the sensor depth (largest piece): {errors}.",
            "### The depth sigma of pycolmap's points",
            "Every (point, image) observation of the SfM models above against the sensor depth at its pixel, each "
            "model scaled by the one factor that fits the sensor best (a metric SLAM's points). Share of "
            f"observations within ±2σ (and the median σ over the distance) per rule ({described}); the fitted rule "
            f"is fitted on {SEQUENCE_NAMES.get(sigma['fitted_on'], sigma['fitted_on'])} and checked on the other "
            "sequence (`PointSigmaRule`, docs/mapping.md).",
            table(header, srows),
            f"As mapped (the network's scale, the default rule widened by the scale's sigma): ±2σ covers {mapped}.",
        ]
    return "\n\n".join(parts)


def _sfm_pieces(runs: dict) -> list[str]:
    """Every piece of each run: its frames, scale and F, or why it was not mapped (`PieceRule`)."""
    rows = []
    for name, r in runs.items():
        for k, p in enumerate(r["pieces"]):
            scale = p.get("scale") or {}
            rows.append(
                [
                    SEQUENCE_NAMES.get(name, name),
                    str(k),
                    f"{p['frames']} ({p.get('first', '')} – {p.get('last', '')})",
                    f"{fmt(scale.get('scale'), 4)} ± {fmt(scale.get('sigma'), 4)} (MAD {pct(scale.get('mad'))})",
                    fmt(p.get("fscore")),
                    fmt(p.get("fscore_mde_only")),
                    p.get("error") or "mapped",
                ]
            )
    if not rows:
        return []
    header = ["sequence", "piece", "frames (first – last)", "scale", "F map", "F MDE only", "mapped"]
    return ["Each piece, in the order `map` writes them (`piece<k>`):", table(header, rows)]


SECTIONS: list[tuple[str, Callable[[dict], str]]] = [
    ("eval_7scenes.json", section_eval_7scenes),
    ("default_model.json", section_default_model),
    ("kitti_paper.json", section_kitti_paper),
    ("calibration.json", section_calibration),
    (
        "engines_kitti.json",
        lambda d: section_engines_kitti(d, "Speed on KITTI (the shared CPU)", "python bench/engines.py"),
    ),
    ("speed.json", section_speed),
    ("cuda.json", section_cuda),
    (
        "engines.json",
        lambda d: section_rows(
            "Engines against each other", "python bench/engines.py", d, f"MDE: {fmt(d.get('mde', ''))}."
        ),
    ),
    ("lattice.json", lambda d: section_rows("The lattice stride", "python bench/lattice.py", d)),
    (
        "kissgp.json",
        lambda d: section_rows("The GPyTorch KISS-GP engine", "python bench/kissgp.py", d, fmt(d.get("benchmark", ""))),
    ),
    ("fit_7scenes.json", lambda d: section_rows("Fitted hyperparameters, 7-Scenes", "python bench/fit.py", d)),
    ("batch.json", section_batch),
    ("viewer_startup.json", section_viewer),
    ("sfm.json", section_sfm),
]
"""One section per results file, in page order; mapping (fusion.json + mapper.json) comes after them."""


def render(results: Path = RESULTS) -> str:
    """The whole of docs/results.md from the JSON files in ``results``."""

    def load(name: str) -> dict:
        path = results / name
        return json.loads(path.read_text(encoding="utf-8")) if path.is_file() else {}

    parts = [
        "# Results",
        "Generated by `python bench/report.py` from `bench/results/*.json`: do not edit by hand; rerun the benchmark, "
        "then the report. Each table names its run: date, machine and load average (timings taken under load are "
        "noisy: compare ratios within one table).",
    ]
    for name, section in SECTIONS:
        d = load(name)
        if d:
            parts.append(section(d))
        if name == "calibration.json":
            parts.append(section_mapping(load("fusion.json"), load("mapper.json")))
            if load("mapping_sequences.json"):
                parts.append(section_mapping_sequences(load("mapping_sequences.json")))
            if load("mapping_selection.json"):
                parts.append(section_mapping_selection(load("mapping_selection.json")))
    return "\n\n".join(parts) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 when docs/results.md differs from the JSON")
    args = parser.parse_args(argv)
    text = render()
    if args.check:
        readme = README.read_text(encoding="utf-8")
        page = RELIABILITY.read_text(encoding="utf-8")
        same = OUTPUT.is_file() and OUTPUT.read_text(encoding="utf-8") == text and render_readme(readme) == readme
        same = same and render_readme(page, blocks={"reliability": reliability_table}) == page
        print("docs/results.md is up to date" if same else "docs/results.md differs: run python bench/report.py")
        return 0 if same else 1
    OUTPUT.parent.mkdir(parents=True, exist_ok=True)
    OUTPUT.write_text(text, encoding="utf-8")
    README.write_text(render_readme(README.read_text(encoding="utf-8")), encoding="utf-8")
    page = RELIABILITY.read_text(encoding="utf-8")
    RELIABILITY.write_text(render_readme(page, blocks={"reliability": reliability_table}), encoding="utf-8")
    print(f"wrote {OUTPUT} and the generated tables of {README} and {RELIABILITY}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
