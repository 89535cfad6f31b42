"""The paper's KITTI experiment on kitti_tiny (and kitti_object) with RT-MonoDepth-S: table and plot.

Protocol and methods: `gpdepth3d.evaluation.kitti_protocol` (1/3 resolution with closest-point
downsampling, 20 % of the LiDAR held out as ground truth before the inputs are drawn, the eight
uniform densities and the horizontal / vertical band protocols; MDE alone, IP-Basic, the paper
preset and `DepthGPConfig()`; scored at 1/3 and at full resolution). Writes
bench/results/kitti_paper.json (every row and the summary), .md (tables beside the paper's numbers)
and .png (RMSE against density per protocol).

    python bench/kitti_paper.py [--data ../shared/data] [--datasets kitti_tiny,kitti_object] [--frames N]
        [--stride K] [--densities 0.015625,0.0625,0.25,1]

Frames are interleaved across the datasets and the outputs rewritten after every frame (marked
PARTIAL until the last), so a run cut short still leaves valid results.
"""

from __future__ import annotations

import argparse
import platform
import time
from dataclasses import asdict
from pathlib import Path

from gpdepth3d.datasets import open_dataset
from gpdepth3d.evaluation.evaluation import write_csv
from gpdepth3d.gp.model import DepthGPConfig
from gpdepth3d.io import atomic_write, write_json
from gpdepth3d.evaluation.kitti_protocol import (
    PAPER_KITTI_RMSE_MM,
    KittiMethods,
    KittiProtocolConfig,
    full_table,
    lidar_frames,
    paper_table,
    plot_kitti,
    run_kitti_frame,
    summarize_kitti,
)
from gpdepth3d.mde import RTMonoDepthONNX

ROOT = Path(__file__).resolve().parents[1]


def _stamp() -> str:
    return time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())


def _jobs(data: Path, names: list[str], frames: int | None, stride: int) -> list[tuple[str, int, tuple]]:
    """(dataset, index in the dataset, (name, rgb, lidar)) interleaved across datasets, so that a run
    cut short still holds frames of each dataset."""
    per: list[list] = []
    for name in names:
        folder = data / name
        if not folder.is_dir():
            print(f"skipping {name}: {folder} not found")
            continue
        dataset = open_dataset(folder)
        indices = list(range(0, len(dataset), stride))[:frames]
        loaded = list(lidar_frames(dataset))
        per.append([(name, i, loaded[i]) for i in indices])
    jobs = []
    for k in range(max((len(p) for p in per), default=0)):
        jobs += [p[k] for p in per if k < len(p)]
    return jobs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    parser.add_argument("--models", type=Path, default=None, help="models folder (default: <data>/../models)")
    parser.add_argument("--datasets", default="kitti_tiny,kitti_object")
    parser.add_argument("--frames", type=int, default=None, help="at most this many frames per dataset")
    parser.add_argument("--stride", type=int, default=1, help="every stride-th frame of each dataset")
    parser.add_argument("--densities", default="", help="comma-separated shares (default: the paper's eight)")
    parser.add_argument("--output", type=Path, default=ROOT / "bench" / "results" / "kitti_paper")
    args = parser.parse_args()
    models = args.models or args.data.parent / "models"
    mde = RTMonoDepthONNX(models_dir=models)
    densities = tuple(float(x) for x in args.densities.split(",") if x.strip())
    config = KittiProtocolConfig(**({"densities": densities} if densities else {}))
    default = DepthGPConfig()
    methods = KittiMethods(paper=DepthGPConfig.paper(), default=default)
    same = default == DepthGPConfig.paper()
    started = _stamp()
    t0 = time.perf_counter()
    names = [d.strip() for d in args.datasets.split(",") if d.strip()]
    jobs = _jobs(args.data, names, args.frames, args.stride)
    results: dict = {
        "what": "the paper's KITTI protocol (Yoon & Kim 2020) with RT-MonoDepth-S on LiDAR-only data",
        "ground_truth": config.gt_description(),
        "protocol": {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(config).items()},
        "mde": {"model": str(mde.model_path.name), "providers": mde.providers},
        "configs": {"gp_paper": asdict(DepthGPConfig.paper()), "gp_default": asdict(default)},
        "default_equals_paper": same,
        "paper_rmse_mm": PAPER_KITTI_RMSE_MM,
        "paper_note": "KITTI depth completion, monodepth2, semi-dense ground truth, full-resolution output, uniform densities",
        "machine": f"{platform.machine()}, {platform.processor() or 'cpu'}; shared CPU (other jobs running): timings are noisy",
        "started": started,
        "frames_planned": [f"{d}/{job[0]}" for d, _, job in jobs],
        "datasets": {},
    }
    rows: dict[str, list[dict]] = {}
    seconds: dict[str, float] = {}
    for k, (name, index, (frame, rgb, lidar)) in enumerate(jobs):
        td = time.perf_counter()
        rows.setdefault(name, []).extend(run_kitti_frame(frame, rgb, lidar, mde, config, index=index, methods=methods))
        seconds[name] = seconds.get(name, 0.0) + time.perf_counter() - td
        print(f"{name} {frame} done ({k + 1}/{len(jobs)}, {time.perf_counter() - t0:.0f} s)", flush=True)
        _write(
            args.output, results, rows, seconds, config, default, same, mde, started, t0, complete=k + 1 == len(jobs)
        )
    print(args.output.with_suffix(".md").read_text())
    print(f"wrote {args.output.with_suffix('.json')}, .md, .png in {time.perf_counter() - t0:.0f} s")


