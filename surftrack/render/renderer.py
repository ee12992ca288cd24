"""Headless multi-modal renderer (moderngl, EGL).

A :class:`Renderer` owns the framebuffers for one image size. Meshes are uploaded once with
:meth:`Renderer.add_mesh` (each call creates an *instance* with its own id, material and flags; a second
instance can share the geometry of the first) and rendered any number of times with different poses,
intrinsics and lights. One :meth:`Renderer.render` call produces, for the instances given poses:

- ``rgb``: shaded colour (uint8), endoscope spot light plus extra lights, metallic/specular materials,
  vertex colours or a texture;
- ``depth``: z in mm (0 where nothing is hit), exact per pixel centre (not a depth-buffer readback);
- ``instance``: id of the visible instance per pixel (0 = background);
- ``xyz``: object coordinates (mm, in the visible instance's own frame);
- ``normal``: camera-frame unit normals facing the camera;
- ``amodal``: the full silhouette of every instance flagged ``amodal``, ignoring occlusion.

The GL projection follows OpenCV's pixel-centre convention exactly (see :mod:`.projection`), so masks and
depth agree with ray casting through pixel centres. Antialiasing is deliberately absent: every modality
must describe the same pixel.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import moderngl
import numpy as np
import trimesh

from surftrack.geometry import PinholeCamera
from surftrack.instruments.part import Material
from surftrack.render.context import RenderError, gl_context
from surftrack.render.lights import Light, endoscope_light
from surftrack.render.meshdata import vertex_buffer
from surftrack.render.projection import gl_projection

MODALITIES = frozenset({"rgb", "depth", "instance", "xyz", "normal", "amodal"})
MAX_LIGHTS = 8
AMODAL_SLOTS = 8  # instances per amodal pass: two RGBA8 targets, one channel each, blended with MAX
# Colour attachments (channels, GL dtype) in shader output order: rgb, xyz, normal, depth, instance id.
_TARGETS = [(4, "f1"), (4, "f4"), (4, "f4"), (1, "f4"), (1, "i4")]
# Readback per modality: (channels, GL dtype, numpy dtype).
_READ = {"rgb": (3, "f1", np.uint8), "xyz": (3, "f4", np.float32), "normal": (3, "f4", np.float32),
         "depth": (1, "f4", np.float32), "instance": (1, "i4", np.int32)}

_VERT = """
#version 330
uniform mat4 mv;
uniform mat4 proj;
uniform mat3 nmat;
in vec3 in_pos; in vec3 in_nrm; in vec3 in_col; in vec2 in_uv;
out vec3 v_obj; out vec3 v_cam; out vec3 v_nrm; out vec3 v_col; out vec2 v_uv;
void main() {
    vec4 pc = mv * vec4(in_pos, 1.0);
    v_obj = in_pos; v_cam = pc.xyz; v_nrm = nmat * in_nrm; v_col = in_col; v_uv = in_uv;
    gl_Position = proj * pc;
}
"""

_FRAG = """
#version 330
uniform int inst_id;
uniform vec3 base_color;
uniform float metallic;
uniform float roughness;
uniform bool use_tex;
uniform sampler2D tex;
uniform vec3 ambient;
uniform int n_lights;
uniform vec3 l_pos[8]; uniform vec3 l_dir[8]; uniform vec3 l_col[8];
uniform float l_cos_in[8]; uniform float l_cos_out[8]; uniform float l_ref[8];
in vec3 v_obj; in vec3 v_cam; in vec3 v_nrm; in vec3 v_col; in vec2 v_uv;
layout(location = 0) out vec4 f_rgb;
layout(location = 1) out vec4 f_xyz;
layout(location = 2) out vec4 f_normal;
layout(location = 3) out float f_depth;
layout(location = 4) out int f_id;
void main() {
    vec3 n = normalize(v_nrm);
    vec3 V = normalize(-v_cam);
    // Open meshes (tissue) seen from behind. The projection flips y (see _TARGETS), which swaps GL's
    // notion of front-facing: our outward-facing triangles are the ones GL calls back-facing.
    if (dot(n, V) < 0.0 && gl_FrontFacing) n = -n;
    vec3 albedo = base_color * v_col;
    if (use_tex) albedo *= texture(tex, v_uv).rgb;
    vec3 F0 = mix(vec3(0.04), albedo, metallic);
    float r = clamp(roughness, 0.04, 1.0);
    float shin = 2.0 / (r * r) - 2.0;  // Blinn-Phong exponent of a GGX-like roughness
    vec3 c = ambient * albedo * (1.0 - 0.5 * metallic) + ambient * F0 * 0.5 * metallic;
    for (int i = 0; i < n_lights; ++i) {
        vec3 L = l_pos[i] - v_cam;
        float d = length(L);
        L /= d;
        float spot = smoothstep(l_cos_out[i], l_cos_in[i], dot(-L, l_dir[i]));
        float att = spot * (l_ref[i] * l_ref[i]) / (d * d);
        float ndl = max(dot(n, L), 0.0);
        vec3 H = normalize(L + V);
        float ndh = max(dot(n, H), 0.0);
        vec3 F = F0 + (1.0 - F0) * pow(clamp(1.0 - dot(H, V), 0.0, 1.0), 5.0);
        vec3 spec = F * (shin + 8.0) / 8.0 * pow(ndh, shin);
        vec3 diff = albedo * (1.0 - 0.7 * metallic);  // rough metal scatters a share of light broadly
        c += l_col[i] * att * ndl * (diff + spec);
    }
    c = c / (1.0 + max(max(c.r, c.g), c.b) * 0.15);  // soft shoulder for specular highlights
    f_rgb = vec4(pow(clamp(c, 0.0, 1.0), vec3(1.0 / 2.2)), 1.0);
    f_xyz = vec4(v_obj, 1.0);
    f_normal = vec4(n, 0.0);
    f_depth = v_cam.z;
    f_id = inst_id;
}
"""

_AMODAL_FRAG = """
#version 330
uniform int slot;
layout(location = 0) out vec4 f0;
layout(location = 1) out vec4 f1;
void main() {
    vec4 one = vec4(equal(ivec4(slot) - ivec4(0, 1, 2, 3), ivec4(0)));
    vec4 two = vec4(equal(ivec4(slot) - ivec4(4, 5, 6, 7), ivec4(0)));
    f0 = one; f1 = two;
}
"""


@dataclass
class _Geometry:
    vbo: moderngl.Buffer
    ibo: moderngl.Buffer
    vao: moderngl.VertexArray
    vao_amodal: moderngl.VertexArray


@dataclass
class _Instance:
    geometry: _Geometry
    material: Material
    amodal: bool
    texture: moderngl.Texture | None
    name: str


@dataclass
class RenderResult:
    """Images of one render; modalities not requested are ``None``. ``amodal`` maps instance id -> mask."""

    rgb: np.ndarray | None = None
    depth: np.ndarray | None = None
    instance: np.ndarray | None = None
    xyz: np.ndarray | None = None
    normal: np.ndarray | None = None
    amodal: dict[int, np.ndarray] = field(default_factory=dict)
    amodal_pad: int = 0  # the amodal masks extend this many pixels beyond every image border

    def amodal_in_image(self, inst_id: int) -> np.ndarray:
        """The amodal mask of one instance cropped to the image."""
        m, p = self.amodal[inst_id], self.amodal_pad
        return m[p:m.shape[0] - p, p:m.shape[1] - p] if p else m

    def mask_visib(self, inst_id: int) -> np.ndarray:
        """Visible (modal) mask of one instance."""
        if self.instance is None:
            raise ValueError("render with the 'instance' modality to get visible masks")
        return self.instance == inst_id


class Renderer:
    """Renders scenes of mesh instances at a fixed image size; see the module docstring.

    ``near`` and ``far`` (mm) bound what is drawn; instruments sit 30-100 mm from an endoscope, so the
    default near plane of 1 mm clips nothing real while keeping depth-buffer precision.
    """

    def __init__(self, width: int, height: int, near: float = 1.0, far: float = 3000.0):
        if width <= 0 or height <= 0:
            raise ValueError(f"image size must be positive, got {width}x{height}")
        if not 0 < near < far:
            raise ValueError(f"need 0 < near < far, got {near}, {far}")
        self.ctx = gl_context()
        self.width, self.height, self.near, self.far = int(width), int(height), float(near), float(far)
        self.prog = self.ctx.program(vertex_shader=_VERT, fragment_shader=_FRAG)
        self.prog_amodal = self.ctx.program(vertex_shader=_VERT, fragment_shader=_AMODAL_FRAG)
        size = (self.width, self.height)
        # One target per modality, in shader output order; read back with the channels each needs, so
        # every returned array is contiguous without a copy.
        self._targets = [self.ctx.texture(size, c, dtype=d) for c, d in _TARGETS]
        self._depth = self.ctx.depth_texture(size)
        self.fbo = self.ctx.framebuffer(self._targets, self._depth)
        self._static_targets = [self.ctx.texture(size, c, dtype=d) for c, d in _TARGETS]
        self._static_depth = self.ctx.depth_texture(size)
        self._static_fbo = self.ctx.framebuffer(self._static_targets, self._static_depth)
        self._static_key: tuple | None = None
        self._amodal_fbos: dict[int, moderngl.Framebuffer] = {}
        self.instances: dict[int, _Instance] = {}
        self._single_fbos: dict[int, moderngl.Framebuffer] = {}
        self._next_id = 0

    # ------------------------------------------------------------------ scene
    def add_mesh(self, mesh: trimesh.Trimesh, material: Material | None = None, *, amodal: bool = True,
                 colors: np.ndarray | None = None, uv: np.ndarray | None = None,
                 texture: np.ndarray | None = None, crease_deg: float = 30.0, name: str = "") -> int:
        """Upload ``mesh`` (its own frame, mm) and return the new instance id (1, 2, ...).

        ``colors`` are per-vertex RGB (uint8 or float in [0, 1]) multiplied with the material colour;
        ``texture`` is an (H, W, 3) uint8 image sampled at per-vertex ``uv``. ``amodal`` asks for this
        instance's full silhouette in the ``amodal`` modality.
        """
        if texture is not None and uv is None:
            raise ValueError("a texture needs per-vertex uv coordinates")
        data, index = vertex_buffer(mesh, crease_deg, colors, uv)
        vbo = self.ctx.buffer(data.tobytes())
        ibo = self.ctx.buffer(index.tobytes())
        fmt = ("3f 3f 3f 2f", "in_pos", "in_nrm", "in_col", "in_uv")
        vao = self.ctx.vertex_array(self.prog, [(vbo, *fmt)], index_buffer=ibo, index_element_size=4)
        vao_am = self.ctx.vertex_array(self.prog_amodal, [(vbo, "3f 32x", "in_pos")], index_buffer=ibo,
                                       index_element_size=4)
        return self._add(_Geometry(vbo, ibo, vao, vao_am), material, amodal, texture, name)

    def add_instance(self, like: int, material: Material | None = None, *, amodal: bool = True, name: str = "") -> int:
        """A new instance sharing the uploaded geometry of instance ``like`` (no re-upload)."""
        src = self.instances[like]
        return self._add(src.geometry, material or src.material, amodal, None, name, src.texture)

    def _add(self, geom: _Geometry, material: Material | None, amodal: bool, texture: np.ndarray | None,
             name: str, gl_tex: moderngl.Texture | None = None) -> int:
        if texture is not None:
            t = np.ascontiguousarray(np.asarray(texture, dtype=np.uint8)[::-1, :, :3])
            gl_tex = self.ctx.texture((t.shape[1], t.shape[0]), 3, t.tobytes())
            gl_tex.build_mipmaps()
            gl_tex.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        self._next_id += 1
        inst_id = self._next_id
        self.instances[inst_id] = _Instance(geom, material or Material(), amodal, gl_tex, name)
        return inst_id

    def remove(self, inst_id: int) -> None:
        """Drop an instance; its geometry and texture are freed once no other instance uses them."""
        inst = self.instances.pop(inst_id)
        others = list(self.instances.values())
        if not any(o.geometry is inst.geometry for o in others):
            g = inst.geometry
            g.vao.release(); g.vao_amodal.release(); g.vbo.release(); g.ibo.release()
        if inst.texture is not None and not any(o.texture is inst.texture for o in others):
            inst.texture.release()
        self._static_key = None

    # ------------------------------------------------------------------ render
    def render(self, camera: PinholeCamera, poses: dict[int, np.ndarray], lights: list[Light] | None = None,
               modalities: frozenset[str] | set[str] | tuple[str, ...] = MODALITIES,
               ambient: tuple[float, float, float] = (0.04, 0.035, 0.035),
               background: tuple[float, float, float] = (0.0, 0.0, 0.0),
               static: frozenset[int] | set[int] = frozenset(), amodal_pad: int = 0) -> RenderResult:
        """Render the instances in ``poses`` (instance id -> 4x4 model-to-camera, mm) with ``camera``.

        ``lights`` default to the endoscope light alone. Instances without a pose are not drawn.
        ``static`` names instances (typically the tissue) whose rendering is cached as a layer and reused
        while the camera, their poses, the lights, ambient and background stay the same: rendering many
        instrument poses over one scene then costs only the instruments. The result is identical.
        ``amodal_pad`` > 0 renders the amodal masks over the image plus that many pixels on every side, so
        silhouettes truncated by the image border are counted whole (as BOP's ``px_count_all`` needs).
        """
        mods = frozenset(modalities)
        if mods - MODALITIES:
            raise ValueError(f"unknown modalities {sorted(mods - MODALITIES)}; available {sorted(MODALITIES)}")
        if (camera.width, camera.height) != (self.width, self.height):
            raise ValueError(f"camera is {camera.width}x{camera.height}, renderer is {self.width}x{self.height}")
        unknown = (set(poses) | set(static)) - set(self.instances)
        if unknown:
            raise ValueError(f"no instance(s) {sorted(unknown)} in the scene")
        if set(static) - set(poses):
            raise ValueError(f"static instance(s) {sorted(set(static) - set(poses))} have no pose")
        lights = [endoscope_light()] if lights is None else list(lights)
        if len(lights) > MAX_LIGHTS:
            raise ValueError(f"at most {MAX_LIGHTS} lights, got {len(lights)}")
        proj = gl_projection(camera.K, self.width, self.height, self.near, self.far)
        ctx = self.ctx
        ctx.disable(moderngl.BLEND | moderngl.CULL_FACE)
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.depth_func = "<"
        self._set_lights(lights, ambient)
        self.prog["proj"].write(proj.T.astype("f4").tobytes())
        if static:
            key = (camera.K.tobytes(), tuple(sorted((i, np.asarray(poses[i], np.float64).tobytes()) for i in static)),
                   repr(lights), tuple(ambient), tuple(background))
            if self._static_key != key:
                self._begin(self._static_fbo, background)
                self._draw({i: poses[i] for i in static})
                self._static_key = key
            ctx.copy_framebuffer(self.fbo, self._static_fbo)
            self.fbo.use()
        else:
            self._begin(self.fbo, background)
        # Amodal (instrument) instances first: they are usually in front, so early depth tests skip
        # most of the occluded fragments of what follows.
        rest = {i: T for i, T in poses.items() if i not in static}
        self._draw(dict(sorted(rest.items(), key=lambda kv: not self.instances[kv[0]].amodal)))
        out = RenderResult()
        for k, name in enumerate(("rgb", "xyz", "normal", "depth", "instance")):
            if name in mods:
                setattr(out, name, self._read(self.fbo, k, *_READ[name]))
        if "amodal" in mods:
            out.amodal = self._render_amodal(camera, poses, int(amodal_pad))
            out.amodal_pad = int(amodal_pad)
        return out

    def _begin(self, fbo: moderngl.Framebuffer, background: tuple[float, float, float]) -> None:
        """Clear ``fbo`` (zeros, far depth; the colour target to ``background``) and bind it."""
        fbo.use()
        fbo.clear(depth=1.0)
        # framebuffer.clear writes one colour to every attachment: clear the colour target on its own.
        colour = fbo.color_attachments[0]
        if colour.glo not in self._single_fbos:
            self._single_fbos[colour.glo] = self.ctx.framebuffer([colour])
        self._single_fbos[colour.glo].clear(*background, 1.0)
        fbo.use()

    def _draw(self, poses: dict[int, np.ndarray]) -> None:
        p = self.prog
        for inst_id, T in poses.items():
            inst = self.instances[inst_id]
            T = np.asarray(T, dtype=np.float64)
            p["mv"].write(T.T.astype("f4").tobytes())
            p["nmat"].write(T[:3, :3].T.astype("f4").tobytes())
            p["inst_id"].value = int(inst_id)
            m = inst.material
            p["base_color"].value = tuple(float(c) for c in m.color)
            p["metallic"].value = float(m.metallic)
            p["roughness"].value = float(m.roughness)
            p["use_tex"].value = inst.texture is not None
            if inst.texture is not None:
                inst.texture.use(0)
                p["tex"].value = 0
            inst.geometry.vao.render(moderngl.TRIANGLES)

    def _set_lights(self, lights: list[Light], ambient: tuple[float, float, float]) -> None:
        p = self.prog
        n = len(lights)
        p["n_lights"].value = n
        p["ambient"].value = tuple(float(a) for a in ambient)
        if n == 0:
            return
        pad = MAX_LIGHTS - n

        def arr(vals: list, width: int) -> bytes:
            a = np.asarray(vals, dtype="f4").reshape(n, width)
            return np.concatenate([a, np.zeros((pad, width), "f4")]).tobytes()

        p["l_pos"].write(arr([lt.position for lt in lights], 3))
        p["l_dir"].write(arr([lt.direction for lt in lights], 3))
        p["l_col"].write(arr([np.asarray(lt.color) * lt.intensity for lt in lights], 3))
        p["l_cos_in"].write(arr([np.cos(np.radians(min(lt.inner_deg, 179.9))) for lt in lights], 1))
        p["l_cos_out"].write(arr([np.cos(np.radians(min(lt.outer_deg, 180.0))) - (1.0 if lt.outer_deg >= 180 else 0.0)
                                  for lt in lights], 1))
        p["l_ref"].write(arr([lt.ref_distance for lt in lights], 1))

    def _amodal_fbo(self, pad: int) -> tuple[moderngl.Framebuffer, int, int]:
        if pad not in self._amodal_fbos:
            size = (self.width + 2 * pad, self.height + 2 * pad)
            self._amodal_fbos[pad] = self.ctx.framebuffer([self.ctx.texture(size, 4, dtype="f1") for _ in range(2)])
        return self._amodal_fbos[pad], self.width + 2 * pad, self.height + 2 * pad

    def _render_amodal(self, camera: PinholeCamera, poses: dict[int, np.ndarray], pad: int) -> dict[int, np.ndarray]:
        ids = [i for i in poses if self.instances[i].amodal]
        fbo, w, h = self._amodal_fbo(pad)
        K = camera.K.copy()
        K[0, 2] += pad
        K[1, 2] += pad
        proj = gl_projection(K, w, h, self.near, self.far)
        out: dict[int, np.ndarray] = {}
        ctx = self.ctx
        ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        ctx.enable(moderngl.BLEND)
        ctx.blend_func = moderngl.ONE, moderngl.ONE
        ctx.blend_equation = moderngl.MAX
        p = self.prog_amodal
        p["proj"].write(proj.T.astype("f4").tobytes())
        try:
            for start in range(0, len(ids), AMODAL_SLOTS):
                group = ids[start:start + AMODAL_SLOTS]
                fbo.use()
                fbo.clear(0.0, 0.0, 0.0, 0.0)
                for slot, inst_id in enumerate(group):
                    p["mv"].write(np.asarray(poses[inst_id], dtype=np.float64).T.astype("f4").tobytes())
                    p["slot"].value = slot
                    self.instances[inst_id].geometry.vao_amodal.render(moderngl.TRIANGLES)
                planes = [self._read(fbo, k, 4, "f1", np.uint8, (w, h)) for k in range(1 + (len(group) - 1) // 4)]
                for slot, inst_id in enumerate(group):
                    out[inst_id] = planes[slot // 4][..., slot % 4] > 127
        finally:
            ctx.disable(moderngl.BLEND)
            ctx.blend_equation = moderngl.FUNC_ADD
            ctx.enable(moderngl.DEPTH_TEST)
        return out

    def _read(self, fbo: moderngl.Framebuffer, attachment: int, comps: int, gl_dtype: str, np_dtype: type,
              size: tuple[int, int] | None = None) -> np.ndarray:
        """Read ``comps`` channels of one colour attachment into a new (H, W[, comps]) array. Rows are
        already in image order (top first) because the projection flips y."""
        w, h = size or (self.width, self.height)
        shape = (h, w) if comps == 1 else (h, w, comps)
        arr = np.empty(shape, dtype=np_dtype)
        fbo.read_into(arr, components=comps, attachment=attachment, dtype=gl_dtype)
        return arr

    def release(self) -> None:
        """Free the GL objects of this renderer (the context stays for the process)."""
        seen = set()
        for inst in self.instances.values():
            g = inst.geometry
            if id(g) not in seen:
                seen.add(id(g))
                g.vao.release(); g.vao_amodal.release(); g.vbo.release(); g.ibo.release()
            if inst.texture is not None and id(inst.texture) not in seen:
                seen.add(id(inst.texture))
                inst.texture.release()
        amodal_targets = [t for f in self._amodal_fbos.values() for t in f.color_attachments]
        for obj in (self.fbo, self._static_fbo, *self._targets, self._depth, *self._static_targets,
                    self._static_depth, *self._amodal_fbos.values(), *amodal_targets,
                    *self._single_fbos.values()):
            obj.release()
        self.instances.clear()
        self.prog.release()
        self.prog_amodal.release()


__all__ = ["MODALITIES", "RenderError", "RenderResult", "Renderer"]
