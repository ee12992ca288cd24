"""Tracking results drawn over the video frames, and the annotated video written to an MP4.

* :func:`project_axes` gives the pixel positions of a part's origin and axis tips (for drawing, and for
  MCAP image annotations).
* :func:`mesh_outline` gives the silhouette contour(s) of a posed mesh in pixels.
* :func:`draw_overlay` draws, for every :class:`PartOverlay`, the mesh outline coloured by tracking
  status, the part's axes (x red, y green, z blue), its detection box and a label, plus a corner legend
  with the time and every part's status.
* :class:`OverlayWriter` draws each frame and encodes it to H.264 through
  :class:`surftrack.io.video.VideoWriter`.

Conventions: OpenCV camera axes and pixel coordinates (pixel centres at integers), millimetres, poses
model-to-camera (``p_cam = R @ p_model + t``), frames uint8 RGB (H, W, 3). Geometry nearer the camera than
``near_mm`` (default 1 mm) is clipped away: it cannot be projected sensibly.

Silhouettes are found without rasterising every triangle: the outline of the union of the projected
triangles lies on the projections of the mesh's contour edges (one face of the edge turned towards the
camera, the other away), its boundary and non-manifold edges, and its cross-section with the near plane.
Those few segments are drawn into a canvas covering the whole outline, and everything not reached by a
flood fill from the canvas border is inside. When the outline would need a canvas much larger than the
image (a long part reaching far outside the view), the clipped triangles are filled one by one instead.
"""

from __future__ import annotations

import hashlib
import math
import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from surftrack.geometry import project_points, se3, transform_points
from surftrack.io.video import VideoWriter
from surftrack.track.status import Status

__all__ = [
    "AXIS_COLORS", "NEAR_MM", "OverlayWriter", "PartOverlay", "STATUS_COLORS", "draw_overlay",
    "mesh_outline", "project_axes",
]

NEAR_MM = 1.0
# RGB, also the MCAP annotations' colours; "lost" colours only the label and the legend line: a lost part
# gets no outline and no axes.
STATUS_COLORS: dict[Status, tuple[int, int, int]] = {
    Status.INIT: (255, 150, 0),
    Status.KEYFRAME: (0, 230, 255),
    Status.TRACKING: (60, 255, 60),
    Status.PREDICTED: (255, 230, 0),
    Status.LOST: (255, 70, 70),
}
AXIS_COLORS = ((255, 40, 40), (40, 230, 40), (40, 110, 255))  # x, y, z (RGB)
BOX_COLOR = (170, 170, 170)

_FONT = cv2.FONT_HERSHEY_SIMPLEX
_FONT_SCALE = 0.45
_LINE_H = 16
_SHIFT = 4  # fixed-point bits for sub-pixel drawing
_ONE = 1 << _SHIFT
_MAX_CANVAS_IMAGES = 4.0  # outline canvas at most this many image areas, else fill triangles instead
_GUARD_PX = 1e6  # triangles reaching beyond this are clipped to the image before filling (int32 safety)
_VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".mkv")


# --------------------------------------------------------------------------------------------- checks


def _check_K(K) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1.0:
        raise ValueError(f"K must be a finite 3x3 intrinsic matrix with fx, fy > 0 and K[2,2] = 1, got {K.tolist()}")
    return K


def _check_R(R) -> np.ndarray:
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise ValueError(f"R must be a finite 3x3 rotation matrix, got shape {R.shape}")
    return R


def _check_t(t_mm) -> np.ndarray:
    t = np.asarray(t_mm, dtype=np.float64).reshape(-1)
    if t.shape != (3,) or not np.all(np.isfinite(t)):
        raise ValueError(f"t must be 3 finite values (mm), got {t_mm!r}")
    return t


def _check_mesh(vertices_mm, faces) -> tuple[np.ndarray, np.ndarray]:
    V = np.asarray(vertices_mm, dtype=np.float64)
    F = np.asarray(faces)
    if V.ndim != 2 or V.shape[1] != 3 or not np.all(np.isfinite(V)):
        raise ValueError(f"vertices must be finite (N, 3) millimetres, got shape {V.shape}")
    if F.ndim != 2 or F.shape[1] != 3 or not (F.size == 0 or np.issubdtype(F.dtype, np.integer)):
        raise ValueError(f"faces must be (M, 3) integer vertex indices, got {F.dtype} {F.shape}")
    if F.size and (F.min() < 0 or F.max() >= len(V)):
        raise ValueError(f"face indices must lie in [0, {len(V)}), got [{F.min()}, {F.max()}]")
    return V, F.astype(np.int64, copy=False)


