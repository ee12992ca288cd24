"""Region-based pose measurement for textureless parts: colour statistics along correspondence lines.

A textureless, specular instrument offers optical flow little to follow, but its silhouette against the
tissue is clear. Following the region-based trackers SRT3D and ICG (Stoiber et al.; the method of
DLR-RM/3DObjectTracking, re-derived here, not copied), each frame:

1. the tracked parts are rendered at their predicted poses (:class:`~surftrack.render.Renderer`, instance
   ids and object coordinates), with the instrument's render-only attachments (the long shaft tube) as
   part of the part they hang on. Contour points are pixels of an instrument's silhouette next to the
   background, each with its 3D point on the part and the silhouette's outward normal in the image;
   contour pixels next to another instrument are skipped (an occlusion edge is not a colour edge);
2. along a short line through each contour point, normal to the silhouette, every pixel's colour gives a
   foreground probability from the instrument's colour histograms (foreground / background, learnt from
   the rendered silhouette and a band around it, :meth:`RegionTracker.learn`); the contour's position
   along the line has the posterior of a smoothed step model (a tanh of amplitude ``alpha`` and slope
   ``slope``), whose mean and variance are the line's measurement;
3. a few Gauss-Newton steps (coarse to fine line scales) move the parameters of a :class:`PoseModel` (one
   free part's pose, or an instrument's root pose and joints, :class:`ArticulatedModel`) so the projected
   contour points land on those means, each weighted by its variance, regularised by the prediction.

The result is a pose measurement with a covariance (the inverse Gauss-Newton Hessian, inflated because
neighbouring lines share pixels and the model's contour is approximate): directions the silhouette does
not constrain (a cylinder's roll) get a huge variance, so the filter keeps its own estimate there.
Poses use the Kalman filter's convention: ``R' = R exp(dtheta)`` (body), ``t' = t + dt`` (camera, mm).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import trimesh

from surftrack.geometry import PinholeCamera, project_pose_jacobian, se3, se3_inv
from surftrack.geometry.transforms import skew, so3_exp, so3_right_jacobian
from surftrack.instruments import Instrument, JointState
from surftrack.instruments.kinematics import JOINT_NAMES
from surftrack.render.renderer import Renderer


@dataclass(frozen=True)
class RegionConfig:
    """``bins``: histogram bins per RGB channel. ``line_half``: samples on each side of a contour point
    along its line; ``scales``: pixels between samples, one Gauss-Newton step per entry (coarse to fine:
    the first catches motions of ``line_half * scales[0]`` px). ``alpha``, ``slope``: the smoothed step's
    amplitude and slope (samples), as ICG's defaults. ``max_points``: contour points per part.
    ``min_points``: lines a part needs for a measurement. ``var_floor_px``: the smallest line variance
    (px^2); ``inflate``: the covariance's factor for correlated lines. ``robust_px``: the Cauchy scale of
    a line's residual (px at 1 px spacing), beyond which a line's pull fades. ``occlusion_px``: contour
    points this close to another instrument are skipped. ``max_std_mm`` / ``max_std_deg``: the units in
    which the lines' information is inverted (what they pin better than these is what the tracker fuses,
    :meth:`RegionResult.observed`)."""

    bins: int = 16
    line_half: int = 8
    scales: tuple[int, ...] = (2, 1, 1)
    alpha: float = 0.43
    slope: float = 0.5
    max_points: int = 100
    min_points: int = 12
    var_floor_px: float = 1.0
    inflate: float = 3.0
    occlusion_px: int = 3
    robust_px: float = 1.5
    max_std_mm: float = 1.0
    max_std_deg: float = 3.0

    def __post_init__(self) -> None:
        if self.bins not in (2, 4, 8, 16, 32, 64, 128, 256):
            raise ValueError(f"bins must be a power of two up to 256, got {self.bins}")
        if self.line_half < 4 or not self.scales or min(self.scales) < 1:
            raise ValueError("line_half must be >= 4 and scales positive integers")


@dataclass
class Contour:
    """Contour points of one part at its rendered pose: ``xyz`` (N, 3) on the part (mm, its frame) and
    ``normal`` (N, 2) the silhouette's outward unit normal in the image."""

    xyz: np.ndarray
    normal: np.ndarray

    @property
    def edge_offset(self) -> np.ndarray:
        """(N,) px from each contour pixel's centre to the silhouette's edge along the normal, on
        average: a contour pixel is the last one inside, its centre within ``max(|nx|, |ny|)`` of the edge
        (a 4-neighbour lies outside). Without it the fit would push every edge out by ~0.5 px: a 40 px
        wide shaft would come 1.5 mm too close."""
        return 0.5 * np.abs(self.normal).max(axis=1)


