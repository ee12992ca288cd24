"""Tracks against the ground truth of a synthetic clip (``gt.json`` of ``surftrack synth-clip``).

:class:`TrackScore` accumulates, per part, every frame's pose against the ground truth while a run
streams (feed it from ``annotate_video(on_frame=...)``) and reports RE, TE, ADD, ADD-10 (with the
SurgRIPE diameter: the model's bounding-box diagonal, the convention of the paper's tables), the share
of frames with a pose while the part is visible, and jitter: the mean frame-to-frame pose change minus
the ground truth's (mm, deg), over consecutive visible frames that both have a pose and one track (below).

Kinematics: path length (sum of the frame-to-frame translation of the part's origin) estimated and true
over the same pairs of consecutive visible frames with a pose, the second continuing the first's track
(not a restart or a fresh start, :func:`~surftrack.track.status.starts_anew`: the jump of a corrected
track is no motion; ``surftrack analyze`` counts alike), and the speed error: the median over
those pairs of |estimated - true speed|, relative to the median true speed. Given the instruments, the
same for each instrument's tool tip (:meth:`~surftrack.instruments.Instrument.tool_tip`, between the jaw
tips), from the tracked part poses (:meth:`TrackScore.tip_summary`). The path length again over the
steps both of whose frames have confidence >= 0.5 (what ``surftrack analyze --min-confidence 0.5``
counts), with the share of steps that leaves; and split by cause (:func:`format_path_causes`): over the steps
whose both ends are within ADD-10 (the smoother's own error), the excess over the others (the track wrong),
and the restart jumps no path counts. Confidence calibration:
ADD-10 of the frames whose confidence is >= 0.5 and of those below, and Spearman's rank correlation
between confidence and ADD (negative when confidence predicts error). For a part of an instrument with a
roll twin (:mod:`surftrack.instruments.twin`, one image cannot tell the two apart), ADD-10 also with the
twin counted as a symmetry, chosen per frame for the instrument's posed parts together.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

from surftrack.eval import add, diameter_bbox_diagonal, re, te
from surftrack.geometry import se3
from surftrack.instruments import Instrument, RollTwin
from surftrack.track.flow import pose_distance
from surftrack.track.status import starts_anew
from surftrack.track.state import PartState


def _instrument_groups(states: list[PartState]) -> dict[tuple[str, int], list[PartState]]:
    """A frame's part states per (instrument, instance)."""
    groups: dict[tuple[str, int], list[PartState]] = {}
    for s in states:
        groups.setdefault((s.spec.instrument, s.spec.instance), []).append(s)
    return groups


class ClipGroundTruth:
    """Per-frame part poses of a clip, keyed by det.json track id."""

    def __init__(self, path: str | Path):
        path = Path(path)
        doc = json.loads(path.read_text())
        if doc.get("format") != "surftrack-clip-gt":
            raise ValueError(f"{path}: not a clip ground-truth file (format {doc.get('format')!r})")
        self.frames: dict[int, dict[int, dict]] = {}
        for k, f in doc["frames"].items():
            self.frames[int(k)] = {int(g["part_id"]): g for g in f["gt"]}

    def pose(self, index: int, track_id: int) -> tuple[np.ndarray, np.ndarray, int]:
        """(R, t mm, visible pixels) of a part at a frame."""
        g = self.frames[index][track_id]
        return (np.asarray(g["cam_R_m2c"], np.float64).reshape(3, 3), np.asarray(g["cam_t_m2c"], np.float64),
                int(g["px_count_visib"]))