def _check_size(image_size) -> tuple[int, int]:
    W, H = (int(s) for s in image_size)
    if W <= 0 or H <= 0:
        raise ValueError(f"image_size must be a positive (width, height), got {image_size!r}")
    return W, H


def _check_frame(frame_rgb) -> np.ndarray:
    img = np.asarray(frame_rgb)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"frame must be uint8 RGB (H, W, 3), got {img.dtype} {img.shape}")
    return img


# --------------------------------------------------------------------------------------------- projection


def project_axes(K: np.ndarray, R: np.ndarray, t_mm: np.ndarray, length_mm: float, *,
                 near_mm: float = NEAR_MM) -> np.ndarray:
    """Pixel positions (4, 2) of a part's origin and of the tips of its x, y and z axes.

    The axes are ``length_mm`` long in the part frame, posed by the model-to-camera ``R`` (3, 3) and
    ``t_mm`` (3,). A point nearer the camera than ``near_mm`` (or behind it) has no sensible projection:
    its row is NaN.
    """
    K, R, t = _check_K(K), _check_R(R), _check_t(t_mm)
    if not (math.isfinite(length_mm) and length_mm > 0):
        raise ValueError(f"length_mm must be positive, got {length_mm!r}")
    p_cam = transform_points(se3(R, t), np.vstack([np.zeros(3), float(length_mm) * np.eye(3)]))
    uv = project_points(K, p_cam)
    uv[p_cam[:, 2] < near_mm] = np.nan
    return uv


# --------------------------------------------------------------------------------------------- silhouettes


@dataclass(frozen=True)
class _Topology:
    """Undirected edges of a triangle mesh and the faces on either side, for contour-edge tests."""

    edges: np.ndarray     # (E, 2) vertex indices
    face_a: np.ndarray    # (E,) a face holding the edge
    face_b: np.ndarray    # (E,) the other face (face_a again where there is none)
    always: np.ndarray    # (E,) boundary or non-manifold edge: always part of the outline candidates
    flip: np.ndarray      # (E,) the two faces are wound inconsistently across this edge
    closed: bool          # every edge has exactly two consistently wound faces


_TOPOLOGY_CACHE: OrderedDict[tuple, _Topology] = OrderedDict()
_TOPOLOGY_LOCK = threading.Lock()
_TOPOLOGY_CACHE_SIZE = 64