@dataclass
class RegionResult:
    """A part's region measurement: pose, covariance (6x6, position mm^2 then body rotation rad^2),
    lines used, and ``agreement``: the share of line pixels the colour model puts on the side of the
    final contour they lie on (0.5 = chance, 1 = a clean silhouette)."""

    R: np.ndarray
    t: np.ndarray
    cov: np.ndarray
    lines: int
    agreement: float

    def observed(self, max_std_mm: float, max_std_deg: float) -> tuple[np.ndarray, np.ndarray]:
        """(basis m x 6, its m x m covariance): the combinations of the pose this measurement pins to
        better than ``max_std_mm`` / ``max_std_deg`` (in units of those), for
        :meth:`~surftrack.track.kalman.PoseKalman.update`'s ``basis``. A silhouette sees its part's
        lateral position and in-plane turns well, its depth and a cylinder's roll poorly: passing those
        on, however wide their variance, would let the fit's wandering there into the track."""
        return observed_directions(self.cov, max_std_mm, max_std_deg)


def observed_directions(cov: np.ndarray, max_std_mm: float, max_std_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(basis m x n, its m x m covariance): the combinations of parameters with covariance ``cov`` (n x n;
    3 positions in mm first, then angles in rad) pinned to better than ``max_std_mm`` / ``max_std_deg``
    in units of those."""
    n = cov.shape[0]
    scale = np.r_[np.full(3, max_std_mm), np.full(n - 3, np.radians(max_std_deg))]
    w, V = np.linalg.eigh(cov / np.outer(scale, scale))
    keep = w < 1.0
    return V[:, keep].T / scale[None, :], np.diag(w[keep])


class ColorModel:
    """Foreground / background RGB histograms of one instrument (``bins`` per channel, each normalised)."""

    def __init__(self, bins: int = 16):
        self.bins = bins
        self.shift = int(np.log2(256 // bins))
        self.fg: np.ndarray | None = None
        self.bg: np.ndarray | None = None

    def index(self, rgb: np.ndarray) -> np.ndarray:
        """Histogram bin of each colour (..., 3) uint8."""
        q = (rgb >> self.shift).astype(np.int64)
        return (q[..., 0] * self.bins + q[..., 1]) * self.bins + q[..., 2]

    def _hist(self, rgb: np.ndarray) -> np.ndarray:
        h = np.bincount(self.index(rgb).ravel(), minlength=self.bins**3).astype(np.float64) + 1e-3
        return h / h.sum()

    def update(self, fg_rgb: np.ndarray, bg_rgb: np.ndarray, rate: float = 1.0) -> bool:
        """Blend the histograms of these foreground and background colours (N, 3) in at ``rate``
        (1 = replace); False (nothing learnt) with fewer than 10 of either."""
        if len(fg_rgb) < 10 or len(bg_rgb) < 10:
            return False
        f, b = self._hist(fg_rgb), self._hist(bg_rgb)
        if self.fg is None or rate >= 1.0:
            self.fg, self.bg = f, b
        else:
            self.fg = (1 - rate) * self.fg + rate * f
            self.bg = (1 - rate) * self.bg + rate * b
        return True

    @property
    def ready(self) -> bool:
        return self.fg is not None

    def p_fg(self, rgb: np.ndarray) -> np.ndarray:
        """Posterior foreground probability of each colour (equal priors), (...,) float."""
        i = self.index(rgb)
        f, b = self.fg[i], self.bg[i]
        return f / (f + b)


#: contour points nearer the lens than this (mm) are not measured: nothing is in focus there, and their
#: projection's Jacobian (~1 / z^2) would swamp every other line (a drifted pose grazing the lens made the
#: normal equations singular)
NEAR_MM = 5.0


def _in_front(pose: tuple[np.ndarray, np.ndarray], xyz: np.ndarray) -> np.ndarray:
    """Which model points ``xyz`` (N, 3) mm lie at least ``NEAR_MM`` in front of the camera under ``pose``
    (R, t)."""
    R, t = pose
    return (np.asarray(xyz) @ np.asarray(R)[2] + float(t[2])) >= NEAR_MM


def _sample(image: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Colours (..., 3) at pixel positions ``pts`` (..., 2) (nearest pixel) and whether each is inside."""
    H, W = image.shape[:2]
    x, y = np.rint(pts[..., 0]).astype(np.int64), np.rint(pts[..., 1]).astype(np.int64)
    inside = (x >= 0) & (x < W) & (y >= 0) & (y < H)
    return image[np.clip(y, 0, H - 1), np.clip(x, 0, W - 1)], inside


class RegionTracker:
    """Renders tracked parts and measures their poses against a frame (see the module docstring).

    ``meshes`` maps a part's name to its mesh (mm, the part's frame) and ``attachments`` to render-only
    meshes rigidly attached to it; ``groups`` maps a part's name to its instrument key (parts of one
    instrument share a silhouette and a colour model).
    """

    def __init__(self, K: np.ndarray, size: tuple[int, int], meshes: Mapping[str, trimesh.Trimesh],
                 groups: Mapping[str, str], attachments: Mapping[str, Sequence[trimesh.Trimesh]] | None = None,
                 cfg: RegionConfig | None = None):
        self.cfg = cfg or RegionConfig()
        self.K = np.asarray(K, np.float64)
        self.size = (int(size[0]), int(size[1]))
        self.camera = PinholeCamera(self.K, *self.size)
        self.renderer = Renderer(*self.size)
        self.groups = dict(groups)
        self.ids: dict[str, list[int]] = {}
        for name, mesh in meshes.items():
            ids = [self.renderer.add_mesh(mesh, amodal=False)]
            for att in (attachments or {}).get(name, ()):
                ids.append(self.renderer.add_mesh(att, amodal=False))
            self.ids[name] = ids
        self._max_id = max((i for ids in self.ids.values() for i in ids), default=0)
        self.colors: dict[str, ColorModel] = {g: ColorModel(self.cfg.bins) for g in set(self.groups.values())}
        # smoothed-step values for every (candidate contour position, sample) pair, shared by all lines
        L = self.cfg.line_half
        self._s = np.arange(-L, L + 1, dtype=np.float64)
        # candidate edge positions, symmetric about +0.5 (between the last pixel inside and the first
        # outside), so a line that sees nothing pulls neither way
        self._d = np.arange(-L + 2, L - 1, dtype=np.float64) + 0.5
        x = self._s[None, :] - self._d[:, None]
        self._hf = 0.5 - 0.5 * self.cfg.alpha * np.tanh(x / (2.0 * self.cfg.slope))

    def release(self) -> None:
        self.renderer.release()

    # ------------------------------------------------------------------ contours
    def contours(self, poses: Mapping[str, tuple[np.ndarray, np.ndarray]]) -> tuple[dict[str, Contour], dict[str, np.ndarray]]:
        """Render ``poses`` (part name -> (R, t)) and return each part's contour points and each
        instrument's silhouette mask (H, W bool)."""
        inst_poses = {i: se3(*poses[name]) for name in poses for i in self.ids[name]}
        res = self.renderer.render(self.camera, inst_poses, modalities=("instance", "xyz"))
        ids, xyz = res.instance, res.xyz
        owner = np.zeros(self._max_id + 1, np.int64)
        names = sorted(poses)
        for k, name in enumerate(names):
            for i in self.ids[name]:
                owner[i] = k + 1
        part_of = owner[ids]  # 0 = background, k + 1 = names[k]
        group_names = sorted({self.groups[n] for n in names})
        group_of_part = np.array([0] + [group_names.index(self.groups[n]) + 1 for n in names])
        group = group_of_part[part_of]
        out: dict[str, Contour] = {}
        masks: dict[str, np.ndarray] = {}
        cfg = self.cfg
        kernel = np.ones((2 * cfg.occlusion_px + 1,) * 2, np.uint8)
        for gi, gname in enumerate(group_names, start=1):
            mask = group == gi
            masks[gname] = mask
            m8 = mask.astype(np.uint8)
            # a contour pixel has a 4-neighbour outside (what Contour.edge_offset models)
            edge = mask & (cv2.erode(m8, cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3)),
                                     borderType=cv2.BORDER_REPLICATE) == 0)
            others = ((group != gi) & (group > 0)).astype(np.uint8)
            if others.any():
                edge &= cv2.dilate(others, kernel) == 0
            ys, xs = np.nonzero(edge)
            if not len(ys):
                continue
            blur = cv2.GaussianBlur(m8.astype(np.float32), (0, 0), 2.0)
            gx = cv2.Sobel(blur, cv2.CV_32F, 1, 0, ksize=3)[ys, xs]
            gy = cv2.Sobel(blur, cv2.CV_32F, 0, 1, ksize=3)[ys, xs]
            norm = np.hypot(gx, gy)
            ok = norm > 1e-3
            ys, xs, nrm = ys[ok], xs[ok], -np.c_[gx[ok], gy[ok]] / norm[ok, None]
            parts = part_of[ys, xs]
            for k in np.unique(parts):
                sel = np.nonzero(parts == k)[0]
                if len(sel) > cfg.max_points:
                    sel = sel[np.linspace(0, len(sel) - 1, cfg.max_points).astype(np.int64)]
                out[names[k - 1]] = Contour(xyz[ys[sel], xs[sel]].astype(np.float64), nrm[sel].astype(np.float64))
        return out, masks

    # ------------------------------------------------------------------ lines
    def _lines(self, image: np.ndarray, colors: ColorModel, uv: np.ndarray, normal: np.ndarray, scale: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per line: (contour offset along the normal (px), its variance (px^2), valid, foreground
        probability of each sample (N, S))."""
        pts = uv[:, None, :] + (self._s * scale)[None, :, None] * normal[:, None, :]
        rgb, inside = _sample(image, pts)
        pf = np.clip(colors.p_fg(rgb), 1e-3, 1 - 1e-3)
        valid = inside.all(axis=1)
        # log-likelihood of each candidate contour position d: sum over the line's samples of
        # log(h_f(s - d) p_f(s) + h_b(s - d) p_b(s))
        hf = self._hf[None]
        ll = np.log(hf * pf[:, None, :] + (1 - hf) * (1 - pf[:, None, :])).sum(axis=2)
        ll -= ll.max(axis=1, keepdims=True)
        p = np.exp(ll)
        p /= p.sum(axis=1, keepdims=True)
        mu = p @ self._d
        var = (p * (self._d[None] - mu[:, None]) ** 2).sum(axis=1)
        return mu * scale, var * scale**2, valid, pf

    def learn(self, image: np.ndarray, group: str, mask: np.ndarray, band_px: int = 12, gap_px: int = 2,
              rate: float = 1.0, within: np.ndarray | None = None) -> bool:
        """Update an instrument's colour model from its silhouette ``mask`` (foreground, less its edge
        pixels) and a band of ``band_px`` around it (background) from ``gap_px`` out, in ``image``: a mask
        off by a pixel or two then mixes little of one side into the other. ``within`` (H, W bool): only
        these pixels are learnt from (where the mask is known). False when too few pixels left nothing learnt."""
        m8 = mask.astype(np.uint8)
        near = cv2.dilate(m8, np.ones((2 * gap_px + 1,) * 2, np.uint8)) > 0
        ring = (cv2.dilate(m8, np.ones((2 * band_px + 1,) * 2, np.uint8)) > 0) & ~near
        inner = cv2.erode(m8, np.ones((3, 3), np.uint8)) > 0
        if within is not None:
            ring &= within
            inner &= within
        return self.colors[group].update(image[inner], image[ring], rate)

    def measure(self, image: np.ndarray, contours: Mapping[str, Contour], model: PoseModel,
                prior_cov: np.ndarray) -> dict[str, RegionResult]:
        """Gauss-Newton steps of the parameters of ``model`` (the parts it places, each with its contour in
        ``contours``) against ``image`` (H, W, 3 uint8 RGB), regularised by the prediction's covariance
        ``prior_cov`` (n x n, ``model``'s parameters): a MAP estimate, so a direction the lines do not see
        stays at the prediction. Per part: its pose and covariance (the lines' information propagated
        through the model). Parts whose instrument has no colour model yet, or with too few valid lines
        in all, get nothing."""
        cfg = self.cfg
        names = [n for n in model.parts if n in contours and self.colors[self.groups[n]].ready]
        if sum(len(contours[n].xyz) for n in names) < cfg.min_points:
            return {}
        info0 = np.linalg.inv(prior_cov)
        x = np.zeros(model.size)  # the MAP steps from the prediction
        for scale in cfg.scales:
            poses, D = model.poses(x), model.derivatives(x)
            rows, res, wts = [], [], []
            for n in names:
                c = contours[n]
                uv, Jp = project_pose_jacobian(self.K, *poses[n], c.xyz)
                mu, var, valid, _ = self._lines(image, self.colors[self.groups[n]], uv, c.normal, scale)
                valid &= _in_front(poses[n], c.xyz)
                rows.append(np.einsum("ni,nij,jk->nk", c.normal, Jp, D[n])[valid])
                res.append((mu - c.edge_offset)[valid])
                wts.append(1.0 / np.maximum(var[valid], cfg.var_floor_px))
            a, r, w = np.concatenate(rows), np.concatenate(res), np.concatenate(wts)
            if len(r) < cfg.min_points:
                return {}
            # Cauchy weights: a line that found another edge (an untracked tool crossing, the image's
            # vignette) far from where the others put the contour loses its pull
            w = w / (1.0 + (r / (cfg.robust_px * scale)) ** 2)
            H = (a * w[:, None]).T @ a / cfg.inflate
            g_lines = a.T @ (w * r) / cfg.inflate
            try:
                x = x + np.linalg.solve(H + info0, g_lines - info0 @ x)
            except np.linalg.LinAlgError:
                return {}  # numerically singular (lines of wildly different weights): no measurement this frame
        model.solution = x
        # The pose reported is the MAP estimate, its covariance the lines' alone: where the lines pin a
        # direction (what the filter fuses, RegionResult.observed) their information dwarfs the
        # prediction's and counting the prediction twice changes little; the lines' own solution instead
        # (x_lin + H^-1 g_lines in those directions) held the seeded wrist of tests/test_track.py 9-11 deg
        # off against 6-8 with the MAP. A direction the lines do not see (a cylinder's roll) gets a huge
        # variance, never pinv's zero.
        caps = np.r_[np.full(3, cfg.max_std_mm), np.full(model.size - 3, np.radians(cfg.max_std_deg))]
        ev, V = np.linalg.eigh(0.5 * (H + H.T) * np.outer(caps, caps))
        cov_x = np.outer(caps, caps) * (V @ np.diag(1.0 / np.maximum(ev, 1e-9)) @ V.T)
        model.solution_cov = cov_x
        poses, D = model.poses(x), model.derivatives(x)
        out = {}
        for n in names:
            c = contours[n]
            uv, _ = project_pose_jacobian(self.K, *poses[n], c.xyz)
            _, _, valid, pf = self._lines(image, self.colors[self.groups[n]], uv, c.normal, cfg.scales[-1])
            valid &= _in_front(poses[n], c.xyz)
            # sample s = 0 is the last pixel inside the outline
            agree = np.where(self._s[None, :] <= 0, pf > 0.5, pf < 0.5)[valid]
            cov = D[n] @ cov_x @ D[n].T
            out[n] = RegionResult(*poses[n], 0.5 * (cov + cov.T), int(valid.sum()),
                                  float(agree.mean()) if agree.size else 0.0)
        return out


class PoseModel:
    """Part poses as a function of a parameter vector ``x`` (steps from a prediction): :meth:`poses` and
    :meth:`derivatives` (per part, d(part pose step: dt camera mm, dtheta body rad) / dx, 6 x ``size``).
    The base class is one free rigid part, ``x`` its own pose step."""

    size = 6

    def __init__(self, name: str, R: np.ndarray, t: np.ndarray):
        self.parts = [name]
        self.solution: np.ndarray | None = None  # set by RegionTracker.measure, with the lines' covariance:
        self.solution_cov: np.ndarray | None = None
        self.R0, self.t0 = np.asarray(R, np.float64), np.asarray(t, np.float64)

    def poses(self, x: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        return {self.parts[0]: (self.R0 @ so3_exp(x[3:6]), self.t0 + x[:3])}

    def derivatives(self, x: np.ndarray) -> dict[str, np.ndarray]:
        D = np.eye(6)
        D[3:, 3:] = so3_right_jacobian(x[3:6])
        return {self.parts[0]: D}


class ArticulatedModel(PoseModel):
    """The parts of one instrument through its forward kinematics: ``x`` = the root part's pose step (6)
    and steps of the joints that move parts relative to it (e.g. pitch, yaw, opening; the roll is the
    root's own rotation). Silhouettes then constrain what one part alone cannot: the wrist's outline pins
    the shaft's roll and its position along its axis."""

    def __init__(self, instrument: Instrument, names: Mapping[str, str], R_root: np.ndarray, t_root: np.ndarray,
                 q0: JointState):
        """``names``: the instrument's part -> the name its pose goes by (the root part among them);
        (``R_root``, ``t_root``): the root's predicted pose; ``q0``: the predicted joints."""
        root = instrument.chain.order[0]
        super().__init__(names[root], R_root, t_root)
        self.instrument = instrument
        self.chain_names = [root] + [p for p in names if p != root]
        self.parts = [names[p] for p in self.chain_names]
        in_root = set(instrument.chain.joints[root].coefficients)
        self.joints = [k for k, n in enumerate(JOINT_NAMES) if n not in in_root
                       and any(n in instrument.chain.joints[p].coefficients for p in self.chain_names)]
        self.size = 6 + len(self.joints)
        self.q0 = np.array([getattr(q0, n) for n in JOINT_NAMES])
        lim = instrument.limits.ranges
        self.lo = np.array([lim.get(n, (-np.inf, np.inf))[0] for n in JOINT_NAMES])
        self.hi = np.array([lim.get(n, (-np.inf, np.inf))[1] for n in JOINT_NAMES])

    def joint_state(self, x: np.ndarray) -> JointState:
        q = self.q0.copy()
        q[self.joints] += x[6:]
        return JointState(*np.clip(q, self.lo, self.hi))

    def poses(self, x: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        root_T = se3(self.R0 @ so3_exp(x[3:6]), self.t0 + x[:3])
        F = self.instrument.forward(np.eye(4), self.joint_state(x))
        to_root = se3_inv(F[self.chain_names[0]])
        out = {}
        for p, n in zip(self.chain_names, self.parts):
            T = root_T @ to_root @ F[p]
            out[n] = (T[:3, :3], T[:3, 3])
        return out

    def derivatives(self, x: np.ndarray) -> dict[str, np.ndarray]:
        """Exact for the root's pose and, in closed form, for the joints: a joint step turns every part
        below the joint about the joint's axis at its origin (a joint at a limit is differentiated as if
        free)."""
        R_root = self.R0 @ so3_exp(x[3:6])
        root_T = se3(R_root, self.t0 + x[:3])
        chain = self.instrument.chain
        F = self.instrument.forward(np.eye(4), self.joint_state(x))
        to_root = root_T @ se3_inv(F[self.chain_names[0]])
        cam = {p: to_root @ T for p, T in F.items()}  # every part's pose in the camera
        Jr = so3_right_jacobian(x[3:6])  # d(root body rotation) / d(its parameters) away from x = 0
        t_root = cam[self.chain_names[0]][:3, 3]
        D = {}
        for p, n in zip(self.chain_names, self.parts):
            R, t = cam[p][:3, :3], cam[p][:3, 3]
            d = np.zeros((6, self.size))
            d[:3, :3] = np.eye(3)  # a root translation step moves every part with it (camera frame)
            d[3:, 3:6] = R.T @ R_root @ Jr  # a root body rotation, in this part's body frame
            # and the part's lever arm: t_n = t_root + R_root r  ->  dt_n = -R_root [r]_x dtheta
            d[:3, 3:6] = -R_root @ skew(R_root.T @ (t - t_root)) @ Jr
            a = p
            while a is not None and a != self.chain_names[0]:
                joint = chain.joints[a]
                axis = np.asarray(joint.axis, np.float64) / np.linalg.norm(joint.axis)
                w_cam = cam[a][:3, :3] @ axis  # the joint's axis in the camera, through its origin
                for col, k in enumerate(self.joints):
                    c = joint.coefficients.get(JOINT_NAMES[k], 0.0)
                    if c:
                        d[:3, 6 + col] += c * np.cross(w_cam, t - cam[a][:3, 3])
                        d[3:, 6 + col] += c * (R.T @ w_cam)
                a = joint.parent
            D[n] = d
        return D