class TrackScore:
    """Accumulates per-part errors over a run; :meth:`summary` gives the table. Parts count on frames
    where at least ``min_visible_px`` of them are visible."""

    def __init__(self, gt: ClipGroundTruth, min_visible_px: int = 100,
                 instruments: Mapping[str, Instrument] | None = None):
        self.gt, self.min_visible_px = gt, min_visible_px
        self.instruments = dict(instruments or {})
        self.tips: dict[str, dict] = {}
        self.rows: dict[str, dict] = {}
        self._prev: dict[str, tuple] = {}
        self._diam: dict[str, float] = {}
        self._pts: dict[str, np.ndarray] = {}

    def add_frame(self, index: int, time_s: float, states: list[PartState]) -> None:
        fresh = {s.spec.name for s in states if starts_anew(s.status, s.info.as_dict())}
        for s in states:
            name, v = s.spec.name, s.spec.vertices
            if name not in self._pts:
                self._pts[name] = v if len(v) <= 2000 else v[np.random.default_rng(0).choice(len(v), 2000, False)]
                self._diam[name] = diameter_bbox_diagonal(v)
        twin_add = self._twin_adds(index, states)
        for s in states:
            name = s.spec.name
            row = self.rows.setdefault(name, {"instrument": s.spec.instrument, "re": [], "te": [], "add": [],
                                              "add_twin": [], "visible": 0, "posed": 0,
                                              "jit_t": [], "jit_r": [], "conf": [], "step_est": [],
                                              "step_gt": [], "step_conf": [], "step_right": [], "jumps": []})
            Rg, tg, vis = self.gt.pose(index, s.spec.track_id)
            scored = vis >= self.min_visible_px and s.R is not None
            a = add(s.R, s.t, Rg, tg, self._pts[name]) if scored else None
            prev = self._prev.get(name)
            # a step counts from a frame where the part was scored (visible) to the next such frame
            self._prev[name] = (index, s.R, s.t, Rg, tg, time_s, s.confidence, a) if vis >= self.min_visible_px else None
            if vis < self.min_visible_px:
                continue
            row["visible"] += 1
            if s.R is None:
                continue
            row["posed"] += 1
            row["re"].append(re(s.R, Rg))
            row["te"].append(te(s.t, tg))
            row["add"].append(a)
            row["add_twin"].append(twin_add.get(name, a))
            row["conf"].append(s.confidence)
            if prev is not None and prev[0] == index - 1 and prev[1] is not None:
                dr, dt = pose_distance(prev[1], prev[2], s.R, s.t)
                gr, gt_ = pose_distance(prev[3], prev[4], Rg, tg)
                if name in fresh:
                    row["jumps"].append(dt)  # the track's correction: left out of the path
                    continue
                row["jit_r"].append(dr - gr)
                row["jit_t"].append(dt - gt_)
                dt_s = time_s - prev[5]
                row["step_est"].append((dt, dt_s))
                row["step_gt"].append(gt_)
                row["step_conf"].append(min(prev[6], s.confidence))
                limit = 0.1 * self._diam[name]
                row["step_right"].append(a < limit and (prev[7] is None or prev[7] < limit))
        self._add_tips(index, time_s, states, fresh)

    def _twin(self, instrument: str) -> RollTwin | None:
        inst = self.instruments.get(instrument)
        return inst.roll_twin if inst is not None else None

    def _twin_adds(self, index: int, states: list[PartState]) -> dict[str, float]:
        """Each posed part's ADD (mm, capped at its diameter) with its instrument's roll twin counted as a
        symmetry (:meth:`RollTwin.nearer`: the poses or their twin, whichever is nearer the truth over the
        instrument's posed parts), for the instruments given that have a twin and whose posed parts hold
        their partners (a jaw posed without the other has no twin)."""
        out: dict[str, float] = {}
        for (name, _), group in _instrument_groups(states).items():
            twin = self._twin(name)
            posed = {s.spec.part: s for s in group if s.R is not None}
            if twin is None or not posed or not twin.closed(posed):
                continue
            truth = {p: self.gt.pose(index, s.spec.track_id) for p, s in posed.items()}

            def capped_add(part: str, R: np.ndarray, t: np.ndarray) -> float:
                key = posed[part].spec.name
                return min(add(R, t, truth[part][0], truth[part][1], self._pts[key]), self._diam[key])

            chosen, _ = twin.nearer({p: (s.R, s.t) for p, s in posed.items()}, capped_add)
            out.update({s.spec.name: capped_add(p, *chosen[p]) for p, s in posed.items()})
        return out

    def _add_tips(self, index: int, time_s: float, states: list[PartState], fresh: set[str]) -> None:
        """The tool tip (:meth:`Instrument.tool_tip`) of each instrument in ``self.instruments``, from the
        frame's part poses and from the ground truth's, on frames where every tip-carrying part has a pose
        and one of them is visible; no step into a frame where one of its parts (names in ``fresh``)
        starts anew."""
        for (name, instance), group in _instrument_groups(states).items():
            inst = self.instruments.get(name)
            if inst is None:
                continue
            parents = {j.parent for j in inst.chain.joints.values()}
            carriers = [s for s in group if s.spec.part not in parents and "tip" in inst.parts[s.spec.part].keypoints]
            rec = self.tips.setdefault(f"{name}.{instance}", {"err": [], "step_est": [], "step_gt": [], "prev": None})
            gt = {s.spec.part: self.gt.pose(index, s.spec.track_id) for s in group}
            if (not carriers or any(s.R is None for s in carriers)
                    or max(gt[s.spec.part][2] for s in carriers) < self.min_visible_px):
                rec["prev"] = None
                continue
            est_tip = inst.tool_tip({s.spec.part: se3(s.R, s.t) for s in group if s.R is not None})[1]
            gt_tip = inst.tool_tip({p: se3(R, t) for p, (R, t, _) in gt.items()})[1]
            rec["err"].append(float(np.linalg.norm(est_tip - gt_tip)))
            prev = rec["prev"]
            if prev is not None and prev[0] == index - 1 and not any(s.spec.name in fresh for s in group):
                rec["step_est"].append((float(np.linalg.norm(est_tip - prev[1])), time_s - prev[3]))
                rec["step_gt"].append(float(np.linalg.norm(gt_tip - prev[2])))
            rec["prev"] = (index, est_tip, gt_tip, time_s)

    def tip_summary(self) -> dict[str, dict]:
        """Per instrument instance: frames scored, median tool-tip error (mm), tool-tip path estimated /
        true (mm) over consecutive scored frames, and the speed error (%, as the parts')."""
        out = {}
        for label, r in self.tips.items():
            est = np.array([d for d, _ in r["step_est"]])
            true = np.asarray(r["step_gt"])
            dts = np.array([t for _, t in r["step_est"]])
            out[label] = {
                "frames": len(r["err"]),
                "tip_err_median_mm": float(np.median(r["err"])) if r["err"] else float("nan"),
                "path_mm": float(est.sum()), "path_gt_mm": float(true.sum()),
                "path_ratio": float(est.sum() / true.sum()) if true.sum() > 0 else float("nan"),
                "speed_err_pct": (100.0 * float(np.median(np.abs(est - true) / dts) / np.median(true / dts))
                                  if len(true) and np.median(true) > 0 else float("nan")),
            }
        return out

    def summary(self) -> dict[str, dict]:
        """Per part: frames visible / with a pose, RE and TE medians, ADD mean, ADD-10 (%, over visible
        frames: a frame without a pose counts as a miss), jitter (mm, deg), path length estimated / true
        (mm), speed error (%), confidence calibration (see the module docstring)."""
        out = {}
        for name, r in self.rows.items():
            n = max(r["visible"], 1)
            ok = sum(a < 0.1 * self._diam[name] for a in r["add"])
            hit = np.asarray(r["add"]) < 0.1 * self._diam[name]
            twin_ok = sum(a < 0.1 * self._diam[name] for a in r["add_twin"])
            conf = np.asarray(r["conf"])
            est = np.array([d for d, _ in r["step_est"]])
            true = np.asarray(r["step_gt"])
            dts = np.array([t for _, t in r["step_est"]])
            speed_err = (100.0 * float(np.median(np.abs(est - true) / dts) / np.median(true / dts))
                         if len(true) and np.median(true) > 0 else float("nan"))
            rho = (float(spearmanr(conf, r["add"]).statistic)
                   if len(conf) > 2 and np.ptp(conf) > 0 and np.ptp(r["add"]) > 0 else float("nan"))
            sure = np.asarray(r["step_conf"]) >= 0.5
            right = np.asarray(r["step_right"], dtype=bool)
            out[name] = {
                "visible_frames": r["visible"], "posed_frames": r["posed"],
                "re_median_deg": float(np.median(r["re"])) if r["re"] else float("nan"),
                "te_median_mm": float(np.median(r["te"])) if r["te"] else float("nan"),
                "add_mean_mm": float(np.mean(r["add"])) if r["add"] else float("nan"),
                "add10_pct": 100.0 * ok / n,
                "add10_twin_pct": 100.0 * twin_ok / n if self._twin(r["instrument"]) is not None else None,
                "jitter_mm": float(np.mean(r["jit_t"])) if r["jit_t"] else float("nan"),
                "jitter_deg": float(np.mean(r["jit_r"])) if r["jit_r"] else float("nan"),
                "diameter_mm": self._diam[name],
                "path_mm": float(est.sum()), "path_gt_mm": float(true.sum()),
                "path_ratio": float(est.sum() / true.sum()) if true.sum() > 0 else float("nan"),
                "speed_err_pct": speed_err,
                "path_conf_mm": float(est[sure].sum()) if len(est) else 0.0,
                "path_conf_gt_mm": float(true[sure].sum()) if len(true) else 0.0,
                "path_conf_ratio": (float(est[sure].sum() / true[sure].sum())
                                    if len(true) and true[sure].sum() > 0 else float("nan")),
                "path_conf_share_pct": 100.0 * float(sure.mean()) if len(sure) else float("nan"),
                "path_right_ratio": (float(est[right].sum() / true[right].sum())
                                     if len(true) and true[right].sum() > 0 else float("nan")),
                "path_right_share_pct": 100.0 * float(right.mean()) if len(right) else float("nan"),
                "excess_wrong_mm": float((est - true)[~right].sum()) if len(est) else 0.0,
                "jumps": len(r["jumps"]), "jump_mm": float(sum(r["jumps"])),
                "add10_conf_hi_pct": 100.0 * float(hit[conf >= 0.5].mean()) if (conf >= 0.5).any() else float("nan"),
                "add10_conf_lo_pct": 100.0 * float(hit[conf < 0.5].mean()) if (conf < 0.5).any() else float("nan"),
                "conf_hi_share_pct": 100.0 * float((conf >= 0.5).mean()) if len(conf) else float("nan"),
                "conf_add_spearman": rho,
            }
        return out


