"""Recipe: a SynSurg6D-size dataset (60k images, six instruments) in BOP format.

    python pipelines/make_synsurg6d.py --out data/synsurg6d [--images 60000] [--workers N] [--seed 0]

Resumable: run the same command again after an interruption and it continues where it stopped. On the
2-core CPU machine this takes days (see bench_synth.py for the rate); on a many-core or GPU machine set
--workers to the core count.
"""

from __future__ import annotations

import argparse
import os

from surftrack.paths import configs_dir
from surftrack.synth.config import load_synth_config
from surftrack.synth.generate import generate_dataset


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--images", type=int, default=60000)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    cfg = load_synth_config(configs_dir() / "synth" / "synsurg6d.yaml")
    r = generate_dataset(args.out, cfg, args.images, seed=args.seed, workers=args.workers)
    print(f"{r.made} images made ({r.skipped} already there, {r.failed} failed) in {r.seconds:.0f} s; "
          f"acceptance {r.acceptance_rate:.1%}; rejections {r.rejections}")


if __name__ == "__main__":
    main()
