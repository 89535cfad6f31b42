"""The paper's KITTI experiment on kitti_tiny (and kitti_object) with RT-MonoDepth-S: table and plot.

Protocol and methods: `gpdepth3d.kitti_protocol` (1/3 resolution with closest-point
downsampling, 20 % of the LiDAR held out as ground truth before the inputs are drawn, the eight
uniform densities and the horizontal / vertical band protocols; MDE alone, IP-Basic, the paper
preset and `DepthGPConfig()`; scored at 1/3 and at full resolution). Writes
bench/results/kitti_paper.json (every row and the summary), .md (tables beside the paper's numbers)
and .png (RMSE against density per protocol).

    python bench/kitti_paper.py [--data ../shared/data] [--datasets kitti_tiny,kitti_object] [--frames N]
"""

from __future__ import annotations

import argparse
import platform
import time
from dataclasses import asdict
from pathlib import Path

from gpdepth3d.datasets import open_dataset
from gpdepth3d.evaluation import write_json
from gpdepth3d.gp.model import DepthGPConfig
from gpdepth3d.io import atomic_write
from gpdepth3d.kitti_protocol import (
    PAPER_KITTI_RMSE_MM,
    KittiMethods,
    KittiProtocolConfig,
    full_table,
    lidar_frames,
    paper_table,
    plot_kitti,
    run_kitti_protocol,
    summarize_kitti,
)
from gpdepth3d.mde import RTMonoDepthONNX

ROOT = Path(__file__).resolve().parents[1]


def _stamp() -> str:
    return time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    parser.add_argument("--models", type=Path, default=None, help="models folder (default: <data>/../models)")
    parser.add_argument("--datasets", default="kitti_tiny,kitti_object")
    parser.add_argument("--frames", type=int, default=None, help="at most this many frames per dataset")
    parser.add_argument("--output", type=Path, default=ROOT / "bench" / "results" / "kitti_paper")
    args = parser.parse_args()
    models = args.models or args.data.parent / "models"
    mde = RTMonoDepthONNX(models_dir=models)
    config = KittiProtocolConfig()
    default = DepthGPConfig()
    methods = KittiMethods(paper=DepthGPConfig.paper(), default=default)
    same = default == DepthGPConfig.paper()
    started = _stamp()
    t0 = time.perf_counter()
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
        "datasets": {},
    }
    md = [
        "# The paper's KITTI experiment with RT-MonoDepth-S",
        "",
        f"Run {started} by `python bench/kitti_paper.py`. **Ground truth: {config.gt_description()}.** "
        "The paper's numbers were measured on KITTI depth completion against its semi-dense ground truth "
        "(which shares pixels with the input LiDAR); ours on held-out LiDAR points that no method sees: "
        "the columns are a reference, not the same test.",
        "",
        f"Methods: `mde` RT-MonoDepth-S alone ({mde.model_path.name}); `ip_basic` IP-Basic from the points only; "
        f"`gp_paper` `DepthGPConfig.paper()`; `gp_default` `DepthGPConfig()` = `{default}`"
        + (" (**identical to the paper preset at this run**)" if same else "")
        + ". GPs at 1/3 resolution; 'full' = output at the full image resolution (GPs predict it, IP-Basic is "
        "resized bilinearly, the MDE alone is the network's full-resolution output).",
    ]
    plotted: list[dict] = []
    for name in [d.strip() for d in args.datasets.split(",") if d.strip()]:
        folder = args.data / name
        if not folder.is_dir():
            print(f"skipping {name}: {folder} not found")
            continue
        dataset = open_dataset(folder)
        frames = list(lidar_frames(dataset))[: args.frames]
        td = time.perf_counter()
        rows = run_kitti_protocol(frames, mde, config, methods=methods, progress=lambda f: print(f"{name} {f} done", flush=True))
        summary = summarize_kitti(rows)
        seconds = time.perf_counter() - td
        results["datasets"][name] = {"frames": [f[0] for f in frames], "seconds": seconds, "summary": summary, "rows": rows}
        md += ["", f"## {name} ({len(frames)} frames, {seconds:.0f} s)", ""]
        for res, what in (("full", "full resolution"), ("grid", "1/3 resolution")):
            md += [f"### RMSE (mm), uniform densities, {what}", "", paper_table(summary, resolution=res), ""]
        for protocol in ("hband", "vband"):
            md += [f"### RMSE (mm), {protocol} (band: {'rows' if protocol == 'hband' else 'columns'} "
                   f"{getattr(config, protocol)}), full resolution", "", paper_table(summary, protocol=protocol), ""]
        md += ["### Every cell (mean over frames)", "", full_table(summary), ""]
        plotted += [dict(s, dataset=name) for s in summary]
    if plotted:
        plot_kitti(plotted, args.output, title="RT-MonoDepth-S; ground truth: 20 % of the LiDAR held out; GP at 1/3")
    results["seconds"] = time.perf_counter() - t0
    write_json(results, args.output.with_suffix(".json"))
    text = "\n".join(md) + "\n"
    atomic_write(args.output.with_suffix(".md"), lambda tmp: tmp.write_text(text))
    print(text)
    print(f"wrote {args.output.with_suffix('.json')}, .md, .png in {results['seconds']:.0f} s")


if __name__ == "__main__":
    main()