def _topology(F: np.ndarray, n_vertices: int) -> _Topology:
    """Edge topology of faces F (M, 3), cached by content: the same mesh is outlined every frame."""
    key = (n_vertices, F.shape[0], hashlib.blake2b(np.ascontiguousarray(F).tobytes(), digest_size=16).digest())
    with _TOPOLOGY_LOCK:
        topo = _TOPOLOGY_CACHE.get(key)
        if topo is not None:
            _TOPOLOGY_CACHE.move_to_end(key)
            return topo
    half = F[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    face = np.repeat(np.arange(len(F)), 3)
    lo, hi = half.min(axis=1), half.max(axis=1)
    order = np.argsort(lo * n_vertices + hi, kind="stable")
    k = (lo * n_vertices + hi)[order]
    starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
    counts = np.diff(np.r_[starts, len(k)])
    first = order[starts]
    second = order[np.minimum(starts + 1, len(k) - 1)]
    two = counts == 2
    forward = half[:, 0] < half[:, 1]
    # consistently wound neighbours traverse their shared edge in opposite directions
    flip = two & (forward[first] == forward[second])
    topo = _Topology(edges=np.stack([lo[first], hi[first]], axis=1), face_a=face[first],
                     face_b=np.where(two, face[second], face[first]), always=~two, flip=flip,
                     closed=bool(two.all() and not flip.any()))
    with _TOPOLOGY_LOCK:
        _TOPOLOGY_CACHE[key] = topo
        while len(_TOPOLOGY_CACHE) > _TOPOLOGY_CACHE_SIZE:
            _TOPOLOGY_CACHE.popitem(last=False)
    return topo


def _odd_vertex_first(tri: np.ndarray, odd: np.ndarray) -> np.ndarray:
    """Triangles (T, 3, 3) rotated so that the vertex that is alone on its side (``odd`` (T, 3)) comes first."""
    first = np.argmax(odd, axis=1)
    idx = (first[:, None] + np.arange(3)) % 3
    return np.take_along_axis(tri, idx[:, :, None], axis=1)


def _on_near_plane(a: np.ndarray, b: np.ndarray, near: float) -> np.ndarray:
    """Where the segments a-b (..., 3) cross the plane z = near (each must cross it)."""
    s = (near - a[..., 2:3]) / (b[..., 2:3] - a[..., 2:3])
    return a + s * (b - a)


def _split_by_near_plane(tri: np.ndarray, behind: np.ndarray, near: float) -> tuple[np.ndarray, np.ndarray]:
    """Triangles (T, 3, 3) each crossing the near plane -> (their parts in front, as triangles (T', 3, 3);
    their cross-sections with the plane, as segments (T, 2, 3))."""
    one_behind = behind.sum(axis=1) == 1
    odd = np.where(one_behind[:, None], behind, ~behind)
    r = _odd_vertex_first(tri, odd)
    pab = _on_near_plane(r[:, 0], r[:, 1], near)
    pac = _on_near_plane(r[:, 0], r[:, 2], near)
    # one vertex behind leaves a quad (B, C, pAC, pAB); two behind leave the triangle (A, pAB, pAC)
    q = one_behind
    parts = np.concatenate([
        np.stack([r[q, 1], r[q, 2], pac[q]], axis=1),
        np.stack([r[q, 1], pac[q], pab[q]], axis=1),
        np.stack([r[~q, 0], pab[~q], pac[~q]], axis=1),
    ])
    return parts, np.stack([pab, pac], axis=1)


def _outline_segments(P: np.ndarray, F: np.ndarray, topo: _Topology, near: float) -> np.ndarray:
    """Camera-frame segments (S, 2, 3), clipped to z >= near, on which the silhouette's outline lies."""
    tri = P[F]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    facing = np.sign(np.einsum("ij,ij->i", normal, tri[:, 0]))
    both = facing[topo.face_a] * facing[topo.face_b]
    contour = topo.always | np.where(topo.flip, both >= 0, both <= 0)
    e = topo.edges[contour]
    a, b = P[e[:, 0]], P[e[:, 1]]
    a_behind, b_behind = a[:, 2] < near, b[:, 2] < near
    keep = ~(a_behind & b_behind)
    a, b, a_behind, b_behind = a[keep], b[keep], a_behind[keep], b_behind[keep]
    crossing = a_behind | b_behind
    if crossing.any():
        x = _on_near_plane(a[crossing], b[crossing], near)
        a[crossing] = np.where(a_behind[crossing, None], x, a[crossing])
        b[crossing] = np.where(b_behind[crossing, None], x, b[crossing])
    segments = [np.stack([a, b], axis=1)]
    behind = tri[:, :, 2] < near
    cut = behind.any(axis=1) & ~behind.all(axis=1)
    if cut.any():
        segments.append(_split_by_near_plane(tri[cut], behind[cut], near)[1])
    return np.concatenate(segments)


def _mask_from_outline(uv: np.ndarray, W: int, H: int) -> tuple[np.ndarray, int, int] | None:
    """Silhouette inside the image from outline segments in pixels (S, 2, 2), by flood-filling the outside;
    None when the canvas holding the whole outline would be too large."""
    pts = uv.reshape(-1, 2)
    x0, y0 = np.floor(pts.min(axis=0)).astype(np.int64) - 2
    x1, y1 = np.ceil(pts.max(axis=0)).astype(np.int64) + 2
    cw, ch = int(x1 - x0 + 1), int(y1 - y0 + 1)
    if cw * ch > _MAX_CANVAS_IMAGES * W * H:
        return None
    canvas = np.zeros((ch, cw), np.uint8)
    fixed = np.round((uv - (x0, y0)) * _ONE).astype(np.int32)
    # 8-connected lines are walls for a 4-connected flood fill
    cv2.polylines(canvas, list(fixed), False, 255, 1, cv2.LINE_8, _SHIFT)
    cv2.floodFill(canvas, None, (0, 0), 128, flags=4)
    ix0, iy0, ix1, iy1 = max(int(x0), 0), max(int(y0), 0), min(int(x1) + 1, W), min(int(y1) + 1, H)
    if ix1 <= ix0 or iy1 <= iy0:
        return np.zeros((0, 0), np.uint8), 0, 0
    crop = canvas[iy0 - y0:iy1 - y0, ix0 - x0:ix1 - x0]
    return (crop != 128).astype(np.uint8), ix0, iy0


def _clip_polygon(poly: np.ndarray, x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    """Sutherland-Hodgman clip of a convex polygon (N, 2) to the rectangle [x0, x1] x [y0, y1]."""
    for axis, bound, keep_below in ((0, x0, False), (0, x1, True), (1, y0, False), (1, y1, True)):
        if len(poly) == 0:
            break
        d = poly[:, axis] - bound
        inside = d <= 0 if keep_below else d >= 0
        out = []
        for i in range(len(poly)):
            j = (i + 1) % len(poly)
            if inside[i]:
                out.append(poly[i])
            if inside[i] != inside[j]:
                out.append(poly[i] + d[i] / (d[i] - d[j]) * (poly[j] - poly[i]))
        poly = np.array(out).reshape(-1, 2)
    return poly


def _mask_from_triangles(K: np.ndarray, P: np.ndarray, F: np.ndarray, topo: _Topology, W: int, H: int,
                         near: float) -> np.ndarray:
    """Silhouette (H, W) by filling every projected triangle in front of the near plane (slow path)."""
    tri = P[F]
    behind = tri[:, :, 2] < near
    front = ~behind.any(axis=1)
    cut = ~front & ~behind.all(axis=1)
    tris = tri[front]
    if topo.closed and not cut.any():
        # every ray through a closed surface crosses faces of both orientations: one orientation covers all
        normal = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
        tris = tris[np.einsum("ij,ij->i", normal, tris[:, 0]) <= 0]
    if cut.any():
        tris = np.concatenate([tris, _split_by_near_plane(tri[cut], behind[cut], near)[0]])
    uv = project_points(K, tris)
    lo, hi = uv.min(axis=1), uv.max(axis=1)
    visible = (hi[:, 0] >= -1) & (lo[:, 0] <= W) & (hi[:, 1] >= -1) & (lo[:, 1] <= H)
    uv, lo, hi = uv[visible], lo[visible], hi[visible]
    mask = np.zeros((H, W), np.uint8)
    huge = (np.abs(lo) > _GUARD_PX).any(axis=1) | (np.abs(hi) > _GUARD_PX).any(axis=1)
    for t in np.round(uv[~huge] * _ONE).astype(np.int32):
        cv2.fillConvexPoly(mask, t, 1, cv2.LINE_8, _SHIFT)
    for t in uv[huge]:
        poly = _clip_polygon(t, -2.0, -2.0, W + 1.0, H + 1.0)
        if len(poly) >= 3:
            cv2.fillConvexPoly(mask, np.round(poly * _ONE).astype(np.int32), 1, cv2.LINE_8, _SHIFT)
    return mask


def mesh_outline(K: np.ndarray, R: np.ndarray, t_mm: np.ndarray, vertices_mm: np.ndarray, faces: np.ndarray,
                 image_size: tuple[int, int], *, near_mm: float = NEAR_MM) -> list[np.ndarray]:
    """Outer contour(s) of the projected silhouette of a posed mesh, in image pixels.

    ``vertices_mm`` (N, 3) and ``faces`` (M, 3) in the part frame are posed by the model-to-camera ``R``,
    ``t_mm``; ``image_size`` = (width, height). Returns one int32 array (P, 2) of pixel-centre (x, y)
    coordinates per connected silhouette region inside the image (holes not included; ``cv2.findContours``
    order and simplification), or ``[]`` when nothing is visible. Pixels the outline passes through count
    as inside, so the region may be up to about a pixel wider than one of pixel centres inside triangles.
    Geometry nearer than ``near_mm`` is clipped. Any triangle soup works; closed or consistently wound
    meshes are not required. The edge topology of ``faces`` is cached (by content), so outlining the same
    mesh every frame costs about 0.5-1.5 ms for 0.5-5k triangles at 640x512.
    """
    K, R, t = _check_K(K), _check_R(R), _check_t(t_mm)
    W, H = _check_size(image_size)
    V, F = _check_mesh(vertices_mm, faces)
    if len(F) == 0:
        return []
    P = transform_points(se3(R, t), V)
    if not (P[F, 2] >= near_mm).any():
        return []
    topo = _topology(F, len(V))
    segments = _outline_segments(P, F, topo, near_mm)
    found = _mask_from_outline(project_points(K, segments), W, H) if len(segments) else None
    if found is None:
        mask, x0, y0 = _mask_from_triangles(K, P, F, topo, W, H, near_mm), 0, 0
    else:
        mask, x0, y0 = found
    if mask.size == 0 or not mask.any():
        return []
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE, offset=(x0, y0))
    return [c.reshape(-1, 2) for c in contours]


# --------------------------------------------------------------------------------------------- drawing


@dataclass
class PartOverlay:
    """What the overlay shows of one part in one frame.

    ``status`` is a :class:`~surftrack.track.status.Status` (or its value); ``confidence`` in [0, 1]. ``R`` (3, 3) and ``t`` (3,) mm are the
    model-to-camera pose, both None when there is none. ``box`` = (x, y, w, h) is a pixel-EDGE box covering
    [x, x + w] x [y, y + h] (the full image is (0, 0, W, H)). ``mesh`` = (vertices mm (N, 3), faces (M, 3))
    in the part frame, for the outline (an object with ``.vertices`` and ``.faces``, such as a
    ``trimesh.Trimesh``, works too). Values are checked and converted to numpy on construction.
    """

    name: str
    status: str
    confidence: float
    R: np.ndarray | None = None
    t: np.ndarray | None = None
    box: tuple[float, float, float, float] | None = None
    mesh: tuple[np.ndarray, np.ndarray] | None = None
    axis_length_mm: float = 10.0

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"part name must be a non-empty string, got {self.name!r}")
        if self.status not in STATUS_COLORS:
            raise ValueError(f"part {self.name!r}: status must be one of {[str(x) for x in Status]}, "
                             f"got {self.status!r}")
        c = float(self.confidence)
        if not 0.0 <= c <= 1.0:
            raise ValueError(f"part {self.name!r}: confidence must lie in [0, 1], got {self.confidence!r}")
        self.confidence = c
        if (self.R is None) != (self.t is None):
            raise ValueError(f"part {self.name!r}: give both R and t, or neither")
        if self.R is not None:
            self.R, self.t = _check_R(self.R), _check_t(self.t)
        if self.box is not None:
            box = tuple(float(v) for v in self.box)
            if len(box) != 4 or not all(map(math.isfinite, box)) or box[2] < 0 or box[3] < 0:
                raise ValueError(f"part {self.name!r}: box must be finite (x, y, w, h) with w, h >= 0, "
                                 f"got {self.box!r}")
            self.box = box
        if self.mesh is not None:
            mesh = self.mesh
            if hasattr(mesh, "vertices") and hasattr(mesh, "faces"):  # e.g. a trimesh.Trimesh
                mesh = (mesh.vertices, mesh.faces)
            self.mesh = _check_mesh(*mesh)
        if not (math.isfinite(self.axis_length_mm) and self.axis_length_mm > 0):
            raise ValueError(f"part {self.name!r}: axis_length_mm must be positive, got {self.axis_length_mm!r}")

    @property
    def label(self) -> str:
        return f"{self.name} {self.status} {self.confidence:.2f}"

    @property
    def short_label(self) -> str:
        """The in-image label: the last dotted component of the name (the part) and the confidence; the
        legend carries the full label."""
        return f"{self.name.rsplit('.', 1)[-1]} {self.confidence:.2f}"


