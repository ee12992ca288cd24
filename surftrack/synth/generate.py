"""SynSurg6D-style dataset generation: sample, reject, render and write BOP images in worker processes.

Every random choice comes from generators seeded by ``(seed, scene, image)`` (and ``(seed, scene,
group)`` for the tissue patch shared by a group of images), so a dataset depends only on the seed and
the configuration: not on the worker count, nor on whether the run was interrupted and resumed.
"""

from __future__ import annotations

import json
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from surftrack import __version__
from surftrack.atomic import write_atomic
from surftrack.configio import build_dataclass
from surftrack.geometry import PinholeCamera
from surftrack.instruments import BUILTIN, Instrument, InstrumentRegistry, assign_obj_ids, export_bop_models
from surftrack.render import Renderer, add_instrument, gl_context, worker_context
from surftrack.synth import bop_writer
from surftrack.synth.checks import PartCollision, TissueCollision, in_view
from surftrack.synth.config import ConfigError, SynthConfig
from surftrack.synth.effects import CameraEffects, apply_effects
from surftrack.synth.sampling import (
    InstrumentSample,
    jitter_pose,
    sample_camera,
    sample_instrument,
    sample_lights,
    sample_tissue_pose,
)
from surftrack.synth.tissue import TissueSource

MAX_INSTRUMENTS = 2
#: Placements of a second tool per scene attempt. Placements are cheap (no rendering); giving up the first
#: tool for each failure of the second made two-tool scenes take 2-3x the attempts of one-tool scenes.
LATER_TOOL_TRIES = 4
REJECTIONS = ("geometry", "out_of_view", "tissue_collision", "part_collision", "tissue_coverage", "low_visibility")


@dataclass
class ImageStats:
    scene_id: int
    im_id: int
    accepted: bool
    attempts: int
    rejections: dict[str, int] = field(default_factory=dict)
    seconds: float = 0.0


