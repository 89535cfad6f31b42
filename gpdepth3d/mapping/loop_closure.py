"""Loop closure on a fused map: rebuild only the TSDF blocks that keyframes moved to new poses reach.

`Mapper.update_poses` checks the poses, then `moved_blocks` lists the blocks a moved keyframe
reached under its old pose or reaches under its new one, and `reintegrate` zeroes them and fuses
into them again every stored keyframe that reaches them, in the order the keyframes were fused:
voxel for voxel the volume that fusing every keyframe from scratch with the new poses gives.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from .tsdf.fusion import IntegrationStats, TSDFFusion
from .map_store import Keyframe


@dataclass(frozen=True)
class PoseUpdate:
    """What `Mapper.update_poses` did.

    Attributes:
        moved: Ids of the keyframes whose pose changed.
        reintegrated: Ids of the keyframes integrated again (the moved ones and those sharing
            a block with them), in integration order.
        blocks: Number of TSDF blocks rebuilt.
        seconds: Wall time.
    """

    moved: tuple[int, ...]
    reintegrated: tuple[int, ...]
    blocks: int
    seconds: float


def moved_blocks(
    fusion: TSDFFusion, keyframes: dict[int, Keyframe], new_poses: dict[int, np.ndarray], moved: Sequence[int]
) -> np.ndarray:
    """(B,) int64 sorted keys of the TSDF blocks the ``moved`` keyframes reach under their stored or their new pose."""
    affected = [keyframes[k].block_keys for k in moved]
    affected += [fusion.block_keys(keyframes[k].depth, new_poses[k], keyframes[k].variance) for k in moved]
    return np.unique(np.concatenate(affected))


def reintegrate(
    fusion: TSDFFusion,
    keyframes: dict[int, Keyframe],
    blocks: np.ndarray,
    moved: Sequence[int],
    integrate: Callable[..., IntegrationStats],
) -> list[int]:
    """Zeroes ``blocks`` and fuses into them again every keyframe (at its stored pose) that reaches them.

    Args:
        fusion: The volume; its ``frames_integrated`` count is left as it was.
        keyframes: The keyframe store, in fusion order; the ``moved`` ones already carry their new
            pose and get the block keys they reach now.
        blocks: Keys of the blocks to rebuild (`moved_blocks`).
        moved: Ids of the keyframes whose pose changed.
        integrate: ``integrate(depth, variance, T_world_camera, rgb, blocks=, points=)`` fusing one
            keyframe into the given blocks only (`Mapper`'s, with its fusion weights).

    Returns:
        Ids of the keyframes fused again, in order.
    """
    frames_before = fusion.frames_integrated
    fusion.reset_blocks(blocks)
    redone = []
    for kid, kf in keyframes.items():
        if kid in moved or np.intersect1d(kf.block_keys, blocks, assume_unique=True).size:
            stats = integrate(kf.depth, kf.variance, kf.T_world_camera, kf.rgb, blocks=blocks, points=kf.points)
            if kid in moved:
                kf.block_keys = stats.block_keys
            redone.append(kid)
    fusion.frames_integrated = frames_before
    return redone