def _clip_segment(p: np.ndarray, q: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple | None:
    """Liang-Barsky clip of the 2D segment p-q to the box [lo, hi]; None when it lies outside."""
    d = q - p
    s0, s1 = 0.0, 1.0
    for k in range(2):
        for num, den in ((p[k] - lo[k], -d[k]), (hi[k] - p[k], d[k])):
            if den == 0:
                if num < 0:
                    return None
                continue
            s = num / den
            if den < 0:
                s0 = max(s0, s)
            else:
                s1 = min(s1, s)
    if s0 > s1:
        return None
    return p + s0 * d, p + s1 * d


def _fixed(p) -> tuple[int, int]:
    return int(round(p[0] * _ONE)), int(round(p[1] * _ONE))


def _draw_axes(img: np.ndarray, K: np.ndarray, part: PartOverlay) -> np.ndarray | None:
    """Draw the part's x, y, z axes; returns the origin's pixel (or None when it is not in front)."""
    H, W = img.shape[:2]
    o = part.t
    lo, hi = np.array([-W, -H], float), np.array([2.0 * W, 2.0 * H])
    for k in range(3):  # z last: it often points at the camera and should stay on top
        a, b = o, part.R[:, k] * part.axis_length_mm + o
        if a[2] < NEAR_MM and b[2] < NEAR_MM:
            continue
        if a[2] < NEAR_MM or b[2] < NEAR_MM:
            x = _on_near_plane(a, b, NEAR_MM)
            a, b = (x, b) if a[2] < NEAR_MM else (a, x)
        seg = _clip_segment(project_points(K, a), project_points(K, b), lo, hi)
        if seg is not None:
            cv2.line(img, _fixed(seg[0]), _fixed(seg[1]), AXIS_COLORS[k], 2, cv2.LINE_AA, _SHIFT)
    return project_points(K, o) if o[2] >= NEAR_MM else None


def _darken(img: np.ndarray, x0: int, y0: int, x1: int, y1: int) -> None:
    """Dim a rectangle (clipped to the image) so that text over it is legible on any tissue."""
    H, W = img.shape[:2]
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, W), min(y1, H)
    if x1 > x0 and y1 > y0:
        img[y0:y1, x0:x1] = (img[y0:y1, x0:x1] * 0.35).astype(np.uint8)


