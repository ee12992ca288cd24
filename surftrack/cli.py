"""The ``surftrack`` command line.

The main command tracks a video: ``surftrack VIDEO --boxes DET.json --camera CAMERA.json`` (the same as
``surftrack track ...``). Other subcommands: batch, demo, instruments, synth, synth-clip, join, train, eval,
analyze, recover.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from surftrack import __version__

if TYPE_CHECKING:
    from surftrack.instruments import InstrumentRegistry
    from surftrack.track import TrackConfig


#: surftrack.pose.preset.PRESETS's names, spelt out so that building the parser does not import torch.
PRESET_NAMES = ("accurate", "fast", "thorough")


#: Exit code of a run whose video stopped decoding part of the way through: what decoded is tracked and
#: every output is finished (2: bad input, nothing tracked; 128 + N: stopped by signal N).
EXIT_PARTIAL = 4


class CLIError(Exception):
    """A user-facing error: printed as one line, exit code 2."""


class Stopped(KeyboardInterrupt):
    """A run stopped by SIGTERM or SIGHUP. A KeyboardInterrupt, so that it unwinds exactly as Ctrl-C
    does and every output is finalised on the way out; the exit code is 128 + ``signum``."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


#: The signals that stop a run cleanly: what ``timeout``, ``kill``, docker, systemd and SLURM send
#: (SIGTERM) and what a closed terminal or SSH session sends (SIGHUP). SIGINT is Python's own.
STOP_SIGNALS = tuple(getattr(signal, n) for n in ("SIGTERM", "SIGHUP") if hasattr(signal, n))


_received: list[int] = []  # stop signals received while a command ran


@contextlib.contextmanager
def _stop_on_signals() -> Iterator[None]:
    """Turn SIGTERM and SIGHUP into :class:`Stopped` while the command runs. After the first one, further
    stop signals (and Ctrl-C) are ignored, so that finalising the outputs cannot itself be cut short."""

    def stop(signum, frame):
        for s in (*STOP_SIGNALS, signal.SIGINT):
            signal.signal(s, signal.SIG_IGN)
        _received.append(signum)  # libraries that catch and re-raise KeyboardInterrupt (Ray) lose Stopped
        raise Stopped(signum)

    _received.clear()
    if threading.current_thread() is not threading.main_thread():  # only the main thread takes signals
        yield
        return
    previous = {s: signal.signal(s, stop) for s in STOP_SIGNALS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def _seed(text: str) -> int:
    """argparse type for seeds: a non-negative integer."""
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"seeds must be >= 0, got {value}")
    return value


def _registry(args: argparse.Namespace) -> InstrumentRegistry:
    """The instruments a command knows: ``$SURFTRACK_INSTRUMENTS`` (read here, once) with the command's
    ``--instrument`` YAML files ahead, each checked so that a bad one fails the command in one line."""
    from surftrack.instruments import InstrumentRegistry

    registry = InstrumentRegistry.from_env(os.environ).ahead(getattr(args, "instrument_files", None) or [])
    registry.files()  # the whole search path is read now: a bad entry fails before any work
    return registry


def _model(args: argparse.Namespace) -> str | None:
    """``--model``, else ``$SURFTRACK_MODEL``, else None (the bundled model)."""
    return args.model or os.environ.get("SURFTRACK_MODEL") or None


def _cmd_demo(args: argparse.Namespace) -> int:
    from surftrack.demo import run_demo

    s = run_demo(Path(args.out), seconds=args.seconds, fps=args.fps, seed=args.seed, model=_model(args),
                 progress=not args.quiet)
    c, t = s["clip"], s["tracking"]
    print(f"surftrack demo: a {c['seconds']:g} s synthetic clip at {c['fps']:g} fps (made in {c['made_in_s']} s; "
          f"the needle driver is out of view in {c['frames_out_of_view']} frames and occluded in "
          f"{c['frames_occluded']})")
    for note in t["notes"]:
        print(f"note: {note}")
    print(f"tracked {t['frames']} frames at {t['fps']:.1f} frames/s ({t['track_ms_per_frame']:.0f} ms/frame in the "
          f"tracker); accuracy against the ground truth:")
    print((Path(args.out) / "summary.md").read_text().split("\n\n", 1)[1], end="")
    print(f"wrote {', '.join(s['outputs'].values())}, {Path(args.out) / 'summary.json'} in {s['total_s']} s")
    return 0


