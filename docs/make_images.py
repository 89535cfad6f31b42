"""Draws the README's picture from real data: ``python docs/make_images.py`` (from the repository root).

KITTI raw frame 0 of ``../shared/data/kitti_tiny`` at the paper's 1/3 resolution: the image with 1/16 of its
LiDAR points (the input), RT-MonoDepth-S's depth (the MDE), the default model's posterior mean (depth) and its
standard deviation (sigma). Writes ``docs/images/kitti_completion.png``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def draw(data: Path, models: Path, output: Path) -> Path:
    """Completes the frame with the default model and draws the four panels into ``output`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import gpdepth3d as g

    frame = g.open_dataset(data / "kitti_tiny")[0].resized(1 / 3)
    mde = g.load_frontend("rtmonodepth", models_dir=models)(frame.rgb)
    s = g.sample_uniform(frame.sparse, density=1 / 16, rng=0)
    post = g.complete(mde, s)
    lo, hi = np.percentile(frame.sparse.depth, [0, 99])  # the scene the LiDAR sees (the sky is far beyond)
    fig, axes = plt.subplots(4, 1, figsize=(8.0, 8.4), constrained_layout=True)
    axes[0].imshow(frame.rgb)
    axes[0].scatter(s.u, s.v, c=s.depth, s=2.0, cmap="turbo", vmin=lo, vmax=hi, linewidths=0)
    axes[0].set_title(f"image + {len(s)} LiDAR points (1/16 of the scan: the sparse input)")
    im = axes[1].imshow(mde, cmap="turbo", vmin=lo, vmax=hi)
    axes[1].set_title("monocular depth network alone (RT-MonoDepth-S)")
    fig.colorbar(im, ax=axes[1], label="depth [m]", shrink=0.9)
    im = axes[2].imshow(post.mean, cmap="turbo", vmin=lo, vmax=hi)
    axes[2].set_title("gpdepth3d: posterior mean (the default model)")
    fig.colorbar(im, ax=axes[2], label="depth [m]", shrink=0.9)
    im = axes[3].imshow(post.std, cmap="viridis", vmin=0, vmax=float(np.percentile(post.std, 90)))
    axes[3].set_title("gpdepth3d: posterior standard deviation (sigma)")
    fig.colorbar(im, ax=axes[3], label="sigma [m]", shrink=0.9)
    for ax in axes:
        ax.set_axis_off()
    fig.colorbar(axes[0].collections[0], ax=axes[0], label="depth [m]", shrink=0.9)
    output.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(output, dpi=90)
    plt.close(fig)
    from PIL import Image

    with Image.open(output) as im:  # 256 colours: a third of the size, the same picture
        small = im.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT)
    small.save(output, optimize=True)
    return output


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    parser.add_argument("--models", type=Path, default=REPO.parent / "shared" / "models")
    parser.add_argument("--output", type=Path, default=REPO / "docs" / "images" / "kitti_completion.png")
    args = parser.parse_args()
    print(f"wrote {draw(args.data, args.models, args.output)}")


if __name__ == "__main__":
    main()