class SceneGenerator:
    """Per-process state: instruments, renderer (one GL context per process), collision checkers."""

    def __init__(self, cfg: SynthConfig, seed: int, out_dir: Path, instruments: InstrumentRegistry = BUILTIN):
        self.cfg, self.seed, self.out = cfg, seed, Path(out_dir)
        self.instruments = {i.name: i for i in load_instruments(cfg, instruments)}
        self.names = list(self.instruments)
        self.obj_ids = {(inst.name, p): oid for oid, (inst, p) in
                        assign_obj_ids(list(self.instruments.values())).items()}
        self.renderer = Renderer(cfg.image.width, cfg.image.height)
        self.handles = {}
        for slot in range(MAX_INSTRUMENTS):
            for name, inst in self.instruments.items():
                self.handles[(slot, name)] = add_instrument(self.renderer, inst, like=self.handles.get((0, name)))
        self.tissue_checks = {n: TissueCollision(i, seed=seed) for n, i in self.instruments.items()}
        self.part_check = PartCollision(list(self.instruments.values()), slots=MAX_INSTRUMENTS)
        self.effects = CameraEffects.from_dict(cfg.effects)
        self.pad = max(cfg.image.width, cfg.image.height) // 2
        self.tissue_source = TissueSource(cfg.tissue)
        self._tissue_key: tuple | None = None
        self._tissue_id: int | None = None
        self._tissue = None

    # ------------------------------------------------------------------ tissue per group
    def _group_tissue(self, scene_id: int, group: int):
        """The group's tissue (per ``tissue.source``) and base pose, from a generator seeded by (seed, scene,
        group); a mesh source yields the same Tissue every time, which stays uploaded."""
        key = (scene_id, group)
        if key != self._tissue_key:
            rng = np.random.default_rng([self.seed, scene_id, group, 7])
            tissue = self.tissue_source(rng)
            pose = sample_tissue_pose(self.cfg.tissue, rng)
            if tissue is not self._tissue or self._tissue_id is None:
                if self._tissue_id is not None:
                    self.renderer.remove(self._tissue_id)
                self._tissue_id = tissue.add_to(self.renderer)
            self._tissue, self._tissue_pose, self._tissue_key = tissue, pose, key
        return self._tissue, self._tissue_pose

    # ------------------------------------------------------------------ one image
    def make_image(self, scene_id: int, im_id: int) -> ImageStats:
        """Sample until a configuration passes every test (or attempts run out), then write it."""
        t0 = time.perf_counter()
        cfg = self.cfg
        group = im_id // cfg.tissue.images_per_tissue
        tissue, base_pose = self._group_tissue(scene_id, group)
        rng = np.random.default_rng([self.seed, scene_id, im_id])
        rejections: Counter = Counter()
        # What is in the image is decided once, so that rejections cannot bias the mix of instruments.
        count = 2 if rng.random() < cfg.two_instruments_prob else 1
        names = [self.names[int(rng.integers(len(self.names)))] for _ in range(count)]
        for attempt in range(1, cfg.rejection.max_attempts + 1):
            camera = sample_camera(cfg.image, cfg.camera, rng)
            tissue_pose = jitter_pose(base_pose, rng, cfg.tissue.jitter_mm, cfg.tissue.jitter_deg)
            reason, samples = self._sample_instruments(rng, names, camera, tissue, tissue_pose, rejections)
            if reason:
                rejections[reason] += 1
                continue
            lights, ambient = sample_lights(cfg.lighting, rng, samples)
            poses = {self._tissue_id: tissue_pose}
            for slot, s in enumerate(samples):
                poses.update(self.handles[(slot, s.instrument.name)].poses(s.poses))
            res = self.renderer.render(camera, poses, lights, ambient=ambient, amodal_pad=self.pad)
            reason = self._check_render(res, samples)
            if reason:
                rejections[reason] += 1
                continue
            self._write(scene_id, im_id, camera, samples, res, rng, attempt, rejections)
            return ImageStats(scene_id, im_id, True, attempt, dict(rejections), time.perf_counter() - t0)
        return ImageStats(scene_id, im_id, False, cfg.rejection.max_attempts, dict(rejections), time.perf_counter() - t0)

    def _sample_instruments(self, rng, names, camera, tissue, tissue_pose,
                            rejections: Counter) -> tuple[str | None, list[InstrumentSample]]:
        """Place the tools one after the other; a later tool that fails its own tests is placed again (up to
        :data:`LATER_TOOL_TRIES` times, each failure counted in ``rejections``) before the attempt is given
        up, so that a good first placement is not thrown away for the second tool's sake."""
        samples: list[InstrumentSample] = []
        for k, name in enumerate(names):
            tries = 1 if k == 0 else LATER_TOOL_TRIES
            for t in range(tries):
                reason, s = self._place(name, rng, camera, tissue, tissue_pose, samples)
                if reason is None:
                    break
                if t < tries - 1:
                    rejections[reason] += 1
            if reason is not None:
                return reason, []
            samples.append(s)
        return None, samples

    def _place(self, name, rng, camera, tissue, tissue_pose,
               placed: list[InstrumentSample]) -> tuple[str | None, InstrumentSample | None]:
        """One placement of tool ``name`` (aimed near the first of ``placed``, the tools already there) and
        its tests: (None, sample) or (rejection reason, None)."""
        cfg = self.cfg
        near = placed[0].target if placed else None
        s = sample_instrument(self.instruments[name], cfg.pose, rng, camera, tissue, tissue_pose, near=near)
        if s is None:
            return "geometry", None
        if not in_view(s, camera, cfg.rejection.margin_px, cfg.pose.min_depth_mm):
            return "out_of_view", None
        if self.tissue_checks[name].collides(s.poses, tissue, tissue_pose):
            return "tissue_collision", None
        if self.part_check.collisions(placed + [s]):  # its own parts, and the tools placed before it
            return "part_collision", None
        return None, s

    def _check_render(self, res, samples: list[InstrumentSample]) -> str | None:
        if (res.instance > 0).mean() < self.cfg.tissue.min_coverage:
            return "tissue_coverage"
        thr = self.cfg.rejection.min_visib_fract
        for slot, s in enumerate(samples):
            h = self.handles[(slot, s.instrument.name)]
            vis = {p: int((res.instance == i).sum()) for p, i in h.parts.items()}
            full = {p: int(res.amodal[i].sum()) for p, i in h.parts.items()}
            if sum(full.values()) == 0 or sum(vis.values()) < thr * sum(full.values()):
                return "low_visibility"
            if "wrist" in full and vis["wrist"] < thr * max(full["wrist"], 1):
                return "low_visibility"
        return None

    def _write(self, scene_id, im_id, camera: PinholeCamera, samples, res, rng, attempts, rejections) -> None:
        cfg = self.cfg
        gt, info, masks, masks_visib = [], [], [], []
        for slot, s in enumerate(samples):
            h = self.handles[(slot, s.instrument.name)]
            joints = {k: float(np.degrees(v)) for k, v in s.q.as_dict().items()}
            for pname, iid in h.parts.items():
                T = s.poses[pname]
                gt.append({
                    "obj_id": self.obj_ids[(s.instrument.name, pname)],
                    "cam_R_m2c": T[:3, :3].ravel().tolist(), "cam_t_m2c": T[:3, 3].tolist(),
                    "instrument": s.instrument.name, "instrument_index": slot, "part": pname,
                    "joints_deg": joints, "trocar_mm": s.trocar.tolist(), "tip_to_tissue_mm": s.tip_to_tissue,
                })
                full_pad = res.amodal[iid]
                full = res.amodal_in_image(iid)
                visib = res.instance == iid
                n_all, n_vis = int(full_pad.sum()), int(visib.sum())
                info.append({
                    "bbox_obj": bop_writer.bbox_xywh(full_pad, offset=self.pad),
                    "bbox_visib": bop_writer.bbox_xywh(visib),
                    "px_count_all": n_all, "px_count_valid": int((full & (res.depth > 0)).sum()),
                    "px_count_visib": n_vis, "visib_fract": n_vis / n_all if n_all else 0.0,
                })
                masks.append(full)
                masks_visib.append(visib)
        rgb = apply_effects(res.rgb, self.effects, rng, principal_point=(camera.cx, camera.cy))
        record = {
            "scene_camera": {"cam_K": camera.K.ravel().tolist(), "depth_scale": cfg.output.depth_scale},
            "scene_gt": gt, "scene_gt_info": info,
            "stats": {"attempts": attempts, "rejections": dict(rejections)},
        }
        bop_writer.write_image(self.out, cfg.output.split, scene_id, im_id, rgb, res.depth, res.normal, masks,
                               masks_visib, record, cfg.output.rgb_format, cfg.output.jpg_quality,
                               cfg.output.depth_scale)