def _cmd_instruments(args: argparse.Namespace) -> int:
    from surftrack.instruments import export_bop_models
    from surftrack.instruments.check import size_warnings

    registry = _registry(args)
    names = args.names or registry.names()
    insts = [registry.load(n) for n in names]
    if args.export:
        ids = export_bop_models(insts, args.export)
        print(f"wrote {len(ids)} models to {args.export}")
    if args.figure:
        from PIL import Image

        from surftrack.render.frames_figure import joint_frames_figure

        if len(insts) != 1:
            raise CLIError(f"--figure draws one instrument; name one (got {len(insts)})")
        if Path(args.figure).suffix.lower() not in (".png", ".jpg", ".jpeg"):
            raise CLIError(f"--figure {args.figure}: give a .png or .jpg file")
        Image.fromarray(joint_frames_figure(insts[0])).save(args.figure)
        print(f"wrote {args.figure}")
        if not args.check:
            return 0
    if args.check:
        from surftrack.instruments.check import check_instrument

        warnings = 0
        for inst in insts:
            report = check_instrument(inst)
            print("\n".join(report.lines))
            for w in report.warnings:
                print(f"  warning: {w}")
            warnings += len(report.warnings)
        return 1 if warnings else 0
    for inst in insts:
        print(f"{inst.name} ({', '.join(inst.aliases) or 'no alias'}): {inst.description}")
        for pname, part in inst.parts.items():
            print(f"  {pname:12s} {len(part.mesh.faces):6d} faces  diameter {part.diameter_max_pairwise:6.2f} mm "
                  f"(bbox diagonal {part.diameter_bbox_diagonal:6.2f})  watertight={part.mesh.is_watertight}")
        for w in size_warnings(inst):
            print(f"  warning: {w}")
    return 0


def _cmd_synth(args: argparse.Namespace) -> int:
    from surftrack.synth.config import load_synth_config
    from surftrack.synth.generate import generate_dataset, likely_cause

    overrides = {}
    if args.instruments:
        names = [n.strip() for n in args.instruments.split(",") if n.strip()]
        # YAML paths travel to the worker processes as absolute paths; names and aliases as they are.
        overrides["instruments"] = [str(Path(n).resolve()) if n.endswith((".yaml", ".yml")) else n for n in names]

    cfg = load_synth_config(args.config, overrides)
    if args.images <= 0:
        raise CLIError(f"--images must be positive, got {args.images}")
    out = Path(args.out)
    r = generate_dataset(out, cfg, args.images, seed=args.seed, workers=args.workers, progress=not args.quiet,
                         instruments=_registry(args))
    rejections = ", ".join(f"{k} {v}" for k, v in r.rejections.items())
    if r.made == 0 and r.skipped == 0:
        raise CLIError(f"{out}: no image accepted in {r.attempts} attempts (rejections: {rejections}); "
                       f"likely cause: {likely_cause(r.rejections)}")
    print(f"surftrack synth: {r.made} images made, {r.skipped} already there, {r.failed} failed "
          f"in {r.seconds:.1f} s ({r.made / max(r.seconds, 1e-9):.2f} images/s, {args.workers} worker(s))")
    print(f"  acceptance {r.acceptance_rate:.1%} of {r.attempts} attempts; rejections: {rejections}")
    if r.failed:
        print(f"  warning: {r.failed} images found no valid scene in {cfg.rejection.max_attempts} attempts; "
              f"likely cause: {likely_cause(r.rejections)}")
    written = [out / cfg.output.split, out / "models", out / "dataset_card.json", out / "contact_sheet.png"]
    print(f"wrote {', '.join(str(w) for w in written if w.exists())}")
    return 0


def _cmd_synth_clip(args: argparse.Namespace) -> int:
    from surftrack.synth.clip import ClipConfig, make_clip

    overrides = {"seconds": args.seconds, "fps": args.fps}
    if args.roll_deg is not None:
        overrides["roll_deg"] = tuple(args.roll_deg)
    if args.roll_swing_deg is not None:
        overrides["roll_swing_deg"] = tuple(args.roll_swing_deg)
    if args.second is not None:
        overrides["second_instrument"] = None if args.second.lower() == "none" else args.second
    if args.seconds <= 0 or args.fps <= 0:
        raise CLIError(f"--seconds and --fps must be positive, got {args.seconds} and {args.fps}")
    try:
        cfg = ClipConfig.from_dict(overrides)
    except ValueError as e:
        raise CLIError(str(e)) from None
    s = make_clip(Path(args.out), args.instrument, cfg, seed=args.seed, progress=not args.quiet,
                  instruments=_registry(args))
    print(f"surftrack synth-clip: {s['frames']} frames in {s['seconds']:.1f} s; main tool out of view in "
          f"{s['main_out_of_view_frames']} frames, occluded by the second tool in {s['occluded_frames']}")
    print(f"wrote {s['video']}, {s['camera']}, {s['gt']}, {s['det']}")
    return 0


def _cmd_train(args: argparse.Namespace) -> int:
    from surftrack.model.config import load_train_config
    from surftrack.model.train import train

    cfg = load_train_config(args.config)
    if args.steps is not None and args.steps <= 0:
        raise CLIError(f"--steps must be positive, got {args.steps}")
    if args.init and args.resume:
        raise CLIError("--init and --resume exclude each other: --resume continues --out, --init starts afresh")
    if args.init and args.imagenet:
        raise CLIError("--init and --imagenet exclude each other: both set the starting weights")
    if args.workers is not None:
        if args.workers < 0:
            raise CLIError(f"--workers must be 0 or more, got {args.workers}")
        cfg = cfg.replace(run={"workers": args.workers})
    s = train(cfg, args.data, args.out, steps=args.steps, resume=args.resume, device=args.device,
              progress=not args.quiet, init=args.init, imagenet=args.imagenet)
    if s["rank"] != 0:  # under torchrun, one summary
        return 0
    val = s["val"]
    extra = (f"; held-out: RE median {val['re_median']:.1f} deg, TE median {val['te_median']:.1f} mm, "
             f"ADD-10 {100 * val['add10']:.1f} %") if "re_median" in val else ""
    print(f"surftrack train: {s['steps']} steps at {s['images_per_s']:.1f} images/s{extra}")
    print(f"wrote {s['checkpoint']} and {s['metrics']}")
    return 0