def _text(img: np.ndarray, text: str, org: tuple[int, int], color) -> None:
    cv2.putText(img, text, org, _FONT, _FONT_SCALE, color, 1, cv2.LINE_AA)


def _draw_label(img: np.ndarray, part: PartOverlay, anchor) -> None:
    """The part's label on a dimmed background whose bottom-left corner is ``anchor`` (moved inside the
    image where needed)."""
    H, W = img.shape[:2]
    if not np.all(np.isfinite(anchor)):
        return
    (tw, th), base = cv2.getTextSize(part.short_label, _FONT, _FONT_SCALE, 1)
    x = int(np.clip(anchor[0] + 2, 2, max(W - tw - 2, 2)))
    y = int(np.clip(anchor[1] - base - 1, th + 2, max(H - base - 2, th + 2)))  # baseline
    _darken(img, x - 2, y - th - 2, x + tw + 2, y + base + 1)
    _text(img, part.short_label, (x, y), STATUS_COLORS[part.status])


def _draw_part(img: np.ndarray, K: np.ndarray, part: PartOverlay) -> None:
    H, W = img.shape[:2]
    color = STATUS_COLORS[part.status]
    anchor = None
    if part.box is not None:
        x, y, w, h = part.box
        # pixel-edge box -> the pixel-centre coordinates of its edges
        cv2.rectangle(img, _fixed((x - 0.5, y - 0.5)), _fixed((x + w - 0.5, y + h - 0.5)), BOX_COLOR, 1,
                      cv2.LINE_AA, _SHIFT)
        anchor = (x - 0.5, y - 2.0)  # just above the box's top edge
    if part.R is not None and part.status != "lost":
        if part.mesh is not None:
            contours = mesh_outline(K, part.R, part.t, part.mesh[0], part.mesh[1], (W, H))
            if contours:
                # pixel-step contours simplified: far fewer anti-aliased segments, no visible change
                curves = [cv2.approxPolyDP(c.reshape(-1, 1, 2).astype(np.int32), 0.7, True) for c in contours]
                cv2.polylines(img, curves, True, color, 2, cv2.LINE_AA)
        origin = _draw_axes(img, K, part)
        if anchor is None and origin is not None and 0 <= origin[0] < W and 0 <= origin[1] < H:
            anchor = (origin[0] + 8, origin[1] - 8)
    if anchor is not None:
        _draw_label(img, part, anchor)


