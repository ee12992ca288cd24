"""Random cameras, tissue placements, lights and instrument configurations under the RCM constraint.

Per the SurfSurg6D paper: a trocar (remote centre of motion) per instrument, the shaft through it, the
tool tip 30..100 mm from the tissue, roll +-30 deg, two wrist angles 0..60 deg, the tool aimed near the
image centre so instrument and tissue are central in view.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from surftrack.geometry import PinholeCamera, rotation_about, se3, so3_exp, transform_points
from surftrack.instruments import Instrument, JointState, rcm_base_pose
from surftrack.render import Light
from surftrack.synth.config import CameraCfg, ImageCfg, LightingCfg, PoseCfg, TissueCfg
from surftrack.synth.tissue import Tissue


@dataclass
class InstrumentSample:
    """One posed instrument: the RCM geometry that produced it and every part's pose (camera frame)."""

    instrument: Instrument
    trocar: np.ndarray
    target: np.ndarray          # tissue point the tool aims at
    tip_to_tissue: float        # mm, along the shaft, before the wrist bends
    q: JointState
    base: np.ndarray
    poses: dict[str, np.ndarray]

    def keypoints(self) -> dict[str, np.ndarray]:
        return self.instrument.keypoints(self.poses)


def uniform(rng: np.random.Generator, r: tuple[float, float]) -> float:
    return float(rng.uniform(r[0], r[1]))


def sample_camera(image: ImageCfg, cfg: CameraCfg, rng: np.random.Generator) -> PinholeCamera:
    """Square-pixel intrinsics from a random horizontal FOV and a jittered principal point."""
    cam = PinholeCamera.from_fov(image.width, image.height, uniform(rng, cfg.hfov_deg))
    K = cam.K.copy()
    K[0, 2] += rng.uniform(-1, 1) * cfg.principal_jitter * image.width
    K[1, 2] += rng.uniform(-1, 1) * cfg.principal_jitter * image.height
    return PinholeCamera(K, image.width, image.height)


def sample_tissue_pose(cfg: TissueCfg, rng: np.random.Generator) -> np.ndarray:
    """Tissue-to-camera pose: the patch centre on the optical axis at a random distance, tilted and spun."""
    axis = rng.normal(size=2)
    tilt = rotation_about([axis[0], axis[1], 0.0], np.radians(uniform(rng, cfg.tilt_deg)))
    spin = rotation_about([0, 0, 1.0], rng.uniform(0, 2 * np.pi))
    return se3(tilt @ spin, [0.0, 0.0, uniform(rng, cfg.distance_mm)])


def jitter_pose(T: np.ndarray, rng: np.random.Generator, mm: float, deg: float) -> np.ndarray:
    """``T`` moved and turned about its own origin by Gaussian amounts of RMS ``mm`` and ``deg`` (the
    paper's scene jitter)."""
    dR = so3_exp(rng.normal(size=3) * np.radians(deg) / np.sqrt(3))
    return se3(dR @ T[:3, :3], T[:3, 3] + rng.normal(size=3) * mm / np.sqrt(3))


def ray_hit_tissue(tissue: Tissue, tissue_pose: np.ndarray, direction: np.ndarray,
                   origin: np.ndarray | None = None, t_range: tuple[float, float] = (0.0, 1000.0)) -> np.ndarray | None:
    """First point where the ray ``origin + t * direction`` (camera frame, default origin the camera
    centre) enters the tissue height field from the front; None if it misses the patch."""
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    o = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64)
    inv = np.linalg.inv(tissue_pose)
    ts = np.linspace(t_range[0], t_range[1], 500)
    local = transform_points(inv, o + ts[:, None] * d)
    w, h = tissue.extent
    inside = (np.abs(local[:, 0]) <= w / 2) & (np.abs(local[:, 1]) <= h / 2)
    f = local[:, 2] - tissue.height_at(local[:, 0], local[:, 1])  # < 0 in front of the surface
    crossing = np.nonzero(inside[1:] & inside[:-1] & (f[:-1] < 0) & (f[1:] >= 0))[0]
    if len(crossing) == 0:
        return None
    lo, hi = ts[crossing[0]], ts[crossing[0] + 1]
    for _ in range(40):  # bisection on the bracketing interval
        mid = 0.5 * (lo + hi)
        p = transform_points(inv, (o + mid * d)[None])[0]
        if p[2] - tissue.height_at(p[:1], p[1:2])[0] < 0:
            lo = mid
        else:
            hi = mid
    return o + 0.5 * (lo + hi) * d


