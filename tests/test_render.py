"""Renderer against a ray-casting oracle, and the consistency of its modalities."""

import multiprocessing as mp

import numpy as np
import pytest
import trimesh

from surftrack.geometry import PinholeCamera, crop_affine, rotation_about, se3, transform_points
from surftrack.instruments import JointState, Material, load_instrument, rcm_base_pose
from surftrack.render import (
    Light,
    Renderer,
    RenderError,
    add_instrument,
    corner_normals,
    endoscope_light,
    gl_context,
    worker_context,
)
from surftrack.synth import procedural_tissue

from .raycast import edge_pixels, raycast

W, H = 320, 256


@pytest.fixture(scope="module")
def scene():
    inst = load_instrument("lnd")
    cam = PinholeCamera(np.array([[300.0, 0, 161.3], [0, 302.0, 125.8], [0, 0, 1]]), W, H)
    tissue = procedural_tissue(np.random.default_rng(3), extent=(200.0, 170.0), spacing=2.5)
    tissue_pose = se3(rotation_about([1, 0.2, 0], 0.3), [0, 0, 95.0])
    base = rcm_base_pose([-60.0, -45.0, 10.0], [-3.0, -1.0, 55.0])
    part_poses = inst.forward(base, JointState.from_degrees(roll=25, pitch=35, yaw=-25, opening=40))
    r = Renderer(W, H)
    tid = tissue.add_to(r)
    handles = add_instrument(r, inst)
    poses = {tid: tissue_pose, **handles.poses(part_poses)}
    result = r.render(cam, poses, [endoscope_light(), Light(position=(20, 0, 0), intensity=0.3)])
    meshes = {tid: (tissue.mesh, tissue_pose)}
    meshes.update({iid: (inst.parts[p].mesh, part_poses[p]) for p, iid in handles.parts.items()})
    meshes.update({iid: (inst.attachments[k].mesh, part_poses[p]) for k, (p, iid) in enumerate(handles.attachments)})
    oracle = raycast(cam, meshes)
    yield dict(inst=inst, cam=cam, r=r, poses=poses, result=result, oracle=oracle, handles=handles,
               part_poses=part_poses, meshes=meshes, tid=tid)
    r.release()


def test_ids_and_depth_match_ray_casting(scene):
    ids, depth, _, _ = scene["oracle"]
    res = scene["result"]
    interior = ~edge_pixels(ids)
    mismatch = (res.instance != ids) & interior
    assert mismatch.sum() == 0, f"{mismatch.sum()} interior pixels differ from ray casting"
    # Instrument parts are present and cover a fair area: the test exercises what it claims to.
    for p, iid in scene["handles"].parts.items():
        assert (ids == iid).sum() > 30, p
    hit = interior & (ids > 0)
    assert np.abs(res.depth[hit] - depth[hit]).max() < 1e-3
    assert (res.depth[ids == 0] == 0).all() and (res.instance[ids == 0] == 0).all()


def test_object_coordinates_reproject_onto_their_pixels(scene):
    res, cam = scene["result"], scene["cam"]
    for iid, T in scene["poses"].items():
        v, u = np.nonzero(res.instance == iid)
        if len(u) == 0:
            continue
        uv = cam.project(transform_points(T, res.xyz[v, u].astype(np.float64)))
        err = np.linalg.norm(uv - np.c_[u, v], axis=1)
        assert err.max() < 0.5, f"instance {iid}: max reprojection error {err.max():.3f} px"


def test_normals_agree_with_mesh(scene):
    ids, _, face, pts = scene["oracle"]
    res = scene["result"]
    interior = ~edge_pixels(ids) & (ids > 0)
    checked = 0
    for iid, (mesh, T) in scene["meshes"].items():
        sel = interior & (ids == iid)
        if not sel.any():
            continue
        crease = 180.0 if iid == scene["tid"] else 30.0
        cn = corner_normals(mesh, crease)[face[sel]]  # (N, 3 corners, 3)
        tri = mesh.vertices[mesh.faces[face[sel]]]
        local = transform_points(np.linalg.inv(T), pts[sel])
        bary = trimesh.triangles.points_to_barycentric(tri, local)
        n = np.einsum("nk,nkj->nj", bary, cn) @ T[:3, :3].T
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        rays = pts[sel] / np.linalg.norm(pts[sel], axis=1, keepdims=True)
        n = np.where((np.einsum("nj,nj->n", n, rays) > 0)[:, None], -n, n)  # renderer faces normals to camera
        cos = np.einsum("nj,nj->n", n, res.normal[sel])
        assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 1.0, f"instance {iid}"
        checked += sel.sum()
    assert checked > 1000
    valid = res.instance > 0
    assert np.allclose(np.linalg.norm(res.normal[valid], axis=1), 1.0, atol=1e-4)


