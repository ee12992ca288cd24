"""Per-part 6D pose from an image and detection boxes with a SurfSurg6D model (SurfEmb-style inference).

Crops are made as in training (:mod:`surftrack.data.dataset`): a square box around the detection box,
side = the model's ``data.scale`` x the box's longer side (:func:`surftrack.geometry.square_crop_box`), no
rotation, warped bilinearly to the model's crop size. All crops of all frames go through the network
together (in batches of ``max_batch``); the rest runs per crop: correspondence field, hypotheses, scoring,
refinement (:mod:`surftrack.pose.solver`). With ``preset.views`` > 1 every box is cropped that many times
(``preset.part_views``: another count for named parts), the crop centre shifted by ``view_shift`` of its
side, and the views' poses merged (:mod:`surftrack.pose.views`). Poses are model-to-camera of the
ORIGINAL camera (a crop without rotation keeps the camera frame), t in mm.

Boxes are pixel-EDGE boxes ``(x, y, w, h)`` as in ``det.json`` (:mod:`surftrack.synth.detections`): the
box covers ``[x, x + w] x [y, y + h]`` with pixel centres at integers. A BOP ``bbox`` (w = xmax - xmin
over pixel indices) is the edge box ``(x, y, w + 1, h + 1)`` (:func:`surftrack.geometry.box_from_bop`).
"""

from __future__ import annotations

import dataclasses
import time
import zlib
from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from surftrack.data.twin_labels import twin_labels
from surftrack.geometry import Box, PinholeCamera, crop_affine, crop_warp, square_crop_box, unwarp_image, warp_image
from surftrack.instruments import BUILTIN, InstrumentRegistry
from surftrack.model.checkpoint import load_checkpoint
from surftrack.model.config import DataCfg
from surftrack.model.surfsurg6d import SurfSurg6D
from surftrack.pose.correspondence import build_field, grid_camera, pool_to_grid
from surftrack.pose.preset import Preset, get_preset
from surftrack.pose.solver import StageTimer, solve_field
from surftrack.pose.surface import bank_is_cached, part_bank
from surftrack.pose.views import merge_views, view_offsets

STAGES = ("crop", "forward", "correspondence", "hypotheses", "scoring", "refinement")


