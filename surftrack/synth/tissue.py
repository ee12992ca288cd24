"""Tissue surfaces: procedural height fields with anatomy-like folds, tissue colours and vessels; a user's
tissue mesh (OBJ/PLY, e.g. an EndoSurf/EndoNeRF reconstruction); or a photograph on a backdrop plane."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.ndimage import distance_transform_edt, gaussian_filter, map_coordinates, zoom
from scipy.spatial import cKDTree

from surftrack.instruments.part import Material
from surftrack.render import Renderer

# Linear-RGB base colours: pink peritoneum, red muscle, pale fat, liver-like brown-red.
TISSUE_PALETTE = np.array([
    [0.74, 0.26, 0.24], [0.62, 0.14, 0.12], [0.82, 0.52, 0.34], [0.50, 0.14, 0.12], [0.72, 0.32, 0.30],
])
MESH_UNITS = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
GAMMA = 2.2  # the renderer writes pow(c, 1 / 2.2): 8-bit colours from files are linearised with the inverse


@dataclass(eq=False)
class Tissue:
    """A tissue surface in its own frame: x, y across, z = depth offset (+z points away from a camera that
    looks down +z). Colour comes from ``texture`` (uint8 RGB, row 0 at y = -extent/2 for the generated
    surfaces) at per-vertex ``uv``, or from per-vertex ``colors`` (linear RGB in [0, 1] or uint8), or from
    the material alone. ``height`` is the height field (``z`` of the surface seen from the camera side) on a
    regular grid over ``extent``, centred on the origin, which the collision and aiming checks use.
    ``source_to_tissue`` is the 4x4 map from the source file's frame and units to this frame (loaded meshes)."""

    mesh: trimesh.Trimesh
    texture: np.ndarray | None
    uv: np.ndarray | None
    material: Material
    height: np.ndarray   # (ny, nx) height field, mm
    extent: tuple[float, float]
    colors: np.ndarray | None = None
    source_to_tissue: np.ndarray | None = None

    def __post_init__(self):
        if self.texture is not None and self.uv is None:
            raise ValueError("a tissue texture needs per-vertex uv coordinates")
        if self.colors is not None and len(self.colors) != len(self.mesh.vertices):
            raise ValueError(f"tissue colors: {len(self.colors)} rows for {len(self.mesh.vertices)} vertices")

    def add_to(self, renderer: Renderer) -> int:
        """Upload into ``renderer`` (smooth normals, textured or vertex-coloured, no amodal mask); returns
        the instance id."""
        return renderer.add_mesh(self.mesh, self.material, amodal=False, colors=self.colors, uv=self.uv,
                                 texture=self.texture, crease_deg=180.0, name="tissue")

    def height_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Surface z at tissue-frame (x, y) by bilinear interpolation (edge values outside)."""
        ny, nx = self.height.shape
        w, h = self.extent
        gx = (np.asarray(x) + w / 2) / w * (nx - 1)
        gy = (np.asarray(y) + h / 2) / h * (ny - 1)
        return map_coordinates(self.height, [np.ravel(gy), np.ravel(gx)], order=1, mode="nearest").reshape(np.shape(x))


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], sigma: float) -> np.ndarray:
    """Gaussian-filtered white noise scaled to [-1, 1]. Wide kernels are applied on a coarser grid and
    interpolated back (the result is band-limited anyway), which keeps big patches fast."""
    f = max(1, int(sigma // 3))
    if f == 1:
        n = gaussian_filter(rng.standard_normal(shape), sigma, mode="reflect")
    else:
        small = (shape[0] // f + 2, shape[1] // f + 2)
        n = zoom(gaussian_filter(rng.standard_normal(small), sigma / f, mode="reflect"), f, order=3)
        n = n[: shape[0], : shape[1]]
    return n / (np.abs(n).max() + 1e-12)


def _vessels(rng: np.random.Generator, w: float, h: float, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Points along random smooth curves (a walk with momentum), and each point's vessel radius."""
    pts, radii = [], []
    for _ in range(count):
        p = rng.uniform([-w / 2, -h / 2], [w / 2, h / 2])
        ang = rng.uniform(0, 2 * np.pi)
        r0 = rng.uniform(0.8, 2.2)
        steps = int(rng.integers(60, 200))
        for s in range(steps):
            ang += rng.normal(0.0, 0.12)
            p = p + 0.8 * np.array([np.cos(ang), np.sin(ang)])
            pts.append(p.copy())
            radii.append(r0 * (1.0 - 0.6 * s / steps))
            if rng.random() < 0.01:  # a branch: restart nearby with a thinner radius
                ang += rng.choice([-1, 1]) * rng.uniform(0.5, 1.0)
                r0 *= 0.7
    return np.asarray(pts), np.asarray(radii)