def test_visible_ids_follow_depth_order_and_amodal_masks(scene):
    r, cam, res = scene["r"], scene["cam"], scene["result"]
    for p, iid in scene["handles"].parts.items():
        alone = r.render(cam, {iid: scene["poses"][iid]}, modalities={"depth", "instance", "amodal"})
        # The amodal mask is the full silhouette: exactly what the part covers when rendered alone.
        assert np.array_equal(res.amodal[iid], alone.instance == iid)
        assert np.array_equal(alone.amodal[iid], alone.instance == iid)
        sil = alone.instance == iid
        # Wherever the part is hidden, whatever is visible is in front of it; where visible, depths agree.
        assert (res.depth[sil] <= alone.depth[sil] + 1e-4).all(), p
        vis = res.instance == iid
        assert np.allclose(res.depth[vis], alone.depth[vis], atol=1e-5)
        assert (vis <= sil).all()


def test_crop_intrinsics_render_the_same_pixels(scene):
    r, cam = scene["r"], scene["cam"]
    res = scene["result"]
    # A crop with unit scale and integer offset renders exactly the corresponding window of the full image.
    _, crop = crop_affine(cam, (40.0, 30.0, 40.0 + W, 30.0 + H), (W, H))
    cropped = r.render(crop, scene["poses"], modalities={"instance", "depth"})
    assert np.array_equal(cropped.instance[: H - 30, : W - 40], res.instance[30:, 40:])
    assert np.allclose(cropped.depth[: H - 30, : W - 40], res.depth[30:, 40:], atol=1e-3)


def test_batch_rendering_is_repeatable_and_shares_geometry(scene):
    r, cam = scene["r"], scene["cam"]
    a = r.render(scene["cam"], scene["poses"])
    moved = {k: se3(np.eye(3), [3.0, 0, 0]) @ T for k, T in scene["poses"].items()}
    r.render(cam, moved)
    b = r.render(cam, scene["poses"])
    for m in ("rgb", "depth", "instance", "xyz", "normal"):
        assert np.array_equal(getattr(a, m), getattr(b, m)), m
    jaw = scene["handles"].parts["jaw_left"]
    twin = r.add_instance(jaw, Material((0.2, 0.9, 0.2), 0.0, 0.5), amodal=True)
    T = scene["poses"][jaw]
    one = r.render(cam, {jaw: T}, modalities={"depth", "amodal"})
    two = r.render(cam, {twin: T}, modalities={"depth", "amodal"})
    assert np.array_equal(one.depth, two.depth) and np.array_equal(one.amodal[jaw], two.amodal[twin])


def test_static_layer_cache_gives_identical_images(scene):
    r, cam, tid = scene["r"], scene["cam"], scene["tid"]
    full = r.render(cam, scene["poses"])
    cached = r.render(cam, scene["poses"], static={tid})
    again = r.render(cam, scene["poses"], static={tid})  # served from the cache
    for m in ("rgb", "depth", "instance", "xyz", "normal"):
        assert np.array_equal(getattr(full, m), getattr(cached, m)), m
        assert np.array_equal(getattr(full, m), getattr(again, m)), m
    # Moving the static instance invalidates the cache.
    moved = dict(scene["poses"])
    moved[tid] = se3(np.eye(3), [0, 0, 8.0]) @ moved[tid]
    assert np.array_equal(r.render(cam, moved, static={tid}).depth, r.render(cam, moved).depth)


def test_rgb_lighting_and_texture():
    cam = PinholeCamera.from_fov(64, 64, 60.0)
    r = Renderer(64, 64)
    quad = trimesh.Trimesh([[-30, -30, 0], [30, -30, 0], [30, 30, 0], [-30, 30, 0]], [[0, 2, 1], [0, 3, 2]])
    tex = np.zeros((2, 2, 3), np.uint8)
    tex[:, 0] = (255, 0, 0)   # left half red, right half blue
    tex[:, 1] = (0, 0, 255)
    uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], float)
    q = r.add_mesh(quad, Material((1, 1, 1), 0.0, 0.8), uv=uv, texture=tex)
    pose = se3(np.eye(3), [0, 0, 60.0])
    lit = r.render(cam, {q: pose}, [endoscope_light(1.0)]).rgb.astype(int)
    assert lit[32, 5, 0] > lit[32, 5, 2] and lit[32, 58, 2] > lit[32, 58, 0]
    dim = r.render(cam, {q: pose}, [endoscope_light(0.2)]).rgb.astype(int)
    dark = r.render(cam, {q: pose}, []).rgb.astype(int)
    assert lit.sum() > dim.sum() > dark.sum()
    # On an untextured plane the spot light is brightest on its axis and falls off towards the corners.
    plain = r.add_mesh(quad, Material((0.8, 0.8, 0.8), 0.0, 0.9))
    grey = r.render(cam, {plain: pose}, [endoscope_light(0.5)]).rgb.astype(int).sum(-1)
    assert grey[32, 32] > grey[2, 2] + 20
    with pytest.raises(ValueError):
        r.render(cam, {99: pose})
    with pytest.raises(ValueError):
        r.render(PinholeCamera.from_fov(32, 32, 60.0), {q: pose})
    r.release()