def load_instruments(cfg: SynthConfig, registry: InstrumentRegistry = BUILTIN) -> list[Instrument]:
    """The configured instruments (names or aliases known to ``registry``, or YAML paths), each once."""
    insts = [registry.load(n) for n in cfg.instruments]
    names = [i.name for i in insts]
    if len(set(names)) != len(names):
        raise ConfigError(f"instruments {list(cfg.instruments)} name the same instrument twice ({names})")
    return insts


def _check_resume(out: Path, cfg: SynthConfig, seed: int, registry: InstrumentRegistry = BUILTIN,
                  instruments: list[Instrument] | None = None) -> None:
    """Refuse to add images made with another seed or configuration, or other instrument geometry, to an
    existing dataset. ``instruments``: ``cfg``'s, when the caller has loaded them already."""
    card = out / "dataset_card.json"
    if not card.is_file():
        return
    try:
        old = json.loads(card.read_text())
        made = old.get("config")
    except (ValueError, AttributeError):
        raise ConfigError(f"{card}: not a dataset card (unreadable JSON); remove it to make the dataset "
                          f"again, or write to a new folder") from None
    if isinstance(made, dict) and made:
        # Keys added to the config since the dataset was made take their defaults. Rule for new keys:
        # the default must reproduce the behaviour from before the key existed.
        try:
            made = build_dataclass(SynthConfig, dict(made), str(card), ConfigError).to_dict()
        except (TypeError, ValueError):  # ConfigError included
            pass
    if old.get("seed") != seed or _comparable(made, registry) != _comparable(cfg.to_dict(), registry):
        raise ConfigError(f"{out}: the dataset was made with another seed or configuration "
                          f"(see {card}); resume with the same ones, or write to a new folder")
    # the config names an instrument by its file; an edited mesh (or its units) makes other images. The
    # hash is exact, so a part whose hash moved is compared, within tolerance, with the dataset's own model
    # file. Cards from before the hash skip the check (the card written at the end then gets today's).
    objects = old.get("objects") if isinstance(old.get("objects"), dict) else {}
    now = {str(oid): inst.parts[p] for oid, (inst, p) in
           assign_obj_ids(instruments or load_instruments(cfg, registry)).items()}

    def moved(oid: str, rec: dict) -> bool:
        part = now.get(oid)
        if part is None or part.mesh_hash == rec["mesh_sha256"]:
            return part is None
        ply = out / "models" / f"obj_{int(oid):06d}.ply"
        try:
            mesh = trimesh.load(ply, force="mesh", process=False)
        except Exception:  # noqa: BLE001 - no readable model to compare with: the hash decides
            return True
        return not part.same_geometry(mesh.vertices, mesh.faces)

    changed = sorted(f"{o.get('instrument')}/{o.get('part')}" for oid, o in objects.items()
                     if isinstance(o, dict) and o.get("mesh_sha256") and moved(oid, o))
    if changed:
        raise ConfigError(f"{out}: the geometry of {', '.join(changed)} changed since the dataset was made "
                          f"(see {card}); resume with the instruments as they were, or write to a new folder")


