"""Synthetic endoscope video clips with per-frame ground truth and simulated detections.

:func:`make_clip` writes into one folder::

    video.mp4     H.264, frame i shown at i / fps
    camera.json   {"K": 3x3, "width", "height", "dist": []}   (PinholeCamera.to_dict() + empty dist)
    gt.json       per-frame BOP scene_gt-like records of every part of every instrument (see docs/formats.md)
    det.json      boxes of a simulated noisy detector (surftrack.synth.detections)

The camera, the tissue patch and the lights are fixed for the whole clip (so the renderer caches the
tissue as a static layer and a frame costs only the instruments). The instruments move smoothly under
the remote-centre-of-motion (RCM) constraint: each has a fixed trocar; per frame the shaft direction is
the starting one turned by small angles about the trocar, the pitch point lies on that direction at the
current insertion depth, and the base pose is recomputed with :func:`rcm_base_pose`, so the shaft axis
passes exactly through the trocar on every frame. Roll, wrist pitch and yaw follow sums of a few random
low-frequency sinusoids in a randomly time-warped clock (so speed varies); the jaw opening swings
periodically between 0 and 60 deg. Every frame is guarded against instrument-tissue (and tool-tool)
collision by retracting along the shaft; the guard retraction is smoothed over time (a max filter then a
Gaussian, which never lowers it) so the tool backs off gently instead of jumping.

Scripted events (``ClipConfig``): with ``leave_view`` the main tool retracts along its shaft until its
wrist and jaws are outside the image for about a second, then comes back; with ``second_instrument`` a
second tool enters through a trocar on the other side, crosses in front of the main tool (nearer the
camera, occluding it) and may leave again. The two events happen in different halves of the clip. A
plan that misses an event (no frame out of view, no occlusion, an unresolvable collision) is discarded
and re-sampled; everything is drawn from generators seeded by ``seed``, so a clip is a function of the
seed and the configuration.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter1d, maximum_filter1d

from surftrack.geometry import PinholeCamera, box_from_bop, so3_exp, transform_points
from surftrack.instruments import BUILTIN, Instrument, InstrumentRegistry, JointState, assign_obj_ids, rcm_base_pose
from surftrack.io.video import VideoWriter  # a leaf module: the one import of a later stage (see surftrack.io)
from surftrack.render import Renderer, add_instrument
from surftrack.atomic import write_atomic
from surftrack.synth.bop_writer import bbox_xywh
from surftrack.synth.checks import PartCollision, TissueCollision, in_view
from surftrack.synth.config import LightingCfg, PoseCfg, TissueCfg
from surftrack.synth.detections import DetectionNoise, detections_document, simulate_detections, write_detections
from surftrack.synth.effects import CameraEffects, apply_effects
from surftrack.synth.sampling import InstrumentSample, sample_instrument, sample_lights, sample_tissue_pose, uniform
from surftrack.synth.tissue import Tissue, procedural_tissue

GT_FORMAT = "surftrack-clip-gt"
GT_VERSION = 1
# Camera effects of a clip unless ClipConfig.effects overrides them: mild sensor noise only. Per-frame
# random blur, vignetting or gamma would flicker from frame to frame.
MILD_EFFECTS = {"noise_std": (0.5, 2.0), "shot_noise": (0.0, 0.3), "blur_prob": 0.0, "motion_blur_prob": 0.0,
                "vignetting": (0.0, 0.0), "gamma_jitter": (1.0, 1.0), "jpeg_quality": None}
MIN_INSERTION_MM = 15.0      # the pitch point never comes nearer the trocar than this
MAX_ATTEMPTS = 60            # motion plans tried before giving up
VIEW_MARGIN_PX = 6.0         # "out of view": every surface sample this far outside the image
TISSUE_CLEARANCE_MM = 0.5
MIN_TISSUE_COVERAGE = 0.995


class ClipError(ValueError):
    """A clip that cannot be made with these settings; the message says why and what to check."""


@dataclass(frozen=True)
class ClipConfig:
    """What a clip looks like, apart from the instrument and the seed (see the module docstring).

    ``detection_noise`` holds :class:`DetectionNoise` fields (missing ones keep their defaults);
    ``effects`` holds :class:`CameraEffects` fields on top of :data:`MILD_EFFECTS`.
    """

    seconds: float = 10.0
    fps: float = 30.0
    width: int = 640
    height: int = 512
    hfov_deg: float = 70.0
    second_instrument: str | None = "cadiere_forceps"  # crosses in front of the main tool; None = single tool
    leave_view: bool = True          # the main tool's tip leaves the view once and re-enters
    detection_noise: dict = field(default_factory=dict)
    effects: dict = field(default_factory=dict)
    crf: int = 18
    # The main tool's roll at the start (deg about the `view` reference: the jaws open towards the camera;
    # [-180, 180] starts it anywhere), and how far it then wanders (amplitude drawn from this range).
    roll_deg: tuple[float, float] = (-30.0, 30.0)
    roll_swing_deg: tuple[float, float] = (20.0, 45.0)

    def __post_init__(self) -> None:
        if not (self.seconds > 0 and math.isfinite(self.seconds)):
            raise ValueError(f"seconds must be a positive number, got {self.seconds}")
        if not (self.fps > 0 and math.isfinite(self.fps)):
            raise ValueError(f"fps must be a positive number, got {self.fps}")
        if self.n_frames < 2:
            raise ValueError(f"a clip needs at least 2 frames, got seconds * fps = {self.seconds * self.fps:g}")
        for name in ("width", "height"):
            v = getattr(self, name)
            if not isinstance(v, int) or v <= 0 or v % 2:
                raise ValueError(f"{name} must be a positive even integer (H.264 4:2:0), got {v!r}")
        if not 1.0 < self.hfov_deg < 170.0:
            raise ValueError(f"hfov_deg must be in (1, 170), got {self.hfov_deg}")
        if not 0 <= int(self.crf) <= 51:
            raise ValueError(f"crf must be in [0, 51], got {self.crf}")
        if not isinstance(self.detection_noise, dict) or not isinstance(self.effects, dict):
            raise ValueError("detection_noise and effects must be mappings")
        for name in ("roll_deg", "roll_swing_deg"):
            v = getattr(self, name)
            if (not isinstance(v, (tuple, list)) or len(v) != 2 or not all(math.isfinite(float(x)) for x in v)
                    or v[0] > v[1] or abs(float(v[0])) > 360 or abs(float(v[1])) > 360):
                raise ValueError(f"{name} must be [lo, hi] degrees with lo <= hi, within +-360, got {v!r}")
            object.__setattr__(self, name, (float(v[0]), float(v[1])))
        if self.roll_swing_deg[0] < 0:
            raise ValueError(f"roll_swing_deg must not be negative, got {list(self.roll_swing_deg)}")
        self.noise()
        self.camera_effects()

    @property
    def n_frames(self) -> int:
        return int(round(self.seconds * self.fps))

    def noise(self) -> DetectionNoise:
        return DetectionNoise.from_dict(self.detection_noise)

    def camera_effects(self) -> CameraEffects:
        return CameraEffects.from_dict({**MILD_EFFECTS, **self.effects})

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict | None) -> ClipConfig:
        """A config from a mapping (e.g. YAML); unknown keys raise ``ValueError``, missing ones keep defaults."""
        d = dict(d or {})
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown clip config key(s) {unknown}; known keys are {sorted(known)}")
        return cls(**d)


# ---------------------------------------------------------------------------------------------- signals
def _smootherstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


def _plateau(t: np.ndarray, start: float, end: float | None, ramp: float) -> np.ndarray:
    """0 before ``start``, a smooth ramp to 1 over ``ramp`` s, 1 until ``end - ramp``, back to 0 at ``end``
    (``end`` None: stays 1)."""
    up = _smootherstep((t - start) / ramp)
    return up if end is None else up * (1.0 - _smootherstep((t - (end - ramp)) / ramp))


def _warped_clock(rng: np.random.Generator, t: np.ndarray) -> np.ndarray:
    """A monotone random time warp ``t + a sin(...)``: motions driven by it speed up and slow down."""
    f = rng.uniform(0.05, 0.25)
    phi = rng.uniform(0.0, 2 * np.pi)
    a = rng.uniform(0.2, 0.7) / (2 * np.pi * f)  # derivative 1 + a 2 pi f cos(.) stays > 0
    return t + a * (np.sin(2 * np.pi * f * t + phi) - np.sin(phi))


def _wiggle(rng: np.random.Generator, t: np.ndarray, freq: tuple[float, float], terms: int = 3) -> np.ndarray:
    """Smooth random signal in [-1, 1] that is 0 at t = 0: half the change of a normalised sum of
    ``terms`` sinusoids (random frequencies in ``freq`` Hz, phases, weights) on a warped clock."""
    tw = _warped_clock(rng, t)
    f = rng.uniform(freq[0], freq[1], terms)
    ph = rng.uniform(0.0, 2 * np.pi, terms)
    amp = rng.uniform(0.3, 1.0, terms)
    amp /= amp.sum()
    s = (amp[:, None] * np.sin(2 * np.pi * f[:, None] * tw[None] + ph[:, None])).sum(0)
    return 0.5 * (s - s[0])


def _joint_track(rng: np.random.Generator, inst: Instrument, t: np.ndarray, q0: JointState,
                 roll_swing_deg: tuple[float, float] = (20.0, 45.0)) -> list[JointState]:
    """Roll, wrist pitch / yaw wandering around ``q0`` (the roll by an amplitude drawn from
    ``roll_swing_deg``); jaw opening cycling 0..60 deg at a varying pace."""
    roll = q0.roll + np.radians(uniform(rng, roll_swing_deg)) * _wiggle(rng, t, (0.05, 0.3))
    lim = np.radians(70.0)
    pitch = np.clip(q0.pitch + np.radians(uniform(rng, (15.0, 35.0))) * _wiggle(rng, t, (0.1, 0.5)), -lim, lim)
    yaw = np.clip(q0.yaw + np.radians(uniform(rng, (15.0, 35.0))) * _wiggle(rng, t, (0.1, 0.5)), -lim, lim)
    phase = 2 * np.pi * rng.uniform(0.25, 0.6) * _warped_clock(rng, t) + rng.uniform(0.0, 2 * np.pi)
    opening = np.radians(30.0) * (1.0 - np.cos(phase))
    return [inst.limits.clip(JointState(float(r), float(p), float(y), float(o)))
            for r, p, y, o in zip(roll, pitch, yaw, opening)]


def _swing(rng: np.random.Generator, t: np.ndarray, d0: np.ndarray, lateral_mm: float, lever_mm: float) -> np.ndarray:
    """Unit shaft directions (n, 3): ``d0`` turned about two axes normal to it by small smooth angles that
    move a point ``lever_mm`` along the shaft by up to ``lateral_mm`` sideways (rotation about the trocar)."""
    e1 = np.cross(d0, [1.0, 0.0, 0.0] if abs(d0[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d0, e1)
    a = lateral_mm / lever_mm * _wiggle(rng, t, (0.05, 0.4))
    b = lateral_mm / lever_mm * _wiggle(rng, t, (0.05, 0.4))
    R = so3_exp(a[:, None] * e1 + b[:, None] * e2)
    return R @ d0


# ---------------------------------------------------------------------------------------------- motion
@dataclass
class _Track:
    """One instrument's motion: fixed trocar, per-frame shaft direction, insertion depth and joints."""

    instrument: Instrument
    trocar: np.ndarray
    dirs: np.ndarray          # (n, 3) unit, trocar -> pitch point
    depth: np.ndarray         # (n,) trocar -> pitch point distance (mm) before the guard retraction
    q: list[JointState]
    retract: np.ndarray       # (n,) collision-guard retraction (mm)

    def insertion(self, i: int, extra: float = 0.0) -> float:
        return max(float(self.depth[i] - self.retract[i] - extra), MIN_INSERTION_MM)

    def base(self, i: int, extra: float = 0.0) -> np.ndarray:
        return rcm_base_pose(self.trocar, self.trocar + self.insertion(i, extra) * self.dirs[i])

    def poses(self, i: int, extra: float = 0.0) -> dict[str, np.ndarray]:
        return self.instrument.forward(self.base(i, extra), self.q[i])

    def sample(self, i: int) -> InstrumentSample:
        base = self.base(i)
        return InstrumentSample(self.instrument, self.trocar, base[:3, 3], 0.0, self.q[i], base,
                                self.instrument.forward(base, self.q[i]))


