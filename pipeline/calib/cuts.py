"""Cut-set sum terms of a group of several sensors (the foot-pair sum of eqs. 5.6-5.12 generalised).

A cut set (:mod:`pipeline.physics.cuts`, labelled by the label stage) is a set of FT sensors whose signed
sum ``sum_k sign_k frame_X_k f_k``, in the set's common frame, has an exact label where no single member
may have one (both legs in double support, the four foot sensors, a leg with its foot's two sensors).
``frame_X_k`` is constant for a member rigidly attached to the common frame (``fixed``, sign folded in),
else built per sample from the member's pose in the common frame (a labelled column block):
``[[R, 0], [p^ R, R]]``, force first. Nothing here reads files.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass(frozen=True)
class CutTerm:
    """One cut set of a group: its label name, members and transforms to its common frame.

    members: indices into the group's sensors. fixed: (K, 6, 6) sign_k frame_X_k of the fixed members
    (zeros for the moving ones). moving: (member position k, sign) of the members whose transform comes
    from a pose; pose_cols: their labelled pose columns (12 each: r00..r22, px, py, pz), same order.
    pair: the foot pair this set is, if any (then its label is the pair's sum in the sole frame).
    """

    label: str
    members: tuple[int, ...]
    fixed: np.ndarray
    moving: tuple[tuple[int, float], ...] = ()
    pose_cols: tuple[tuple[str, ...], ...] = ()
    pair: str | None = None

    @property
    def is_fixed(self) -> bool:
        """True if every member's transform is constant (no pose needed)."""
        return not self.moving


def _map(poses: torch.Tensor, wrench: torch.Tensor) -> torch.Tensor:
    """(B, 6) wrenches in frame a from (B, 12) poses of b in a and (B, 6) wrenches in b:
    ``f_a = R f_b``, ``tau_a = R tau_b + p x f_a``."""
    rot = poses[:, :9].reshape(-1, 3, 3)
    force = torch.einsum("nij,nj->ni", rot, wrench[:, :3])
    moment = torch.einsum("nij,nj->ni", rot, wrench[:, 3:]) + torch.cross(poses[:, 9:], force, dim=1)
    return torch.cat([force, moment], dim=1)


def _fixed(cut: CutTerm, dtype: torch.dtype) -> torch.Tensor:
    """`cut.fixed` as a tensor of `dtype`, converted once per cut set (a training step calls this per set)."""
    tensors = cut.__dict__.setdefault("_tensors", {})  # beside the frozen fields: not compared, not hashed
    if dtype not in tensors:
        tensors[dtype] = torch.as_tensor(cut.fixed, dtype=dtype)
    return tensors[dtype]


def cut_sums(cuts: tuple[CutTerm, ...], pred: torch.Tensor, poses: torch.Tensor | None) -> torch.Tensor:
    """(B, C, 6) signed sums of every cut set of predicted wrenches `pred` (B, S, 6), in each cut set's
    common frame; `poses` (B, P, 12): the moving members' poses, cut sets in order, members in order."""
    out, p = [], 0
    for cut in cuts:
        fixed = _fixed(cut, pred.dtype)
        total = torch.einsum("kij,bkj->bi", fixed, pred[:, list(cut.members)])
        for k, sign in cut.moving:
            total = total + sign * _map(poses[:, p], pred[:, cut.members[k]])
            p += 1
        out.append(total)
    return torch.stack(out, dim=1)


def cut_sums_np(cuts: tuple[CutTerm, ...], pred: np.ndarray, poses: np.ndarray | None) -> np.ndarray:
    """`cut_sums` on float64 arrays: (N, C, 6) from pred (N, S, 6) and poses (N, P, 12)."""
    with torch.no_grad():
        t_poses = None if poses is None else torch.as_tensor(poses, dtype=torch.float64)
        return cut_sums(cuts, torch.as_tensor(pred, dtype=torch.float64), t_poses).numpy()