def format_tip_summary(summary: dict[str, dict]) -> str:
    """A markdown table of :meth:`TrackScore.tip_summary`."""
    lines = ["| tool tip | frames | error median (mm) | path est / gt (mm) | speed err (%) |", "|---|---|---|---|---|"]
    for label, r in summary.items():
        lines.append(f"| {label} | {r['frames']} | {r['tip_err_median_mm']:.1f} | {r['path_mm']:.0f} / "
                     f"{r['path_gt_mm']:.0f} = {r['path_ratio']:.2f} | {r['speed_err_pct']:.0f} |")
    return "\n".join(lines) + "\n"


def format_path_causes(summary: dict[str, dict]) -> str:
    """A markdown table of where each part's path error comes from (:meth:`TrackScore.summary`): the path
    over the steps whose both ends are within ADD-10 of the truth (the smoother's own error: jitter, lag),
    the excess over the other counted steps (the track wrong), and the jumps of restarts and fresh starts,
    which no path counts."""
    lines = ["| part | path est / gt | path where the track is right: est / gt (share of steps %) "
             "| excess where it is wrong (mm) | restart / fresh-start jumps left out (n, mm) |",
             "|---|---|---|---|---|"]
    for name, r in summary.items():
        lines.append(f"| {name} | {r['path_ratio']:.2f} | {r['path_right_ratio']:.2f} ({r['path_right_share_pct']:.0f}) | "
                     f"{r['excess_wrong_mm']:.0f} | {r['jumps']}, {r['jump_mm']:.0f} |")
    return "\n".join(lines) + "\n"


