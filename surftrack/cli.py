"""The ``surftrack`` command line."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from surftrack import __version__


class CLIError(Exception):
    """A user-facing error: printed as one line, exit code 2."""


def _cmd_demo(args: argparse.Namespace) -> int:
    from surftrack.demo import run_demo

    s = run_demo(Path(args.out), instrument=args.instrument, seed=args.seed)
    print(f"surftrack demo: {s['instrument']} over procedural tissue, rendered in {s['render_ms']} ms "
          f"({s['gl']['GL_RENDERER']})")
    for pname, p in s["parts"].items():
        print(f"  {pname:10s} t = {p['t_mm']} mm  visible {p['visible_px']} / {p['silhouette_px']} px")
    print(f"wrote {s['rgb']}")
    print(f"wrote {s['modalities']}")
    return 0


def _cmd_instruments(args: argparse.Namespace) -> int:
    from surftrack.instruments import export_bop_models, list_instruments, load_instrument

    names = args.names or list_instruments()
    insts = [load_instrument(n) for n in names]
    for inst in insts:
        print(f"{inst.name} ({', '.join(inst.aliases) or 'no alias'}): {inst.description}")
        for pname, part in inst.parts.items():
            print(f"  {pname:12s} {len(part.mesh.faces):6d} faces  diameter {part.diameter_max_pairwise:6.2f} mm "
                  f"(bbox diagonal {part.diameter_bbox_diagonal:6.2f})  watertight={part.mesh.is_watertight}")
    if args.export:
        ids = export_bop_models(insts, args.export)
        print(f"wrote {len(ids)} models to {args.export}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="surftrack", description=__doc__)
    p.add_argument("--version", action="version", version=f"surftrack {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    d = sub.add_parser("demo", help="run the end-to-end demo on built-in data")
    d.add_argument("--out", default="out/demo", help="output folder (default: out/demo)")
    d.add_argument("--instrument", default="lnd", help="instrument name or alias (default: lnd)")
    d.add_argument("--seed", type=int, default=0)
    d.set_defaults(func=_cmd_demo)
    i = sub.add_parser("instruments", help="list instruments (parts, sizes) and export BOP models")
    i.add_argument("names", nargs="*", help="instrument names, aliases or YAML files (default: all built-in)")
    i.add_argument("--export", metavar="DIR", help="write a BOP models/ folder with models_info.json")
    i.set_defaults(func=_cmd_instruments)
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point: user errors become one line on stderr and exit code 2."""
    from surftrack.instruments import InstrumentError
    from surftrack.render import RenderError

    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except (CLIError, InstrumentError, RenderError, FileNotFoundError, PermissionError) as e:
        print(f"surftrack: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("surftrack: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