def procedural_tissue(rng: np.random.Generator, extent: tuple[float, float] = (280.0, 230.0),
                      spacing: float = 2.5, texel: float = 0.5, fold_depth: float = 14.0, vessels: int = 6) -> Tissue:
    """A random tissue patch ``extent`` mm wide with folds up to ``fold_depth`` mm deep and vessels.

    Geometry is a grid of about ``spacing`` mm (folds are far wider, so it need not be fine); colour,
    vessels and fine relief live in a texture of ``texel`` mm per pixel.
    """
    w, h = extent
    step = max(1, int(round(spacing / texel)))
    nx, ny = int(round(w / texel / step)) * step + 1, int(round(h / texel / step)) * step + 1
    spacing = texel
    xs, ys = np.linspace(-w / 2, w / 2, nx), np.linspace(-h / 2, h / 2, ny)
    X, Y = np.meshgrid(xs, ys)
    # Folds: a few elongated ridges and valleys, plus broad undulation and fine texture.
    Z = np.zeros_like(X)
    for _ in range(int(rng.integers(3, 7))):
        c = rng.uniform([-w / 2, -h / 2], [w / 2, h / 2])
        a = rng.uniform(0, np.pi)
        u = (X - c[0]) * np.cos(a) + (Y - c[1]) * np.sin(a)
        v = -(X - c[0]) * np.sin(a) + (Y - c[1]) * np.cos(a)
        su, sv = rng.uniform(25, 70), rng.uniform(6, 18)
        Z += rng.uniform(-1, 1) * fold_depth * np.exp(-0.5 * ((u / su) ** 2 + (v / sv) ** 2))
    Z += 0.35 * fold_depth * _smooth_noise(rng, Z.shape, sigma=18.0 / spacing)
    Z += 0.6 * _smooth_noise(rng, Z.shape, sigma=1.5 / spacing)
    # Colour: a palette mix varying across the patch, darker in valleys, with vessels on top.
    k = rng.choice(len(TISSUE_PALETTE), size=2, replace=False)
    mix = 0.5 + 0.5 * _smooth_noise(rng, Z.shape, sigma=25.0 / spacing)
    col = TISSUE_PALETTE[k[0]] * mix[..., None] + TISSUE_PALETTE[k[1]] * (1 - mix[..., None])
    col = col * (1.0 + 0.12 * _smooth_noise(rng, Z.shape, sigma=2.0 / spacing))[..., None]
    col *= (1.0 - 0.25 * np.clip(Z / max(fold_depth, 1e-6), 0, 1))[..., None]
    if vessels:
        vp, vr = _vessels(rng, w, h, vessels)
        d, idx = cKDTree(vp).query(np.stack([X.ravel(), Y.ravel()], -1), distance_upper_bound=6.0)
        near = np.isfinite(d)
        strength = np.zeros(X.size)
        # Soft profile at least one grid spacing wide, so vessels do not alias into dotted lines.
        width = np.maximum(vr[idx[near]], spacing)
        strength[near] = np.exp(-((d[near] / width) ** 2))
        vessel_col = np.array([0.45, 0.06, 0.10]) if rng.random() < 0.7 else np.array([0.30, 0.12, 0.35])
        s = strength.reshape(X.shape)[..., None] * 0.8
        col = col * (1 - s) + vessel_col * s
    texture = (np.clip(col, 0, 1) * 255).astype(np.uint8)
    Xc, Yc, Zc = X[::step, ::step], Y[::step, ::step], Z[::step, ::step]
    vertices = np.stack([Xc.ravel(), Yc.ravel(), Zc.ravel()], axis=-1)
    # Texture row 0 is y = -h/2; the renderer uploads rows flipped, so GL's v runs from the last row up.
    uv = np.stack([(Xc.ravel() + w / 2) / w, 1.0 - (Yc.ravel() + h / 2) / h], axis=-1)
    ny, nx = Xc.shape
    i = np.arange(ny - 1)[:, None] * nx + np.arange(nx - 1)[None, :]
    i = i.ravel()
    # Faces wound so that their normals face -z (towards a camera looking down +z).
    faces = np.concatenate([np.stack([i, i + nx, i + 1], -1), np.stack([i + 1, i + nx, i + nx + 1], -1)])
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    material = Material(color=(1.0, 1.0, 1.0), metallic=0.0, roughness=float(rng.uniform(0.25, 0.45)))
    return Tissue(mesh, texture, uv, material, Z, (w, h))