def _checked_views(views: int, flag: str = "--views") -> int:
    """``--views`` (or ``flag``), or a CLIError when it is out of range."""
    if not 1 <= views <= 9:
        raise CLIError(f"{flag} must be between 1 and 9, got {views}")
    return views


def _checked_anchor_views(args: argparse.Namespace, fit: bool, without_fit: str) -> int:
    """``--anchor-views``, or a CLIError when it is out of range or there is no instrument fit (``fit``
    False; ``without_fit`` says why) whose anchor would get the views."""
    if not fit:
        raise CLIError(f"--anchor-views gives the instrument fit's anchor part more crop views: {without_fit}")
    return _checked_views(args.anchor_views, "--anchor-views")


def _eval_preset(args: argparse.Namespace):
    """``eval``'s estimator preset: --preset with --views and --anchor-views."""
    from surftrack.pose.kinematic import KinematicConfig
    from surftrack.pose.preset import get_preset

    preset = get_preset(args.preset)
    if args.views is not None:
        preset = preset.replace(views=_checked_views(args.views))
    if args.anchor_views is not None:
        n = _checked_anchor_views(args, args.kinematic, "it needs --kinematic")
        preset = preset.replace(part_views=((KinematicConfig().anchor, n),))
    return preset


def _cmd_eval(args: argparse.Namespace) -> int:
    from surftrack.pose.evaluate import evaluate, evaluate_seeds, markdown_table, seed_table, write_eval_outputs

    if args.suite is not None:
        if args.by_cause:
            raise CLIError("--by-cause bins one set (--data), not the suite")
        return _eval_suite(args)
    if args.data is None:
        raise CLIError("eval needs --data DATASET (or --suite)")
    args.seed = args.seed or [0]
    if args.max_images is not None and args.max_images <= 0:
        raise CLIError(f"--max-images must be positive, got {args.max_images}")
    if not 0.0 < args.occlusion_threshold <= 1.0:
        raise CLIError(f"--occlusion-threshold must be in (0, 1], got {args.occlusion_threshold}")
    if any(s < 0 for s in args.seed) or len(set(args.seed)) != len(args.seed):
        raise CLIError(f"--seed takes distinct numbers >= 0, got {' '.join(map(str, args.seed))}")
    out = Path(args.out)
    preset = _eval_preset(args)
    kwargs = dict(split=args.split, max_images=args.max_images, occlusion_threshold=args.occlusion_threshold,
                  device=args.device, progress=not args.quiet, kinematic=args.kinematic,
                  instruments=_registry(args))
    if len(args.seed) == 1:
        results = [evaluate(args.model, args.data, preset=preset.replace(seed=args.seed[0]), **kwargs)]
    else:  # one network forward for all seeds; one set of outputs each, <stem>.seedN.*, and a table
        results = evaluate_seeds(args.model, args.data, args.seed, preset=preset, **kwargs)
    for r in results:
        one = out if len(results) == 1 else out.with_name(f"{out.stem}.seed{r['seed']}{out.suffix}")
        paths = write_eval_outputs(r, one)
        print(f"surftrack eval: {r['n_instances']} instances in {r['n_images']} images of {args.data} "
              f"({args.split}), preset {r['preset']} (seed {r['seed']}"
              f"{'' if r['views'] == 1 else ', %d crop views per box' % r['views']}"
              f"{''.join(f', {n} crop views on {p}' for p, n in r.get('part_views', {}).items())})"
              f"{', instrument-consistent poses' if r['kinematic_instruments'] else ''}, "
              f"{r['timings']['per_image_s_mean'] * 1e3:.0f} ms/image on {r['device']}")
        print(markdown_table(r), end="")
        for w in r["warnings"] if r is results[0] else ():  # the same for every seed
            print(f"warning: {w}")
        print("wrote " + ", ".join(str(p) for p in paths.values()))
    if len(results) > 1:
        table = seed_table(results)
        out.with_suffix(".seeds.md").write_text(table)  # the per-seed outputs made its folder
        print(f"\nADD-10 per solver seed:\n{table}wrote {out.with_suffix('.seeds.md')}")
    if args.by_cause:
        from surftrack.pose.causes import cause_tables, instance_conditions

        # every seed's instances pooled: each bin's rate is then the mean over the seeds
        conditions = [c for r in results for c in instance_conditions(r, args.data, args.split)]
        tables = cause_tables(conditions)
        out.with_suffix(".causes.md").write_text(tables + "\n")
        print(f"\nADD-10 (%) by condition, instances in brackets{', seeds pooled' if len(results) > 1 else ''}:\n"
              f"{tables}\nwrote {out.with_suffix('.causes.md')}")
    return 0