def _write(output, results, rows, seconds, config, default, same, mde, started, t0, *, complete: bool) -> None:
    """Writes the json, md and png of the frames done so far (atomically; called after every frame)."""
    done = sum(len({r["frame"] for r in rs}) for rs in rows.values())
    status = "complete" if complete else f"PARTIAL: {done} of {len(results['frames_planned'])} planned frames done"
    md = [
        "# The paper's KITTI experiment with RT-MonoDepth-S",
        "",
        f"Run started {started} by `python bench/kitti_paper.py`; {status}. "
        f"**Ground truth: {config.gt_description()}.** "
        "The paper's numbers were measured on KITTI depth completion against its semi-dense ground truth "
        "(which shares pixels with the input LiDAR); ours on held-out LiDAR points that no method sees: "
        "the columns are a reference, not the same test. Shared 2-core CPU (other jobs running): times are noisy.",
        "",
        f"Methods: `mde` RT-MonoDepth-S alone ({mde.model_path.name}); `ip_basic` IP-Basic from the points only; "
        f"`gp_paper` `DepthGPConfig.paper()`; `gp_default` `DepthGPConfig()` = `{default}`"
        + (" (**identical to the paper preset at this run**)" if same else "")
        + ". GPs at 1/3 resolution; 'full' = output at the full image resolution (GPs predict it, IP-Basic is "
        "resized bilinearly, the MDE alone is the network's full-resolution output). Every GP call fits from "
        "the config (no warm start across calls).",
    ]
    plotted: list[dict] = []
    for name, rs in rows.items():
        summary = summarize_kitti(rs)
        frames = list(dict.fromkeys(r["frame"] for r in rs))
        rows_csv = write_csv(rs, output.with_name(f"{output.name}_rows_{name}.csv"))  # every cell of every frame
        results["datasets"][name] = {
            "frames": frames,
            "seconds": seconds[name],
            "summary": summary,
            "rows": rows_csv.name,
        }
        md += ["", f"## {name} ({len(frames)} frames: {', '.join(frames)}; {seconds[name]:.0f} s)", ""]
        for res, what in (("full", "full resolution"), ("grid", "1/3 resolution")):
            md += [f"### RMSE (mm), uniform densities, {what}", "", paper_table(summary, resolution=res), ""]
        for protocol in ("hband", "vband"):
            band = "rows" if protocol == "hband" else "columns"
            md += [
                f"### RMSE (mm), {protocol} ({band} {getattr(config, protocol)}), full resolution",
                "",
                paper_table(summary, protocol=protocol),
                "",
            ]
        md += ["### Every cell (mean over frames)", "", full_table(summary), ""]
        plotted += [dict(s, dataset=name) for s in summary]
    results["status"] = status
    results["seconds"] = time.perf_counter() - t0
    write_json(output.with_suffix(".json"), results)
    text = "\n".join(md) + "\n"
    atomic_write(output.with_suffix(".md"), lambda tmp: tmp.write_text(text))
    plot_kitti(plotted, output, title=f"RT-MonoDepth-S; ground truth: 20 % of the LiDAR held out; GP at 1/3 ({status})")


if __name__ == "__main__":
    main()
