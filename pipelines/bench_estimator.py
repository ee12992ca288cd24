"""Pose estimator latency per part, split by stage, per preset, on the CPU and (when available) CUDA.

    python pipelines/bench_estimator.py [--model ckpt.pt] [--data BOP_DIR] [--runs 5] [--threads N]
                                        [--solver-threads 1] [--presets fast accurate] [--devices cpu cuda]

Two measurements per device and preset:

1. The whole estimator on one image. Without --model it builds an UNTRAINED model of the paper's size
   (ResNet18 U-Net, decoders 256-128-64-64-64, SIREN 256, crop 224, the LND's four parts): the network's
   cost does not depend on the weights, but the solver's does: an untrained model marks about half of
   the crop as object (many active pixels: a costly correspondence stage) and its random correspondences
   leave few plausible hypotheses (cheap scoring). Without --data it renders one synthetic LND image
   (surftrack.synth) into a temporary folder and uses its ground-truth visible boxes as detections.
2. The solver on correspondences from RENDERED object coordinates of each LND part (0.1 mm noise, 30 %
   outliers; surftrack.pose.synthetic) at --poses random poses: realistic loads for the stages after the
   network, and the pose errors against the truth. Add the forward of (1) for a per-part total.

Reported: median ms per part of each stage over --runs calls after one warm-up call (which also computes
and caches the surface keys), and the pose errors against the ground truth (in (1) meaningful only with a
trained model). --threads sets torch's intra-op threads (the
network forward); the solver stages run with --solver-threads (PoseEstimator's default, 1).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from surftrack.data.bop import BopDataset
from surftrack.geometry import box_from_bop, rotation_angle_deg
from surftrack.pose import PoseEstimator
from surftrack.pose.estimator import STAGES


def paper_model():
    from surftrack.instruments import load_instrument
    from surftrack.model.config import ModelCfg
    from surftrack.model.surfsurg6d import PartInfo, SurfSurg6D

    inst = load_instrument("large_needle_driver")
    parts = [PartInfo.from_part(i + 1, inst.name, inst.parts[n]) for i, n in enumerate(inst.part_names)]
    torch.manual_seed(0)
    return SurfSurg6D(parts, ModelCfg())


def synthetic_frame(tmp: Path) -> tuple[np.ndarray, np.ndarray, dict, dict]:
    """(rgb, K, boxes obj_id -> edge box, gt poses obj_id -> 4x4) of one generated LND image."""
    from surftrack.synth.config import load_synth_config
    from surftrack.synth.generate import generate_dataset

    cfg = load_synth_config(overrides={"two_instruments_prob": 0.0, "tissue": {"images_per_tissue": 1},
                                      "output": {"images_per_scene": 1, "rgb_format": "png"}})
    generate_dataset(tmp, cfg, 1, seed=0, workers=1, progress=False)
    return first_frame(tmp)


def first_frame(root: Path) -> tuple[np.ndarray, np.ndarray, dict, dict]:
    ds = BopDataset(root, min_visib_fract=0.0, min_px_visib=1)
    first = ds.instances[0]
    insts = [i for i in ds.instances if (i.scene_id, i.im_id) == (first.scene_id, first.im_id)]
    rgb = ds.load_rgb(first.scene_id, first.im_id)
    K = insts[0].camera(rgb.shape[1], rgb.shape[0]).K
    boxes = {i.obj_id: box_from_bop(i.bbox_visib) for i in insts}
    return rgb, K, boxes, {i.obj_id: i.pose for i in insts}


def bench(est: PoseEstimator, rgb, K, boxes, gt, runs: int) -> None:
    first = est.estimate(rgb, boxes, K)  # warm-up: keys of every part computed and cached
    keys_ms = {p.part: p.timings.get("keys", 0.0) for p in first}
    walls, per_part = [], {}
    for _ in range(runs):
        t0 = time.perf_counter()
        res = est.estimate(rgb, boxes, K)
        walls.append((time.perf_counter() - t0) * 1e3)
        for p in res:
            per_part.setdefault((p.obj_id, p.part), []).append(p)
    head = "".join(f"{s:>15}" for s in STAGES)
    head += f"{'total':>9}  {'RE deg':>7} {'TE mm':>7} {'score':>7} {'inl':>5} active"
    print(f"  {'part':<10}{head}")
    totals = []
    for (obj_id, name), ps in per_part.items():
        med = {s: statistics.median(p.timings[s] for p in ps) for s in list(STAGES) + ["total"]}
        totals.append(med["total"])
        last = ps[-1]
        re = float(rotation_angle_deg(last.R, gt[obj_id][:3, :3])) if obj_id in gt else float("nan")
        te = float(np.linalg.norm(last.t - gt[obj_id][:3, 3])) if obj_id in gt else float("nan")
        row = "".join(f"{med[s]:>15.1f}" for s in STAGES)
        print(f"  {name:<10}{row}{med['total']:>9.1f}  {re:>7.2f} {te:>7.2f} {last.score:>7.3f} {last.n_inliers:>5} "
              f"{last.counts.get('active', '')}")
    print(f"  per part: mean {statistics.mean(totals):.1f} ms, max {max(totals):.1f} ms; whole call "
          f"(all {len(boxes)} parts, one batched forward): median {statistics.median(walls):.1f} ms; "
          f"first call's key computation per part: "
          + ", ".join(f"{k} {v:.0f} ms" for k, v in keys_ms.items()))


def rendered(preset_name: str, device: str, n_poses: int) -> None:
    """Section 2 of the module docstring. The correspondence stage is timed again on the problem's
    queries and keys padded with zeros to the network's 12 dimensions (the same logits)."""
    from scipy.spatial.transform import Rotation

    from surftrack.geometry import PinholeCamera
    from surftrack.instruments import load_instrument
    from surftrack.pose import PRESETS
    from surftrack.pose.correspondence import build_field
    from surftrack.pose.solver import StageTimer, solve_field
    from surftrack.pose.synthetic import rendered_problem

    lnd = load_instrument("large_needle_driver")
    cam = PinholeCamera(np.array([[818.05, 0.0, 476.31], [0.0, 816.0, 298.18], [0.0, 0.0, 1.0]]), 960, 540)
    preset = PRESETS[preset_name]
    stages = ("correspondence", "hypotheses", "scoring", "refinement")
    print(f"  solver on rendered correspondences, {n_poses} poses per part (median ms; max errors):")
    print(f"  {'part':<10}{'active':>8}" + "".join(f"{s:>15}" for s in stages) + f"{'sum':>9}  {'RE deg':>7} {'TE mm':>7}")
    for name in lnd.part_names:
        rows, res, tes, act = [], [], [], []
        for k in range(n_poses):
            rng = np.random.default_rng(k)
            T = np.eye(4)
            T[:3, :3] = Rotation.random(random_state=k).as_matrix()
            T[:3, 3] = [rng.uniform(-10, 10), rng.uniform(-5, 5), rng.uniform(45, 80)]
            pb = rendered_problem(lnd.parts[name], T, cam, preset, seed=k, device=device)
            f = pb.field
            q = torch.zeros(12, f.g * f.g, device=device)
            q[: f.query.shape[1], f.active] = f.query.T
            keys = torch.nn.functional.pad(pb.bank.keys, (0, 12 - pb.bank.keys.shape[1]))
            for rep in range(2 if k == 0 else 1):  # warm-up on the first pose
                timer = StageTimer(device)
                gen = torch.Generator(device=device)
                gen.manual_seed(k)
                with timer("correspondence"):
                    build_field(f.mask_logit.view(f.g, f.g), q.view(12, f.g, f.g), keys, preset.alpha, preset.stride,
                                preset.mask_threshold, preset.min_active, preset.max_active, 4 * preset.n_hypotheses,
                                gen)
                sol = solve_field(f, pb.bank, pb.K_grid, pb.box_side, preset, gen, timer)
            rows.append(timer.ms)
            res.append(float(rotation_angle_deg(sol.R, pb.R)))
            tes.append(float(np.linalg.norm(sol.t - pb.t)))
            act.append(len(f.active))
        med = {s: statistics.median(r.get(s, 0.0) for r in rows) for s in stages}
        print(f"  {name:<10}{int(statistics.median(act)):>8}" + "".join(f"{med[s]:>15.1f}" for s in stages)
              + f"{sum(med.values()):>9.1f}  {max(res):>7.2f} {max(tes):>7.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", help="checkpoint (default: untrained paper-size model)")
    ap.add_argument("--data", help="BOP dataset root; its first image is used (default: render one)")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--threads", type=int, help="torch CPU threads for the forward (default: torch's choice)")
    ap.add_argument("--solver-threads", type=int, default=1, help="CPU threads of the solver stages (0: as --threads)")
    ap.add_argument("--presets", nargs="+", default=["fast", "accurate"])
    ap.add_argument("--poses", type=int, default=3, help="rendered poses per part for section 2 (0: skip it)")
    ap.add_argument("--devices", nargs="+", default=["cpu", "cuda"])
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        rgb, K, boxes, gt = first_frame(Path(args.data)) if args.data else synthetic_frame(Path(tmp) / "data")
    model = args.model or paper_model()
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"image {rgb.shape[1]}x{rgb.shape[0]}, parts {sorted(boxes)}; model: "
          f"{args.model or 'untrained, paper size (timings do not depend on training)'}; torch {torch.__version__}, "
          f"{torch.get_num_threads()} CPU threads (solver {args.solver_threads or torch.get_num_threads()}) on "
          f"{os.cpu_count()} cores, load average {load:.2f}")
    for dev in args.devices:
        if torch.device(dev).type == "cuda" and not torch.cuda.is_available():
            print("cuda: not available, skipped")
            continue
        name = torch.cuda.get_device_name(dev) if torch.device(dev).type == "cuda" else "CPU"
        for preset in args.presets:
            est = PoseEstimator(model, preset, device=dev, solver_threads=args.solver_threads or None)
            print(f"\n{dev} ({name}), preset {preset}: crop {est.crop_size}, stride {est.preset.stride}, "
                  f"{est.preset.n_samples} surface samples, {est.preset.n_hypotheses} hypotheses, "
                  f"{est.preset.max_scored} scored; median ms per part over {args.runs} runs")
            bench(est, rgb, K, boxes, gt, args.runs)
            if args.poses:
                threads = torch.get_num_threads()
                if dev == "cpu" and args.solver_threads:
                    torch.set_num_threads(args.solver_threads)
                rendered(preset, dev, args.poses)
                torch.set_num_threads(threads)
    sys.stdout.flush()


if __name__ == "__main__":
    main()