def _draw_legend(img: np.ndarray, parts: Sequence[PartOverlay], time_s: float | None) -> None:
    """Top-left panel: the time, then one line per part in its status colour."""
    lines = [] if time_s is None else [(f"t = {time_s:.3f} s", (255, 255, 255))]
    lines += [(p.label, STATUS_COLORS[p.status]) for p in parts]
    if not lines:
        return
    width = max(cv2.getTextSize(text, _FONT, _FONT_SCALE, 1)[0][0] for text, _ in lines) + 12
    _darken(img, 0, 0, width, len(lines) * _LINE_H + 6)
    for i, (text, color) in enumerate(lines):
        _text(img, text, (6, (i + 1) * _LINE_H), color)


def draw_overlay(frame_rgb: np.ndarray, K: np.ndarray, parts: Sequence[PartOverlay],
                 time_s: float | None = None) -> np.ndarray:
    """A copy of ``frame_rgb`` (uint8 RGB (H, W, 3)) with the tracking state of ``parts`` drawn over it.

    Per part with a pose (status not "lost"): the mesh outline in the status colour
    (:data:`STATUS_COLORS`), the axes (x red, y green, z blue) and a label ``name status 0.87``; the box
    (thin grey) whenever given, posed or not. A legend in the top-left corner shows ``time_s`` and every
    part's label, including lost ones. ``K`` is the 3x3 intrinsic matrix of the frame.
    """
    img = np.array(_check_frame(frame_rgb), dtype=np.uint8, order="C", copy=True)
    K = _check_K(K)
    for part in parts:
        _draw_part(img, K, part)
    _draw_legend(img, parts, time_s)
    return img


