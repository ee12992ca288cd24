"""A lab's own CAD, end to end, on CAD-like meshes the tests build: separate parts touching at their pins,
a binary PLY with n-gon faces, COLLADA and GLB files, meshes in metres and centimetres, a 300 mm shaft tube in
a foreign frame that needs the per-mesh transform."""

import json
import struct

import numpy as np
import pytest
import trimesh
from mcap.reader import make_reader

from surftrack.cli import main
from surftrack.instruments import InstrumentError, InstrumentRegistry, JointState, fit_configuration, load_instrument_file
from surftrack.instruments.cad import read_mesh_file
from surftrack.instruments.check import check_instrument, size_warnings
from surftrack.instruments.contacts import ContactRule, collision_manager, contact_depths
from surftrack.synth.checks import PartCollision

_QUADS = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]


def _box_corners(lo, hi) -> np.ndarray:
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    return np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                     [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], dtype=np.float64)


def write_ngon_ply(path, vertices, polygons, binary=True) -> None:
    """A PLY as Blender writes it: faces of several lengths in one list property."""
    head = (f"ply\nformat {'binary_little_endian' if binary else 'ascii'} 1.0\nelement vertex {len(vertices)}\n"
            "property float x\nproperty float y\nproperty float z\n"
            f"element face {len(polygons)}\nproperty list uchar int vertex_indices\nend_header\n")
    with open(path, "wb") as f:
        f.write(head.encode())
        for v in vertices:
            f.write(struct.pack("<3f", *v) if binary else ("%g %g %g\n" % tuple(v)).encode())
        for poly in polygons:
            f.write(struct.pack(f"<B{len(poly)}i", len(poly), *poly) if binary
                    else (" ".join(map(str, [len(poly), *poly])) + "\n").encode())


def make_cad_tool(d, shaft_cut: bool = True, name: str = "cad_tool", units_wrist: str = "mm"):
    """Files and a YAML of a four-part wristed tool, each mesh as a CAD tool would hand it over."""
    d.mkdir(parents=True, exist_ok=True)
    # Shaft: a 300 mm tube along +x of its file, in metres, with a flat on one side (so its roll shows).
    tube = trimesh.creation.cylinder(radius=0.004, segment=[[0.0, 0, 0], [0.3, 0, 0]], sections=24)
    flat = trimesh.creation.box(bounds=[[0.0, 0.0032, -0.005], [0.02, 0.006, 0.005]])
    tube = trimesh.boolean.difference([tube, flat], engine="manifold")
    tube.export(d / "shaft.stl")
    # Wrist: a clevis block from 2 mm behind the pitch axis to the yaw axis at 9 mm (n-gon PLY, mm), a
    # pin through it along x (OBJ).
    write_ngon_ply(d / "wrist.ply", _box_corners((-3, -2.5, -2), (3, 2.5, 10)), _QUADS)
    trimesh.creation.cylinder(radius=0.7, segment=[[-4, 0, 0], [4, 0, 0]]).export(d / "pitch_pin.obj")
    # Jaws: 12 mm long, touching each other and the wrist at the yaw pin; the left one COLLADA (mm), the
    # right one GLB in centimetres.
    left = trimesh.creation.box(bounds=[[0.0, -1.0, -1.5], [1.4, 1.0, 12.0]])
    left.export(d / "jaw_left.dae")
    right = trimesh.creation.box(bounds=[[-0.14, -0.1, -0.15], [0.0, 0.1, 1.2]])
    trimesh.Scene(right).export(d / "jaw_right.glb")
    shaft_mesh = "{file: shaft.stl, units: m, rpy_deg: [0, 90, 0], origin: [0, 0, 2]" + \
        (", shaft_length_mm: 40}" if shaft_cut else "}")
    (d / f"{name}.yaml").write_text(f"""name: {name}
aliases: []
description: CAD-like test tool
joint_limits_deg: {{roll: [-180, 180], pitch: [-70, 70], yaw: [-70, 70], opening: [0, 60]}}
parts:
  - name: shaft
    mesh: {shaft_mesh}
    joint: {{axis: [0, 0, 1], angle: {{roll: 1.0}}}}
    material: {{color: [0.05, 0.05, 0.05], metallic: 0.1, roughness: 0.45}}
  - name: wrist
    parent: shaft
    mesh:
      - {{file: wrist.ply, units: {units_wrist}}}
      - {{file: pitch_pin.obj, units: mm}}
    joint: {{axis: [1, 0, 0], angle: {{pitch: 1.0}}}}
  - name: jaw_left
    parent: wrist
    mesh: {{file: jaw_left.dae, units: mm}}
    joint: {{origin: [0, 0, 9], axis: [0, 1, 0], angle: {{yaw: 1.0, opening: 0.5}}}}
  - name: jaw_right
    parent: wrist
    mesh: {{file: jaw_right.glb, units: cm}}
    joint: {{origin: [0, 0, 9], axis: [0, 1, 0], angle: {{yaw: 1.0, opening: -0.5}}}}
""")
    return d / f"{name}.yaml"


