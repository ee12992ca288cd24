"""Joint tracks: ``foxglove.JointStates`` messages in the MCAP log and the joint CSV."""

import csv
import json
import math

import jsonschema
import numpy as np
import pytest
from mcap.reader import make_reader

from surftrack.geometry import matrix_from_quat_xyzw
from surftrack.instruments import JOINT_NAMES, JointState, fit_configuration, load_instrument, rcm_base_pose
from surftrack.io import JOINT_CSV_COLUMNS, SCHEMAS, TrackWriter, write_joint_csv

TIMES = (0.0, 0.1, 0.25)


def positions(i):
    return [0.1 * i - 0.5, 0.2, -0.3 * i, 0.4 + 0.05 * i]  # rad


def read_all(path):
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        return [(s, c, m, json.loads(m.data)) for s, c, m in reader.iter_messages(log_time_order=True)]


def test_joint_states_round_trip(tmp_path):
    path = tmp_path / "joints.mcap"
    with TrackWriter(path) as w:
        for i, t in enumerate(TIMES):
            w.joint_states(t, "large_needle_driver", JOINT_NAMES, positions(i),
                           extra={"velocity": [1.0, None, math.nan, 2.5]})
        w.joint_states(0.3, "scissors", ["roll", "opening"], [0.5, math.nan])

    msgs = read_all(path)
    assert len(msgs) == len(TIMES) + 1
    lnd = [m for m in msgs if m[1].topic == "/instruments/large_needle_driver/joints"]
    assert len(lnd) == len(TIMES)
    for i, (schema, channel, message, msg) in enumerate(lnd):
        assert schema.name == "foxglove.JointStates" and schema.encoding == "jsonschema"
        assert channel.message_encoding == "json"
        schema_doc = json.loads(schema.data)
        assert schema_doc == SCHEMAS["foxglove.JointStates"]
        jsonschema.validate(msg, schema_doc)
        ns = round(TIMES[i] * 1e9)
        assert message.log_time == message.publish_time == ns
        assert msg["timestamp"]["sec"] * 1_000_000_000 + msg["timestamp"]["nsec"] == ns
        assert [j["name"] for j in msg["joints"]] == list(JOINT_NAMES)
        assert [j["position"] for j in msg["joints"]] == pytest.approx(positions(i))  # radians as given
        # None / NaN leave the field out (JSON has no NaN); given values are kept
        assert [j.get("velocity") for j in msg["joints"]] == [1.0, None, None, 2.5]
        assert all("effort" not in j and "acceleration" not in j for j in msg["joints"])
    sc = [m for m in msgs if m[1].topic == "/instruments/scissors/joints"][0][3]
    assert sc["joints"] == [{"name": "roll", "position": 0.5}, {"name": "opening"}]


def test_joint_states_rejects_bad_input(tmp_path):
    with TrackWriter(tmp_path / "bad.mcap") as w:
        with pytest.raises(ValueError, match="2 names but 1 positions"):
            w.joint_states(0.0, "lnd", ["roll", "pitch"], [0.1])
        with pytest.raises(ValueError, match="unknown extra"):
            w.joint_states(0.0, "lnd", ["roll"], [0.1], extra={"torque": [1.0]})
        with pytest.raises(ValueError, match="velocity"):
            w.joint_states(0.0, "lnd", ["roll", "pitch"], [0.1, 0.2], extra={"velocity": [1.0]})
        with pytest.raises(ValueError, match="name"):
            w.joint_states(0.0, "a/b", ["roll"], [0.1])
        with pytest.raises(ValueError, match="time"):
            w.joint_states(-1.0, "lnd", ["roll"], [0.1])


def test_joint_csv(tmp_path):
    inst = load_instrument("lnd")
    base = rcm_base_pose(np.array([-60.0, -40.0, 0.0]), np.array([5.0, 3.0, 80.0]))
    rows = []
    for i, t in enumerate(TIMES):
        q = JointState.from_degrees(roll=10.0 * i, pitch=-20.0, yaw=15.0 + i, opening=30.0 - 5 * i)
        poses = {n: (T[:3, :3], T[:3, 3]) for n, T in inst.forward(base, q).items()}
        if i == 2:
            del poses["shaft"]
        rows.append((t, inst.name, fit_configuration(inst, poses, init=rows[-1][2] if rows else None)))
    path = write_joint_csv(tmp_path / "joints.csv", rows)

    with open(path, newline="") as f:
        table = list(csv.DictReader(f))
    assert tuple(table[0]) == JOINT_CSV_COLUMNS
    assert len(table) == len(rows)
    for (t, name, fit), row in zip(rows, table):
        assert float(row["time_s"]) == pytest.approx(t) and row["instrument"] == name
        for n in JOINT_NAMES:  # degrees
            assert float(row[f"{n}_deg"]) == pytest.approx(np.degrees(getattr(fit.joints, n)), abs=1e-5)
        assert [float(row[f"base_t{a}_mm"]) for a in "xyz"] == pytest.approx(fit.base_t, abs=1e-5)
        q = [float(row[f"base_q{a}"]) for a in "xyzw"]
        assert np.allclose(matrix_from_quat_xyzw(np.array(q)), fit.base_R, atol=1e-7)
        assert float(row["rms_mm"]) == pytest.approx(fit.rms_mm, abs=1e-5)
        assert row["parts_used"].split(";") == list(fit.parts_used)
        assert row["ok"] == str(int(fit.ok))
    assert float(table[1]["roll_deg"]) == pytest.approx(10.0, abs=1e-4)
    assert table[2]["parts_used"] == "wrist;jaw_left;jaw_right" and table[2]["held"] == "pitch"
    with pytest.raises(OSError, match="joint CSV"):
        write_joint_csv(tmp_path / "missing_dir" / "x.csv", rows)