# ---------------------------------------------------------------------- a user's tissue mesh
def _linear(rgb8: np.ndarray) -> np.ndarray:
    """8-bit (sRGB-like) colours to linear values in [0, 1]."""
    return (np.asarray(rgb8, dtype=np.float64)[..., :3] / 255.0) ** GAMMA


def _linear_u8(rgb8: np.ndarray) -> np.ndarray:
    return np.round(_linear(rgb8) * 255.0).astype(np.uint8)


def _material_image(material) -> np.ndarray | None:
    """The colour image of a trimesh material (SimpleMaterial.image or PBRMaterial.baseColorTexture)."""
    for attr in ("image", "baseColorTexture"):
        img = getattr(material, attr, None)
        if img is not None:
            try:
                return np.asarray(img.convert("RGB"), dtype=np.uint8)
            except AttributeError:
                arr = np.asarray(img)
                return arr[..., :3].astype(np.uint8) if arr.ndim == 3 else np.repeat(arr[..., None], 3, -1)
    return None


def _orientation(p: Path, V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Rotation that makes the surface face -z: kept if it does, flipped (180 deg about x) if it faces +z,
    and, when its mean normal is mostly horizontal, its principal plane (PCA) turned onto x-y."""
    area_vec = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    total = np.linalg.norm(area_vec, axis=1).sum()
    if not total > 0:
        raise ValueError(f"{p}: the tissue mesh has no area (all faces degenerate)")
    m = area_vec.sum(axis=0)
    if np.linalg.norm(m) < 0.2 * total:
        raise ValueError(f"{p}: not a surface seen from one side (its faces point every way: a closed or strongly "
                         f"folded mesh?); crop it to the visible tissue surface")
    m /= np.linalg.norm(m)
    if abs(m[2]) >= 0.5:
        return np.eye(3) if m[2] < 0 else np.diag([1.0, -1.0, -1.0])
    c = V - V.mean(axis=0)
    _, vecs = np.linalg.eigh(c.T @ c)  # ascending variance: vecs[:, 0] is the plane normal
    n, e1 = vecs[:, 0], vecs[:, 2]
    if n @ m < 0:
        n = -n
    if n @ m < 0.3:  # PCA disagrees with the faces (a strip, a saddle): trust the mean normal
        n = m
    r3 = -n
    r1 = e1 - (e1 @ r3) * r3
    if np.linalg.norm(r1) < 1e-6:
        r1 = np.cross(r3, [1.0, 0.0, 0.0]) if abs(r3[0]) < 0.9 else np.cross(r3, [0.0, 1.0, 0.0])
    r1 /= np.linalg.norm(r1)
    return np.stack([r1, np.cross(r3, r1), r3])


def load_tissue_mesh(path: str | Path, units: str = "mm", spacing: float = 1.0) -> Tissue:
    """A user's tissue surface (OBJ/PLY/..., e.g. an EndoSurf or EndoNeRF reconstruction) as a :class:`Tissue`.

    The mesh is scaled from ``units`` (mm, cm or m) to mm, turned so that its surface faces -z (see
    :func:`_orientation`), centred (x, y at the middle of its bounding box, the median surface height at
    z = 0), and given a height field on a grid of about ``spacing`` mm by casting rays straight down +z
    (first hit; holes filled with the nearest valid height). Colour: the texture trimesh loads (with its
    uv), else vertex (or face) colours, else a default tissue colour. 8-bit colours are linearised for the
    renderer. Raises a one-line ValueError naming the file for unreadable, empty or non-surface meshes.
    """
    p = Path(path)
    if units not in MESH_UNITS:
        raise ValueError(f"{p}: unknown mesh units {units!r}; use one of {sorted(MESH_UNITS)}")
    if not p.is_file():
        raise ValueError(f"{p}: tissue mesh file not found")
    try:
        mesh = trimesh.load(p, force="mesh", process=False)
    except Exception as e:  # noqa: BLE001 - every loader failure is reported the same way
        msg = str(e).splitlines()[0] if str(e) else ""
        raise ValueError(f"{p}: cannot read a tissue mesh ({type(e).__name__}: {msg})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0 or len(mesh.vertices) < 3:
        raise ValueError(f"{p}: no triangles (an empty file or a point cloud?); a tissue mesh must be a "
                         f"triangulated surface")
    V = np.asarray(mesh.vertices, dtype=np.float64) * MESH_UNITS[units]
    F = np.asarray(mesh.faces, dtype=np.int64)
    texture = uv = colors = None
    vis = mesh.visual
    if vis.kind == "texture" and getattr(vis, "uv", None) is not None and len(vis.uv) == len(V):
        img = _material_image(vis.material)
        if img is not None:
            texture, uv = _linear_u8(img), np.asarray(vis.uv, dtype=np.float64)[:, :2]
    if texture is None and vis.kind in ("vertex", "face"):
        colors = _linear(np.asarray(vis.vertex_colors))
    # Keep faces with finite, distinct corners and drop unreferenced vertices (with their colours / uv).
    ok = np.isfinite(V).all(axis=1)
    F = F[ok[F].all(axis=1) & (F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])]
    if len(F) == 0:
        raise ValueError(f"{p}: no valid triangles in the tissue mesh")
    used, F = np.unique(F, return_inverse=True)
    F = F.reshape(-1, 3)
    V = V[used]
    colors = None if colors is None else colors[used]
    uv = None if uv is None else uv[used]
    R = _orientation(p, V, F)
    Vr = V @ R.T
    lo, hi = Vr.min(axis=0), Vr.max(axis=0)
    w, h = float(hi[0] - lo[0]), float(hi[1] - lo[1])
    if min(w, h) < 2 * spacing:
        raise ValueError(f"{p}: the tissue surface spans only {w:.2f} x {h:.2f} mm across the view")
    centre = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, 0.0])
    Vr -= centre
    # Height field: first hits of rays cast down +z through a regular grid over the bounding box.
    nx, ny = int(np.ceil(w / spacing)) + 1, int(np.ceil(h / spacing)) + 1
    X, Y = np.meshgrid(np.linspace(-w / 2, w / 2, nx), np.linspace(-h / 2, h / 2, ny))
    origins = np.stack([X.ravel(), Y.ravel(), np.full(X.size, lo[2] - 1.0 - 0.01 * (hi[2] - lo[2]))], -1)
    dirs = np.tile([0.0, 0.0, 1.0], (X.size, 1))
    loc, ray, _ = trimesh.Trimesh(Vr, F, process=False).ray.intersects_location(origins, dirs, multiple_hits=True)
    Z = np.full(X.size, np.inf)
    np.minimum.at(Z, ray, loc[:, 2])
    Z = Z.reshape(X.shape)
    valid = np.isfinite(Z)
    if not valid.any():
        raise ValueError(f"{p}: rays down the view axis hit no part of the tissue mesh")
    if not valid.all():
        idx = distance_transform_edt(~valid, return_distances=False, return_indices=True)
        Z = Z[tuple(idx)]
    z0 = float(np.median(Z[valid]))
    Z -= z0
    Vr[:, 2] -= z0
    T = np.eye(4)
    T[:3, :3] = MESH_UNITS[units] * R
    T[:3, 3] = -(centre + [0.0, 0.0, z0])
    coloured = texture is not None or colors is not None
    material = Material(color=(1.0, 1.0, 1.0) if coloured else tuple(float(c) for c in TISSUE_PALETTE[0]),
                        metallic=0.0, roughness=0.35)
    return Tissue(trimesh.Trimesh(Vr, F, process=False), texture, uv, material, Z, (w, h), colors=colors,
                  source_to_tissue=T)


# ---------------------------------------------------------------------- photographs as backdrops
def image_files(path: str | Path) -> list[Path]:
    """The image files a ``tissue.images`` entry names: the file itself, or a folder's images (sorted)."""
    p = Path(path)
    if p.is_file():
        return [p]
    if not p.is_dir():
        raise ValueError(f"{p}: no such image file or folder")
    files = sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise ValueError(f"{p}: no images ({', '.join(IMAGE_SUFFIXES)}) in this folder")
    return files


def read_image(path: str | Path) -> np.ndarray:
    """An image file as uint8 RGB; a one-line ValueError naming the file if it cannot be read."""
    import cv2

    p = Path(path)
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED) if p.is_file() else None
    if img is None or img.size == 0:
        raise ValueError(f"{p}: cannot read the image" if p.is_file() else f"{p}: image file not found")
    return _as_rgb8(img[..., 2::-1] if img.ndim == 3 else img, p)


