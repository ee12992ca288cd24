"""The recipe of the bundled default model (`models/default.pt`): Large Needle Driver, lite config, CPU.

    python pipelines/make_default_model.py --work runs/default [--device cpu|cuda] [--skip-eval]

Steps (each resumable: an existing output is reused):

1. ``surftrack synth``: 400 LND images (seed 11), 2,000 (seed 12) and 2,000 more (seed 15) with the
   paper's synthesis config (``configs/synth/paper.yaml``: roll within +-30 deg of ``roll_zero: view``); 2,000 with ``roll_zero:
   across`` (seed 16), 2,000 with the roll anywhere in +-180 deg (seed 18) and 2,000 more of those
   (seed 20). Held out for evaluation: 100 images of each kind (seeds 13, 17 and 19).
2. ``surftrack train --config lite``, each stage started from the previous one's weights (``--init``):
   2,000 steps on the 400 images with a constant learning rate (``schedule: constant``); 3,500 steps on
   the first 2,000 images with the lite config's cosine decay; 3,000 more on them at half the learning
   rates (1.5e-4 / 1.5e-5), cosine again; 7,500 steps on both ``view`` sets (4,000 images, joined as one
   BOP folder whose scene folders link to theirs) at the same rates; 10,000 steps on the first four
   2,000-image sets (8,000 images) at the same rates; 10,000 steps on all five (10,000 images) at the same
   rates. Each stage holds out its own validation images from its data,
   so most of the later stages' were training images of earlier ones: their validation curves flatter;
   the held-out evaluation below is independent of all stages.
3. Export with int8 U-Net weights (SIREN fields fp16) to ``models/default.pt`` and the training curves to
   ``models/default.curves.png``.
4. ``surftrack eval`` (fast preset, per-part and instrument-consistent poses, solver seeds 0, 1 and 2) on
   the three held-out sets; the tables (seed 0, and ADD-10 per seed with the mean) go to
   ``models/default.eval.md`` and, by hand, into ``models/MODEL_CARD.md``.

On the 2-core CPU machine of the model card the whole recipe takes about 9 hours (synthesis ~30 min,
training ~8 h 10 min, evaluation a few minutes).
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def _synth(out: Path, images: int, seed: int, **pose) -> None:
    """``images`` LND images with the paper's synthesis config, its ``pose`` settings replaced by ``pose``."""
    from surftrack.synth.config import load_synth_config
    from surftrack.synth.generate import generate_dataset

    cfg = load_synth_config("paper", overrides={"instruments": ["large_needle_driver"]})
    cfg = dataclasses.replace(cfg, pose=dataclasses.replace(cfg.pose, **pose)).validate()
    generate_dataset(out, cfg, images, seed=seed, workers=2, progress=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", default="runs/default", help="working folder (datasets, full checkpoints)")
    ap.add_argument("--device", help="cpu or cuda (default: cuda when available)")
    ap.add_argument("--skip-eval", action="store_true")
    args = ap.parse_args(argv)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)

    from surftrack.model import load_checkpoint, load_train_config, save_checkpoint
    from surftrack.data.join import join_datasets
    from surftrack.model.train import train

    for name, n, seed in (("lnd400", 400, 11), ("lnd2k", 2000, 12), ("lnd2k_b", 2000, 15), ("lnd_test100", 100, 13)):
        _synth(work / name, n, seed)
    for name, n, seed in (("lnd_across2k", 2000, 16), ("lnd_across_test100", 100, 17)):
        _synth(work / name, n, seed, roll_zero="across")
    for name, n, seed in (("lnd_fullroll2k", 2000, 18), ("lnd_fullroll2k_b", 2000, 20), ("lnd_fullroll_test100", 100, 19)):
        _synth(work / name, n, seed, roll_deg=(-180.0, 180.0))
    view, across, roll = [work / "lnd2k", work / "lnd2k_b"], [work / "lnd_across2k"], [work / "lnd_fullroll2k"]
    join_datasets(work / "lnd4k", view)
    join_datasets(work / "lnd8k_mix", view + across + roll)
    join_datasets(work / "lnd10k_mix", view + across + roll + [work / "lnd_fullroll2k_b"])

    lite = load_train_config("lite")
    stage1 = work / "stage1.pt"
    if not stage1.is_file():
        train(lite.replace(optim={"schedule": "constant"}), work / "lnd400", stage1, steps=2000, device=args.device)
    half = lite.replace(optim={"lr_net": 1.5e-4, "lr_field": 1.5e-5})
    # stages 2-6: (config, data, steps), each from the previous stage's weights; resumed when cut short
    prev = stage1
    for k, (stage_cfg, data, steps) in enumerate(((lite, "lnd2k", 3500), (half, "lnd2k", 3000), (half, "lnd4k", 7500),
                                                  (half, "lnd8k_mix", 10000), (half, "lnd10k_mix", 10000)), start=2):
        stage = work / f"stage{k}.pt"
        if not stage.is_file() or load_checkpoint(stage)[2]["step"] < steps:
            train(stage_cfg, work / data, stage, steps=steps, device=args.device, init=prev, resume=stage.is_file())
        prev = stage

    model, cfg, blob = load_checkpoint(prev)
    models = REPO / "models"
    models.mkdir(exist_ok=True)
    save_checkpoint(models / "default.pt", model, cfg, blob["step"], int8=True)
    shutil.copy(prev.with_suffix(".curves.png"), models / "default.curves.png")
    print(f"wrote {models / 'default.pt'} ({(models / 'default.pt').stat().st_size / 1e6:.1f} MB)")

    if not args.skip_eval:
        from surftrack.pose import evaluate_seeds, get_preset, markdown_table, seed_table, write_eval_outputs

        tables = []
        for name in ("lnd_test100", "lnd_across_test100", "lnd_fullroll_test100"):
            for kinematic in (False, True):
                # one seed's figure moves by a few points on 100 images: seeds 0-2, one network forward
                runs = evaluate_seeds(models / "default.pt", work / name, (0, 1, 2), split="train",
                                      device=args.device, preset=get_preset("fast"), kinematic=kinematic)
                for r in runs:
                    write_eval_outputs(r, work / f"eval_{name}{'_kinematic' if kinematic else ''}.seed{r['seed']}.json")
                what = "instrument-consistent poses" if kinematic else "per-part poses"
                tables.append(f"## {name}, {what}\n\n{markdown_table(runs[0])}\n{seed_table(runs)}")
        (models / "default.eval.md").write_text("\n\n".join(tables) + "\n")
        print("\n\n".join(tables))
    return 0


if __name__ == "__main__":
    sys.exit(main())