def _tip_distance(instrument: Instrument) -> float:
    """Distance along the shaft from the pitch axis to the tool tip(s) of the straight instrument."""
    poses = instrument.forward(np.eye(4), JointState())
    tips = [p for k, p in instrument.keypoints(poses).items() if k.endswith("/tip")]
    return float(np.mean([t[2] for t in tips])) if tips else 20.0


def roll_reference(cfg: PoseCfg, shaft: np.ndarray) -> np.ndarray | None:
    """The direction that defines zero roll for a shaft pointing along ``shaft`` (camera frame), for
    :func:`rcm_base_pose`. The paper samples roll within +-30 deg without saying about what; the zero
    decides which views of the jaws the data holds. ``view`` (None: the viewing direction) turns the
    jaws' opening direction (the pitch axis) towards the camera, so one jaw of a two-jaw tool is mostly
    behind the other; ``across`` turns it across the view, perpendicular to the shaft and the viewing
    direction. The whole wrist turns with it: with ``view`` the wrist pitch bends in the image plane and
    the yaw towards the camera, with ``across`` the other way round. The recorded roll (``joints_deg``)
    counts from this zero. Mean visible fraction of the LND's parts (80 images, seed 21), shaft / wrist /
    left jaw / right jaw: ``view`` 79 / 51 / 43 / 84 %, ``across`` 76 / 74 / 51 / 56 %."""
    if cfg.roll_zero == "view":
        return None
    across = np.cross(shaft, [0.0, 0.0, 1.0])
    return across if np.linalg.norm(across) > 1e-6 else None


def sample_joints(instrument: Instrument, cfg: PoseCfg, rng: np.random.Generator) -> JointState:
    """Joint values: with ``cfg.joint_source == 'limits'`` uniform over the instrument's whole reach
    (:meth:`~surftrack.instruments.Instrument.reach`); with ``'ranges'`` from the configured ranges (the
    paper's), clipped to the limits. Either way a joint without a limit stays at 0 (a spatula has no
    opening to record)."""
    if cfg.joint_source == "limits":
        return JointState(**{n: float(rng.uniform(lo, hi)) for n, (lo, hi) in instrument.reach().items()})

    def wrist(r: tuple[float, float]) -> float:
        a = uniform(rng, r)
        return a * (rng.choice([-1.0, 1.0]) if cfg.wrist_sign == "random" else 1.0)

    q = JointState.from_degrees(roll=uniform(rng, cfg.roll_deg), pitch=wrist(cfg.pitch_deg),
                                yaw=wrist(cfg.yaw_deg), opening=uniform(rng, cfg.opening_deg))
    limited = instrument.limits.ranges
    return JointState(**{n: v if n in limited else 0.0 for n, v in instrument.limits.clip(q).as_dict().items()})


