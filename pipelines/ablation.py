"""Loss ablation (the paper's ablation table): SurfEmb (alpha = beta = 0), + hard negatives (alpha only),
+ consistency (beta only) and the full SurfSurg6D, trained on the same data with the same seed and steps,
then evaluated on the same held-out images.

    python pipelines/ablation.py --data DIR [--config lite] [--steps N] [--out out/ablation]
                                 [--preset accurate|fast] [--eval-data DIR [--eval-split test]]
                                 [--max-images N] [--device cpu|cuda]

alpha and beta of the "on" variants are the config's (lite: alpha = 1, beta = 1; alpha = 1 needs
``loss.pen_floor > 0``, which the config keeps; see :func:`surftrack.model.losses.pen_log_weights`).
Everything else (including ``pen_floor``) is the config's.

Evaluation set: ``--eval-data`` (a BOP dataset with the same models, split ``--eval-split``) is the
proper held-out set. Without it the variants are evaluated on the images that :func:`train` held out of
the training data for validation (the same for all variants: same seed and ``run.val_images``); a warning
says so, since those images come from the same generator / scenes as the training images.

Writes to ``--out``: ``<variant>.pt`` (+ training logs), ``<variant>.eval.{json,md,bop.csv,png}``,
``ablation.json`` and ``ablation.md`` (rows = variants; RE, TE: mean over instances; ADD-10 with the
SurgRIPE diameter (bbox diagonal), the BOP one (max pairwise) in the JSON and a second column; AUC of ADD
on 0-5 mm). A variant whose checkpoint already exists with the same config and step count is not retrained.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

from surftrack.model import load_train_config
from surftrack.model.checkpoint import CheckpointError, load_checkpoint
from surftrack.model.train import train, validation_split
from surftrack.pose.evaluate import evaluate, write_eval_outputs


def variants(cfg) -> list[tuple[str, str, float, float]]:
    """(key, table name, alpha, beta) of the four variants; "on" values are the config's."""
    a, b = float(cfg.loss.alpha), float(cfg.loss.beta)
    if a <= 0 or b <= 0:
        raise SystemExit(f"the config's loss.alpha ({a}) and loss.beta ({b}) must be positive: they are the values "
                         "of the 'on' variants")
    return [("surfemb", "SurfEmb (alpha = beta = 0)", 0.0, 0.0),
            ("hardneg", f"+ hard negatives (alpha = {a:g})", a, 0.0),
            ("consistency", f"+ consistency (beta = {b:g})", 0.0, b),
            ("full", f"SurfSurg6D (alpha = {a:g}, beta = {b:g})", a, b)]


def _trained(path: Path, cfg, steps: int) -> bool:
    if not path.is_file():
        return False
    try:
        _, c, blob = load_checkpoint(path)
    except CheckpointError:
        return False
    return c == cfg and int(blob["step"]) == steps


def _pct(v) -> str:
    return "–" if v is None else f"{100 * v:.2f}"


def _num(v) -> str:
    return "–" if v is None else f"{v:.2f}"