def _eval_suite(args: argparse.Namespace) -> int:
    """``eval --suite``: make the suite's sets and clips where missing, evaluate each, print and write the
    tables (sets, then clips)."""
    from surftrack.pose.suite import evaluate_suite, load_suite, load_suite_clips, make_suite, suite_table

    seeds = args.seed or [0, 1, 2]
    if any(s < 0 for s in seeds) or len(set(seeds)) != len(seeds):
        raise CLIError(f"--seed takes distinct numbers >= 0, got {' '.join(map(str, seeds))}")
    sets = load_suite(None if args.suite == "default" else args.suite)
    clips = load_suite_clips(None if args.suite == "default" else args.suite)  # checked before any work
    registry = _registry(args)
    preset = _eval_preset(args)  # checked before any work
    folders = make_suite(sets, args.suite_dir, workers=2, progress=not args.quiet, instruments=registry)
    table = evaluate_suite(args.model, sets, folders, seeds, preset=preset, device=args.device,
                           kinematic=args.kinematic, instruments=registry, progress=not args.quiet)
    text = suite_table(table, sets)
    if clips:
        text += "\n" + _suite_clips_table(args, clips, seeds, registry)
    out = Path(args.out).with_suffix(".suite.md")
    out.parent.mkdir(parents=True, exist_ok=True)
    views = (f", {preset.views} crop views" if preset.views > 1 else "") + \
        "".join(f", {n} crop views on {p}" for p, n in preset.part_views)
    out.write_text(f"Model {args.model}, preset {preset.name}{views}{', kinematic fit' if args.kinematic else ''}, "
                   f"solver seeds {' '.join(map(str, seeds))}.\n\n{text}")
    print(text, end="")
    print(f"wrote {out}")
    return 0


def _suite_clips_table(args: argparse.Namespace, clips, seeds: list[int], registry) -> str:
    """Per-frame estimation on the suite's tracking clips (made in --suite-dir on first use), each solver
    seed in ``seeds``, with --preset, --views, --anchor-views and --kinematic as for the sets: the clips'
    table."""
    from surftrack.annotate import evaluate_clips
    from surftrack.pose.suite import clip_table, make_suite_clips

    folders = make_suite_clips(clips, args.suite_dir, instruments=registry)
    views = _checked_views(args.views) if args.views is not None else 0
    table = evaluate_clips(args.model, [c.name for c in clips], folders, seeds, preset=args.preset, views=views,
                           kinematic=bool(args.kinematic), device=args.device, instruments=registry,
                           progress=not args.quiet, anchor_views=args.anchor_views or 0)
    return clip_table(table, clips)


def _track_config(args: argparse.Namespace) -> TrackConfig:
    """The tracking config of ``track`` and ``batch``: ``--config`` with the command-line overrides."""
    from surftrack.annotate import check_span
    from surftrack.track import load_track_config

    cfg = load_track_config(args.config)
    check_span(getattr(args, "start", None), getattr(args, "end", None))  # before a folder meets it on every video
    if args.keyframe_every is not None:
        if args.keyframe_every < 1:
            raise CLIError(f"--keyframe-every must be >= 1, got {args.keyframe_every}")
        cfg = cfg.replace(keyframe_every=args.keyframe_every, keyframe_max_s=0.0)  # frames, as asked
    if args.preset is not None:
        cfg = cfg.replace(preset=args.preset)
    if args.causal:
        cfg = cfg.replace(smooth_lag_s=0.0)
    if args.views is not None:
        cfg = cfg.replace(views=_checked_views(args.views))
    if args.anchor_views is not None:
        cfg = cfg.replace(anchor_views=_checked_anchor_views(args, cfg.kinematic,
                                                             "the config turns the fit off (kinematic: false)"))
    if args.device == "cuda":
        import torch

        if not torch.cuda.is_available():
            raise CLIError("--device cuda: no CUDA device is available (use --device cpu)")
    return cfg


def _cmd_track(args: argparse.Namespace) -> int:
    from surftrack.annotate import AnnotateOptions, annotate_video

    cfg = _track_config(args)
    registry = _registry(args)
    if Path(args.video).is_dir():
        # a folder is a batch: the same machinery as `surftrack batch` (a local Ray, a bad video skipped)
        if args.overlay or args.export_tum or args.joints_csv:
            raise CLIError("--overlay, --export-tum and --joints-csv take one video; with a folder, run the "
                           "videos one by one")
        return _run_batch(args, AnnotateOptions(model=_model(args), config=cfg, device=args.device, start=args.start,
                                                end=args.end, mcap_images=args.images, progress=False,
                                                joints=not args.no_joints, instruments=registry),
                          args.video, args.out or args.video, address=None, workers=None, force=True)
    opts = AnnotateOptions(model=_model(args), camera=args.camera, out=args.out, config=cfg, device=args.device,
                           start=args.start, end=args.end, overlay=args.overlay, export_tum=args.export_tum,
                           mcap_images=args.images, progress=not args.quiet, joints=not args.no_joints,
                           joints_csv=args.joints_csv, instruments=registry)
    s = annotate_video(args.video, args.boxes, opts)
    for note in s["notes"]:
        print(f"note: {note}")
    print(f"surftrack: {s['video']}: {s['frames']} frames in {s['seconds']:.1f} s ({s['fps']:.1f} frames/s)")
    for name, p in s["parts"].items():
        fr = ", ".join(f"{k} {v}" for k, v in sorted(p["frames"].items()))
        print(f"  {name:34s} {fr}; mean confidence {p['mean_confidence']:.2f}")
    print("wrote " + ", ".join(s["outputs"].values()))
    if s["partial"]:
        p = s["partial"]
        print(f"surftrack: partial: {args.video}: {p['frames_decoded']} of {p['frames_in_video'] or '?'} frames, "
              f"decoding stopped at t = {p['stopped_at_s']:.3f} s ({p['error']})", file=sys.stderr)
        return EXIT_PARTIAL
    return 0