def _render_sphere_depth(_=None):
    cam = PinholeCamera.from_fov(48, 40, 60.0)
    r = Renderer(48, 40)
    i = r.add_mesh(trimesh.creation.icosphere(radius=8))
    return r.render(cam, {i: se3(np.eye(3), [0, 0, 50.0])}, modalities={"depth"}).depth


def _context_in_forked_child(queue):
    try:
        gl_context()
        queue.put("created")
    except RenderError as e:
        queue.put(str(e))


def test_pool_workers_render_and_forked_children_fail_clearly():
    parent = _render_sphere_depth()  # the parent holds a context
    with worker_context().Pool(1) as pool:
        child = pool.map(_render_sphere_depth, [0])[0]
    assert np.array_equal(parent, child)
    q = mp.get_context("fork").Queue()
    p = mp.get_context("fork").Process(target=_context_in_forked_child, args=(q,))
    p.start()
    msg = q.get(timeout=60)
    p.join(timeout=60)
    assert "worker_context" in msg


def test_missing_egl_gives_a_clear_error(monkeypatch):
    import moderngl

    import surftrack.render.context as c

    def fail(**kw):
        raise Exception("libEGL.so: cannot open shared object file")

    monkeypatch.setattr(c, "_CTX", None)
    monkeypatch.setattr(moderngl, "create_context", fail)
    with pytest.raises(RenderError, match="libegl1"):
        c.gl_context()


def test_padded_amodal_masks_count_truncated_silhouettes(scene):
    r, cam = scene["r"], scene["cam"]
    shaft = scene["handles"].parts["shaft"]
    plain = r.render(cam, scene["poses"], modalities={"amodal"})
    padded = r.render(cam, scene["poses"], modalities={"amodal"}, amodal_pad=64)
    assert padded.amodal[shaft].shape == (H + 128, W + 128)
    for iid in plain.amodal:
        # The image part of a padded mask is exactly the unpadded mask: same rays through the same pixels.
        assert np.array_equal(padded.amodal_in_image(iid), plain.amodal[iid])
        assert padded.amodal[iid].sum() >= plain.amodal[iid].sum()
    # The shaft runs out of the image: padding finds more of its silhouette.
    assert padded.amodal[shaft].sum() > plain.amodal[shaft].sum()


def test_removing_an_instance_frees_unshared_geometry():
    cam = PinholeCamera.from_fov(48, 40, 60.0)
    r = Renderer(48, 40)
    a = r.add_mesh(trimesh.creation.icosphere(radius=8))
    b = r.add_instance(a)
    r.remove(a)  # b still uses the geometry
    depth = r.render(cam, {b: se3(np.eye(3), [0, 0, 50.0])}, modalities={"depth"}).depth
    assert (depth > 0).sum() > 50
    r.remove(b)
    with pytest.raises(ValueError):
        r.render(cam, {b: se3(np.eye(3), [0, 0, 50.0])})
    r.release()


def test_the_readme_rendering_example_runs():
    """The README's "Rendering an instrument yourself" snippet, with the built-in LND for the user's YAML."""
    import re
    from pathlib import Path

    readme = (Path(__file__).resolve().parent.parent / "README.md").read_text()
    code = re.search(r"```python\n(.*?)```", readme, re.S).group(1)
    scope: dict = {}
    exec("\n".join(line[2:] for line in code.splitlines()).replace('"my_tool.yaml"', '"lnd"'), scope)
    res = scope["res"]
    assert res.rgb.shape == (512, 640, 3) and 0.01 < (res.instance > 0).mean() < 0.5
    scope["renderer"].release()


def test_the_roll_twin_renders_the_same_silhouettes_with_the_jaws_exchanged(scene):
    """Half a turn about the shaft, the wrist's angles negated: every part's visible pixels are those of
    its partner in the original configuration (the jaws exchanged); only the shaft's groove differs. This
    is why one image cannot tell the twin from the truth (surftrack.instruments.twin)."""
    inst, r, cam, handles = scene["inst"], scene["r"], scene["cam"], scene["handles"]
    twin = inst.roll_twin
    base = rcm_base_pose([-60.0, -45.0, 10.0], [-3.0, -1.0, 55.0])
    q = JointState.from_degrees(roll=25, pitch=35, yaw=-25, opening=40)
    ids = set(handles.parts.values())

    def visible(q):
        poses = handles.poses(inst.forward(base, q))
        res = r.render(cam, poses, modalities={"instance"})
        return {p: res.instance == iid for p, iid in handles.parts.items()}, np.isin(res.instance, list(ids))

    a, union_a = visible(q)
    b, union_b = visible(twin.joints(q))
    iou = lambda m, n: (m & n).sum() / max((m | n).sum(), 1)  # noqa: E731
    assert iou(union_a, union_b) > 0.98
    for p in inst.part_names:
        assert a[p].sum() > 30, p
        assert iou(b[twin.partner[p]], a[p]) > 0.95, p
    assert iou(b["jaw_left"], a["jaw_left"]) < 0.5  # the labels did trade places
