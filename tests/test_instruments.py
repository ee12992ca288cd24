"""Built-in instruments: meshes, kinematics, joint limits, derived quantities, collisions, CAD import,
BOP model export and malformed descriptions."""

from __future__ import annotations

import itertools
import json
import os
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from surftrack.geometry import rotation_about, se3, transform_points
from surftrack.instruments import (
    InstrumentError,
    JointLimits,
    JointState,
    KinematicChain,
    PartJoint,
    export_bop_models,
    list_instruments,
    load_bop_models,
    load_instrument,
    load_instrument_file,
    RollTwin,
)
from surftrack.instruments.procedural import BUILDERS
from surftrack.instruments.twin import TWIN_TOL_MM

EXPECTED = {
    "large_needle_driver": "lnd",
    "scissors": "mcs",
    "small_clip_applier": "sca",
    "cadiere_forceps": "cf",
    "biopsy_forceps": "bf",
    "permanent_cautery_spatula": "pcs",
}
PITCH_TO_YAW = 9.1
# Distance from the yaw axis to the 'tip' keypoint, mm (the builders' length parameters).
TIP_DISTANCE = {"large_needle_driver": 10.2, "scissors": 9.0, "small_clip_applier": 8.5,
                "cadiere_forceps": 12.0, "biopsy_forceps": 6.5, "permanent_cautery_spatula": 10.0}


@pytest.fixture(scope="module")
def instruments():
    return {name: load_instrument(name) for name in list_instruments()}


@pytest.fixture(scope="module")
def unique_parts(instruments):
    """Every distinct part mesh once (the shaft and wrist are shared by all instruments)."""
    out = {}
    for inst in instruments.values():
        for part in inst.parts.values():
            out.setdefault(part.mesh_hash, (f"{inst.name}/{part.name}", part))
    return list(out.values())


def tip_parts(inst):
    """Parts turning on the yaw axis (jaws, blades, the spatula)."""
    return [n for n, j in inst.chain.joints.items() if j.parent == "wrist"]


def Ry(a):
    return rotation_about(np.array([0.0, 1.0, 0.0]), a)


def Rz(a):
    return rotation_about(np.array([0.0, 0.0, 1.0]), a)


# --------------------------------------------------------------------------------------------------
# Library and meshes
# --------------------------------------------------------------------------------------------------

def test_builtin_instruments_load(instruments):
    assert sorted(instruments) == sorted(EXPECTED)
    for name, alias in EXPECTED.items():
        assert load_instrument(alias) is instruments[name]
        assert alias in instruments[name].aliases
        inst = instruments[name]
        assert inst.part_names[:2] == ("shaft", "wrist")
        assert inst.source is not None and inst.source.is_file()
        assert len(inst.attachments) == 1 and inst.attachments[0].part == "shaft"


def test_part_meshes_are_closed_solids(instruments):
    for inst in instruments.values():
        for part in inst.parts.values():
            m = part.mesh
            where = f"{inst.name}/{part.name}"
            assert m.is_watertight, where
            assert m.is_winding_consistent, where
            assert m.is_volume, where
            assert m.volume > 0, where
            assert m.body_count == 1, where
            assert 200 <= len(m.faces) <= 6000, (where, len(m.faces))


def test_builders_registered_and_distinct(instruments):
    for b in ("jaw_needle_driver", "jaw_scissors", "jaw_cadiere", "jaw_biopsy", "jaw_clip_applier", "spatula"):
        assert b in BUILDERS
    hashes = {inst.name: {inst.parts[p].mesh_hash for p in tip_parts(inst)} for inst in instruments.values()}
    for (a, ha), (b, hb) in itertools.combinations(hashes.items(), 2):
        assert not ha & hb, (a, b)
    # every instrument shares the same shaft and wrist geometry
    assert len({inst.parts["shaft"].mesh_hash for inst in instruments.values()}) == 1
    assert len({inst.parts["wrist"].mesh_hash for inst in instruments.values()}) == 1