#: Exit code of a batch in which some video failed, stopped decoding part of the way, or did not run.
EXIT_BATCH_INCOMPLETE = 3


def _cmd_batch(args: argparse.Namespace) -> int:
    from surftrack.annotate import AnnotateOptions

    if args.workers is not None and args.workers < 1:
        raise CLIError(f"--workers must be >= 1, got {args.workers}")
    opts = AnnotateOptions(model=_model(args), config=_track_config(args), device=args.device,
                           progress=False, instruments=_registry(args))
    return _run_batch(args, opts, args.videos, args.out, address=args.address, workers=args.workers,
                      force=args.force)


def _run_batch(args: argparse.Namespace, opts, videos, out, *, address, workers, force: bool) -> int:
    """``surftrack batch`` and the main command on a folder: run the jobs, print a line per video and the
    total; exit 0 when every video finished, :data:`EXIT_BATCH_INCOMPLETE` otherwise."""
    from surftrack.batch import FINISHED, batch_jobs, run_batch

    jobs = batch_jobs(videos, args.boxes, args.camera, out)
    rows = run_batch(jobs, out, opts, address=address, workers=workers, force=force, progress=not args.quiet)
    for r in rows:
        line = f"  {r['status']:8s} {r['video']}: {r['frames']} frames in {r['seconds']:.1f} s"
        print(line + (f" ({r['error']})" if r["error"] else ""))
    bad = [r for r in rows if r["status"] not in FINISHED]
    print(f"surftrack batch: {len(rows) - len(bad)} of {len(rows)} videos finished; wrote "
          f"{Path(out) / 'manifest.jsonl'}")
    return EXIT_BATCH_INCOMPLETE if bad else 0


def _cmd_join(args: argparse.Namespace) -> int:
    from surftrack.data.join import join_datasets

    n = join_datasets(args.out, args.sources)
    print(f"{args.out}: {n} scenes of {len(args.sources)} datasets (links, no copies); train on it with "
          f"`surftrack train --data {args.out}`")
    return 0


def _cmd_analyze(args: argparse.Namespace) -> int:
    from surftrack.io.analyze import analyze_mcap, format_analysis, plot_analysis

    png = Path(args.png) if args.png else Path(args.mcap).with_suffix(".analysis.png")
    if args.png:  # the default sits beside the MCAP, whose own problems analyze_mcap names
        if png.suffix.lower() not in (".png", ".jpg", ".jpeg", ".pdf", ".svg"):
            raise CLIError(f"--png {png}: give a .png, .jpg, .jpeg, .pdf or .svg file")
        if not png.parent.is_dir():
            raise CLIError(f"--png {png}: no folder {png.parent}")
    try:
        s = analyze_mcap(args.mcap, min_confidence=args.min_confidence)
    except ValueError as e:
        raise CLIError(str(e)) from None
    print(format_analysis(s).rstrip("\n"))
    plot_analysis(s, png)
    print(f"wrote {png}")
    return 0


