"""The recipe of the bundled default model (`models/default.pt`): Large Needle Driver, lite config, CPU.

    python pipelines/make_default_model.py --work runs/default [--device cpu|cuda] [--skip-eval]
                                           [--from-stage K --init CHECKPOINT] [--workers N]

Steps (each resumable: an existing output is reused):

1. ``surftrack synth``: 400 LND images (seed 11), 2,000 (seed 12) and 2,000 more (seed 15) with the
   paper's synthesis config (``configs/synth/paper.yaml``: roll within +-30 deg of ``roll_zero: view``);
   2,000 with ``roll_zero: across`` (seed 16), 2,000 with the roll anywhere in +-180 deg (seed 18) and
   2,000 more of those (seed 20); for stage 7, 3 x 2,000 over the instrument's whole reach (the synthesis
   default, ``configs/synth/default.yaml``: every joint within its limits; seeds 31, 32, 33) and 2,000
   more with the paper's config (seed 34); for stage 8 the same again with seeds 41, 42, 43 and 44, and
   1,000 far (seed 45; 928 made, the others' placements fail at that distance) and 1,000 near (seed 46)
   tools: the held-out suite's ``far`` and ``near`` settings (``configs/eval/suite.yaml``) with seeds of
   their own.
2. ``surftrack train --config lite``, each stage started from the previous one's weights (``--init``):
   2,000 steps on the 400 images with a constant learning rate (``schedule: constant``); 3,500 steps on
   the first 2,000 images with the lite config's cosine decay; 3,000 more on them at half the learning
   rates (1.5e-4 / 1.5e-5), cosine again; 7,500 steps on both ``view`` sets (4,000 images, joined as one
   BOP folder whose scene folders link to theirs) at the same rates; 10,000 steps on the first four
   2,000-image sets (8,000 images) at the same rates; 10,000 steps on all five (10,000 images) at the same
   rates; stage 7: 12,000 steps on the 8,000 stage-7 images at a quarter of the lite rates (7.5e-5 /
   7.5e-6) after a 500-step warm-up, cosine, the LND labelled as one of its roll twins
   (``data.canonical_twin``; stages 1-6 without); stage 8: 8,000 steps on the 9,928 stage-8 images, the
   same rates and warm-up. Each stage holds out its own validation images from its
   data, so most of the later stages' were training images of earlier ones: their validation curves
   flatter; the held-out evaluation below is independent of all stages. ``--from-stage K --init CKPT`` runs
   stages K onwards alone, stage K from another checkpoint (the bundled model's stage 7 started from the
   int8 export of stage 6, its stage 8 from that of stage 7, when the fp32 weights were gone).
3. Export with int8 U-Net weights (SIREN fields fp16) to ``models/default.pt`` and the training curves to
   ``models/default.curves.png``.
4. ``surftrack eval --suite`` (the fixed held-out suite of ``configs/eval/suite.yaml``, its image sets and
   its tracking clips; fast preset, one crop view, with the kinematic fit, solver seeds 0, 1 and 2): the
   tables go to
   ``models/default.eval.suite.md`` and, by hand, into ``models/MODEL_CARD.md``.

On the 2-core CPU machine of the model card stages 1-6 took about 9 hours (synthesis ~30 min, training
~8 h 10 min); stage 7 adds about 40 min of synthesis and 2.5-3 h of training, stage 8 about 50 min of synthesis
and 1.5 h of training.
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
STAGES = 8  # training stages of the recipe


def _synth(out: Path, images: int, seed: int, config: str = "paper", workers: int = 2, **pose) -> None:
    """``images`` LND images with the synthesis ``config``, its ``pose`` settings replaced by ``pose``
    (the images do not depend on ``workers``)."""
    from surftrack.synth.config import load_synth_config
    from surftrack.synth.generate import generate_dataset

    cfg = load_synth_config(config, overrides={"instruments": ["large_needle_driver"]})
    cfg = dataclasses.replace(cfg, pose=dataclasses.replace(cfg.pose, **pose)).validate()
    generate_dataset(out, cfg, images, seed=seed, workers=workers, progress=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", default="runs/default", help="working folder (datasets, full checkpoints)")
    ap.add_argument("--device", help="cpu or cuda (default: cuda when available)")
    ap.add_argument("--skip-eval", action="store_true")
    ap.add_argument("--from-stage", type=int, help="run this stage and the later ones alone, the first of them "
                    "from --init (the bundled model's stages 7 and 8 started from the previous stage's int8 "
                    "export, whose fp32 weights were not kept)")
    ap.add_argument("--init", help="the checkpoint --from-stage starts from")
    ap.add_argument("--workers", type=int, help="synthesis processes and training-loader workers, about one per "
                    "core on a GPU machine (default: 2 for synthesis, the lite config's loader setting, 0, "
                    "for training: the 2-core machine the recipe was made on)")
    args = ap.parse_args(argv)
    if (args.from_stage is None) != (args.init is None):
        ap.error("--from-stage and --init go together")
    if args.from_stage is not None and not 2 <= args.from_stage <= STAGES:
        ap.error(f"--from-stage must be 2-{STAGES}, got {args.from_stage}")
    if args.init is not None and not Path(args.init).is_file():
        ap.error(f"--init {args.init}: no such file")
    if args.workers is not None and args.workers < 1:
        ap.error(f"--workers must be 1 or more, got {args.workers}")
    synth_workers = args.workers or 2
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)

    from surftrack.model import load_checkpoint, load_train_config, save_checkpoint
    from surftrack.data.join import join_datasets
    from surftrack.model.train import train
    from surftrack.pose.suite import SuiteSet, set_config
    from surftrack.synth.generate import generate_dataset

    # stages 1-6 as the bundled model was trained, before data.canonical_twin existed (labels as drawn);
    # stages 7 and 8, over the instrument's whole reach, label the LND as one of its roll twins: both twins are
    # drawn alike there and give the same image (docs/results/2026-12-05-roll-twin.md)
    lite = load_train_config("lite").replace(data={"canonical_twin": False})
    half = lite.replace(optim={"lr_net": 1.5e-4, "lr_field": 1.5e-5})
    # a converged model moved to a new pose distribution at half rates lost most of what it knew
    # (docs/decisions.md): stage 7 warms up over 500 steps to a quarter of the lite rates
    quarter = lite.replace(optim={"lr_net": 7.5e-5, "lr_field": 7.5e-6, "warmup": 500},
                           data={"canonical_twin": True})
    # (config, data, steps): stage 1 from scratch, each later one from the previous stage's weights
    stages = [(lite.replace(optim={"schedule": "constant"}), "lnd400", 2000), (lite, "lnd2k", 3500),
              (half, "lnd2k", 3000), (half, "lnd4k", 7500), (half, "lnd8k_mix", 10000), (half, "lnd10k_mix", 10000),
              (quarter, "lnd8k_reach", 12000), (quarter, "lnd10k_reach_b", 8000)]
    assert len(stages) == STAGES
    first = args.from_stage or 1
    if first <= 6:
        for name, n, seed in (("lnd400", 400, 11), ("lnd2k", 2000, 12), ("lnd2k_b", 2000, 15)):
            _synth(work / name, n, seed, workers=synth_workers)
        _synth(work / "lnd_across2k", 2000, 16, workers=synth_workers, roll_zero="across")
        for name, seed in (("lnd_fullroll2k", 18), ("lnd_fullroll2k_b", 20)):
            _synth(work / name, 2000, seed, workers=synth_workers, roll_deg=(-180.0, 180.0))
        view, across, roll = [work / "lnd2k", work / "lnd2k_b"], [work / "lnd_across2k"], [work / "lnd_fullroll2k"]
        join_datasets(work / "lnd4k", view)
        join_datasets(work / "lnd8k_mix", view + across + roll)
        join_datasets(work / "lnd10k_mix", view + across + roll + [work / "lnd_fullroll2k_b"])
    # stage 7: the instrument's whole reach (the synthesis default), a quarter paper-range images kept in;
    # stage 8 the same on new images, with far and near tools (a stage without them lost those,
    # docs/results/2026-12-06-stage8.md): the held-out suite's far and near settings when it was trained,
    # written out here so that the recipe does not move with the suite's file
    reach_sets = {7: ("lnd8k_reach", "abc", "lnd2k_c", (31, 32, 33, 34)),
                  8: ("lnd10k_reach_b", "def", "lnd2k_d", (41, 42, 43, 44))}
    lnd = ["large_needle_driver"]
    depth_sets = {"far": (45, {"instruments": lnd, "tissue": {"distance_mm": [170, 220]},
                               "pose": {"tip_to_tissue_mm": [40, 90]}}),
                  "near": (46, {"instruments": lnd, "tissue": {"distance_mm": [80, 110]},
                                "pose": {"tip_to_tissue_mm": [40, 80], "min_depth_mm": 15}})}
    for k, (joined, letters, paper_set, seeds) in reach_sets.items():
        if k < first:
            continue
        names = [f"lnd_reach2k_{c}" for c in letters] + [paper_set]
        for name, seed in zip(names, seeds):
            _synth(work / name, 2000, seed, "paper" if name == paper_set else "default", workers=synth_workers)
        if k == 8:
            for name, (seed, overrides) in depth_sets.items():
                s = SuiteSet(name, "default", seed, 1000, overrides)
                generate_dataset(work / f"lnd_{name}1k", set_config(s), s.images, seed=s.seed,
                                 workers=synth_workers, progress=True)
                names.append(f"lnd_{name}1k")
        join_datasets(work / joined, [work / n for n in names])

    prev = None
    for k, (stage_cfg, data, steps) in enumerate(stages, start=1):
        if k < first:
            continue
        if k == args.from_stage:
            prev = Path(args.init)
        stage = work / f"stage{k}.pt"
        if args.workers is not None:  # the loader's workers change the speed, not the batches
            stage_cfg = stage_cfg.replace(run={"workers": args.workers})
        if not stage.is_file() or load_checkpoint(stage)[2]["step"] < steps:  # resumed when cut short
            train(stage_cfg, work / data, stage, steps=steps, device=args.device, init=prev, resume=stage.is_file())
        prev = stage

    model, cfg, blob = load_checkpoint(prev)
    models = REPO / "models"
    models.mkdir(exist_ok=True)
    save_checkpoint(models / "default.pt", model, cfg, blob["step"], int8=True)
    shutil.copy(prev.with_suffix(".curves.png"), models / "default.curves.png")
    print(f"wrote {models / 'default.pt'} ({(models / 'default.pt').stat().st_size / 1e6:.1f} MB)")

    if not args.skip_eval:
        from surftrack.cli import main as surftrack

        # `surftrack eval --suite` itself: the fixed held-out suite (configs/eval/suite.yaml), its image sets
        # and tracking clips, fast preset with the fit, solver seeds 0-2
        code = surftrack(["eval", "--model", str(models / "default.pt"), "--suite", "--suite-dir", str(work / "suite"),
                          "--preset", "fast", "--kinematic", "--out", str(models / "default.eval")]
                         + (["--device", args.device] if args.device else []))
        if code:
            return code
    return 0


if __name__ == "__main__":
    sys.exit(main())