def test_two_jaw_hubs_interleave(instruments):
    """Side +1 jaws keep their hub on +y near the yaw axis, side -1 on -y; jaws stay within |y| <= 1.5
    near the hub (the wrist lugs start at |y| = 1.65)."""
    for inst in instruments.values():
        for pname in tip_parts(inst):
            v = inst.parts[pname].mesh.vertices
            near = np.linalg.norm(v[:, [0, 2]], axis=1) < 3.0
            assert np.abs(v[near, 1]).max() <= 1.5 + 1e-9, (inst.name, pname)
        if len(tip_parts(inst)) == 2:
            hub = {}
            for pname in ("jaw_left", "jaw_right"):
                v = inst.parts[pname].mesh.vertices
                core = np.linalg.norm(v[:, [0, 2]], axis=1) < 1.0  # the hub around the bore
                hub[pname] = v[core, 1]
            assert hub["jaw_left"].min() > 0 and hub["jaw_right"].max() < 0, inst.name


# --------------------------------------------------------------------------------------------------
# Kinematics
# --------------------------------------------------------------------------------------------------

def test_zero_configuration(instruments):
    for inst in instruments.values():
        poses = inst.forward(np.eye(4), JointState())
        np.testing.assert_allclose(poses["shaft"], np.eye(4), atol=1e-12)
        np.testing.assert_allclose(poses["wrist"], np.eye(4), atol=1e-12)
        for p in tip_parts(inst):
            np.testing.assert_allclose(poses[p][:3, 3], [0, 0, PITCH_TO_YAW], atol=1e-12)
            np.testing.assert_allclose(poses[p][:3, :3], np.eye(3), atol=1e-12)
        kps = inst.keypoints(poses)
        np.testing.assert_allclose(kps["wrist/yaw_axis"], [0, 0, PITCH_TO_YAW], atol=1e-12)


def test_pitch_rotates_wrist_about_x(instruments):
    inst = instruments["large_needle_driver"]
    poses = inst.forward(np.eye(4), JointState.from_degrees(pitch=90))
    # the wrist turns about +x: +z goes to -y
    for p in tip_parts(inst):
        np.testing.assert_allclose(poses[p][:3, 3], [0, -PITCH_TO_YAW, 0], atol=1e-9)
    np.testing.assert_allclose(inst.keypoints(poses)["wrist/yaw_axis"], [0, -PITCH_TO_YAW, 0], atol=1e-9)
    poses = inst.forward(np.eye(4), JointState.from_degrees(pitch=-30))
    np.testing.assert_allclose(poses["wrist"][:3, 2], [0, -np.sin(np.radians(-30)), np.cos(np.radians(-30))], atol=1e-12)


@pytest.mark.parametrize("yaw,opening", [(0, 40), (30, 0), (-50, 60), (80, -20)])
def test_yaw_and_opening(instruments, yaw, opening):
    y, o = np.radians(yaw), np.radians(opening)
    for inst in instruments.values():
        poses = inst.forward(np.eye(4), JointState(yaw=y, opening=o))
        if len(tip_parts(inst)) == 2:
            np.testing.assert_allclose(poses["jaw_left"][:3, :3], Ry(y + o / 2), atol=1e-12)
            np.testing.assert_allclose(poses["jaw_right"][:3, :3], Ry(y - o / 2), atol=1e-12)
            # positive opening moves the left (+x) jaw's tip towards +x relative to the right one
            kps = inst.keypoints(poses)
            if opening > 0:
                assert kps["jaw_left/tip"][0] > kps["jaw_right/tip"][0]
        else:
            np.testing.assert_allclose(poses["spatula"][:3, :3], Ry(y), atol=1e-12)
        for p in tip_parts(inst):
            np.testing.assert_allclose(poses[p][:3, 3], [0, 0, PITCH_TO_YAW], atol=1e-12)


def test_roll_rotates_every_part_about_shaft_axis(instruments):
    rng = np.random.default_rng(1)
    for inst in instruments.values():
        q = JointState(roll=0.0, pitch=0.4, yaw=-0.7, opening=0.5)
        r = float(rng.uniform(-3, 3))
        p0 = inst.forward(np.eye(4), q)
        p1 = inst.forward(np.eye(4), JointState(roll=r, pitch=0.4, yaw=-0.7, opening=0.5))
        for n in inst.part_names:
            np.testing.assert_allclose(p1[n], se3(Rz(r), np.zeros(3)) @ p0[n], atol=1e-12)


