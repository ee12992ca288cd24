"""The pose solver of one crop: hypotheses -> scoring -> bounded refinement -> final inlier PnP.

Input is a correspondence field (:mod:`surftrack.pose.correspondence`), not the network, so the solver can
be tested with synthetic correspondence distributions.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
import torch

from surftrack.pose.correspondence import CorrField
from surftrack.pose.hypotheses import sample_hypotheses
from surftrack.pose.preset import Preset
from surftrack.pose.refine import refine_pose
from surftrack.pose.scoring import score_poses
from surftrack.pose.surface import SurfaceBank


class StageTimer:
    """Wall-clock milliseconds per named stage (accumulated); synchronises CUDA around each stage."""

    def __init__(self, device: torch.device | str = "cpu"):
        self.device = torch.device(device)
        self.cuda = self.device.type == "cuda"
        self.ms: dict[str, float] = {}

    def _sync(self) -> None:
        if self.cuda:
            torch.cuda.synchronize(self.device)

    @contextmanager
    def __call__(self, name: str):
        self._sync()
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self._sync()
            self.ms[name] = self.ms.get(name, 0.0) + (time.perf_counter() - t0) * 1e3


@dataclass
class Solution:
    """Model-to-camera pose (mm) of the crop's camera frame, its score, inlier count and diagnostics.
    ``ok`` is False when no hypothesis could be solved (the pose is then a placeholder on the box ray).
    ``prior_won``: whether the prior handed in scored best of all hypotheses (None without a prior)."""

    R: np.ndarray
    t: np.ndarray
    score: float
    n_inliers: int
    ok: bool
    counts: dict[str, int] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    prior_won: bool | None = None


def _placeholder(field_: CorrField, bank: SurfaceBank, K_grid: torch.Tensor,
                 box_side: float) -> tuple[np.ndarray, np.ndarray]:
    K = K_grid.cpu().numpy()
    z = (K[0, 0] + K[1, 1]) / 2.0 * 2.0 * bank.radius / max(box_side, 1e-6)
    centre = np.array([(field_.g - 1) / 2.0, (field_.g - 1) / 2.0, 1.0])
    return np.eye(3), np.linalg.solve(K, centre) * z - bank.center


@torch.inference_mode()
def solve_field(field_: CorrField, bank: SurfaceBank, K_grid: torch.Tensor, box_side: float, preset: Preset,
                generator: torch.Generator | None = None, timer: StageTimer | None = None,
                prior: tuple[np.ndarray, np.ndarray] | None = None) -> Solution:
    """Pose of the part seen in ``field_``. ``K_grid``: grid intrinsics (3, 3); ``box_side``: the
    detection box's longer side in grid pixels; ``generator``: torch generator on the field's device.
    ``prior`` (R, t): a pose from elsewhere (e.g. the tracker's) scored with the hypotheses; it wins, and
    is then refined, only if it scores best (``Solution.prior_won``)."""
    dev = field_.query.device
    timer = timer or StageTimer(dev)
    K = K_grid.to(dev, torch.float64)
    with timer("hypotheses"):
        hyp = sample_hypotheses(field_, bank, K, box_side, preset, generator)
    counts = dict(hyp.counts, relaxed=int(hyp.relaxed), active=len(field_.active))
    if len(hyp.R) == 0 and (prior is None or len(field_.active) == 0):
        R, t = _placeholder(field_, bank, K, box_side)
        return Solution(R, t, float("-inf"), 0, False, counts, dict(timer.ms))
    with timer("scoring"):
        Rh, th = hyp.R, hyp.t
        if preset.prescore_density > 0 and len(Rh) > preset.rescore_top:
            pre = score_poses(Rh, th, field_, bank, K, preset, density=preset.prescore_density)
            top = torch.topk(pre, preset.rescore_top).indices
            Rh, th = Rh[top], th[top]
        if prior is not None:
            Rp = torch.as_tensor(np.asarray(prior[0]), dtype=Rh.dtype, device=Rh.device).reshape(1, 3, 3)
            tp = torch.as_tensor(np.asarray(prior[1]), dtype=th.dtype, device=th.device).reshape(1, 3)
            Rh, th = torch.cat([Rh, Rp]), torch.cat([th, tp])
        scores = score_poses(Rh, th, field_, bank, K, preset)
        best = int(torch.argmax(scores))
        prior_won = None if prior is None else best == len(Rh) - 1
        R0, t0, s0 = Rh[best].cpu().numpy(), th[best].cpu().numpy(), float(scores[best])
    with timer("refinement"):
        pts = bank.points[field_.best].double().cpu().numpy()
        uv = field_.active_xy().cpu().numpy()
        Kn = K.cpu().numpy()

        def score_one(R: np.ndarray, t: np.ndarray) -> float:
            Rt = torch.as_tensor(R, dtype=torch.float64, device=dev)[None]
            tt = torch.as_tensor(t, dtype=torch.float64, device=dev)[None]
            return float(score_poses(Rt, tt, field_, bank, K, preset)[0])

        ref = refine_pose(R0, t0, s0, pts, uv, Kn, bank.radius, preset, score_one)
    counts.update(refine_rounds=ref.rounds_kept, final_pnp=int(ref.final_kept))
    return Solution(ref.R, ref.t, ref.score, ref.n_inliers, True, counts, dict(timer.ms), prior_won)