def format_summary(summary: dict[str, dict]) -> str:
    """A markdown table of :meth:`TrackScore.summary`; the last column, ADD-10 with the roll twin counted as
    a symmetry, where some part's instrument has one."""
    twin = any(r.get("add10_twin_pct") is not None for r in summary.values())
    head = ("| part | visible | posed | RE med (deg) | TE med (mm) | ADD mean (mm) | ADD-10 (%) | jitter (mm / deg) "
            "| path est / gt (mm) | speed err (%) | path over conf >= 0.5 (share of steps %) "
            "| ADD-10 conf >= / < 0.5 (%, share >=) | rho(conf, ADD) |")
    lines = [head + (" ADD-10 up to the roll twin (%) |" if twin else ""), "|---" * (14 if twin else 13) + "|"]
    for name, r in summary.items():
        extra = ""
        if twin:
            extra = f" {r['add10_twin_pct']:.1f} |" if r.get("add10_twin_pct") is not None else " – |"
        lines.append(f"| {name} | {r['visible_frames']} | {r['posed_frames']} | {r['re_median_deg']:.1f} | "
                     f"{r['te_median_mm']:.1f} | {r['add_mean_mm']:.1f} | {r['add10_pct']:.1f} | "
                     f"{r['jitter_mm']:.2f} / {r['jitter_deg']:.2f} | {r['path_mm']:.0f} / {r['path_gt_mm']:.0f} "
                     f"= {r['path_ratio']:.2f} | {r['speed_err_pct']:.0f} | {r['path_conf_mm']:.0f} / "
                     f"{r['path_conf_gt_mm']:.0f} = {r['path_conf_ratio']:.2f} ({r['path_conf_share_pct']:.0f}) | "
                     f"{r['add10_conf_hi_pct']:.0f} / "
                     f"{r['add10_conf_lo_pct']:.0f} ({r['conf_hi_share_pct']:.0f}) | {r['conf_add_spearman']:.2f} |"
                     + extra)
    return "\n".join(lines) + "\n"