class _ViewTest:
    """Whether an instrument's wrist and jaws (every part but the root, the shaft) are out of the image:
    dense surface samples and vertices all project ``margin`` px outside it, or lie behind the near plane."""

    def __init__(self, inst: Instrument, camera: PinholeCamera, margin: float = VIEW_MARGIN_PX, seed: int = 0):
        root = inst.part_names[0]
        self.camera, self.margin = camera, margin
        self.points = {p: np.concatenate([part.sample_surface(3000, seed=seed)[0], part.mesh.vertices])
                       for p, part in inst.parts.items() if p != root}

    def out(self, poses: dict[str, np.ndarray]) -> bool:
        cam, m = self.camera, self.margin
        for p, pts in self.points.items():
            x = transform_points(poses[p], pts)
            x = x[x[:, 2] > 1.0]
            if not len(x):
                continue
            uv = cam.project(x)
            inside = ((uv[:, 0] > -0.5 - m) & (uv[:, 0] < cam.width - 0.5 + m)
                      & (uv[:, 1] > -0.5 - m) & (uv[:, 1] < cam.height - 0.5 + m))
            if inside.any():
                return False
        return True


def _outside_frustum(p: np.ndarray, camera: PinholeCamera, frac: float = 0.15) -> bool:
    """``p`` is behind the camera plane or projects ``frac`` of the image size outside the image."""
    if p[2] <= 1.0:
        return True
    u, v = camera.project(p[None])[0]
    w, h = camera.width, camera.height
    return bool(u < -frac * w or u > (1 + frac) * w or v < -frac * h or v > (1 + frac) * h)