def sample_instrument(instrument: Instrument, cfg: PoseCfg, rng: np.random.Generator, camera: PinholeCamera,
                      tissue: Tissue, tissue_pose: np.ndarray, near: np.ndarray | None = None) -> InstrumentSample | None:
    """Pose ``instrument`` through a random trocar with its tip ``tip_to_tissue_mm`` from the tissue.

    The tool tip sits on the camera ray of a pixel near the image centre (or near the point ``near``, for
    a second tool), in front of the tissue by about the sampled distance; the shaft comes in at a random
    angle to the optical axis from a random side. The tip-to-tissue distance is then measured along the
    shaft direction. Returns None when the geometry fails (a ray misses the tissue, the distance falls
    outside the range, the tip is nearer the lens than ``min_depth_mm``).
    """
    if near is None:
        r = cfg.target_radius * np.sqrt(rng.random())
        a = rng.uniform(0, 2 * np.pi)
        px = np.array([[camera.cx + r * np.cos(a) * camera.width / 2, camera.cy + r * np.sin(a) * camera.height / 2]])
        ray = camera.backproject(px, np.ones(1))[0]
    else:
        ray = near + rng.normal(size=3) * cfg.second_target_mm / np.sqrt(3)
    under = ray_hit_tissue(tissue, tissue_pose, ray)
    if under is None:
        return None
    theta, phi = np.radians(uniform(rng, cfg.shaft_to_axis_deg)), rng.uniform(0, 2 * np.pi)
    shaft = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
    d_wanted = uniform(rng, cfg.tip_to_tissue_mm)
    # Slide the tip along the pixel's ray until the tissue ahead along the shaft is d_wanted away (a few
    # secant-like steps; the tissue is smooth at this scale).
    tip = under * max(0.0, 1.0 - d_wanted * np.cos(theta) / max(under[2], 1e-6))
    for _ in range(4):
        if tip[2] < cfg.min_depth_mm:
            return None
        target = ray_hit_tissue(tissue, tissue_pose, shaft, origin=tip)
        if target is None:
            return None
        d = float(np.linalg.norm(target - tip))
        if abs(d - d_wanted) < 1.0:
            break
        tip = under + (tip - under) * (d_wanted / max(d, 1e-6))
    else:
        return None  # not converged: d would describe an earlier tip
    if not cfg.tip_to_tissue_mm[0] <= d <= cfg.tip_to_tissue_mm[1]:
        return None
    pitch_point = tip - _tip_distance(instrument) * shaft
    trocar = pitch_point - rng.uniform(60.0, 140.0) * shaft
    q = sample_joints(instrument, cfg, rng)
    base = rcm_base_pose(trocar, pitch_point, roll_reference(cfg, shaft))
    return InstrumentSample(instrument, trocar, target, d, q, base, instrument.forward(base, q))


def sample_lights(cfg: LightingCfg, rng: np.random.Generator, samples: list[InstrumentSample]) -> tuple[list[Light], tuple]:
    """The endoscope light plus extra spots that follow a trocar and shaft; returns (lights, ambient)."""
    def colour() -> tuple[float, float, float]:
        c = np.array([1.0, 0.97, 0.92]) * (1.0 + rng.uniform(-1, 1, 3) * cfg.color_jitter)
        return tuple(float(x) for x in c)

    lights = [Light(position=tuple(rng.normal(size=3) * 2.0), direction=(0.0, 0.0, 1.0), color=colour(),
                    intensity=uniform(rng, cfg.endoscope_intensity), inner_deg=30.0, outer_deg=75.0)]
    for _ in range(int(rng.integers(cfg.extra_lights[0], cfg.extra_lights[1] + 1))):
        s = samples[int(rng.integers(len(samples)))]
        shaft = s.base[:3, 2]
        # Between the trocar and the wrist, shining along the shaft.
        pos = s.trocar + rng.uniform(0.3, 0.8) * (s.base[:3, 3] - s.trocar) + rng.normal(size=3) * 10.0
        lights.append(Light(position=tuple(pos), direction=tuple(shaft + rng.normal(size=3) * 0.2), color=colour(),
                            intensity=uniform(rng, cfg.extra_intensity), inner_deg=20.0, outer_deg=60.0))
    a = uniform(rng, cfg.ambient)
    return lights, (a, a * 0.9, a * 0.9)
