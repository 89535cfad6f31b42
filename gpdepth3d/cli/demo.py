"""``gpdepth3d demo``: the whole flow on built-in synthetic data."""

from __future__ import annotations

from pathlib import Path

from ..io import check_output_folder


def demo_command(*, output: Path = Path("gpdepth3d_demo"), seed: int = 0) -> None:
    """Run the whole flow on built-in synthetic data (no arguments needed) and say where the outputs are.

    Args:
        output: Folder for the outputs.
        seed: Seed of the synthetic scene.
    """
    from ..pipelines.demo import run_demo

    check_output_folder(output, "--output")
    for line in run_demo(output, seed=seed):
        print(line)