def _as_rgb8(img: np.ndarray, name) -> np.ndarray:
    a = np.asarray(img)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=-1)
    if a.ndim != 3 or a.shape[2] < 3 or min(a.shape[:2]) < 2:
        raise ValueError(f"{name}: expected an RGB image, got an array of shape {a.shape}")
    a = a[..., :3]
    if a.dtype == np.uint16:
        a = (a / 257.0).round()
    elif np.issubdtype(a.dtype, np.floating):
        a = np.clip(a, 0.0, 1.0) * 255.0
    return np.ascontiguousarray(a).astype(np.uint8)


def image_backdrop(image: str | Path | np.ndarray, extent: tuple[float, float] = (400.0, 340.0),
                   bowl_mm: float = 0.0, spacing: float = 5.0, max_texture: int = 4096) -> Tissue:
    """A photograph (a file, or an RGB array: uint8 or float in [0, 1]) on a plane ``extent`` mm wide, e.g.
    a real endoscopic frame without tools. The image is centre-cropped to the extent's aspect (not
    stretched), its top row at y = -extent/2 (up in a camera that looks down +z with y down).
    ``bowl_mm`` > 0 curves the plane gently into a bowl whose corners lie that much nearer the camera
    than its centre; the height field follows (flat for 0)."""
    name = image if isinstance(image, (str, Path)) else "image array"
    img = read_image(image) if isinstance(image, (str, Path)) else _as_rgb8(image, name)
    w, h = (float(v) for v in extent)
    if not (w > 0 and h > 0):
        raise ValueError(f"backdrop extent must be positive, got {extent}")
    H, W = img.shape[:2]
    if W / H > w / h:
        cw = max(1, int(round(H * w / h)))
        img = img[:, (W - cw) // 2:(W - cw) // 2 + cw]
    else:
        ch = max(1, int(round(W * h / w)))
        img = img[(H - ch) // 2:(H - ch) // 2 + ch]
    if max(img.shape[:2]) > max_texture:
        import cv2

        f = max_texture / max(img.shape[:2])
        img = cv2.resize(img, (max(1, int(img.shape[1] * f)), max(1, int(img.shape[0] * f))),
                         interpolation=cv2.INTER_AREA)
    nx, ny = int(np.ceil(w / spacing)) + 1, int(np.ceil(h / spacing)) + 1
    X, Y = np.meshgrid(np.linspace(-w / 2, w / 2, nx), np.linspace(-h / 2, h / 2, ny))
    Z = -float(bowl_mm) * 0.5 * ((X / (w / 2)) ** 2 + (Y / (h / 2)) ** 2)
    vertices = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=-1)
    uv = np.stack([(X.ravel() + w / 2) / w, 1.0 - (Y.ravel() + h / 2) / h], axis=-1)
    i = (np.arange(ny - 1)[:, None] * nx + np.arange(nx - 1)[None, :]).ravel()
    faces = np.concatenate([np.stack([i, i + nx, i + 1], -1), np.stack([i + 1, i + nx, i + nx + 1], -1)])
    material = Material(color=(1.0, 1.0, 1.0), metallic=0.0, roughness=0.6)
    return Tissue(trimesh.Trimesh(vertices, faces, process=False), _linear_u8(img), uv, material, Z, (w, h))


# ---------------------------------------------------------------------- configured source
class TissueSource:
    """Makes the tissue for a group of images as ``tissue.source`` says (a :class:`TissueCfg`):

    - ``procedural``: a new random patch (:func:`procedural_tissue`);
    - ``mesh``: the user's mesh (:func:`load_tissue_mesh`, loaded once and reused: the random pose and
      per-image jitter vary it);
    - ``images``: a random image of ``tissue.images`` (a file or a folder), mirrored at random, as a
      backdrop of ``extent_mm`` gently bowled by a depth drawn from ``fold_depth_mm``.

    Every random choice comes from the ``rng`` passed in, so a group's tissue depends only on it.
    """

    def __init__(self, cfg):
        self.cfg = cfg
        self._mesh: Tissue | None = None
        self._images = image_files(cfg.images) if cfg.source == "images" else []

    def check(self) -> None:
        """Read now what the images will read (the mesh, every image), so that a bad file stops a run before
        its first image rather than in a worker hours in: ``ValueError`` naming the file."""
        if self.cfg.source == "mesh":
            self(np.random.default_rng(0))
        for f in self._images:
            read_image(f)

    def __call__(self, rng: np.random.Generator) -> Tissue:
        t = self.cfg
        if t.source == "mesh":
            if self._mesh is None:
                self._mesh = load_tissue_mesh(t.mesh, t.mesh_units, spacing=t.texel_mm)
            return self._mesh
        if t.source == "images":
            img = read_image(self._images[int(rng.integers(len(self._images)))])
            if rng.random() < 0.5:
                img = img[:, ::-1]
            return image_backdrop(img, tuple(t.extent_mm), bowl_mm=float(rng.uniform(*t.fold_depth_mm)),
                                  spacing=t.spacing_mm)
        return procedural_tissue(rng, extent=tuple(t.extent_mm), spacing=t.spacing_mm, texel=t.texel_mm,
                                 fold_depth=float(rng.uniform(t.fold_depth_mm[0], t.fold_depth_mm[1])))