def _shaft_clear_of_lens(trocar: np.ndarray, pitch: np.ndarray, camera: PinholeCamera, min_depth: float = 20.0) -> bool:
    """The drawn shaft (40 mm before the pitch point plus its 360 mm extension) is nowhere in view
    nearer the lens than ``min_depth`` (it would cover much of the image)."""
    d = (pitch - trocar) / np.linalg.norm(pitch - trocar)
    pts = pitch - np.linspace(0.0, 400.0, 400)[:, None] * d
    pts = pts[pts[:, 2] > 1.0]
    if not len(pts):
        return True
    uv = camera.project(pts)
    r = 4.0 * camera.fx / pts[:, 2]
    seen = ((uv[:, 0] > -r) & (uv[:, 0] < camera.width + r) & (uv[:, 1] > -r) & (uv[:, 1] < camera.height + r))
    return bool((pts[seen, 2] >= min_depth).all())


def _segment_distance(a0: np.ndarray, a1: np.ndarray, b0: np.ndarray, b1: np.ndarray, n: int = 300) -> float:
    """Smallest distance between two segments (sampled; error below half a sample spacing)."""
    s = np.linspace(0.0, 1.0, n)[:, None]
    pa, pb = a0 + s * (a1 - a0), b0 + s * (b1 - b0)
    return float(np.sqrt(((pa[:, None] - pb[None]) ** 2).sum(-1).min()))


