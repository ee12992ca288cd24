"""Model-based optical-flow tracking of one rigid part between frames.

At a known pose, :func:`visible_points` picks pixels whose 3D model points are known: surface samples of
the part are projected, a coarse z-buffer over all parts of the instrument (so a jaw hides the wrist
behind it) keeps the visible ones, samples on the silhouette border are dropped (their pixels mix part
and background, which move differently), and among the rest the most textured (Shi-Tomasi response of
the frame) are kept, spread over the part. Between frames those pixels are followed by pyramidal
Lucas-Kanade with a forward-backward check (:func:`track_points`); PnP on the surviving 2D-3D pairs, from
the predicted pose, is the measurement (:func:`pnp_measurement`), with a covariance from its Jacobian so
a degenerate view (a bare cylinder's roll, few points) weighs little in the Kalman filter.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import trimesh

from surftrack.geometry import project_points, project_pose_jacobian, rotation_angle_deg, se3, transform_points

LK_PARAMS = dict(winSize=(21, 21), maxLevel=3,
                 criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))


@dataclass(frozen=True)
class SurfaceSamples:
    """Points (N, 3) mm and outward unit normals (N, 3) on a part's surface, in the part frame."""

    points: np.ndarray
    normals: np.ndarray

    @classmethod
    def of_mesh(cls, mesh: trimesh.Trimesh, n: int = 4000, seed: int = 0) -> SurfaceSamples:
        """``n`` area-uniform samples (deterministic for ``seed``)."""
        pts, face = trimesh.sample.sample_surface(mesh, n, seed=seed)
        return cls(np.asarray(pts, np.float64), np.asarray(mesh.face_normals[face], np.float64))


@dataclass
class TrackPoints:
    """Pixels (N, 2) being tracked and the model points (N, 3, mm, part frame) they show."""

    uv: np.ndarray
    xyz: np.ndarray

    def __len__(self) -> int:
        return len(self.uv)

    def subset(self, keep: np.ndarray) -> TrackPoints:
        return TrackPoints(self.uv[keep], self.xyz[keep])