def test_base_pose_composes(instruments):
    rng = np.random.default_rng(2)
    base = se3(rotation_about(rng.normal(size=3), 1.3), np.array([5.0, -20.0, 120.0]))
    for inst in instruments.values():
        q = JointState(roll=0.9, pitch=-0.6, yaw=0.3, opening=0.8)
        a = inst.forward(base, q)
        b = inst.forward(np.eye(4), q)
        for n in inst.part_names:
            np.testing.assert_allclose(a[n], base @ b[n], atol=1e-9)
        ka, kb = inst.keypoints(a), inst.keypoints(b)
        for k in kb:
            np.testing.assert_allclose(ka[k], transform_points(base, kb[k][None])[0], atol=1e-9)


def test_tip_keypoints(instruments):
    lnd = instruments["large_needle_driver"]
    for p in ("jaw_left", "jaw_right"):
        assert abs(np.linalg.norm(lnd.parts[p].keypoints["tip"]) - 10.2) <= 0.3
    rng = np.random.default_rng(3)
    for inst in instruments.values():
        for p in tip_parts(inst):
            assert "tip" in inst.parts[p].keypoints, (inst.name, p)
        for _ in range(5):
            q = JointState(*rng.uniform(-1.2, 1.2, size=4))
            kps = inst.keypoints(inst.forward(np.eye(4), q))
            for p in tip_parts(inst):
                d = np.linalg.norm(kps[f"{p}/tip"] - kps["wrist/yaw_axis"])
                assert abs(d - TIP_DISTANCE[inst.name]) <= 0.3, (inst.name, p, d)


# --------------------------------------------------------------------------------------------------
# Joint limits
# --------------------------------------------------------------------------------------------------

def test_joint_limits(instruments):
    lnd = instruments["large_needle_driver"]
    lim = lnd.limits
    assert set(lim.ranges) == {"roll", "pitch", "yaw", "opening"}
    np.testing.assert_allclose(lim.ranges["pitch"], np.radians([-80, 80]))
    inside = JointState.from_degrees(roll=100, pitch=-80, yaw=45, opening=80)
    assert lim.contains(inside)
    assert lim.clip(inside) == inside
    outside = JointState.from_degrees(roll=300, pitch=-95, yaw=10, opening=-30)
    assert not lim.contains(outside)
    c = lim.clip(outside)
    assert lim.contains(c)
    np.testing.assert_allclose([c.roll, c.pitch, c.yaw, c.opening], np.radians([260, -80, 10, -20]))
    # the spatula has no opening limit: any opening is fine, clipping leaves it alone
    pcs = instruments["permanent_cautery_spatula"].limits
    assert "opening" not in pcs.ranges
    q = JointState.from_degrees(yaw=30, opening=500)
    assert pcs.contains(q) and pcs.clip(q).opening == q.opening
    assert not pcs.contains(JointState.from_degrees(yaw=81))
    with pytest.raises(ValueError):
        JointLimits({"pitch": (1.0, -1.0)})
    with pytest.raises(ValueError):
        JointLimits({"elbow": (-1.0, 1.0)})


# --------------------------------------------------------------------------------------------------
# Derived quantities: diameters, normalisation, surface samples
# --------------------------------------------------------------------------------------------------

def test_diameters_and_normalisation(unique_parts):
    rng = np.random.default_rng(4)
    for where, part in unique_parts:
        v = part.mesh.vertices
        d = part.diameter_max_pairwise
        i, j = rng.integers(0, len(v), size=(2, 5000))
        assert d >= np.linalg.norm(v[i] - v[j], axis=1).max() - 1e-9, where
        far = np.linalg.norm(v - v[0], axis=1).max()
        assert d >= far - 1e-9, where
        assert d <= part.diameter_bbox_diagonal + 1e-9, where
        assert d >= part.mesh.extents.max() - 1e-9, where
        n = part.normalise(v)
        assert np.linalg.norm(n, axis=1).max() <= 1.0 + 1e-9, where
        np.testing.assert_allclose(part.denormalise(n), v, atol=1e-9)
        c, r = part.bounding_sphere
        assert d / 2 - 1e-9 <= r <= d / np.sqrt(3) + 1e-9, where  # Jung's theorem bounds