def _comparable(config, registry: InstrumentRegistry) -> object:
    """A config as JSON data, instruments known to ``registry`` as their description files (``lnd`` and
    ``large_needle_driver`` name the same file and make the same images)."""
    data = json.loads(json.dumps(config))
    if isinstance(data, dict) and isinstance(data.get("instruments"), list):
        known = registry.files()
        data["instruments"] = [str(known[n]) if isinstance(n, str) and n in known else n
                               for n in data["instruments"]]
    return data


# ---------------------------------------------------------------------- worker pool plumbing
_GEN: SceneGenerator | None = None


def _init_worker(cfg: SynthConfig, seed: int, out_dir: str, registry: InstrumentRegistry) -> None:
    global _GEN
    _GEN = SceneGenerator(cfg, seed, Path(out_dir), registry)


def _run_task(task: tuple[int, list[int]]) -> list[ImageStats]:
    scene_id, im_ids = task
    return [_GEN.make_image(scene_id, i) for i in im_ids]


def plan_tasks(cfg: SynthConfig, out: Path, n_images: int) -> list[tuple[int, list[int]]]:
    """Groups of images (sharing a tissue patch) still to make, as (scene id, image ids)."""
    per_scene, per_group = cfg.output.images_per_scene, cfg.tissue.images_per_tissue
    tasks, done_cache = [], {}
    for g in range(0, n_images, per_group):
        scene_id, first = g // per_scene, g % per_scene
        if scene_id not in done_cache:
            done_cache[scene_id] = bop_writer.finished_images(out, cfg.output.split, scene_id)
        ids = [i for i in range(first, min(first + per_group, n_images - scene_id * per_scene))
               if i not in done_cache[scene_id]]
        if ids:
            tasks.append((scene_id, ids))
    return tasks


@dataclass
class GenerationReport:
    requested: int
    made: int
    skipped: int
    failed: int
    attempts: int
    rejections: dict[str, int]
    seconds: float

    @property
    def acceptance_rate(self) -> float:
        return self.made / self.attempts if self.attempts else 0.0