def _pixels(K: np.ndarray, R: np.ndarray, t: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of model points ``pts`` (N, 3, mm) at the model-to-camera pose (R, t)."""
    return project_points(K, transform_points(se3(R, t), pts))


def visible_points(gray: np.ndarray, K: np.ndarray, samples: dict[str, SurfaceSamples],
                   poses: dict[str, tuple[np.ndarray, np.ndarray]], part: str, max_points: int = 80,
                   cell_px: int = 2, depth_tol_mm: float = 1.0, spread_px: float | None = None,
                   min_quality: float = 1e-4) -> TrackPoints:
    """Trackable pixels of ``part`` at ``poses[part]`` with their model points.

    ``samples`` and ``poses`` hold every posed part of the instrument (they occlude each other). A sample
    is kept when it faces the camera, lies in the image, is within ``depth_tol_mm`` of the nearest sample
    in its ``cell_px`` cell, and its cell is inside the part's silhouette (no neighbouring cell belongs
    to another part, at most 2 are empty).
    Among those, one per ``spread_px`` cell with the strongest Shi-Tomasi corner response is kept, best
    first, up to ``max_points``; responses below ``min_quality`` x the best are dropped. ``spread_px``
    defaults to the spacing that would fit ``max_points`` over the part's interior (3 to 12 px)."""
    H, W = gray.shape
    gh, gw = (H + cell_px - 1) // cell_px, (W + cell_px - 1) // cell_px
    names = list(poses)
    all_uv, all_z, all_pid, all_idx = [], [], [], []
    for k, name in enumerate(names):
        R, t = poses[name]
        s = samples[name]
        X = transform_points(se3(R, t), s.points)
        uv, z = project_points(K, X), X[:, 2]
        facing = ((s.normals @ R.T) * X).sum(1) < 0
        ok = facing & (z > 1e-3) & np.all(np.isfinite(uv), 1)
        ok &= (uv[:, 0] >= 0) & (uv[:, 0] < W - 1) & (uv[:, 1] >= 0) & (uv[:, 1] < H - 1)
        idx = np.nonzero(ok)[0]
        all_uv.append(uv[idx])
        all_z.append(z[idx])
        all_pid.append(np.full(len(idx), k))
        all_idx.append(idx)
    uv, z, pid, idx = (np.concatenate(a) for a in (all_uv, all_z, all_pid, all_idx))
    target = names.index(part)
    if not np.any(pid == target):
        return TrackPoints(np.zeros((0, 2)), np.zeros((0, 3)))
    cell = (uv[:, 1] // cell_px).astype(np.int64) * gw + (uv[:, 0] // cell_px).astype(np.int64)
    # nearest sample per cell: sort by (cell, depth), the first of each cell run
    order = np.lexsort((z, cell))
    head = order[np.r_[True, cell[order][1:] != cell[order][:-1]]]
    zmin = np.full(gh * gw, np.inf)
    zmin[cell[head]] = z[head]
    front = z <= zmin[cell] + depth_tol_mm
    owner = np.full(gh * gw, -1)  # the part of each cell's nearest sample (-1 = empty)
    owner[cell[head]] = pid[head]
    owner = owner.reshape(gh, gw)
    # Interior cells: no neighbour owned by another part and at most 2 empty neighbours (a sampling hole
    # inside the part leaves isolated empty cells; the background borders a cell with 3 or more).
    pad = np.pad(owner, 1, constant_values=-1)
    other = np.zeros_like(owner, bool)
    empty = np.zeros_like(owner)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            nb = pad[1 + dy:1 + dy + gh, 1 + dx:1 + dx + gw]
            other |= (nb != owner) & (nb >= 0)
            empty += nb < 0
    interior = (owner >= 0) & ~other & (empty <= 2)
    keep = front & (pid == target) & interior.reshape(-1)[cell]
    if not np.any(keep):
        return TrackPoints(np.zeros((0, 2)), np.zeros((0, 3)))
    uv_k, idx_k = uv[keep], idx[keep]
    px = np.round(uv_k).astype(int)
    x0, y0 = np.maximum(px.min(0) - 4, 0)
    x1, y1 = px.max(0) + 5
    resp = cv2.cornerMinEigenVal(np.ascontiguousarray(gray[y0:y1, x0:x1]), 5, 3)  # only around the part
    q = resp[px[:, 1] - y0, px[:, 0] - x0]
    best_q = float(q.max())
    good = q >= min_quality * max(best_q, 1e-12)
    uv_k, idx_k, q = uv_k[good], idx_k[good], q[good]
    # strongest response per spread cell, best first
    if spread_px is None:
        area = len(np.unique(cell[keep])) * cell_px**2
        spread_px = float(np.clip(np.sqrt(area / max_points), 3.0, 12.0))
    sc = (uv_k[:, 1] // spread_px).astype(np.int64) * (W // spread_px + 1) + (uv_k[:, 0] // spread_px).astype(np.int64)
    order = np.lexsort((-q, sc))
    first = np.ones(len(order), bool)
    first[1:] = sc[order][1:] != sc[order][:-1]
    chosen = order[first]
    chosen = chosen[np.argsort(-q[chosen])][:max_points]
    return TrackPoints(uv_k[chosen].astype(np.float32).astype(np.float64), samples[part].points[idx_k[chosen]])


def track_points(prev_gray: np.ndarray, gray: np.ndarray, pts: TrackPoints, max_fb_px: float = 1.0,
                 margin_px: int = 64) -> TrackPoints:
    """``pts`` followed from ``prev_gray`` to ``gray`` by pyramidal LK; points lost, leaving the image or
    failing the forward-backward check (round trip error > ``max_fb_px``) are dropped. LK runs on the
    region around the points grown by ``margin_px`` (motion up to about that far is followed), so its
    pyramids cost what the parts cover, not the whole frame."""
    if len(pts) == 0:
        return pts
    H, W = gray.shape
    x0, y0 = np.maximum(np.floor(pts.uv.min(0)).astype(int) - margin_px, 0)
    x1, y1 = np.minimum(np.ceil(pts.uv.max(0)).astype(int) + margin_px + 1, (W, H))
    a, b = prev_gray[y0:y1, x0:x1], gray[y0:y1, x0:x1]
    off = np.array([x0, y0], np.float32)
    p0 = (pts.uv.astype(np.float32) - off).reshape(-1, 1, 2)
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(a, b, p0, None, **LK_PARAMS)
    p0b, st2, _ = cv2.calcOpticalFlowPyrLK(b, a, p1, None, **LK_PARAMS)
    fb = np.linalg.norm((p0b - p0).reshape(-1, 2), axis=1)
    uv = p1.reshape(-1, 2).astype(np.float64) + off
    ok = (st1.reshape(-1) == 1) & (st2.reshape(-1) == 1) & (fb < max_fb_px)
    ok &= (uv[:, 0] >= 0) & (uv[:, 0] <= W - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= H - 1)
    return TrackPoints(uv[ok], pts.xyz[ok])


@dataclass
class PnPResult:
    """A pose measurement from tracked points: pose, covariance (6x6: position mm^2 then body rotation
    rad^2, the Kalman filter's order), inlier mask, inlier ratio and RMS reprojection error (px)."""

    R: np.ndarray
    t: np.ndarray
    cov: np.ndarray
    inliers: np.ndarray
    inlier_ratio: float
    rms_px: float


def pnp_measurement(pts: TrackPoints, K: np.ndarray, R0: np.ndarray, t0: np.ndarray, inlier_px: float = 3.0,
                    min_points: int = 6, noise_floor_px: float = 0.5) -> PnPResult | None:
    """Pose of the part from tracked 2D-3D pairs, starting at (R0, t0) (the predicted pose): an iterative
    PnP, then again on the pairs within ``inlier_px``. None when fewer than ``min_points`` pairs (or
    inliers) remain or PnP fails. The covariance is ``sigma^2 (J^T J)^-1`` with sigma the inliers' RMS
    error (at least ``noise_floor_px``)."""
    if len(pts) < min_points:
        return None
    obj = pts.xyz.astype(np.float64)
    img = pts.uv.astype(np.float64)
    rvec, tvec = cv2.Rodrigues(np.asarray(R0, np.float64))[0], np.asarray(t0, np.float64).reshape(3, 1).copy()
    inl = np.ones(len(obj), bool)
    for _ in range(2):
        ok, rvec, tvec = cv2.solvePnP(obj[inl], img[inl], K, None, rvec, tvec, useExtrinsicGuess=True,
                                      flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok or not np.all(np.isfinite(tvec)) or tvec[2, 0] <= 0:
            return None
        R, t = cv2.Rodrigues(rvec)[0], tvec.reshape(3)
        uv = _pixels(K, R, t, obj)
        err = np.linalg.norm(uv - img, axis=1)
        inl = err < inlier_px
        if inl.sum() < min_points:
            return None
    rms = float(np.sqrt(np.mean(err[inl] ** 2)))
    J = project_pose_jacobian(K, R, t, obj[inl])[1].reshape(-1, 6)
    sigma = max(rms, noise_floor_px)
    info = J.T @ J / sigma**2
    # Invert through the eigen-decomposition with a floor on the information: a direction the points do
    # not constrain (a bare cylinder's roll) gets a huge variance, never pinv's zero.
    w, V = np.linalg.eigh(0.5 * (info + info.T))
    cov = V @ np.diag(1.0 / np.maximum(w, 1e-6)) @ V.T
    return PnPResult(R, t, 0.5 * (cov + cov.T), inl, float(inl.mean()), rms)


def pose_distance(R_a: np.ndarray, t_a: np.ndarray, R_b: np.ndarray, t_b: np.ndarray) -> tuple[float, float]:
    """(rotation angle deg, translation distance mm) between two poses."""
    return float(rotation_angle_deg(R_a, R_b)), float(np.linalg.norm(t_a - t_b))