@pytest.fixture(scope="module")
def cad_yaml(tmp_path_factory):
    return make_cad_tool(tmp_path_factory.mktemp("cad"))


def test_ngon_ply_is_read_where_trimesh_fails(tmp_path):
    corners = _box_corners((0, 0, 0), (1, 1, 1))
    polys = _QUADS[:5] + [[3, 0, 4], [3, 4, 7]]  # quads and triangles mixed, as Blender writes them
    write_ngon_ply(tmp_path / "b.ply", corners, polys, binary=True)
    mesh = read_mesh_file(tmp_path / "b.ply")
    assert len(mesh.faces) == 12 and trimesh.Trimesh(mesh.vertices, mesh.faces).is_watertight
    assert trimesh.Trimesh(mesh.vertices, mesh.faces).volume == pytest.approx(1.0)
    pent = np.array([[np.cos(a), np.sin(a), 0.0] for a in np.linspace(0, 2 * np.pi, 6)[:5]])
    write_ngon_ply(tmp_path / "p.ply", pent, [[0, 1, 2, 3, 4]], binary=False)
    assert len(read_mesh_file(tmp_path / "p.ply").faces) == 3
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat ascii 1.0\nend_header\n")
    with pytest.raises(ValueError, match="bad.ply"):
        read_mesh_file(tmp_path / "bad.ply")


def test_cad_parts_come_out_in_mm_and_joint_frames(cad_yaml):
    tool = load_instrument_file(cad_yaml)
    shaft = tool.parts["shaft"].mesh
    # the tube, turned from +x onto -z and cut 40 mm behind the pitch axis; the rest is rendered only
    assert shaft.bounds[0][2] == pytest.approx(-40.0, abs=1e-3) and shaft.bounds[1][2] == pytest.approx(2.0, abs=1e-3)
    assert shaft.is_watertight and np.abs(shaft.bounds[:, :2]).max() == pytest.approx(4.0, abs=0.01)
    (att,) = tool.attachments
    assert att.part == "shaft" and att.mesh.bounds[0][2] == pytest.approx(-298.0, abs=1e-3)
    assert size_warnings(tool) == []
    assert tool.parts["wrist"].mesh.extents == pytest.approx([8.0, 5.0, 12.0])  # block and pin joined
    assert tool.parts["jaw_right"].mesh.extents == pytest.approx([1.4, 2.0, 13.5])  # cm -> mm
    assert tool.parts["jaw_left"].mesh.extents == pytest.approx([1.4, 2.0, 13.5])  # COLLADA
    # tips derived where none are given: the farthest point along the tool's axis
    assert set(tool.derived_tips) == {"jaw_left", "jaw_right"}
    assert tool.parts["jaw_left"].keypoints["tip"][2] == pytest.approx(12.0)
    long = load_instrument_file(make_cad_tool(cad_yaml.parent / "uncut", shaft_cut=False))
    (warning,) = size_warnings(long)
    assert "'shaft' is 300 mm long" in warning and "shaft_length_mm: 40" in warning