def test_surface_samples(unique_parts):
    for where, part in unique_parts:
        pts, nrm = part.sample_surface(3000, seed=5)
        assert pts.shape == (3000, 3) and nrm.shape == (3000, 3)
        closest, dist, tri = trimesh.proximity.closest_point(part.mesh, pts)
        assert dist.max() < 1e-6, where
        np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1.0, atol=1e-9)
        # outward: a step along the normal leaves the solid; a step against it enters it, except for
        # samples within 0.01 mm of a sharp convex edge (blade tips), where it may exit again: allow 1 %.
        sub = slice(0, 600)
        out = ~part.mesh.contains(pts[sub] + 0.01 * nrm[sub])
        inn = part.mesh.contains(pts[sub] - 0.01 * nrm[sub])
        assert out.all(), (where, np.flatnonzero(~out)[:5])
        assert inn.mean() >= 0.99, (where, inn.mean())
        # area-uniform: split the faces into the small ones and the large ones at half the area; the
        # samples must split by area (a face-uniform sampler would put most of them on the small faces)
        areas = part.mesh.area_faces
        order = np.argsort(areas)
        cum = np.cumsum(areas[order]) / areas.sum()
        small = np.zeros(len(areas), bool)
        small[order[: np.searchsorted(cum, 0.5) + 1]] = True
        p = areas[small].sum() / areas.sum()
        frac = small[tri].mean()
        sigma = np.sqrt(p * (1 - p) / len(pts))
        assert abs(frac - p) < 5 * sigma + 0.005, (where, frac, p)
        assert small.mean() - p > 0.1, where  # the split does discriminate between the two samplers


# --------------------------------------------------------------------------------------------------
# Part-part collisions within the joint limits
# --------------------------------------------------------------------------------------------------

def _configurations(inst, count=50, seed=6):
    lim = {k: np.degrees(v) for k, v in inst.limits.ranges.items()}
    two_jaw = "opening" in lim
    openings = [0.0, 80.0] if two_jaw else [0.0]
    grid = [dict(roll=0.0, pitch=p, yaw=y, opening=o)
            for p, y, o in itertools.product([lim["pitch"][0], 0.0, lim["pitch"][1]],
                                             [lim["yaw"][0], 0.0, lim["yaw"][1]], openings)]
    rng = np.random.default_rng(seed)
    rand = [dict(roll=rng.uniform(*lim["roll"]), pitch=rng.uniform(*lim["pitch"]), yaw=rng.uniform(*lim["yaw"]),
                 opening=rng.uniform(0.0, 80.0) if two_jaw else 0.0) for _ in range(count - len(grid))]
    return grid + rand


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_no_part_collisions(instruments, name):
    inst = instruments[name]
    cm = trimesh.collision.CollisionManager()
    for pname, part in inst.parts.items():
        cm.add_object(pname, part.mesh)
    configs = _configurations(inst)
    assert len(configs) >= 50
    bad = []
    for deg in configs:
        q = JointState.from_degrees(**deg)
        assert inst.limits.contains(q)
        for pname, T in inst.forward(np.eye(4), q).items():
            cm.set_transform(pname, T)
        hit, pairs = cm.in_collision_internal(return_names=True)
        if hit:
            bad.append((deg, sorted(pairs)))
    assert not bad, f"{name}: part collisions at {len(bad)} configurations, first: {bad[0]}"


def test_collision_check_detects_clamping(instruments):
    """Negative control: clamped past closure (opening < 0) the grasper jaws do intersect."""
    inst = instruments["large_needle_driver"]
    cm = trimesh.collision.CollisionManager()
    for pname, part in inst.parts.items():
        cm.add_object(pname, part.mesh)
    for pname, T in inst.forward(np.eye(4), JointState.from_degrees(opening=-20)).items():
        cm.set_transform(pname, T)
    hit, pairs = cm.in_collision_internal(return_names=True)
    assert hit and ("jaw_left", "jaw_right") in {tuple(sorted(p)) for p in pairs}


