"""Settings of the pose estimator, with three presets: ``accurate`` (close to SurfEmb's inference), ``fast``
(fewer hypotheses and samples on a coarser grid) and ``thorough`` (``accurate`` on five crop views per box,
:mod:`surftrack.pose.views`: about four times its time, for offline annotation and evaluation).

Pixel quantities are in pixels of the correspondence GRID: the network's crop output average-pooled by
``stride`` (grid pixel i is centred on crop pixel ``stride * i``). Scores are per-pixel averages of log
likelihood ratios over that grid (see :mod:`surftrack.pose.scoring`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass


@dataclass(frozen=True)
class Preset:
    """All settings of the estimator; the defaults are the ``accurate`` preset. ``PRESETS`` holds the named
    ones; ``PRESETS["fast"].replace(n_hypotheses=3000)`` makes a variant."""

    name: str = "accurate"
    # correspondence distribution
    stride: int = 3                  # crop -> grid downsampling of queries and mask (SurfEmb: 3)
    n_samples: int = 20000           # surface samples per part; their keys are computed once and cached
    alpha: float = 1.5               # hypotheses are drawn from corr ** alpha (SurfEmb: 1.5)
    mask_threshold: float = 0.5      # grid pixels with sigmoid(mask) above it carry correspondences ...
    min_active: int = 16             # ... at least this many (the most confident) ...
    max_active: int = 3000           # ... and at most this many (the most confident)
    # hypotheses
    n_hypotheses: int = 10000        # 4-point hypotheses drawn (SurfEmb: 10k)
    max_scored: int = 1000           # survivors of pruning that are scored (SurfEmb: 1000)
    min_spread_2d: float = 0.1       # min pairwise distance of the 4 pixels, x sqrt(number of active pixels)
    min_spread_3d: float = 0.1       # min pairwise distance of the 4 model points, x part radius
    max_4th_error: float = 3.0       # reprojection error of the 4th point (grid px)
    normal_slack: float = 0.25       # cos of the view ray and the normal may reach this (0 = strictly facing)
    depth_range: tuple[float, float] = (0.1, 1.5)  # part centre depth / (f * 2r / box side), + r at the top
    # scoring
    prescore_density: float = 1.0    # every hypothesis is scored with this many samples per active pixel ...
    rescore_top: int = 50            # ... this many of the best again (and every refined pose) with ...
    score_density: float = 8.0       # ... this many (prescore_density 0: all hypotheses at score_density),
    min_score_samples: int = 500     # at least this many samples either way (a prefix of the bank)
    depth_tol_px: float = 4.0        # visibility slack behind a pixel's nearest sample, in pixels' worth of depth
    corr_floor: float = -3.0         # floor of the per-pixel correspondence log-likelihood ratio
    mask_floor: float = -7.0         # floor of the per-pixel mask log-probabilities
    score_chunk: int = 2_000_000     # projected points per scoring chunk (memory bound)
    # refinement
    inlier_px: float = 2.5           # inlier reprojection threshold (grid px) of the arg-max correspondences
    refine_rounds: int = 3           # inlier-set -> LM -> score rounds, each kept only if the score improves
    lm_iters: int = 10               # LM iterations per refinement round
    final_rounds: int = 3            # inlier-set -> LM rounds of the final inlier PnP ...
    final_lm_iters: int = 30         # ... with this many LM iterations each
    max_step_deg: float = 20.0       # a refinement step may rotate the pose at most this much ...
    max_step_radius: float = 0.5     # ... and move it at most this many part radii
    score_tol: float = 0.05          # the final PnP is kept unless it lowers the (per-pixel) score by more
    min_inliers: int = 6
    # test-time crop views (:mod:`surftrack.pose.views`)
    views: int = 1                   # crops per box, each solved on its own, their poses merged
    part_views: tuple[tuple[str, int], ...] = ()  # (part name, views) overriding ``views`` for those parts
    view_shift: float = 0.06         # crop-centre shift of the shifted views, x the crop's side
    view_radius_deg: float = 15.0    # views within this rotation of the modal one are averaged
    # network
    amp: bool = True                 # CUDA only: fp16 autocast for the image network
    max_batch: int = 16              # crops per network forward
    seed: int = 0

    def __post_init__(self) -> None:
        if self.stride < 1 or self.n_samples < 4 or self.n_hypotheses < 1 or self.max_scored < 1:
            raise ValueError(f"invalid preset {self}")
        if not 0.0 < self.mask_threshold < 1.0 or self.alpha <= 0:
            raise ValueError(f"preset {self.name}: need 0 < mask_threshold < 1 and alpha > 0")
        if not 1 <= self.views <= 9 or not 0 <= self.view_shift <= 0.5 or not self.view_radius_deg > 0:
            raise ValueError(f"preset {self.name}: need 1 <= views <= 9, 0 <= view_shift <= 0.5 and "
                             f"view_radius_deg > 0")
        def pair(p) -> bool:
            return (isinstance(p, (tuple, list)) and len(p) == 2 and isinstance(p[0], str)
                    and isinstance(p[1], int) and not isinstance(p[1], bool) and 1 <= p[1] <= 9)

        if not isinstance(self.part_views, (tuple, list)) or not all(pair(p) for p in self.part_views):
            raise ValueError(f"preset {self.name}: part_views must be (part name, 1-9) pairs, got {self.part_views!r}")
        object.__setattr__(self, "part_views", tuple(tuple(p) for p in self.part_views))  # hashable
        if not 0 < self.depth_range[0] < self.depth_range[1]:
            raise ValueError(f"preset {self.name}: invalid depth_range {self.depth_range}")

    def replace(self, **changes) -> Preset:
        return dataclasses.replace(self, **changes)

    def views_of(self, part: str) -> int:
        """Crop views per box of the part named ``part``."""
        return int(dict(self.part_views).get(part, self.views))


PRESETS: dict[str, Preset] = {
    "accurate": Preset(),
    "fast": Preset(name="fast", stride=4, n_samples=5000, n_hypotheses=1500, max_scored=200, max_active=1000,
                   rescore_top=20, refine_rounds=1, final_rounds=2, final_lm_iters=20),
    "thorough": Preset(name="thorough", views=5),
}


def get_preset(preset: str | Preset) -> Preset:
    if isinstance(preset, Preset):
        return preset
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; available: {sorted(PRESETS)}")
    return PRESETS[preset]