@dataclass
class PartPose:
    """The pose of one requested part. ``R`` (3, 3), ``t`` (3,) mm: model-to-camera. ``score``: per-pixel
    log-likelihood ratio of the pose (:mod:`surftrack.pose.scoring`; higher is better, about 0 means the
    network sees nothing that agrees), ``n_inliers``: grid pixels whose most likely correspondence
    reprojects within ``inlier_px``. ``ok`` is False only if no hypothesis could be solved (the pose is then
    a placeholder on the box's ray). ``timings``: ms per stage (``forward`` and ``crop`` are this part's
    share of the batch; ``keys`` only on the first use of a part, when its surface keys are computed and
    cached), ``total`` their sum. ``crop_box`` (x0, y0, x1, y1) pixel edges and ``crop_K`` the
    crop's intrinsics (of the unshifted view when the box has several). With several views, ``timings``
    add up all views, ``score`` and ``n_inliers`` are the merged views' means, and ``counts`` are the
    reference view's plus ``views`` (crops solved) and ``views_merged`` (poses averaged). ``prior_won``:
    the prior handed in scored best (the reference view's; None without a prior); ``kinematic``: the
    pose is the instrument fit's (:func:`surftrack.pose.kinematic.apply_kinematics`), not this crop's own.
    ``mask``: the network's foreground probability over the crop (S, S) float32 (the unshifted view's, as
    ``crop_box``; amodal where the model was trained so), only where asked for (``masks=True``);
    :meth:`image_mask` puts it into the frame."""

    obj_id: int
    part: str
    instrument: str
    R: np.ndarray
    t: np.ndarray
    score: float
    n_inliers: int
    ok: bool
    timings: dict[str, float]
    crop_box: Box
    crop_K: np.ndarray
    image_index: int = 0
    counts: dict[str, int] = field(default_factory=dict)
    prior_won: bool | None = None
    kinematic: bool = False
    mask: np.ndarray | None = None

    def image_mask(self, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """The network's foreground probability of this part (``mask``, its crop's) carried into the
        image of ``size`` (width, height): (probability (H, W) float32, 0 outside the crop; covered (H, W)
        bool, the pixels the crop saw)."""
        if self.mask is None:
            raise ValueError("this pose was estimated without its mask (estimate(..., masks=True))")
        return unwarp_image(self.mask, crop_warp(self.crop_box, self.mask.shape[::-1]), size)

    @property
    def pose(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.R, self.t
        return T


@dataclass
class _Crop:
    image_index: int
    obj_id: int
    part_index: int
    box: Box
    crop_box: Box
    K_crop: np.ndarray
    pixels: np.ndarray
    prior: tuple[np.ndarray, np.ndarray] | None = None
    views: int = 1  # crops of this box (consecutive in the crop list, this one among them)


def _crop_seed(seed: int, crop: _Crop) -> int:
    """The random seed of one crop's solver: from the part and the crop box (to a thousandth of a pixel),
    not from the crop's place in the batch, so a box gets the same pose whichever other boxes and frames
    share its network forward (an evaluation's batches, the tracker's per-frame calls)."""
    key = np.asarray([crop.obj_id, *crop.crop_box], np.float64).round(3).tobytes()
    return int(seed) * 1_000_003 + zlib.crc32(key)


def check_seeds(seeds: Sequence[int]) -> list[int]:
    """``seeds`` as a list of ints; ValueError unless they are distinct numbers >= 0 (at least one)."""
    seeds = [int(s) for s in seeds]
    if not seeds or len(set(seeds)) != len(seeds) or min(seeds) < 0:
        raise ValueError(f"seeds must be distinct numbers >= 0, got {seeds}")
    return seeds


class PoseEstimator:
    """``PoseEstimator(model_or_checkpoint, preset="accurate" | "fast" | Preset, device=None)``.

    ``model_or_checkpoint``: a :class:`SurfSurg6D` (put in eval mode and moved to ``device``; crop size
    and box scale default to the training defaults, 224 and 1.2, unless given) or a checkpoint path (its
    training config gives both). ``device`` defaults to CUDA when available. Surface samples and their
    keys are computed once per (model, part, count) and cached (:func:`surftrack.pose.surface.part_bank`).

    ``solver_threads``: on the CPU, the stages after the network (many small tensor ops) run with this
    many torch intra-op threads (restored afterwards; None leaves torch's setting). Default 1: measured on
    2 cores shared with another process, two OpenMP threads made those stages up to 30x slower (the
    threads wait for each other), and on small ops a second thread gains little even on an idle machine.
    The network forward always uses torch's setting (``torch.set_num_threads``).
    """

    def __init__(self, model: SurfSurg6D | str | Path, preset: str | Preset = "accurate",
                 device: str | torch.device | None = None, crop_size: int | None = None,
                 box_scale: float | None = None, solver_threads: int | None = 1,
                 instruments: InstrumentRegistry = BUILTIN):
        self.device = torch.device(device) if device is not None else \
            torch.device("cuda" if torch.cuda.is_available() else "cpu")
        self.preset = get_preset(preset)
        data = DataCfg()
        if isinstance(model, (str, Path)):
            model, cfg, _ = load_checkpoint(model, self.device)
            data = cfg.data
        elif not isinstance(model, SurfSurg6D):
            raise ValueError(f"expected a SurfSurg6D model or a checkpoint path, got {type(model).__name__}")
        self.model = model.to(self.device).eval()
        self.crop_size = int(crop_size if crop_size is not None else data.crop)
        self.box_scale = float(box_scale if box_scale is not None else data.scale)
        if self.crop_size < 8 or not self.box_scale > 0:
            raise ValueError(f"invalid crop size {self.crop_size} or box scale {self.box_scale}")
        if solver_threads is not None and int(solver_threads) < 1:
            raise ValueError(f"solver_threads must be >= 1 or None, got {solver_threads}")
        self.solver_threads = None if solver_threads is None else int(solver_threads)
        names = {p.name for p in self.model.parts}
        unknown = sorted({n for n, _ in self.preset.part_views} - names)
        if unknown:
            raise ValueError(f"crop views asked for {', '.join(unknown)}, not a part of the model (parts: "
                             f"{', '.join(sorted(names))})")
        twins = twin_labels({p.obj_id: (p.instrument, p.name) for p in self.model.parts}, instruments)
        # obj id -> the part its instrument's roll twin shows in its place (jaw_left <-> jaw_right)
        self.twin_partner = {} if twins is None else {a: b for a, b in twins.partner.items() if a != b}

    @property
    def obj_ids(self) -> list[int]:
        return [p.obj_id for p in self.model.parts]

    # ------------------------------------------------------------------ inputs
    def _boxes(self, boxes, shape: tuple[int, int], where: str) -> list[tuple[int, Box]]:
        if isinstance(boxes, Mapping):
            items = list(boxes.items())
        elif isinstance(boxes, Sequence) and not isinstance(boxes, (str, bytes)):
            items = list(boxes)
        else:
            raise ValueError(f"{where}: boxes must be a dict obj_id -> (x, y, w, h) or a list of (obj_id, box), "
                             f"got {type(boxes).__name__}")
        H, W = shape
        out = []
        for k, item in enumerate(items):
            try:
                obj_id, box = item
                obj_id = int(obj_id)
                b = np.asarray(box, dtype=np.float64).reshape(-1)
            except (TypeError, ValueError):
                raise ValueError(f"{where}: box entry {k} must be (obj_id, (x, y, w, h)), got {item!r}") from None
            if obj_id not in self.obj_ids:
                raise ValueError(f"{where}: unknown obj_id {obj_id}; the model knows {self.obj_ids}")
            if b.size != 4 or not np.all(np.isfinite(b)):
                raise ValueError(f"{where}: box of obj_id {obj_id} must be 4 finite numbers (x, y, w, h), got {box!r}")
            x, y, w, h = (float(v) for v in b)
            if w <= 0 or h <= 0:
                raise ValueError(f"{where}: empty or degenerate box {[x, y, w, h]} for obj_id {obj_id} (need w, h > 0)")
            if x >= W or y >= H or x + w <= 0 or y + h <= 0:
                raise ValueError(f"{where}: box {[x, y, w, h]} of obj_id {obj_id} lies outside the {W}x{H} image")
            out.append((obj_id, (x, y, w, h)))
        return out

    @staticmethod
    def _image(image, where: str) -> np.ndarray:
        if not isinstance(image, np.ndarray):
            raise ValueError(f"{where}: image must be a numpy array, got {type(image).__name__}")
        if image.dtype != np.uint8:
            raise ValueError(f"{where}: image must be uint8 RGB, got dtype {image.dtype}")
        if image.ndim != 3 or image.shape[2] != 3 or image.shape[0] < 1 or image.shape[1] < 1:
            raise ValueError(f"{where}: image must have shape (H, W, 3), got {image.shape}")
        return image

    @staticmethod
    def _camera(K, shape: tuple[int, int], where: str) -> PinholeCamera:
        try:
            Km = np.asarray(K, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{where}: K must be a 3x3 matrix") from None
        if Km.shape != (3, 3) or not np.all(np.isfinite(Km)):
            raise ValueError(f"{where}: K must be a finite 3x3 matrix, got shape {Km.shape}")
        try:
            return PinholeCamera(Km, shape[1], shape[0])
        except ValueError as e:
            raise ValueError(f"{where}: {e}") from None

    # ------------------------------------------------------------------ estimation
    def estimate(self, image: np.ndarray, boxes, K: np.ndarray,
                 priors: Mapping[int, tuple[np.ndarray, np.ndarray]] | None = None,
                 groups: Sequence[Hashable] | None = None, masks: bool = False) -> list[PartPose]:
        """Poses of the parts in ``boxes`` (dict obj_id -> (x, y, w, h), or a list of (obj_id, box) for
        repeated ids) seen in ``image`` ((H, W, 3) uint8 RGB) with intrinsics ``K``; one
        :class:`PartPose` per box, in order. ``priors`` (obj_id -> (R, t), or a list aligned with a list
        of boxes, None entries allowed): poses known from elsewhere (a tracker's), scored with the
        hypotheses and kept when they explain the image best. ``groups`` (one instrument-instance key per
        box): lets the twin parts of one instrument trade boxes (:meth:`_twin_pairs`). ``masks``: each pose
        also carries the network's mask of its crop (``PartPose.mask``)."""
        return self.estimate_batch([image], [boxes], [K], None if priors is None else [priors],
                                   None if groups is None else [groups], masks)[0]

    @torch.inference_mode()
    def estimate_batch(self, images: Sequence[np.ndarray], boxes_per_image: Sequence,
                       Ks: Sequence, priors: Sequence[Mapping | None] | None = None,
                       groups: Sequence[Sequence[Hashable] | None] | None = None,
                       masks: bool = False) -> list[list[PartPose]]:
        """:meth:`estimate` for several frames; all crops share the network forward passes."""
        return self.estimate_batch_seeds(images, boxes_per_image, Ks, [self.preset.seed], priors, groups, masks)[0]

    @torch.inference_mode()
    def estimate_batch_seeds(self, images: Sequence[np.ndarray], boxes_per_image: Sequence, Ks: Sequence,
                             seeds: Sequence[int], priors: Sequence[Mapping | None] | None = None,
                             groups: Sequence[Sequence[Hashable] | None] | None = None, masks: bool = False
                             ) -> list[list[list[PartPose]]]:
        """:meth:`estimate_batch` once per solver seed in ``seeds`` (distinct, >= 0; the preset's seed
        replaced), from one network forward: ``result[s][i]`` are image ``i``'s poses under ``seeds[s]``,
        each equal to what ``estimate_batch`` with that seed returns. For measuring how much a figure owes
        to the solver's random draws at the cost of one forward. The ``forward`` and ``crop`` timings are
        reported in every seed's poses."""
        seeds = check_seeds(seeds)
        boxes_per_image, priors, pairs = self._with_twin_boxes(boxes_per_image, priors, groups)
        crops, crop_ms = self._crops(images, boxes_per_image, Ks, priors)
        if not crops:
            return [[[] for _ in images] for _ in seeds]
        grids, queries, probs, fwd_ms = self._forward(crops, masks)
        return [[self._pick_twin_boxes(poses, n, p) for poses, (n, p) in
                 zip(self._solve_all(len(images), crops, grids, queries, crop_ms, fwd_ms, s, probs), pairs)]
                for s in seeds]

    # ------------------------------------------------------------------ twin parts
    def _twin_pairs(self, obj_ids: Sequence[int], groups: Sequence[Hashable]) -> list[tuple[int, int]]:
        """Index pairs (a, b) of boxes of one instrument instance (same ``groups`` key) whose parts are
        each other's roll twin's (``twin_partner``: the LND's jaws). Beyond a quarter turn of roll the
        model, trained on one twin's labels, calls the part in box a the part of box b, and a decoder run
        on the other's box sees its part off-centre (the jaws lost 6-8 points ADD-10 to this on the
        full-reach suite set): each pair is therefore also estimated crossed."""
        pairs = []
        for a, (oa, ga) in enumerate(zip(obj_ids, groups)):
            for b in range(a + 1, len(obj_ids)):
                if groups[b] == ga and self.twin_partner.get(oa) == obj_ids[b]:
                    pairs.append((a, b))
        return pairs

    def _with_twin_boxes(self, boxes_per_image: Sequence, priors: Sequence | None,
                         groups: Sequence | None) -> tuple[list, list | None, list[tuple[int, list]]]:
        """Each image's boxes with the crossed twin boxes appended (part a on box b, part b on box a, per
        pair), its priors to match, and per image (number of boxes asked, pairs)."""
        out_boxes, out_priors, pairs = [], ([] if priors is not None else None), []
        for i, boxes in enumerate(boxes_per_image):
            g = groups[i] if groups is not None else None
            try:
                items = list(boxes.items()) if isinstance(boxes, Mapping) else list(boxes)
                n = len(items)
                p = (self._twin_pairs([int(o) for o, _ in items], g)
                     if g is not None and self.twin_partner and len(g) == n else [])
            except (TypeError, ValueError):
                n, p = 0, []  # malformed boxes: _crops says what is wrong with them
            pri = priors[i] if priors is not None else None
            if p:
                items += [x for a, b in p for x in ((items[a][0], items[b][1]), (items[b][0], items[a][1]))]
                if pri is not None and not isinstance(pri, Mapping):
                    pri = list(pri) + [x for a, b in p for x in (pri[a], pri[b])]
            pairs.append((n, p))
            out_boxes.append(items if p else boxes)
            if out_priors is not None:
                out_priors.append(pri)
        return out_boxes, out_priors, pairs

    @staticmethod
    def _pick_twin_boxes(poses: list[PartPose], n: int, pairs: list[tuple[int, int]]) -> list[PartPose]:
        """The ``n`` asked poses, each twin pair's taken crossed where the crossed crops' summed score is
        the higher (a failed estimate counts as -inf); the discarded crops' timings are added to the kept
        ones'."""
        def total(x: PartPose, y: PartPose) -> float:
            return x.score + y.score if x.ok and y.ok else -np.inf

        kept = list(poses[:n])
        for k, (a, b) in enumerate(pairs):
            a_on_b, b_on_a = poses[n + 2 * k], poses[n + 2 * k + 1]
            if total(a_on_b, b_on_a) > total(kept[a], kept[b]):
                kept[a], kept[b], lost = a_on_b, b_on_a, (kept[a], kept[b])
            else:
                lost = (a_on_b, b_on_a)
            for i, other in zip((a, b), lost):
                ms = {st: kept[i].timings.get(st, 0.0) + other.timings.get(st, 0.0)
                      for st in set(kept[i].timings) | set(other.timings)}
                kept[i] = dataclasses.replace(kept[i], timings=ms)
        return kept

    def _crops(self, images: Sequence[np.ndarray], boxes_per_image: Sequence, Ks: Sequence,
               priors: Sequence[Mapping | None] | None) -> tuple[list[_Crop], float]:
        """The checked inputs as crops (in image, then box order) and the crop ms per crop."""
        if not (len(images) == len(boxes_per_image) == len(Ks)):
            raise ValueError(f"need as many box sets and K as images, got {len(images)}, {len(boxes_per_image)} "
                             f"and {len(Ks)}")
        if priors is not None and len(priors) != len(images):
            raise ValueError(f"need one prior mapping (or None) per image, got {len(priors)} for {len(images)}")
        S = self.crop_size
        names = {p.obj_id: p.name for p in self.model.parts}
        crops: list[_Crop] = []
        t0 = time.perf_counter()
        for i, (img, bx, K) in enumerate(zip(images, boxes_per_image, Ks)):
            where = f"image {i}"
            img = self._image(img, where)
            cam = self._camera(K, img.shape[:2], where)
            pri = priors[i] if priors is not None else None
            for j, (obj_id, box) in enumerate(self._boxes(bx, img.shape[:2], where)):
                prior = None if pri is None else (pri.get(obj_id) if isinstance(pri, Mapping) else pri[j])
                x0, y0, x1, y1 = square_crop_box(box, self.box_scale)
                side = x1 - x0
                offsets = view_offsets(self.preset.views_of(names[obj_id]), self.preset.view_shift)
                for dx, dy in offsets:
                    cbox = (x0 + dx * side, y0 + dy * side, x1 + dx * side, y1 + dy * side)
                    M, ccam = crop_affine(cam, cbox, (S, S))
                    crops.append(_Crop(i, obj_id, self.model.part_index(obj_id), box, cbox, ccam.K,
                                       warp_image(img, M, S), prior, len(offsets)))
        return crops, (time.perf_counter() - t0) * 1e3 / max(len(crops), 1)

    def _solve_all(self, n_images: int, crops: list[_Crop], grids: torch.Tensor, queries: torch.Tensor,
                   crop_ms: float, fwd_ms: float, seed: int, probs: np.ndarray | None = None) -> list[list[PartPose]]:
        """Every crop's pose with solver seed ``seed``, grouped per image (with its crop's foreground
        probability ``probs[k]`` where given)."""
        results: list[list[PartPose]] = [[] for _ in range(n_images)]
        threads = torch.get_num_threads()
        limit = self.device.type == "cpu" and self.solver_threads is not None and self.solver_threads != threads
        try:
            if limit:
                torch.set_num_threads(self.solver_threads)
            s = 0
            while s < len(crops):  # each box's views are consecutive crops (see _crops)
                n = crops[s].views
                views = [self._solve(crops[k], grids[k], queries[k], crop_ms, fwd_ms, seed) for k in range(s, s + n)]
                if probs is not None:
                    views[0] = dataclasses.replace(views[0], mask=probs[s])
                results[crops[s].image_index].append(views[0] if n == 1 else self._merge(views))
                s += n
        finally:
            if limit:
                torch.set_num_threads(threads)
        return results

    def _merge(self, views: list[PartPose]) -> PartPose:
        """One box's pose from its views' (:func:`surftrack.pose.views.merge_views` over the solved ones)."""
        ok = [v for v in views if v.ok]
        timings = {s: sum(v.timings.get(s, 0.0) for v in views) for s in views[0].timings}
        counts = {"views": len(views), "views_merged": 0}
        if not ok:
            return dataclasses.replace(views[0], timings=timings, counts={**views[0].counts, **counts})
        R, t, score, ref, members = merge_views([v.R for v in ok], [v.t for v in ok], [v.score for v in ok],
                                                self.preset.view_radius_deg)
        counts["views_merged"] = len(members)
        return dataclasses.replace(views[0], R=R, t=t, score=score, ok=True, timings=timings,
                                   n_inliers=int(round(np.mean([ok[m].n_inliers for m in members]))),
                                   counts={**ok[ref].counts, **counts}, prior_won=ok[ref].prior_won)

    def _forward(self, crops: list[_Crop], keep_masks: bool = False
                 ) -> tuple[torch.Tensor, torch.Tensor, np.ndarray | None, float]:
        """Pooled mask logits (B, g, g) and queries (B, E, g, g), the crops' foreground probabilities (B, S,
        S) float32 with ``keep_masks`` (else None), and the forward ms per crop."""
        timer = StageTimer(self.device)
        masks, queries, probs = [], [], []
        use_amp = self.preset.amp and self.device.type == "cuda"
        with timer("forward"):
            for s in range(0, len(crops), self.preset.max_batch):
                part = crops[s:s + self.preset.max_batch]
                x = torch.from_numpy(np.stack([c.pixels for c in part])).to(self.device)
                idx = torch.tensor([c.part_index for c in part], device=self.device)
                with torch.autocast(self.device.type, dtype=torch.float16, enabled=use_amp):
                    m, q = self.model(self.model.normalize_images(x), idx)
                if keep_masks:
                    probs.append(torch.sigmoid(m.float()).cpu().numpy())
                m, q = pool_to_grid(m.float(), q.float(), self.preset.stride)
                masks.append(m)
                queries.append(q)
        return (torch.cat(masks), torch.cat(queries), np.concatenate(probs) if keep_masks else None,
                timer.ms["forward"] / len(crops))

    def _solve(self, c: _Crop, mask: torch.Tensor, query: torch.Tensor, crop_ms: float,
               fwd_ms: float, seed: int) -> PartPose:
        P, dev = self.preset, self.device
        timer = StageTimer(dev)
        gen = torch.Generator(device=dev)
        gen.manual_seed(_crop_seed(seed, c))
        if bank_is_cached(self.model, c.part_index, P.n_samples, seed, dev):
            bank = part_bank(self.model, c.part_index, P.n_samples, seed, dev)
        else:
            with timer("keys"):  # first use of this part: sample the surface, compute and cache the keys
                bank = part_bank(self.model, c.part_index, P.n_samples, seed, dev)
        with timer("correspondence"):
            field_ = build_field(mask, query, bank.keys, P.alpha, P.stride, P.mask_threshold, P.min_active,
                                 P.max_active, 4 * P.n_hypotheses, gen)
        box_side = self.crop_size / self.box_scale / P.stride
        sol = solve_field(field_, bank, grid_camera(c.K_crop, P.stride), box_side, P, gen, timer, prior=c.prior)
        ms = dict(timer.ms, crop=crop_ms, forward=fwd_ms)
        ms = {s: ms.get(s, 0.0) for s in STAGES} | ({"keys": ms["keys"]} if "keys" in ms else {})
        ms["total"] = sum(ms.values())
        info = self.model.parts[c.part_index]
        ok = sol.ok and bool(np.isfinite(sol.R).all() and np.isfinite(sol.t).all())
        return PartPose(c.obj_id, info.name, info.instrument, sol.R, sol.t, sol.score, sol.n_inliers, ok, ms,
                        c.crop_box, c.K_crop, c.image_index, sol.counts, sol.prior_won)