def generate_dataset(out_dir: str | Path, cfg: SynthConfig, n_images: int, seed: int = 0, workers: int = 1,
                     progress: bool = True, instruments: InstrumentRegistry = BUILTIN) -> GenerationReport:
    """Generate (or resume) a BOP dataset of ``n_images`` images in ``out_dir``; see the module docstring.
    ``instruments``: where the config's instrument names are looked up.

    Finalises every touched scene and writes ``models/``, ``dataset_card.json`` and a contact sheet, also
    when interrupted.
    """
    from tqdm import tqdm

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    insts = load_instruments(cfg, instruments)
    _check_resume(out, cfg, seed, instruments, insts)
    gl_context()  # fail here, with a clear error, rather than in workers that a pool would respawn forever
    try:
        TissueSource(cfg.tissue).check()
    except ValueError as e:
        raise ConfigError(f"tissue: {e}") from None
    export_bop_models(insts, out / "models")
    tasks = plan_tasks(cfg, out, n_images)
    todo = sum(len(ids) for _, ids in tasks)
    stats: list[ImageStats] = []
    t0 = time.perf_counter()
    bar = tqdm(total=todo, desc="synth", unit="img", disable=not progress)
    try:
        if workers <= 1:
            _init_worker(cfg, seed, str(out), instruments)
            for task in tasks:
                res = _run_task(task)
                stats += res
                bar.update(len(res))
        elif tasks:
            with worker_context((__name__,)).Pool(workers, initializer=_init_worker,
                                                  initargs=(cfg, seed, str(out), instruments)) as pool:
                for res in pool.imap_unordered(_run_task, tasks):
                    stats += res
                    bar.update(len(res))
    finally:
        bar.close()
        scenes = sorted({st.scene_id for st in stats}
                        | set(range((n_images + cfg.output.images_per_scene - 1) // cfg.output.images_per_scene)))
        for s in scenes:
            if bop_writer.scene_dir(out, cfg.output.split, s).is_dir():
                bop_writer.finalize_scene(out, cfg.output.split, s)
        report = _report(stats, n_images, todo, time.perf_counter() - t0)
        write_dataset_card(out, cfg, seed, insts, report)
        from surftrack.synth.contact_sheet import write_contact_sheet

        write_contact_sheet(out, cfg.output.split)
    return report


_CAUSES = {
    "part_collision": "the instrument's parts collide with each other in most poses; run `surftrack instruments "
                      "YOUR.yaml --check` (joint frames, limits, contacts)",
    "out_of_view": "the tool's tips leave the image in most poses; check the mesh units and the tip keypoints "
                   "(`surftrack instruments YOUR.yaml --check`)",
    "tissue_collision": "the instrument runs into the tissue; check the mesh units and sizes, or pose.tip_to_tissue_mm",
    "geometry": "no trocar and aim fit the pose ranges; widen pose.shaft_to_axis_deg or pose.tip_to_tissue_mm",
    "tissue_coverage": "the tissue does not cover the image; check the tissue settings (distance_mm, extent_mm)",
    "low_visibility": "the instrument is hidden or too small to see; check the mesh units (a metre mesh read as mm "
                      "is 1000 times too small) and rejection.min_visib_fract",
}


def likely_cause(rejections: dict[str, int]) -> str:
    """What most often stopped scenes (the largest rejection count) and what to check, in words."""
    if not any(rejections.values()):
        return "no attempt was made"
    top = max(rejections, key=lambda k: rejections[k])
    return f"{top} ({_CAUSES.get(top, 'see the dataset card')})"


def _report(stats: list[ImageStats], requested: int, todo: int, seconds: float) -> GenerationReport:
    rej: Counter = Counter()
    for s in stats:
        rej.update(s.rejections)
    return GenerationReport(requested=requested, made=sum(s.accepted for s in stats), skipped=requested - todo,
                            failed=sum(not s.accepted for s in stats), attempts=sum(s.attempts for s in stats),
                            rejections={k: rej.get(k, 0) for k in REJECTIONS}, seconds=seconds)


def write_dataset_card(out: Path, cfg: SynthConfig, seed: int, instruments: list[Instrument],
                       report: GenerationReport) -> None:
    """``dataset_card.json``: generation config, counts, acceptance statistics and object ids."""
    card_path = out / "dataset_card.json"
    card = json.loads(card_path.read_text()) if card_path.is_file() else {"runs": []}
    split = cfg.output.split
    n_images = sum(len(json.loads((d / "scene_gt.json").read_text()))
                   for d in sorted((out / split).glob("[0-9]" * 6)) if (d / "scene_gt.json").is_file())
    card["runs"].append({"made": report.made, "skipped_existing": report.skipped, "failed": report.failed,
                         "attempts": report.attempts, "acceptance_rate": round(report.acceptance_rate, 4),
                         "rejections": report.rejections, "seconds": round(report.seconds, 1)})
    all_runs = card["runs"]
    card.update({
        "format": "BOP (bop_toolkit layout); extra scene_gt keys: instrument, instrument_index, part, joints_deg "
                  "(roll from the zero of config.pose.roll_zero), trocar_mm, tip_to_tissue_mm; "
                  "normal/<im>.png = uint8 RGB (n + 1) / 2 * 255, camera frame",
        "generator": f"surftrack {__version__}", "seed": seed, "split": split, "config": cfg.to_dict(),
        "images": n_images,
        "objects": {str(oid): {"instrument": inst.name, "part": p, "mesh_sha256": inst.parts[p].mesh_hash}
                    for oid, (inst, p) in assign_obj_ids(instruments).items()},
        "acceptance": {
            "attempts": sum(r["attempts"] for r in all_runs),
            "accepted": sum(r["made"] for r in all_runs),
            "rejections": {k: sum(r["rejections"].get(k, 0) for r in all_runs) for k in REJECTIONS},
        },
    })
    a = card["acceptance"]
    a["acceptance_rate"] = round(a["accepted"] / a["attempts"], 4) if a["attempts"] else 0.0
    write_atomic(card_path, json.dumps(card, indent=2))