# --------------------------------------------------------------------------------------------- video


def check_overlay_video(path: str | Path, width: int, height: int) -> None:
    """The overlay writer's rules for its file, checkable before anything is opened: a video suffix, and
    an even frame size (H.264 4:2:0). ``ValueError`` naming the path otherwise."""
    path = Path(path)
    if path.suffix.lower() not in _VIDEO_SUFFIXES:
        raise ValueError(f"overlay video {str(path)!r}: the name must end in one of {', '.join(_VIDEO_SUFFIXES)}")
    if width % 2 or height % 2:
        raise ValueError(f"overlay video {str(path)!r}: H.264 4:2:0 needs an even width and height, the video "
                         f"is {width}x{height}")


def _check_writable(path: Path) -> None:
    """Fail early, naming the path: the encoder only opens its file at the first frame."""
    try:
        # replaces an older file at once: a stale video must not pass for this run's
        with open(path, "wb"):
            pass
        path.unlink()
    except OSError as e:
        raise OSError(e.errno, f"cannot write the overlay video {str(path)!r}: {e.strerror}") from e


class OverlayWriter:
    """Context manager writing tracking overlays to an H.264 video (MP4 by the file name).

    ``OverlayWriter(path, fps, width, height, K)``: frames are uint8 RGB (height, width, 3) seen through
    intrinsics ``K``; ``fps`` is the nominal rate (see :class:`~surftrack.io.video.VideoWriter`; even
    width and height are required). An unwritable path raises ``OSError`` naming it, a name without a
    video suffix ``ValueError``. :meth:`close` (also run on leaving the ``with`` block, exception or not)
    finishes the file, so the frames written so far stay playable; when no frame was written no file is
    left, as an MP4 without frames is not playable.
    """

    def __init__(self, path: str | Path, fps: float, width: int, height: int, K: np.ndarray, *,
                 crf: int = 20) -> None:
        self.path = Path(path)
        self.K = _check_K(K)
        check_overlay_video(self.path, width, height)
        _check_writable(self.path)
        self._video = VideoWriter(self.path, fps, width, height, crf=crf)

    @property
    def closed(self) -> bool:
        return self._video.closed

    @property
    def frames_written(self) -> int:
        return self._video.frames_written

    def write(self, frame_rgb: np.ndarray, time_s: float, parts: Sequence[PartOverlay] = ()) -> None:
        """Draw ``parts`` over ``frame_rgb`` and encode it shown at ``time_s`` (seconds, increasing)."""
        if self.closed:
            raise ValueError(f"{self.path}: write() on a closed OverlayWriter")
        self._video.write(draw_overlay(frame_rgb, self.K, parts, time_s), time_s)

    def close(self) -> None:
        """Flush the encoder and finish the file (idempotent)."""
        self._video.close()

    def __enter__(self) -> OverlayWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close()