def test_mesh_transform_forms_agree_and_joint_rotation_composes(tmp_path):
    trimesh.creation.box(bounds=[[0, 0, 0], [1, 2, 3]]).export(tmp_path / "b.stl")

    def tool(mesh_extra: str, joint_extra: str = "") -> object:
        (tmp_path / "t.yaml").write_text(
            "name: t\nparts:\n  - name: shaft\n    mesh: {file: b.stl, units: mm, origin: [5, 0, 0]"
            f"{mesh_extra}}}\n  - name: jaw\n    parent: shaft\n    mesh: {{file: b.stl, units: mm}}\n"
            f"    joint: {{origin: [0, 0, 9], axis: [0, 0, 1], angle: {{yaw: 1.0}}{joint_extra}}}\n")
        return load_instrument_file(tmp_path / "t.yaml")

    rpy = tool(", rpy: [0, 0, 1.5707963267948966], scale: 2").parts["shaft"].mesh.bounds
    deg = tool(", rpy_deg: [0, 0, 90], scale: [2, 2, 2]").parts["shaft"].mesh.bounds
    quat = tool(", quat_xyzw: [0, 0, 0.7071067811865476, 0.7071067811865476], scale: 2").parts["shaft"].mesh.bounds
    assert rpy == pytest.approx(deg) and rpy == pytest.approx(quat)
    assert rpy == pytest.approx(np.array([[5 - 4, 0, 0], [5, 2, 6]]))  # scaled, turned +x -> +y, then moved
    # three angles: URDF's fixed-axis roll (x), pitch (y), yaw (z), R = Rz @ Ry @ Rx; scale before rotation
    a = [0.3, -0.7, 1.1]
    R = (trimesh.transformations.rotation_matrix(a[2], [0, 0, 1]) @ trimesh.transformations.rotation_matrix(a[1], [0, 1, 0])
         @ trimesh.transformations.rotation_matrix(a[0], [1, 0, 0]))
    got = tool(f", rpy: {a}, scale: [1, 2, 3]").parts["shaft"].mesh.bounds
    corners = trimesh.creation.box(bounds=[[0, 0, 0], [1, 4, 9]]).vertices
    want = corners @ R[:3, :3].T + [5, 0, 0]
    assert got == pytest.approx(np.array([want.min(0), want.max(0)]))
    T = tool("", f", rpy: {a}").forward(np.eye(4), JointState(yaw=0.4))["jaw"]
    assert T == pytest.approx(trimesh.transformations.translation_matrix([0, 0, 9]) @ R
                              @ trimesh.transformations.rotation_matrix(0.4, [0, 0, 1]))
    with pytest.raises(InstrumentError, match="give one of rpy, rpy_deg, quat_xyzw"):
        tool(", rpy: [0, 0, 1], quat_xyzw: [0, 0, 0, 1]")
    t = tool("", ", rpy_deg: [90, 0, 0]")
    T = t.forward(np.eye(4), JointState(yaw=0.3))["jaw"]
    Rx = trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0])
    Rz = trimesh.transformations.rotation_matrix(0.3, [0, 0, 1])
    assert T == pytest.approx(trimesh.transformations.translation_matrix([0, 0, 9]) @ Rx @ Rz)