# --------------------------------------------------------------------------------------------------
# CAD import and BOP models
# --------------------------------------------------------------------------------------------------

def _write_cad_instrument(tmp_path: Path) -> Path:
    body = trimesh.creation.box(extents=(0.008, 0.004, 0.02))  # metres
    body.apply_translation((0, 0, -0.01))
    tip = trimesh.creation.cylinder(radius=0.0015, height=0.01, sections=24)
    tip.apply_translation((0, 0, 0.005))
    body.export(tmp_path / "body.stl")
    tip.export(tmp_path / "tip.stl")
    doc = {
        "name": "cad_tool",
        "aliases": ["ct"],
        "joint_limits_deg": {"roll": [-180, 180], "yaw": [-60, 60]},
        "parts": [
            {"name": "body", "mesh": {"file": "body.stl", "units": "m"},
             "joint": {"axis": [0, 0, 1], "angle": {"roll": 1.0}}, "keypoints": {"end": [0, 0, -20]}},
            {"name": "tip", "parent": "body", "mesh": {"file": "tip.stl", "units": "m"},
             "joint": {"axis": [0, 1, 0], "origin": [0, 0, 2], "angle": {"yaw": 1.0}},
             "material": {"color": [0.9, 0.1, 0.1], "metallic": 0.0, "roughness": 0.8},
             "keypoints": {"tip": [0, 0, 10]}},
        ],
    }
    path = tmp_path / "cad_tool.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def test_cad_import_and_bop_round_trip(tmp_path):
    inst = load_instrument_file(_write_cad_instrument(tmp_path))
    assert inst.name == "cad_tool" and inst.part_names == ("body", "tip")
    body, tip = inst.parts["body"], inst.parts["tip"]
    np.testing.assert_allclose(body.mesh.bounds, [[-4, -2, -20], [4, 2, 0]], atol=1e-5)
    assert len(body.mesh.vertices) == 8
    np.testing.assert_allclose(tip.mesh.bounds, [[-1.5, -1.5, 0], [1.5, 1.5, 10]], atol=1e-5)
    assert tip.mesh.is_watertight and body.mesh.is_watertight
    assert abs(body.mesh.volume - 8 * 4 * 20) < 1e-3
    np.testing.assert_allclose(body.diameter_max_pairwise, np.sqrt(8**2 + 4**2 + 20**2), atol=1e-5)
    np.testing.assert_allclose(body.diameter_bbox_diagonal, np.sqrt(8**2 + 4**2 + 20**2), atol=1e-5)
    assert tuple(tip.material.color) == (0.9, 0.1, 0.1)
    poses = inst.forward(np.eye(4), JointState(yaw=np.pi / 2))
    np.testing.assert_allclose(inst.keypoints(poses)["tip/tip"], [10, 0, 2], atol=1e-9)

    models = tmp_path / "models"
    names = export_bop_models([inst], models)
    assert names == {1: ("cad_tool", "body"), 2: ("cad_tool", "tip")}
    info = json.loads((models / "models_info.json").read_text())
    loaded = load_bop_models(models)
    assert sorted(loaded) == [1, 2]
    for obj_id, pname in names.items():
        orig, back = inst.parts[pname[1]], loaded[obj_id]
        assert back.name == pname[1]
        np.testing.assert_allclose(back.mesh.vertices, orig.mesh.vertices, atol=1e-4)
        np.testing.assert_array_equal(back.mesh.faces, orig.mesh.faces)
        rec = info[str(obj_id)]
        for k in ("diameter", "min_x", "min_y", "min_z", "size_x", "size_y", "size_z",
                  "instrument", "part", "diameter_bbox_diagonal", "mesh_sha256", "keypoints"):
            assert k in rec, k
        assert rec["instrument"] == "cad_tool" and rec["part"] == pname[1]
        np.testing.assert_allclose(rec["diameter"], orig.diameter_max_pairwise, rtol=1e-12)
        np.testing.assert_allclose([rec["min_x"], rec["min_y"], rec["min_z"]], orig.mesh.bounds[0], atol=1e-12)
        np.testing.assert_allclose([rec["size_x"], rec["size_y"], rec["size_z"]], orig.mesh.extents, atol=1e-12)
        assert rec["mesh_sha256"] == orig.mesh_hash
        np.testing.assert_allclose(rec["diameter"], back.diameter_max_pairwise, atol=1e-4)
        assert set(back.keypoints) == set(orig.keypoints)
        for k in orig.keypoints:
            np.testing.assert_allclose(back.keypoints[k], orig.keypoints[k])