def ablation_table(rows: list[dict], eval_desc: str) -> str:
    head = ["Variant", "alpha", "beta", "RE (°) ↓", "TE (mm) ↓", "ADD-10 (%) ↑", "AUC 0-5 mm (%) ↑",
            "ADD-10 BOP diam. (%)", "n"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        s = r["overall"]["all"]
        lines.append("| " + " | ".join([r["name"], f"{r['alpha']:g}", f"{r['beta']:g}", _num(s["re_mean"]),
                                        _num(s["te_mean"]), _pct(s["add10_surgripe"]), _pct(s["auc_add_0_5mm"]),
                                        _pct(s["add10_bop"]), str(s["count"])]) + " |")
    lines += ["", "RE, TE: mean over all instances (occluded and not). ADD-10: ADD < 10 % of the SurgRIPE diameter "
                  "(bbox diagonal of the model); the BOP column uses the max-pairwise diameter. AUC 0-5 mm: area under "
                  f"the ADD accuracy-threshold curve on [0, 5] mm. Ground-truth boxes. Evaluated on {eval_desc}."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, help="BOP training dataset (split 'train')")
    ap.add_argument("--config", default="lite", help="training YAML or a name in configs/train (default: lite)")
    ap.add_argument("--steps", type=int, help="training steps per variant (default: the config's)")
    ap.add_argument("--out", default="out/ablation", help="output folder (default: out/ablation)")
    ap.add_argument("--preset", default="accurate", choices=["accurate", "fast"])
    ap.add_argument("--eval-data", help="held-out BOP dataset (default: the training run's held-out images)")
    ap.add_argument("--eval-split", default="test", help="split of --eval-data (default: test)")
    ap.add_argument("--max-images", type=int, help="evaluate at most this many images")
    ap.add_argument("--device", help="cpu or cuda (default: cuda when available)")
    ap.add_argument("--quiet", action="store_true")
    args = ap.parse_args(argv)

    cfg = load_train_config(args.config)
    steps = args.steps if args.steps is not None else cfg.optim.steps
    if steps <= 0:
        ap.error(f"--steps must be positive, got {steps}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.eval_data:
        eval_data, eval_split, images = args.eval_data, args.eval_split, None
        eval_desc = f"{eval_data} (split {eval_split})"
    else:
        from surftrack.data import BopDataset

        bop = BopDataset(args.data, min_visib_fract=cfg.data.min_visib_fract)  # as train() reads it
        _, val_idx = validation_split(bop, args.data, cfg)  # the images train() holds out
        images = sorted({(bop.instances[i].scene_id, bop.instances[i].im_id) for i in val_idx})
        if not images:
            raise SystemExit(f"{args.data}: too few images to hold any out; pass --eval-data")
        eval_data, eval_split = args.data, "train"
        eval_desc = (f"the {len(images)} images of {args.data} held out of training (run.val_images="
                     f"{cfg.run.val_images}, seed {cfg.run.seed})")
        warnings.warn(f"no --eval-data: evaluating on {eval_desc}; they come from the training dataset's "
                      "generator and scenes, so this is not an independent test set", stacklevel=1)

    rows = []
    for key, name, alpha, beta in variants(cfg):
        vcfg = cfg.replace(loss={"alpha": alpha, "beta": beta})
        ckpt = out / f"{key}.pt"
        t0 = time.perf_counter()
        if _trained(ckpt, vcfg, steps):
            print(f"[{key}] {ckpt} already trained for {steps} steps; not retrained")
            summary = None
        else:
            print(f"[{key}] training {name} for {steps} steps")
            summary = train(vcfg, args.data, ckpt, steps=steps, device=args.device, progress=not args.quiet)
        train_s = time.perf_counter() - t0
        r = evaluate(ckpt, eval_data, split=eval_split, preset=args.preset, max_images=args.max_images,
                     device=args.device, images=images, progress=not args.quiet)
        paths = write_eval_outputs(r, out / f"{key}.eval.json")
        s = r["overall"]["all"]
        print(f"[{key}] RE {_num(s['re_mean'])} deg, TE {_num(s['te_mean'])} mm, ADD-10 {_pct(s['add10_surgripe'])} %, "
              f"AUC 0-5 mm {_pct(s['auc_add_0_5mm'])} % over {s['count']} instances")
        rows.append({"key": key, "name": name, "alpha": alpha, "beta": beta, "checkpoint": str(ckpt),
                     "train_seconds": train_s, "train_summary": summary, "overall": r["overall"], "parts": r["parts"],
                     "eval_files": {k: str(v) for k, v in paths.items()}, "timings": r["timings"]})

    table = ablation_table(rows, eval_desc)
    (out / "ablation.md").write_text("# Loss ablation\n\n" + f"Config {args.config}, {steps} steps per variant, "
                                     f"seed {cfg.run.seed}, data {args.data}, preset {args.preset}.\n\n" + table)
    (out / "ablation.json").write_text(json.dumps({
        "config": cfg.to_dict(), "config_name": args.config, "steps": steps, "data": args.data,
        "eval": {"data": eval_data, "split": eval_split, "images": images, "description": eval_desc,
                 "preset": args.preset, "max_images": args.max_images},
        "variants": rows}, indent=1, default=lambda o: None))
    print(table, end="")
    print(f"wrote {out / 'ablation.md'} and {out / 'ablation.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