@pytest.mark.parametrize("where", ["top", "part", "mesh", "joint", "material", "limits", "attachment", "list"])
def test_unknown_keys_are_errors_naming_key_and_file(tmp_path, capsys, where):
    trimesh.creation.box().export(tmp_path / "b.stl")
    body = ("name: t\nparts:\n  - name: shaft\n    mesh: {file: b.stl, units: mm}\n"
            "    joint: {axis: [0, 0, 1]}\n    material: {color: [1, 1, 1]}\n")
    body = {"top": body + "rotation: 1\n", "part": body + "    rotation: [0, 0, 0]\n",
            "mesh": body.replace("units: mm}", "units: mm, rotation: [0, 0, 0]}"),
            "joint": body.replace("axis: [0, 0, 1]}", "axis: [0, 0, 1], scale: 2}"),
            "material": body.replace("color:", "colour:"),
            "limits": body + "joint_limits_deg: {roll: [-90, 90], rotation: [0, 1]}\n",
            "attachment": body + "    attachments: [{file: b.stl, units: mm, rotation: 1}]\n",
            "list": body.replace("mesh: {file: b.stl, units: mm}", "mesh: [{file: b.stl, units: mm}, "
                                 "{file: b.stl, units: mm, rotation: 1}]")}[where]
    (tmp_path / "t.yaml").write_text(body)
    with pytest.raises(InstrumentError, match=r"t\.yaml.*unknown key '(rotation|scale|colour)'"):
        load_instrument_file(tmp_path / "t.yaml")
    assert main(["instruments", str(tmp_path / "t.yaml")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "unknown key" in err and "t.yaml" in err


def test_touching_cad_parts_pass_the_collision_rule_and_check_reports_them(cad_yaml, capsys):
    tool = load_instrument_file(cad_yaml)
    rest = tool.forward(np.eye(4), tool.limits.clip(__import__("surftrack").instruments.JointState()))
    touching = contact_depths(collision_manager({n: p.mesh for n, p in tool.parts.items()}), rest)
    assert ("shaft", "wrist") in touching and ("jaw_left", "wrist") in touching  # what rejected every pose
    rule = ContactRule.of(tool)
    assert set(rule.at_rest) == set(touching)
    assert PartCollision([tool]).collisions_of([(tool, rest)]) == []
    report = check_instrument(tool, samples=40)
    assert report.warnings == []
    assert main(["instruments", str(cad_yaml), "--check"]) == 0
    out = capsys.readouterr().out
    assert "shaft - wrist: in contact at rest" in out and "tip (derived)" in out
    assert "jaw_left - shaft: not linked: any contact rejects" in out
    uncut = cad_yaml.parent / "uncut" / "cad_tool.yaml"
    if not uncut.is_file():
        make_cad_tool(cad_yaml.parent / "uncut", shaft_cut=False)
    assert main(["instruments", str(uncut), "--check"]) == 1
    assert "warning:" in capsys.readouterr().out


def test_frames_figure_draws_the_cad_tool(cad_yaml, tmp_path):
    assert main(["instruments", str(cad_yaml), "--figure", str(tmp_path / "f.png")]) == 0
    from PIL import Image
    img = np.asarray(Image.open(tmp_path / "f.png")).astype(int)
    assert img.shape == (480, 1280, 3)
    joint_axes = (np.abs(img - [255, 220, 0]).max(axis=-1) < 40).sum()       # the yellow joint axes and labels
    x_axes = ((img[..., 0] > 180) & (img[..., 1] < 90) & (img[..., 2] < 90)).sum()  # the red x axes
    assert joint_axes > 200 and x_axes > 50


def test_cad_geometry_survives_the_dataset_round_trip(cad_yaml, tmp_path):
    """The float32 PLY models of a dataset change every byte of a metre-unit mesh, not the part."""
    from surftrack.instruments import export_bop_models, load_bop_models
    from surftrack.model.surfsurg6d import PartInfo
    from surftrack.pose.kinematic import described_instrument, instrument_parts

    tool = load_instrument_file(cad_yaml)
    ids = export_bop_models([tool], tmp_path / "models")
    models = load_bop_models(tmp_path / "models")
    infos = [PartInfo.from_part(o, tool.name, models[o]) for o in sorted(ids)]
    assert any(i.mesh_sha256 != tool.parts[i.name].mesh_hash for i in infos)  # the bytes moved (metres)
    registry = InstrumentRegistry().ahead([cad_yaml])
    inst, why = described_instrument(tool.name, instrument_parts(infos)[tool.name], registry=registry)
    assert inst is not None and why == ""
    infos[1].vertices = infos[1].vertices + [0.0, 0.0, 0.01]  # an edited mesh is another part
    infos[1].mesh_sha256 = "edited"
    inst, why = described_instrument(tool.name, instrument_parts(infos)[tool.name], registry=registry)
    assert inst is None and "differ" in why


def test_synth_accepts_cad_images_and_fails_honestly_on_a_unit_mistake(cad_yaml, tmp_path, capsys):
    cfg = tmp_path / "small.yaml"
    cfg.write_text("image: {width: 320, height: 256}\ntwo_instruments_prob: 0.0\n"
                   "tissue: {images_per_tissue: 4, spacing_mm: 4.0, texel_mm: 1.0}\n"
                   "output: {images_per_scene: 4, rgb_format: png}\n")
    out = tmp_path / "ok"
    assert main(["synth", "--instruments", str(cad_yaml), "--images", "4", "--out", str(out), "--config", str(cfg),
                 "--quiet"]) == 0
    card = json.loads((out / "dataset_card.json").read_text())
    assert card["acceptance"]["accepted"] == 4 and card["acceptance"]["acceptance_rate"] >= 0.5
    capsys.readouterr()
    # the wrist declared in metres is 1000 times too large: nothing fits, and the command says so
    giant = make_cad_tool(tmp_path / "giant", name="giant_tool", units_wrist="m")
    bad = tmp_path / "bad"
    assert main(["synth", "--instruments", str(giant), "--images", "2", "--out", str(bad), "--config", str(cfg),
                 "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "no image accepted in 120 attempts" in err and "likely cause" in err


def test_synth_clip_failure_is_one_line(cad_yaml, tmp_path, capsys):
    giant = make_cad_tool(tmp_path / "giant", name="giant_tool", units_wrist="m")
    assert main(["synth-clip", "--instrument", str(giant), "--second", "none", "--out", str(tmp_path / "c"),
                 "--seconds", "1", "--fps", "5", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "no valid motion plan for giant_tool" in err and "--check" in err


def test_a_model_trained_on_cad_tracks_with_joint_angles(cad_yaml, tmp_path, capsys):
    """synth -> train (a few real steps) -> synth-clip -> track with --instrument: JointStates in the MCAP."""
    from surftrack.model.config import TrainConfig
    from surftrack.model.train import train
    from surftrack.synth.config import load_synth_config
    from surftrack.synth.generate import generate_dataset
    from tests.test_train import TINY

    data = tmp_path / "data"
    cfg = load_synth_config(overrides={
        "instruments": [str(cad_yaml)], "image": {"width": 320, "height": 256}, "two_instruments_prob": 0.0,
        "tissue": {"images_per_tissue": 3, "spacing_mm": 4.0, "texel_mm": 1.0},
        "output": {"images_per_scene": 6, "rgb_format": "png"}})
    generate_dataset(data, cfg, 4, seed=5, workers=1, progress=False, instruments=InstrumentRegistry().ahead([cad_yaml]))
    ckpt = tmp_path / "cad.pt"
    train(TrainConfig.from_dict(TINY).replace(optim={"steps": 3}, run={"val_every": 100, "ckpt_every": 100}),
          data, ckpt, progress=False)
    clip = tmp_path / "clip"
    assert main(["synth-clip", "--instrument", str(cad_yaml), "--second", "none", "--out", str(clip),
                 "--seconds", "1", "--fps", "5", "--seed", "2", "--quiet"]) == 0
    (tmp_path / "accept_all.yaml").write_text("init_min_score: -1000000000.0\ninit_min_inliers: 0\n")
    capsys.readouterr()
    assert main([str(clip / "video.mp4"), "--boxes", str(clip / "det.json"), "--camera", str(clip / "camera.json"),
                 "--model", str(ckpt), "--instrument", str(cad_yaml), "-o", str(tmp_path / "t.mcap"),
                 "--config", str(tmp_path / "accept_all.yaml"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "differ" not in out and "no joint angles" not in out
    with open(tmp_path / "t.mcap", "rb") as f:
        topics = {c.topic for c in make_reader(f).get_summary().channels.values()}
    assert "/instruments/cad_tool.0/joints" in topics


def test_contact_rule_rejects_deep_linked_and_any_unlinked_contact(cad_yaml):
    tool = load_instrument_file(cad_yaml)
    rule = ContactRule.of(tool)
    assert rule.rejects("jaw_left", "shaft", 0.0)               # not linked, not touching at rest
    assert not rule.rejects("jaw_left", "wrist", 5.0)            # touching at rest: not tested
    lnd = __import__("surftrack").instruments.load_instrument("lnd")
    lnd_rule = ContactRule.of(lnd)
    assert not lnd_rule.at_rest and ("shaft", "wrist") in lnd_rule.linked
    assert not lnd_rule.rejects("shaft", "wrist", 0.2) and lnd_rule.rejects("shaft", "wrist", 0.5)
    # jaws clamped into each other (a negative opening) are rejected by the synthesis check
    poses = lnd.forward(np.eye(4), JointState.from_degrees(opening=-20))
    assert ("0|jaw_left", "0|jaw_right") in PartCollision([lnd]).collisions_of([(lnd, poses)])


def test_fixed_joint_rotations_reach_the_instrument_fit(tmp_path):
    """A URDF-like chain (joint frames turned by rpy) is fitted back to its joints from its part poses."""
    yaml_text = (make_cad_tool(tmp_path / "t").read_text()
                 .replace("joint: {axis: [1, 0, 0], angle: {pitch: 1.0}}",
                          "joint: {rpy_deg: [-90, -90, 0], axis: [0, 0, 1], angle: {pitch: 1.0}}")
                 .replace("joint: {origin: [0, 0, 9], axis: [0, 1, 0]",
                          "joint: {origin: [0, 0, 9], rpy_deg: [0, -90, -90], axis: [0, 0, 1]"))
    (tmp_path / "t" / "rot.yaml").write_text(yaml_text.replace("name: cad_tool", "name: rot_tool"))
    tool = load_instrument_file(tmp_path / "t" / "rot.yaml")
    q = JointState.from_degrees(roll=20, pitch=25, yaw=-30, opening=35)
    from surftrack.instruments import rcm_base_pose
    poses = tool.forward(rcm_base_pose(np.array([-60.0, -40.0, 20.0]), np.array([5.0, -3.0, 90.0])), q)
    from surftrack.instruments.fit import _pair_relations  # the closed-form start: exact for exact poses
    A, b = _pair_relations(tool, poses)
    assert len(A) == 3 and A @ np.array([q.roll, q.pitch, q.yaw, q.opening]) == pytest.approx(b, abs=1e-9)
    fit = fit_configuration(tool, {p: (T[:3, :3], T[:3, 3]) for p, T in poses.items()})
    assert np.degrees([getattr(fit.joints, n) - getattr(q, n) for n in ("roll", "pitch", "yaw", "opening")]) == \
        pytest.approx([0, 0, 0, 0], abs=0.05)


def test_reach_takes_one_turn_of_roll_and_closed_to_open_jaws(tmp_path):
    trimesh.creation.box().export(tmp_path / "b.stl")
    (tmp_path / "t.yaml").write_text(
        "name: t\njoint_limits_deg: {roll: [0, 400], opening: [-20, 60]}\nparts:\n"
        "  - name: shaft\n    mesh: {file: b.stl, units: mm}\n    joint: {angle: {roll: 1.0}}\n")
    reach = load_instrument_file(tmp_path / "t.yaml").reach()
    assert np.degrees(reach["roll"]) == pytest.approx([0, 360]) and np.degrees(reach["opening"]) == pytest.approx([0, 60])
    assert reach["pitch"] == (0.0, 0.0)


def test_a_one_part_tool_gets_a_figure_and_a_warning_for_an_unlimited_joint(tmp_path, capsys):
    trimesh.creation.box(bounds=[[-1, -1, -20], [1, 1, 5]]).export(tmp_path / "b.stl")
    (tmp_path / "t.yaml").write_text("name: stick\nparts:\n  - name: shaft\n    mesh: {file: b.stl, units: mm}\n"
                                     "    joint: {angle: {roll: 1.0}}\n")
    assert main(["instruments", str(tmp_path / "t.yaml"), "--figure", str(tmp_path / "f.png"), "--check"]) == 1
    out = capsys.readouterr().out
    assert "joint 'roll' turns a part but has no limit" in out and (tmp_path / "f.png").is_file()
    assert main(["instruments", str(tmp_path / "t.yaml"), "--figure", str(tmp_path / "f")]) == 2