def test_bop_export_of_builtin_instruments(instruments, tmp_path):
    insts = [instruments["large_needle_driver"], instruments["permanent_cautery_spatula"]]
    names = export_bop_models(insts, tmp_path / "models")
    assert len(names) == 4 + 3
    loaded = load_bop_models(tmp_path / "models")
    for obj_id, (iname, pname) in names.items():
        inst = next(i for i in insts if i.name == iname)
        np.testing.assert_allclose(loaded[obj_id].mesh.vertices, inst.parts[pname].mesh.vertices, atol=1e-4)


# --------------------------------------------------------------------------------------------------
# Malformed descriptions
# --------------------------------------------------------------------------------------------------

def _bad(tmp_path: Path, parts: list[dict], **extra) -> Path:
    trimesh.creation.box(extents=(1, 1, 1)).export(tmp_path / "cube.stl")
    path = tmp_path / "bad_tool.yaml"
    path.write_text(yaml.safe_dump({"name": "bad_tool", "parts": parts, **extra}))
    return path


CUBE = {"file": "cube.stl", "units": "mm"}


@pytest.mark.parametrize("parts,extra,message", [
    ([{"name": "a", "mesh": {"file": "missing.stl", "units": "mm"}}], {}, "does not exist"),
    ([{"name": "a", "mesh": {"builder": "no_such_builder"}}], {}, "unknown mesh builder"),
    ([{"name": "a", "mesh": {"builder": "shaft", "wingspan": 3}}], {}, "bad parameters"),
    ([{"name": "a", "mesh": {"file": "cube.stl", "units": "furlong"}}], {}, "units"),
    ([{"name": "a", "mesh": {"file": "cube.stl"}}], {}, "units"),
    ([{"name": "a", "mesh": {}}], {}, "builder"),
    ([{"name": "a", "mesh": CUBE}, {"name": "b", "parent": "ghost", "mesh": CUBE}], {}, "unknown parents"),
    ([{"name": "r", "mesh": CUBE}, {"name": "a", "parent": "b", "mesh": CUBE},
      {"name": "b", "parent": "a", "mesh": CUBE}], {}, "cycle"),
    ([{"name": "a", "mesh": CUBE}, {"name": "b", "mesh": CUBE}], {}, "exactly one root"),
    ([{"name": "a", "mesh": CUBE}, {"name": "a", "parent": "a", "mesh": CUBE}], {}, "used twice"),
    ([{"mesh": CUBE}], {}, "no 'name'"),
    ([{"name": "a", "mesh": CUBE, "joint": {"angle": {"elbow": 1.0}}}], {}, "unknown joint"),
    ([{"name": "a", "mesh": CUBE}], {"joint_limits_deg": {"pitch": [10, -10]}}, "lower"),
    ([], {}, "'parts'"),
])
def test_bad_descriptions_name_the_file(tmp_path, parts, extra, message):
    path = _bad(tmp_path, parts, **extra)
    with pytest.raises(InstrumentError) as e:
        load_instrument_file(path)
    assert str(path) in str(e.value)
    assert message in str(e.value)