def _cmd_recover(args: argparse.Namespace) -> int:
    from surftrack.io.recover import recover_mcap

    try:
        r = recover_mcap(args.mcap, args.out)
    except ValueError as e:
        raise CLIError(str(e)) from None
    span = (f", {r.start_ns / 1e9:.3f} s to {r.end_ns / 1e9:.3f} s" if r.messages else "")
    print(f"surftrack recover: {r.messages} messages on {r.channels} channels{span}, from the first "
          f"{r.bytes_read} bytes of {args.mcap}" + (f" ({r.stopped})" if r.stopped else " (the whole file)"))
    print(f"wrote {args.out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="surftrack", description=__doc__)
    p.add_argument("--version", action="version", version=f"surftrack {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    d = sub.add_parser("demo", help="make a synthetic clip, track it with the bundled model, score the tracks")
    d.add_argument("--out", default="out/demo", help="output folder (default: out/demo)")
    d.add_argument("--seconds", type=float, default=6.0, help="clip length (default: 6)")
    d.add_argument("--fps", type=float, default=15.0, help="clip frame rate (default: 15)")
    d.add_argument("--seed", type=_seed, default=0, help="the clip's random seed (default: 0)")
    d.add_argument("--model", help="checkpoint (default: the bundled model)")
    d.add_argument("--quiet", action="store_true", help="no progress bars")
    d.set_defaults(func=_cmd_demo)
    i = sub.add_parser("instruments", help="list instruments (parts, sizes) and export BOP models")
    i.add_argument("names", nargs="*", help="instrument names, aliases or YAML files (default: all known, "
                                           "built-in and from $SURFTRACK_INSTRUMENTS)")
    i.add_argument("--export", metavar="DIR", help="write a BOP models/ folder with models_info.json")
    i.add_argument("--check", action="store_true", help="check each part and pair of parts (sizes, contacts at rest, "
                                                       "collisions over the joint range); exit 1 on a warning")
    i.add_argument("--figure", metavar="PNG", help="draw the joint frames of one instrument (rest and bent)")
    i.set_defaults(func=_cmd_instruments)
    sy = sub.add_parser("synth", help="generate a SynSurg6D-style BOP dataset (resumable)")
    sy.add_argument("--out", required=True, help="dataset folder (created; an existing one is resumed)")
    sy.add_argument("--instruments", help="comma-separated names, aliases or instrument YAML files (default: from the config)")
    sy.add_argument("--images", type=int, default=100, help="total number of images (default: 100)")
    sy.add_argument("--seed", type=_seed, default=0, help="the dataset's random seed (default: 0); images are "
                    "a function of it and their index")
    sy.add_argument("--workers", type=int, default=1, help="worker processes, each with its own GL context")
    sy.add_argument("--config", help="synthesis YAML, or 'paper' for the paper's ranges (default: configs/synth/"
                                     "default.yaml, the instrument's whole reach)")
    sy.add_argument("--quiet", action="store_true", help="no progress bar")
    sy.set_defaults(func=_cmd_synth)
    sc = sub.add_parser("synth-clip", help="make a synthetic tracking clip: video, camera, ground truth, detections")
    sc.add_argument("--out", required=True, help="output folder")
    sc.add_argument("--instrument", default="lnd", help="the main instrument (default: lnd)")
    sc.add_argument("--second", help="the crossing instrument (default: cadiere_forceps; 'none' for a single tool)")
    sc.add_argument("--seconds", type=float, default=10.0, help="clip length (default: 10)")
    sc.add_argument("--fps", type=float, default=30.0, help="frame rate (default: 30)")
    sc.add_argument("--seed", type=_seed, default=0, help="the clip's random seed (default: 0)")
    sc.add_argument("--roll-deg", type=float, nargs=2, metavar=("LO", "HI"),
                    help="the main tool's roll at the start, degrees about the jaws opening towards the camera "
                         "(default: -30 30; -180 180 for anywhere)")
    sc.add_argument("--roll-swing-deg", type=float, nargs=2, metavar=("LO", "HI"),
                    help="how far its roll then wanders, an amplitude drawn from LO..HI degrees (default: 20 45)")
    sc.add_argument("--quiet", action="store_true", help="no progress bar")
    sc.set_defaults(func=_cmd_synth_clip)
    jo = sub.add_parser("join", help="join BOP datasets of the same instruments into one training folder (links)")
    jo.add_argument("sources", nargs="+", help="dataset folders (e.g. made by `surftrack synth` with different configs)")
    jo.add_argument("--out", required=True, help="the joined folder (created)")
    jo.set_defaults(func=_cmd_join)
    tr = sub.add_parser("train", help="train a SurfSurg6D model on a BOP dataset")
    tr.add_argument("--config", default="lite", help="training YAML or a name in configs/train (default: lite)")
    tr.add_argument("--data", required=True, help="BOP dataset folder (e.g. made by `surftrack synth`)")
    tr.add_argument("--out", default="model.pt", help="checkpoint file (default: model.pt)")
    tr.add_argument("--steps", type=int, help="override the number of training steps")
    tr.add_argument("--resume", action="store_true", help="continue from --out if it exists")
    tr.add_argument("--init", metavar="CKPT", help="start from this checkpoint's weights (fresh optimiser, step 0)")
    tr.add_argument("--imagenet", metavar="PTH", help="initialise the encoder of a new run from a torchvision "
                                                      "resnet18 state-dict file (e.g. resnet18-f37072fd.pth)")
    tr.add_argument("--device", help="cpu or cuda (default: cuda when available)")
    tr.add_argument("--workers", type=int, help="data loader processes, each rendering targets with its own GL "
                                                "context (default: the config's run.workers; on a GPU, about "
                                                "one per core: the loader, not the network, limits the step)")
    tr.add_argument("--quiet", action="store_true", help="no progress bar")
    tr.set_defaults(func=_cmd_train)
    ev = sub.add_parser("eval", help="evaluate a checkpoint on a BOP split (RE, TE, ADD-10, AUC; paper table, BOP CSV)")
    ev.add_argument("--model", required=True, help="checkpoint file (from `surftrack train`)")
    ev.add_argument("--data", help="BOP dataset folder")
    ev.add_argument("--suite", nargs="?", const="default", metavar="YAML",
                    help="evaluate on the fixed held-out suite instead (default configs/eval/suite.yaml): its sets and "
                         "tracking clips are made in --suite-dir on first use; one table per part and set, one "
                         "per part and clip (per-frame estimation), mean of solver seeds 0-2")
    ev.add_argument("--suite-dir", default="data/suite", help="where the suite's sets live (default: data/suite)")
    ev.add_argument("--split", default="test", help="split folder to evaluate (default: test)")
    ev.add_argument("--by-cause", action="store_true",
                    help="also bin ADD-10 by each instance's depth, visible box size, visible fraction and (sets "
                         "made by `surftrack synth`) joint angles, to see where the estimator fails; writes "
                         "<out stem>.causes.md")
    ev.add_argument("--out", default="eval.json", help="results JSON; .md, .bop.csv and .png go next to it "
                    "(default: eval.json)")
    ev.add_argument("--preset", default="accurate", choices=PRESET_NAMES, help="estimator preset (default: "
                    "accurate; thorough: accurate on five crop views per box, about 4x its time)")
    ev.add_argument("--views", type=int, metavar="N", help="crop views per box, 1-9 (default: the preset's)")
    ev.add_argument("--anchor-views", type=int, metavar="N", help="with --kinematic: crop views per box of the "
                    "instrument fit's anchor part (the wrist), 1-9; its depth places the whole instrument "
                    "(default: as --views)")
    ev.add_argument("--max-images", type=int, help="evaluate only the first N images")
    ev.add_argument("--seed", type=int, nargs="+", metavar="N",
                    help="random seed(s) of the pose solver (surface samples, hypotheses; default 0). On ~100 "
                         "images the figures move by a few points with it: give several (--seed 0 1 2) to get "
                         "one evaluation each (<out stem>.seedN.*; one network forward for all) and a table of "
                         "ADD-10 per seed with the mean")
    ev.add_argument("--occlusion-threshold", type=float, default=0.9,
                    help="instances with visib_fract below it count as occluded (default: 0.9)")
    ev.add_argument("--kinematic", action="store_true",
                    help="evaluate instrument-consistent poses: each instrument's articulated configuration "
                         "fitted to its parts' estimates (surftrack.pose.kinematic), as the tracker outputs them")
    ev.add_argument("--instrument", action="append", metavar="YAML", dest="instrument_files",
                    help="an instrument description the built-in ones lack, for --kinematic (repeatable)")
    ev.add_argument("--device", help="cpu or cuda (default: cuda when available)")
    ev.add_argument("--quiet", action="store_true", help="no progress bar")
    ev.set_defaults(func=_cmd_eval)

    tk = sub.add_parser("track", help="track the instrument parts of a video (the main command; "
                                      "`surftrack VIDEO ...` means `surftrack track VIDEO ...`)")
    tk.add_argument("video", help="video file, or a folder of videos (run as `surftrack batch`, on a local Ray)")
    tk.add_argument("--boxes", required=True, help="det.json or COCO detections (a folder for a folder of videos)")
    tk.add_argument("--camera", help="camera.json (K, width, height, dist) or a BOP scene_camera.json "
                                     "(default: <video stem>.camera.json or camera.json beside the video)")
    tk.add_argument("--model", help="checkpoint (default: the bundled Large Needle Driver model)")
    tk.add_argument("-o", "--out", help="MCAP file (default: the video's name with .mcap; a folder for a folder)")
    tk.add_argument("--keyframe-every", type=int, help="frames between estimator runs on tracked parts at most "
                                                       "(default: 10, and 0.34 s of video)")
    tk.add_argument("--causal", action="store_true", help="write each frame's pose from the frames up to it "
                    "only (online use); by default poses are smoothed with the second after them too")
    tk.add_argument("--preset", choices=PRESET_NAMES, help="estimator preset (default from the config)")
    tk.add_argument("--views", type=int, metavar="N", help="crop views per box on keyframes, 1-9 (default: the "
                    "preset's; 5: about 4x the keyframe time, better poses)")
    tk.add_argument("--anchor-views", type=int, metavar="N", help="crop views per box of the instrument fit's "
                    "anchor part (the wrist) on keyframes, 1-9 (default from the config)")
    tk.add_argument("--config", help="tracking YAML or a name in configs/track: default (outlines between keyframes), "
                                     "every_frame (the estimator on every frame), articulated (one state per "
                                     "instrument, its parts views of it)")
    tk.add_argument("--device", choices=["cpu", "cuda"], help="default: cuda when available")
    tk.add_argument("--start", type=float, help="start time of the stretch to track (s from the video's start)")
    tk.add_argument("--end", type=float, help="end time of the stretch to track (s)")
    tk.add_argument("--overlay", metavar="OUT.mp4", help="also write a video with axes, outlines and status")
    tk.add_argument("--export-tum", metavar="DIR", help="also write one TUM trajectory per part (metres)")
    tk.add_argument("--images", action="store_true", help="store JPEG frames and annotations in the MCAP")
    tk.add_argument("--joints-csv", metavar="CSV",
                    help="also write the joint angles per frame (degrees) as CSV (with their standard "
                         "deviations under --config articulated)")
    tk.add_argument("--no-joints", action="store_true", help="skip the per-frame joint-angle fit")
    tk.add_argument("--instrument", action="append", metavar="YAML", dest="instrument_files",
                    help="your instrument's description (the YAML its model was trained from), for joint angles "
                         "and the instrument-consistent fit; repeatable")
    tk.add_argument("--quiet", action="store_true", help="no progress bar")
    tk.set_defaults(func=_cmd_track)

    an = sub.add_parser("analyze", help="per-part trajectories, speeds, path length and jaw opening of a "
                                        "tracking MCAP (table and PNG)")
    an.add_argument("mcap", help="MCAP written by `surftrack VIDEO ...`")
    an.add_argument("--png", help="plot file (default: <mcap stem>.analysis.png)")
    an.add_argument("--min-confidence", type=float, default=0.0, metavar="C",
                    help="count motion only over frames whose confidence (the probability of being within "
                         "ADD-10) is >= C, 0-1 (default 0: every posed frame)")
    an.set_defaults(func=_cmd_analyze)

    ba = sub.add_parser("batch", help="track a folder of videos (or a CSV manifest) on Ray: one task per video, "
                                      "a manifest of results; exit 3 when some video did not finish")
    ba.add_argument("videos", help="a folder of videos, or a CSV with columns video, boxes[, camera]")
    ba.add_argument("-o", "--out", required=True, help="output folder: <stem>.mcap per video and manifest.jsonl")
    ba.add_argument("--boxes", help="folder of <video stem>.json (or .det.json) detections (with a folder of videos)")
    ba.add_argument("--camera", help="camera.json for every video, or a folder of <video stem>.json "
                                     "(default: camera.json beside each video)")
    ba.add_argument("--address", help="Ray cluster to join ('auto' or ray://host:port; default: a local Ray "
                                      "on this machine)")
    ba.add_argument("--workers", type=int, help="videos tracked at once on a local Ray (default: the cores)")
    ba.add_argument("--force", action="store_true", help="redo videos an earlier run of the batch finished")
    ba.add_argument("--model", help="checkpoint (default: the bundled model)")
    ba.add_argument("--config", help="tracking YAML or a name in configs/track: default, every_frame, articulated")
    ba.add_argument("--keyframe-every", type=int, help="frames between estimator runs on tracked parts")
    ba.add_argument("--causal", action="store_true", help="no smoothing with later frames (see track --causal)")
    ba.add_argument("--preset", choices=PRESET_NAMES, help="estimator preset (default from the config)")
    ba.add_argument("--views", type=int, metavar="N", help="crop views per box on keyframes, 1-9")
    ba.add_argument("--anchor-views", type=int, metavar="N", help="crop views of the fit's anchor part, 1-9")
    ba.add_argument("--device", choices=["cpu", "cuda"], help="default: cuda on workers that have a GPU")
    ba.add_argument("--instrument", action="append", metavar="YAML", dest="instrument_files",
                    help="your instrument's description, for joint angles and the fit; repeatable")
    ba.add_argument("--quiet", action="store_true", help="no progress bar")
    ba.set_defaults(func=_cmd_batch)

    rc = sub.add_parser("recover", help="rewrite an unfinished MCAP (a run killed by SIGKILL or a crash) into a "
                                        "valid file with every readable message")
    rc.add_argument("mcap", help="the unfinished MCAP file")
    rc.add_argument("-o", "--out", required=True, help="the recovered MCAP file (a new file)")
    rc.set_defaults(func=_cmd_recover)
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point: user errors become one line on stderr and exit code 2."""
    from surftrack.data import DatasetError
    from surftrack.instruments import InstrumentError
    from surftrack.render import RenderError
    from surftrack.pose.suite import SuiteError
    from surftrack.synth.clip import ClipError
    from surftrack.synth.config import ConfigError

    from surftrack.model.checkpoint import CheckpointError
    from surftrack.model.config import TrainConfigError

    from surftrack.track import InputError, TrackConfigError

    errors = (CLIError, InstrumentError, RenderError, ConfigError, ClipError, SuiteError, TrainConfigError, CheckpointError,
              DatasetError, InputError, TrackConfigError, OSError)

    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    if argv and not argv[0].startswith("-") and argv[0] not in commands:
        argv.insert(0, "track")  # `surftrack VIDEO --boxes ...` is the main command
    args = parser.parse_args(argv)
    sigint = signal.getsignal(signal.SIGINT)  # a stop signal sets it to SIG_IGN while outputs are finalised
    try:
        with _stop_on_signals():
            return int(args.func(args))
    except BrokenPipeError:  # `surftrack ... | head`: the reader left; say nothing more
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except errors as e:
        lines = [line.strip() for line in str(e).splitlines() if line.strip()]
        print(f"surftrack: error: {'; '.join(lines)}", file=sys.stderr)  # one line, whatever raised it
        return 2
    except KeyboardInterrupt as e:  # Ctrl-C, or SIGTERM / SIGHUP as Stopped
        signum = getattr(e, "signum", _received[-1] if _received else signal.SIGINT)
        done, frames = getattr(e, "outputs", None), getattr(e, "frames_done", None)
        print(f"surftrack: stopped by {signal.Signals(signum).name}"
              + (f" after {frames} frames" if frames is not None else "")
              + (f"; finalised {', '.join(map(str, done))}" if done else ""), file=sys.stderr)
        return 128 + signum
    finally:
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, sigint)


if __name__ == "__main__":
    sys.exit(main())
