"""Synthesis throughput: accepted BOP images per second at 640x512 with every modality written.

    python pipelines/bench_synth.py [--images 60] [--workers 1 2] [--instruments lnd]

Runs the real generator (sampling, rejection, rendering, camera effects, BOP files) into a temporary
folder and prints accepted images/s in total and per worker process, with the acceptance statistics.
"""

from __future__ import annotations

import argparse
import os
import tempfile

from surftrack.instruments import load_instrument
from surftrack.render import gl_info
from surftrack.synth.config import load_synth_config
from surftrack.synth.generate import generate_dataset


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", type=int, default=60)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--instruments", default="lnd")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    names = [load_instrument(n).name for n in args.instruments.split(",")]
    cfg = load_synth_config(overrides={"instruments": names})
    print(f"renderer: {gl_info()['GL_RENDERER']} | {os.cpu_count()} CPU cores | "
          f"{cfg.image.width}x{cfg.image.height}, instruments {names}")
    for w in args.workers:
        with tempfile.TemporaryDirectory() as tmp:
            r = generate_dataset(tmp, cfg, args.images, seed=args.seed, workers=w, progress=False)
        rate = r.made / r.seconds
        print(f"{w} worker(s): {r.made} accepted in {r.seconds:.1f} s = {rate:.2f} images/s "
              f"({rate / w:.2f} per worker) | acceptance {r.acceptance_rate:.1%} of {r.attempts} attempts | "
              f"rejections {r.rejections}")


if __name__ == "__main__":
    main()