def _smoothed_need(need: np.ndarray, sigma: float) -> np.ndarray:
    """A smooth retraction never below ``need``: Gaussian (truncated at 4 sigma) of a max filter at
    least as wide as the kernel, so every kernel tap sees a value >= need[i]."""
    if sigma <= 0 or not need.any():
        return need.copy()
    half = int(math.ceil(4.0 * sigma))
    m = maximum_filter1d(need, size=2 * half + 1, mode="nearest")
    return np.maximum(gaussian_filter1d(m, sigma, mode="nearest", truncate=4.0), need)


class _Planner:
    """Samples the start configuration, the trajectories and the scripted events; see the module docstring."""

    def __init__(self, cfg: ClipConfig, camera: PinholeCamera, tissue: Tissue, tissue_pose: np.ndarray,
                 main: Instrument, second: Instrument | None, seed: int, renderer: Renderer, handles: list):
        self.cfg, self.camera, self.tissue, self.tissue_pose = cfg, camera, tissue, tissue_pose
        self.main, self.second, self.seed = main, second, seed
        self.renderer, self.handles = renderer, handles
        self.n = cfg.n_frames
        self.t = np.arange(self.n) / cfg.fps
        self.pose_cfg = PoseCfg(roll_deg=cfg.roll_deg)
        insts = {main.name: main, **({second.name: second} if second is not None else {})}
        self.tissue_checks = {k: TissueCollision(v, seed=seed) for k, v in insts.items()}
        self.view_tests = {k: _ViewTest(v, camera, seed=seed) for k, v in insts.items()}
        self.tool_check = PartCollision([main, second]) if second is not None else None
        self.sigma = max(1.0, 0.15 * cfg.fps)  # guard smoothing, frames
        self.info: dict = {}

    # ------------------------------------------------------------------ layout of the events
    def _layout(self, rng: np.random.Generator) -> tuple[tuple | None, tuple | None]:
        T = self.n / self.cfg.fps
        leave, cross = self.cfg.leave_view, self.second is not None
        leave_win = cross_win = None
        if leave and cross:
            first = rng.random() < 0.5
            leave_win, cross_win = ((0.0, T / 2), (T / 2, T)) if first else ((T / 2, T), (0.0, T / 2))
        elif leave:
            leave_win = (0.0, T)
        elif cross:
            cross_win = (0.0, T)
        leave_ev = cross_ev = None
        if leave_win:
            a, b = leave_win
            w = b - a
            ramp, out = min(0.6, 0.15 * w), min(1.0, 0.35 * w)
            total = out + 2 * ramp
            lo, hi = a + 0.15 * w + total / 2, b - 0.1 * w - total / 2
            c = rng.uniform(lo, hi) if hi > lo else 0.5 * (a + b)
            leave_ev = (c - total / 2, c + total / 2, ramp)
        if cross_win:
            a, b = cross_win
            w = b - a
            ramp = min(0.8, 0.2 * w)
            start = a + rng.uniform(0.02, 0.1) * w
            end = None if (b >= T - 1e-9 and rng.random() < 0.5) else b - rng.uniform(0.02, 0.1) * w
            cross_ev = (start, end, ramp)
        return leave_ev, cross_ev

    # ------------------------------------------------------------------ main tool
    def _main_track(self, rng: np.random.Generator) -> _Track | None:
        cam, inst = self.camera, self.main
        margin = 0.1 * min(cam.width, cam.height)
        for _ in range(200):
            s = sample_instrument(inst, self.pose_cfg, rng, cam, self.tissue, self.tissue_pose)
            if s is None or not in_view(s, cam, margin, self.pose_cfg.min_depth_mm):
                continue
            if self.tissue_checks[inst.name].collides(s.poses, self.tissue, self.tissue_pose, TISSUE_CLEARANCE_MM):
                continue
            pitch = s.base[:3, 3]
            d0 = s.base[:3, 2]
            # The RCM may sit anywhere on the shaft line: move it back until it is out of view (a real
            # trocar is), so that retracting the tool takes its tip out of the image.
            L = float(np.linalg.norm(pitch - s.trocar))
            while not _outside_frustum(pitch - L * d0, cam) and L < 260.0:
                L += 10.0
            if not _outside_frustum(pitch - L * d0, cam) or not _shaft_clear_of_lens(pitch - L * d0, pitch, cam):
                continue
            trocar = pitch - L * d0
            t = self.t
            dirs = _swing(rng, t, d0, uniform(rng, (6.0, 14.0)), L)
            depth = L + uniform(rng, (5.0, 15.0)) * _wiggle(rng, t, (0.05, 0.4))
            q = _joint_track(rng, inst, t, s.q, self.cfg.roll_swing_deg)
            return _Track(inst, trocar, dirs, depth, q, np.zeros(self.n))
        return None

    def _apply_leave(self, track: _Track, ev: tuple) -> bool:
        """Retract the main tool by the same amount over the event so its wrist and jaws leave the view."""
        start, end, ramp = ev
        prof = _plateau(self.t, start, end, ramp)
        full = np.flatnonzero(prof > 1 - 1e-9)
        if not len(full):
            full = np.array([int(np.argmax(prof))])
        test = self.view_tests[track.instrument.name]
        need = 0.0
        for i in full:
            r, top = 0.0, track.depth[i] - MIN_INSERTION_MM
            while r <= top and not test.out(track.poses(i, r)):
                r += 2.0
            if r > top:
                return False
            need = max(need, r)
        track.depth = track.depth - (need + 4.0) * prof
        self.info["leave_frames"] = full
        return True

    # ------------------------------------------------------------------ second tool
    def _second_track(self, rng: np.random.Generator, main: _Track, ev: tuple) -> _Track | None:
        cam, inst = self.camera, self.second
        start, end, ramp = ev
        prof = _plateau(self.t, start, end, ramp)
        full = np.flatnonzero(prof > 1 - 1e-9)
        if not len(full):
            return None
        i_mid = int(full[len(full) // 2])
        mp = main.base(i_mid)
        d_main = mp[:3, 2]
        for _ in range(30):
            Q = mp[:3, 3] - uniform(rng, (-3.0, 12.0)) * d_main   # a point on the main shaft near the wrist
            gap = min(uniform(rng, (15.0, 30.0)), Q[2] - 35.0)
            if gap < 10.0:
                return None
            P = Q * (Q[2] - gap) / Q[2]                             # nearer the camera on Q's ray
            uq, ub = cam.project(np.stack([Q, Q - 20.0 * d_main]))
            u_main = (ub - uq) / max(np.linalg.norm(ub - uq), 1e-9)  # image direction towards the main trocar
            alpha = np.radians(uniform(rng, (45.0, 80.0))) * rng.choice([-1.0, 1.0])
            w = np.array([[np.cos(alpha), -np.sin(alpha)], [np.sin(alpha), np.cos(alpha)]]) @ u_main
            theta = np.radians(uniform(rng, (50.0, 75.0)))
            # A direction whose image at P points along w (the tool comes from the -w side).
            v = np.append(np.sin(theta) * w + P[:2] / P[2] * np.cos(theta), np.cos(theta))
            d2 = v / np.linalg.norm(v)
            L = uniform(rng, (90.0, 150.0))
            while not _outside_frustum(P - L * d2, cam) and L < 260.0:
                L += 10.0
            trocar = P - L * d2
            reach = L + uniform(rng, (5.0, 18.0))
            if not _outside_frustum(trocar, cam) or not _shaft_clear_of_lens(trocar, trocar + reach * d2, cam, 30.0):
                continue
            # Shaft lines (with the drawn extension and the jaws) apart by more than two radii plus margin.
            m0, m1 = main.trocar - 300.0 * main.dirs[i_mid], mp[:3, 3] + 22.0 * d_main
            if _segment_distance(m0, m1, trocar - 300.0 * d2, trocar + (reach + 22.0) * d2) < 14.0:
                continue
            t = self.t
            dirs = _swing(rng, t, d2, uniform(rng, (2.0, 5.0)), reach)
            q0 = JointState.from_degrees(roll=uniform(rng, (-30.0, 30.0)), pitch=uniform(rng, (-40.0, 40.0)),
                                         yaw=uniform(rng, (-40.0, 40.0)))
            q = _joint_track(rng, inst, t, inst.limits.clip(q0))
            track = _Track(inst, trocar, dirs, np.full(self.n, reach), q, np.zeros(self.n))
            # Out of view before it enters (and after it leaves): retract until the wrist and jaws are out.
            test = self.view_tests[inst.name]
            i0 = int(np.argmin(prof))
            r = 0.0
            while r <= reach - MIN_INSERTION_MM and not test.out(track.poses(i0, r)):
                r += 2.0
            if r > reach - MIN_INSERTION_MM:
                continue
            out_depth = reach - r - 4.0
            track.depth = out_depth + (reach + uniform(rng, (2.0, 6.0)) * _wiggle(rng, t, (0.05, 0.4))
                                       - out_depth) * prof
            self.info["cross_frames"] = full
            return track
        return None

    # ------------------------------------------------------------------ guards and checks
    def _retract_until_clear(self, track: _Track, collides, step_mm: float) -> bool:
        """Retract ``track`` along its shaft, smoothly over time, wherever ``collides(i, retract_mm)`` holds;
        False when a frame cannot be cleared before the tool would leave its trocar."""
        for _ in range(3):
            need = np.zeros(self.n)
            for i in range(self.n):
                r, top = 0.0, track.depth[i] - track.retract[i] - MIN_INSERTION_MM
                while collides(i, r):
                    r += step_mm
                    if r > top:
                        return False
                need[i] = r
            if not need.any():
                return True
            track.retract = track.retract + _smoothed_need(need, self.sigma)
        return False

    def _guard_tissue(self, track: _Track) -> bool:
        check = self.tissue_checks[track.instrument.name]
        return self._retract_until_clear(
            track, lambda i, r: check.collides(track.poses(i, r), self.tissue, self.tissue_pose, TISSUE_CLEARANCE_MM),
            1.0)

    def _guard_parts(self, main: _Track, second: _Track) -> bool:
        """Retract the second tool (along its shaft) wherever the two tools would touch."""
        return self._retract_until_clear(
            second, lambda i, r: bool(self.tool_check.collisions_of([(self.main, main.poses(i)),
                                                                       (self.second, second.poses(i, r))])),
            2.0)

    def _left_view(self, track: _Track) -> int:
        test = self.view_tests[track.instrument.name]
        return sum(test.out(track.poses(i)) for i in self.info["leave_frames"])

    def _occluded_frames(self, main: _Track, second: _Track) -> int:
        """Frames of the crossing where the second tool hides at least a few of the main tool's pixels
        while the main wrist/jaws are in the image (instrument-only renders)."""
        h_main, h_sec = self.handles
        sec_ids = np.array(sorted(set(h_sec.parts.values()) | {i for _, i in h_sec.attachments}))
        root = main.instrument.part_names[0]
        margin = max(20, int(5e-4 * self.camera.width * self.camera.height))
        count = 0
        for i in self.info["cross_frames"]:
            poses = {**h_main.poses(main.poses(i)), **h_sec.poses(second.poses(i))}
            res = self.renderer.render(self.camera, poses, modalities={"instance", "amodal"})
            by_second = np.isin(res.instance, sec_ids)
            hidden = sum(int((res.amodal[iid] & by_second).sum()) for iid in h_main.parts.values())
            in_img = sum(int(res.amodal[iid].sum()) for p, iid in h_main.parts.items() if p != root)
            count += hidden >= margin and in_img > 0
        return count

    # ------------------------------------------------------------------ one plan
    def plan(self, rng: np.random.Generator) -> tuple[list[_Track] | None, str]:
        leave_ev, cross_ev = self._layout(rng)
        main = self._main_track(rng)
        if main is None:
            return None, "start"
        if leave_ev is not None and not self._apply_leave(main, leave_ev):
            return None, "leave"
        tracks = [main]
        if cross_ev is not None:
            second = self._second_track(rng, main, cross_ev)
            if second is None:
                return None, "second"
            tracks.append(second)
        for tr in tracks:
            if not self._guard_tissue(tr):
                return None, "tissue_collision"
        if len(tracks) == 2 and not self._guard_parts(*tracks):
            return None, "part_collision"
        if leave_ev is not None and self._left_view(main) < max(1, len(self.info["leave_frames"]) // 2):
            return None, "leave"
        if len(tracks) == 2 and self._occluded_frames(*tracks) < 2:
            return None, "occlusion"
        return tracks, ""


# ---------------------------------------------------------------------------------------------- output
def _gt_text(doc: dict) -> str:
    """gt.json text: the header keys indented, then one frame per line."""
    head = [f"  {json.dumps(k)}: {json.dumps(v, allow_nan=False)}" for k, v in doc.items() if k != "frames"]
    frames = [f"    {json.dumps(k)}: {json.dumps(v, allow_nan=False)}" for k, v in doc["frames"].items()]
    return "{\n" + ",\n".join(head) + ',\n  "frames": {\n' + ",\n".join(frames) + "\n  }\n}\n"


def _sample_scene(camera: PinholeCamera, renderer: Renderer, seed: int):
    """Tissue patch and pose covering the whole image; returns (tissue, pose, instance id)."""
    tcfg = TissueCfg()
    for k in range(50):
        rng = np.random.default_rng([seed, 1, k])
        tissue = procedural_tissue(rng, extent=tuple(tcfg.extent_mm), spacing=tcfg.spacing_mm, texel=tcfg.texel_mm,
                                   fold_depth=uniform(rng, tcfg.fold_depth_mm))
        pose = sample_tissue_pose(tcfg, rng)
        tid = tissue.add_to(renderer)
        res = renderer.render(camera, {tid: pose}, modalities={"instance"})
        if (res.instance > 0).mean() >= MIN_TISSUE_COVERAGE:
            return tissue, pose, tid
        renderer.remove(tid)
    raise ClipError("could not place a tissue patch covering the image; check the clip's camera settings")


def make_clip(out_dir: str | Path, instrument: str = "lnd", cfg: ClipConfig = ClipConfig(), seed: int = 0,
              progress: bool = False, instruments: InstrumentRegistry = BUILTIN) -> dict:
    """Render a synthetic clip of ``instrument`` (name or alias known to ``instruments``, or a YAML path)
    into ``out_dir``: ``video.mp4``, ``camera.json``, ``gt.json`` and ``det.json`` (see the module
    docstring and docs/formats.md).

    Returns a summary: the file paths, frame count, fps, visible-frame count per part (keyed
    ``"<instrument_index>:<instrument>/<part>"``), how many frames have the main tool's wrist and jaws
    out of the image and how many have the second tool hiding part of it, the motion-plan attempts (and
    why earlier ones were discarded) and the seconds taken.
    Deterministic for a given ``seed`` and ``cfg``.
    """
    from tqdm import tqdm

    t0 = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    main = instruments.load(instrument)
    second = instruments.load(cfg.second_instrument) if cfg.second_instrument else None
    tools = [main] + ([second] if second is not None else [])
    noise, effects = cfg.noise(), cfg.camera_effects()
    W, H, n, fps = cfg.width, cfg.height, cfg.n_frames, float(cfg.fps)
    camera = PinholeCamera.from_fov(W, H, cfg.hfov_deg)

    # Object ids (deduplicated when both tools are the same model) and det.json track ids (one per part
    # of each tool; "instance" counts tools of the same name).
    unique = list({inst.name: inst for inst in tools}.values())
    obj_ids = {(inst.name, p): oid for oid, (inst, p) in assign_obj_ids(unique).items()}
    parts_doc, track_ids = {}, {}
    for k, inst in enumerate(tools):
        instance = sum(o.name == inst.name for o in tools[:k])
        for p in inst.part_names:
            pid = len(parts_doc) + 1
            parts_doc[str(pid)] = {"instrument": inst.name, "instance": instance, "part": p}
            track_ids[(k, p)] = pid

    renderer = Renderer(W, H)
    try:
        tissue, tissue_pose, tid = _sample_scene(camera, renderer, seed)
        handles = []
        for k, inst in enumerate(tools):
            like = next((h for h, o in zip(handles, tools) if o.name == inst.name), None)
            handles.append(add_instrument(renderer, inst, like=like))
        planner = _Planner(cfg, camera, tissue, tissue_pose, main, second, seed, renderer, handles)
        tracks, reasons = None, {}
        for attempt in range(1, MAX_ATTEMPTS + 1):
            planner.info = {}
            tracks, why = planner.plan(np.random.default_rng([seed, 2, attempt]))
            if tracks is not None:
                break
            reasons[why] = reasons.get(why, 0) + 1
        if tracks is None:
            top = max(reasons, key=lambda k: reasons[k])
            raise ClipError(f"{out}: no valid motion plan for {main.name} with seed {seed} in {MAX_ATTEMPTS} attempts "
                            f"(failures: {', '.join(f'{k} {v}' for k, v in reasons.items())}); most often {top}: "
                            f"check the instrument with `surftrack instruments {main.source or main.name} --check`, "
                            f"or try another --seed")
        # Lights fixed for the clip (the static tissue layer stays cached); extra spots follow the shafts.
        lights, ambient = sample_lights(LightingCfg(), np.random.default_rng([seed, 3]),
                                        [tr.sample(n // 2) for tr in tracks])

        pad = max(W, H) // 2
        all_ids = np.array(sorted(renderer.instances))
        frames_gt, det_frames, occluded = {}, [], 0
        sec_ids = (np.array(sorted(set(handles[1].parts.values()) | {i for _, i in handles[1].attachments}))
                   if len(handles) == 2 else None)
        visible = {f"{k}:{inst.name}/{p}": 0 for k, inst in enumerate(tools) for p in inst.part_names}
        # an earlier clip's truth must not sit beside this clip's video if this one stops part way
        for old in ("camera.json", "gt.json", "det.json"):
            (out / old).unlink(missing_ok=True)
        with VideoWriter(out / "video.mp4", fps, W, H, crf=cfg.crf) as writer:
            for i in tqdm(range(n), desc="clip", unit="frame", disable=not progress):
                part_poses = [tr.poses(i) for tr in tracks]
                poses = {tid: tissue_pose}
                for h, pp in zip(handles, part_poses):
                    poses.update(h.poses(pp))
                res = renderer.render(camera, poses, lights, modalities={"rgb", "instance", "amodal"},
                                      ambient=ambient, static={tid}, amodal_pad=pad)
                rgb = apply_effects(res.rgb, effects, np.random.default_rng([seed, 4, i]),
                                    principal_point=(camera.cx, camera.cy))
                writer.write(rgb, i / fps)
                counts = np.bincount(res.instance.ravel(), minlength=int(all_ids.max()) + 1)
                gt, boxes, vis_px = [], {}, {}
                for k, (tr, h, pp) in enumerate(zip(tracks, handles, part_poses)):
                    joints = {name: float(np.degrees(v)) for name, v in tr.q[i].as_dict().items()}
                    for p, iid in h.parts.items():
                        T, pid = pp[p], track_ids[(k, p)]
                        n_vis = int(counts[iid])
                        box = bbox_xywh(res.instance == iid) if n_vis else [-1, -1, -1, -1]
                        gt.append({
                            "obj_id": obj_ids[(tr.instrument.name, p)],
                            "cam_R_m2c": T[:3, :3].ravel().tolist(), "cam_t_m2c": T[:3, 3].tolist(),
                            "instrument": tr.instrument.name, "instrument_index": k, "part": p, "part_id": pid,
                            "joints_deg": joints, "trocar_mm": tr.trocar.tolist(),
                            "px_count_visib": n_vis, "px_count_all": int(res.amodal[iid].sum()),
                            "bbox_visib": box,
                        })
                        visible[f"{k}:{tr.instrument.name}/{p}"] += n_vis > 0
                        # det.json boxes are pixel-EDGE boxes, the gt's BOP boxes count pixel indices
                        boxes[pid] = box_from_bop(box) if n_vis else None
                        vis_px[pid] = n_vis
                frames_gt[str(i)] = {"time": i / fps, "gt": gt}
                if len(handles) == 2:
                    by_second = np.isin(res.instance, sec_ids)
                    occluded += any((res.amodal_in_image(iid) & by_second).any() for iid in handles[0].parts.values())
                dets = simulate_detections(boxes, vis_px, (W, H), noise, np.random.default_rng([seed, 5, i]))
                det_frames.append({"index": i, "time": i / fps, "detections": dets})
        test = planner.view_tests[main.name]
        leave_out = sum(test.out(tracks[0].poses(i)) for i in range(n)) if cfg.leave_view else 0
    finally:
        renderer.release()

    camera_doc = {**camera.to_dict(), "dist": camera.dist.tolist()}
    write_atomic(out / "camera.json", json.dumps(camera_doc, indent=2) + "\n")
    gt_doc = {
        "format": GT_FORMAT, "version": GT_VERSION, "fps": fps, "image_size": [W, H], "seed": int(seed),
        "config": cfg.to_dict(), "parts": parts_doc,
        "models": {str(oid): {"instrument": name, "part": p} for (name, p), oid in
                   sorted(obj_ids.items(), key=lambda kv: kv[1])},
        "frames": frames_gt,
    }
    write_atomic(out / "gt.json", _gt_text(gt_doc))
    meta = {"detector": "simulated", "generator": "surftrack.synth.clip", "seed": int(seed), "video": "video.mp4",
            "noise": dataclasses.asdict(noise)}
    write_detections(out / "det.json", detections_document((W, H), parts_doc, det_frames, meta))
    return {
        "out_dir": str(out), "video": str(out / "video.mp4"), "camera": str(out / "camera.json"),
        "gt": str(out / "gt.json"), "det": str(out / "det.json"),
        "frames": n, "fps": fps, "instruments": [inst.name for inst in tools],
        "visible_frames": visible, "main_out_of_view_frames": leave_out, "occluded_frames": occluded,
        "attempts": attempt, "plan_failures": reasons, "seconds": round(time.perf_counter() - t0, 2),
    }


__all__ = ["ClipConfig", "MILD_EFFECTS", "make_clip"]
