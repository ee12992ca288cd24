"""Instrument-consistent poses (surftrack.pose.kinematic): a wrong shaft roll and displaced jaws are
corrected from the wrist; the parts' depths are fused; groups, single parts, unknown instruments and
foreign meshes are left alone."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from surftrack.geometry import rotation_angle_deg
from surftrack.instruments import load_instrument
from surftrack.instruments.kinematics import JointState
from surftrack.model.surfsurg6d import PartInfo
from surftrack.pose.estimator import PartPose
from surftrack.pose import kinematic
from surftrack.pose.kinematic import KinematicConfig, apply_kinematics, consistent_poses

Q = JointState(roll=0.4, pitch=0.35, yaw=-0.25, opening=0.5)


@pytest.fixture(scope="module")
def lnd():
    return load_instrument("large_needle_driver")


def _truth(lnd, t=(5.0, -3.0, 110.0), seed=0):
    base = np.eye(4)
    base[:3, :3] = Rotation.from_euler("xyz", [120, 20, 10], degrees=True).as_matrix()
    base[:3, 3] = t
    return {p: (T[:3, :3], T[:3, 3]) for p, T in lnd.forward(base, Q).items()}


def _corrupt(truth, seed=0):
    """Shaft rolled 50 deg about its own axis (the ambiguity of a near-symmetric part), jaws rotated 12 deg
    and moved 2.5 mm: what the per-part estimator gets wrong; the wrist is right."""
    rng = np.random.default_rng(seed)
    out = dict(truth)
    R, t = truth["shaft"]
    out["shaft"] = (R @ Rotation.from_euler("z", 50, degrees=True).as_matrix(), t)
    for jaw in ("jaw_left", "jaw_right"):
        R, t = truth[jaw]
        axis = rng.normal(size=3)
        dR = Rotation.from_rotvec(np.radians(12) * axis / np.linalg.norm(axis)).as_matrix()
        d = rng.normal(size=3)
        out[jaw] = (dR @ R, t + 2.5 * d / np.linalg.norm(d))
    return out


def test_wrong_roll_and_jaws_are_corrected_from_the_wrist(lnd):
    truth = _truth(lnd)
    bad = _corrupt(truth)
    obs = {p: (R, t, 1.0) for p, (R, t) in bad.items()}
    fitted, fit = consistent_poses(lnd, obs)
    assert set(fitted) == set(lnd.part_names)
    assert rotation_angle_deg(fitted["shaft"][0], truth["shaft"][0]) < 1.0  # the roll comes from the wrist
    assert rotation_angle_deg(fitted["wrist"][0], truth["wrist"][0]) < 1.0
    # its position is fused with the others' (the two jaws 2.5 mm off pull it by a fraction of that)
    assert np.linalg.norm(fitted["wrist"][1] - truth["wrist"][1]) < 1.0
    for jaw in ("jaw_left", "jaw_right"):  # placed by the wrist; only their opening comes from themselves
        assert np.linalg.norm(fitted[jaw][1] - truth[jaw][1]) < 1.0
        assert rotation_angle_deg(fitted[jaw][0], truth[jaw][0]) < rotation_angle_deg(bad[jaw][0], truth[jaw][0])
    assert abs(fit.joints.pitch - Q.pitch) < np.radians(2.0)  # (roll is relative to the fit's own zero-roll base)
    # Without the anchor weight the wrong shaft pulls the wrist along: the weight is what keeps it.
    loose, _ = consistent_poses(lnd, obs, KinematicConfig(anchor_weight=1.0))
    assert (rotation_angle_deg(loose["wrist"][0], truth["wrist"][0])
            > rotation_angle_deg(fitted["wrist"][0], truth["wrist"][0]))


def test_depth_is_fused_across_parts(lnd):
    """Monocular part poses are off mostly along the viewing ray, independently per part. The fit weighs
    the anchor's translation about 3x a part's (not 10x, as its rotation): the fitted wrist is then
    nearer the truth in depth than the wrist's own estimate, and nearer than with the anchor's rotation
    weight on its translation too."""
    truth = _truth(lnd)
    rng = np.random.default_rng(3)
    sd = {"wrist": 1.0, "shaft": 1.8, "jaw_left": 3.5, "jaw_right": 1.8}  # mm, as measured (module docstring)
    own, fused, heavy = [], [], []
    for _ in range(40):
        obs = {}
        for p, (R, t) in truth.items():
            ray = t / np.linalg.norm(t)
            obs[p] = (R, t + rng.normal(0.0, sd[p]) * ray + rng.normal(0.0, 0.1, 3), 1.0)
        ray = truth["wrist"][1] / np.linalg.norm(truth["wrist"][1])
        own.append((obs["wrist"][1] - truth["wrist"][1]) @ ray)
        fused.append((consistent_poses(lnd, obs)[0]["wrist"][1] - truth["wrist"][1]) @ ray)
        old = consistent_poses(lnd, obs, KinematicConfig(anchor_translation_weight=10.0))[0]
        heavy.append((old["wrist"][1] - truth["wrist"][1]) @ ray)
    rms = lambda e: float(np.sqrt(np.mean(np.square(e))))  # noqa: E731
    assert rms(fused) < 0.85 * rms(own), (rms(fused), rms(own))
    assert rms(fused) < rms(heavy) < rms(own) * 1.05, (rms(fused), rms(heavy), rms(own))


def _part_poses(lnd, poses, instrument="large_needle_driver", score=1.0, ok=True):
    ids = {p: i + 1 for i, p in enumerate(lnd.part_names)}
    return [PartPose(ids[p], p, instrument, R.copy(), t.copy(), score, 50, ok, {}, (0, 0, 1, 1), np.eye(3))
            for p, (R, t) in poses.items()]


def _infos(lnd):
    return [PartInfo.from_part(i + 1, "large_needle_driver", lnd.parts[p]) for i, p in enumerate(lnd.part_names)]


def test_apply_kinematics_per_instance(lnd):
    a, b = _truth(lnd), _truth(lnd, t=(-30.0, 10.0, 140.0))
    results = _part_poses(lnd, _corrupt(a)) + _part_poses(lnd, _corrupt(b, seed=1))
    groups = [0] * 4 + [1] * 4
    out = apply_kinematics(results, groups, _infos(lnd))
    assert len(out) == 8
    for r, o in zip(results, out):  # every part takes its fitted pose, the anchor (wrist) too
        assert o.kinematic and o is not r
    for res, truth in ((out[:4], a), (out[4:], b)):  # each instance fitted to its own parts
        shaft = next(r for r in res if r.part == "shaft")
        assert rotation_angle_deg(shaft.R, truth["shaft"][0]) < 1.0
    assert results[0].counts == {}  # inputs untouched
    # A failed estimate stays as it is and does not pull the others.
    res = _part_poses(lnd, _corrupt(a))
    res[0].ok = False
    res[0].R, res[0].t = np.eye(3), np.zeros(3)
    out = apply_kinematics(res, [0] * 4, _infos(lnd))
    assert out[0] is res[0] and out[2].kinematic and not out[0].kinematic
    assert np.linalg.norm(out[2].t - a["jaw_left"][1]) < 1.0
    # Without the anchor (the wrist) nothing is fitted: the others would only follow each other.
    no_wrist = [r for r in _part_poses(lnd, _corrupt(a)) if r.part != "wrist"]
    assert all(o is r for o, r in zip(apply_kinematics(no_wrist, [0] * 3, _infos(lnd)), no_wrist))
    # Nor when the network sees nothing of the anchor (score <= 0), even if a pose was solved.
    unseen = _part_poses(lnd, _corrupt(a))
    next(r for r in unseen if r.part == "wrist").score = -0.2
    assert all(o is r for o, r in zip(apply_kinematics(unseen, [0] * 4, _infos(lnd)), unseen))


def test_apply_kinematics_leaves_what_it_cannot_fit(lnd, monkeypatch):
    monkeypatch.setattr(kinematic, "_instruments", {})  # warnings are given once per process
    monkeypatch.setattr(kinematic, "_warned", set())
    bad = _corrupt(_truth(lnd))
    one = _part_poses(lnd, {"shaft": bad["shaft"]})
    assert apply_kinematics(one, [0], _infos(lnd))[0] is one[0]  # a lone part: nothing to be consistent with
    split = _part_poses(lnd, bad)
    out = apply_kinematics(split, [0, 1, 2, 3], _infos(lnd))  # four instances of one part each
    assert all(o is s for o, s in zip(out, split))
    unknown = _part_poses(lnd, bad, instrument="my_custom_tool")
    with pytest.warns(UserWarning, match="has no description"):
        out = apply_kinematics(unknown, [0] * 4, _infos(lnd))
    assert all(o is s for o, s in zip(out, unknown))
    foreign = _infos(lnd)
    foreign[1].mesh_sha256 = "0" * 64  # the model was trained on another wrist mesh
    foreign[1].vertices = foreign[1].vertices + [0.0, 0.0, 0.01]
    with pytest.warns(UserWarning, match="differ"):
        out = apply_kinematics(split, [0] * 4, foreign)
    assert all(o is s for o, s in zip(out, split))
    with pytest.raises(ValueError, match="one group key per result"):
        apply_kinematics(split, [0], _infos(lnd))


def test_kinematic_config_checks():
    with pytest.raises(ValueError, match="anchor_weight"):
        KinematicConfig(anchor_weight=0.0)
    with pytest.raises(ValueError, match="anchor_translation_weight"):
        KinematicConfig(anchor_translation_weight=float("nan"))
    c = KinematicConfig()
    assert c.weight("wrist", 0.5) == pytest.approx(5.0) and c.weight("shaft", -1.0) == pytest.approx(0.05)
    assert c.weight("wrist", 0.5, translation=True) == pytest.approx(1.5)
    assert c.weight("shaft", 0.5, translation=True) == pytest.approx(0.5)
    assert c.weight("shaft", float("nan")) == pytest.approx(0.05)