def test_unreadable_descriptions(tmp_path):
    missing = tmp_path / "nope.yaml"
    with pytest.raises(InstrumentError, match="nope.yaml"):
        load_instrument_file(missing)
    with pytest.raises(InstrumentError, match="nope.yaml"):
        load_instrument(missing)
    broken = tmp_path / "broken.yaml"
    broken.write_text("name: [unclosed\n")
    with pytest.raises(InstrumentError, match="broken.yaml"):
        load_instrument_file(broken)
    junk = tmp_path / "junk.stl"
    junk.write_text("this is not a mesh")
    path = _bad(tmp_path, [{"name": "a", "mesh": {"file": "junk.stl", "units": "mm"}}])
    with pytest.raises(InstrumentError, match="bad_tool.yaml"):
        load_instrument_file(path)
    with pytest.raises(InstrumentError, match="unknown instrument"):
        load_instrument("no_such_instrument")


def test_user_instruments_from_the_search_path(tmp_path, monkeypatch):
    """A registry of the user's files or folders (``$SURFTRACK_INSTRUMENTS``, read by
    :meth:`InstrumentRegistry.from_env`) makes a user's description known by name, beside the built-in
    ones, without touching the process environment; an entry that does not exist is an error naming it."""
    from surftrack.instruments import INSTRUMENTS_ENV, InstrumentError, InstrumentRegistry, load_instrument

    lnd_yaml = Path(load_instrument("lnd").source).read_text()
    folder = tmp_path / "tools"
    folder.mkdir()
    (folder / "my_tool.yaml").write_text(lnd_yaml.replace("name: large_needle_driver", "name: my_tool")
                                         .replace("aliases: [lnd]", "aliases: [mt]"))
    with pytest.raises(InstrumentError, match="unknown instrument 'my_tool'"):
        load_instrument("my_tool")
    monkeypatch.setenv(INSTRUMENTS_ENV, str(folder))
    with pytest.raises(InstrumentError, match="unknown instrument 'my_tool'"):
        load_instrument("my_tool")  # the environment is read where a registry is made, nowhere else
    user = InstrumentRegistry.from_env()
    assert user == InstrumentRegistry.from_env({INSTRUMENTS_ENV: str(folder)}) == InstrumentRegistry((folder,))
    assert user.load("mt").name == "my_tool" and "my_tool" in user.names()
    assert user.load("lnd").name == "large_needle_driver"
    with pytest.raises(InstrumentError, match="missing.yaml: instrument description not found"):
        InstrumentRegistry((tmp_path / "missing.yaml",)).load("my_tool")
    # among the user's descriptions the first listed wins; none may claim a built-in name or alias
    v2 = tmp_path / "v2.yaml"
    v2.write_text((folder / "my_tool.yaml").read_text().replace("aliases: [mt]", "aliases: [mt2]"))
    both = InstrumentRegistry.from_env({INSTRUMENTS_ENV: os.pathsep.join([str(v2), str(folder)])})
    assert both.load("my_tool").source.resolve() == v2.resolve()
    assert both.load("mt").source.resolve() == (folder / "my_tool.yaml").resolve()
    assert user.ahead([v2]).load("my_tool").source.resolve() == v2.resolve()
    with pytest.raises(InstrumentError, match="nope.yaml: no such instrument description"):
        user.ahead([tmp_path / "nope.yaml"])
    for bad, msg in (("aliases: [mt]", "'lnd' is the built-in instrument"), ("aliases:\n  - ''", "'aliases' must be"),
                     ("aliases: mt", "'aliases' must be a list of names")):
        v2.write_text((folder / "my_tool.yaml").read_text().replace("aliases: [mt]", bad.replace("[mt]", "[lnd]")
                                                                    if "built-in" in msg else bad))
        with pytest.raises(InstrumentError, match=msg):
            both.load("lnd")


@pytest.mark.parametrize("name,twin", [("large_needle_driver", True), ("cadiere_forceps", True),
                                       ("biopsy_forceps", True), ("scissors", False),
                                       ("small_clip_applier", False), ("permanent_cautery_spatula", False)])
def test_roll_twins_of_the_builtin_instruments(instruments, name, twin):
    """Graspers with straight, mirrored jaws look the same half a turn about the shaft with the jaws
    exchanged (the LND's shaft groove deviates 0.45 mm); curved or bent blades and a one-sided spatula do
    not. The twin joint state's forward kinematics give the twin poses."""
    inst = instruments[name]
    tw = inst.roll_twin
    if not twin:
        assert tw is None
        return
    assert tw.partner == {"shaft": "shaft", "wrist": "wrist", "jaw_left": "jaw_right", "jaw_right": "jaw_left"}
    assert 0.3 < tw.deviation_mm["shaft"] < TWIN_TOL_MM and tw.deviation_mm["jaw_left"] < 0.05
    base = se3(rotation_about([0.3, 1.0, 0.2], 0.7), [4.0, -2.0, 90.0])
    q = JointState.from_degrees(roll=140, pitch=-50, yaw=30, opening=35)
    poses = {p: (T[:3, :3], T[:3, 3]) for p, T in inst.forward(base, q).items()}
    expect = inst.forward(base, RollTwin.joints(q))
    for p, (R, t) in tw.poses(poses).items():
        assert np.allclose(R, expect[p][:3, :3]) and np.allclose(t, expect[p][:3, 3]), p
    with pytest.raises(ValueError, match="partners"):
        tw.poses({"jaw_left": poses["jaw_left"]})


def test_the_nearer_of_poses_and_their_roll_twin():
    """RollTwin.nearer: poses that are the twin of the truth come back turned onto it; the truth stays."""
    from surftrack.instruments import load_instrument
    from surftrack.instruments.kinematics import JointState

    lnd = load_instrument("lnd")
    twin = lnd.roll_twin
    base = np.eye(4)
    base[:3, 3] = [5.0, -3.0, 90.0]
    truth = {p: (T[:3, :3], T[:3, 3]) for p, T in lnd.forward(base, JointState(0.4, 0.3, -0.2, 0.5)).items()}

    def cost(part, R, t):
        return float(np.linalg.norm(R - truth[part][0]) + np.linalg.norm(t - truth[part][1]))

    chosen, turned = twin.nearer(twin.poses(truth), cost)
    assert turned and all(cost(p, *pose) < 1e-9 for p, pose in chosen.items())
    same, turned = twin.nearer(truth, cost)
    assert not turned and all(cost(p, *pose) == 0.0 for p, pose in same.items())


def test_the_chain_bounds_how_far_apart_two_parts_origins_can_be():
    """The reach between two parts' origins is the summed lengths of the joint offsets between them, and
    no pose of the instrument puts them farther apart."""
    lnd = load_instrument("lnd")
    chain = lnd.chain
    assert chain.origin_reach("shaft", "wrist") == 0.0
    assert chain.origin_reach("wrist", "jaw_left") == pytest.approx(9.1)
    assert chain.origin_reach("jaw_left", "shaft") == pytest.approx(9.1)
    assert chain.origin_reach("jaw_left", "jaw_right") == pytest.approx(18.2)
    assert chain.origin_reach("jaw_right", "jaw_right") == 0.0
    # a deeper tree, offsets everywhere (the common ancestor's own offset is not between its children)
    deep = KinematicChain({
        "root": PartJoint(None, (3.0, 0.0, 0.0), (0.0, 0.0, 1.0), {"roll": 1.0}),
        "a": PartJoint("root", (0.0, 0.0, 5.0), (1.0, 0.0, 0.0), {"pitch": 1.0}),
        "b": PartJoint("a", (0.0, 7.0, 0.0), (0.0, 1.0, 0.0), {"yaw": 1.0}),
        "c": PartJoint("root", (11.0, 0.0, 0.0), (0.0, 0.0, 1.0), {"opening": 1.0}),
    })
    assert deep.origin_reach("b", "c") == pytest.approx(23.0) and deep.origin_reach("a", "b") == pytest.approx(7.0)
    with pytest.raises(KeyError):
        deep.origin_reach("b", "nowhere")
    rng = np.random.default_rng(0)
    for _ in range(50):
        q = JointState(*(rng.uniform(-3.0, 3.0, 4)))
        for tree, poses in ((chain, lnd.forward(np.eye(4), q)), (deep, deep.forward(np.eye(4), q))):
            for a in poses:
                for b in poses:
                    assert np.linalg.norm(poses[a][:3, 3] - poses[b][:3, 3]) <= tree.origin_reach(a, b) + 1e-9
