"""Write tracking results to an MCAP file that Foxglove opens with its built-in panels.

Every message is JSON (channel ``message_encoding="json"``) with a JSON Schema (schema ``encoding=
"jsonschema"``) whose name is Foxglove's well-known name (``foxglove.PoseInFrame``,
``foxglove.FrameTransforms``, ``foxglove.CameraCalibration``, ``foxglove.CompressedImage``,
``foxglove.ImageAnnotations``, ``foxglove.SceneUpdate``, ``foxglove.JointStates``), so Foxglove
recognises them by name; the part status and the tool tip's uncertainty use small schemas of our own,
``surftrack.PartStatus`` and ``surftrack.PointUncertainty``. The
schemas are written here, following Foxglove's documented field names.

Units and conventions:

* Poses are given to the writer as model-to-camera rotation ``R`` (3x3) and translation ``t_mm`` in
  MILLIMETRES; they are written in METRES (``t_mm / 1000``) with the rotation as a unit quaternion
  ``(x, y, z, w)`` (``w >= 0``). Mesh vertices likewise go in as millimetres and are written as metres.
* Image coordinates (annotations, intrinsics) are pixels, unchanged.
* Times are seconds (float) and become integer nanoseconds ``round(time_s * 1e9)``. For EVERY message
  ``log_time == publish_time == the message's own timestamp`` (``{sec, nsec}`` in the JSON) == the frame's
  time, identical across topics for one frame.
* MCAP allows messages in any time order (readers sort by the index); the writer does not enforce it,
  but keep times non-decreasing per channel for streaming readers.

Topics: ``/parts/<name>/pose`` (PoseInFrame, frame ``camera``), ``/tf`` (FrameTransforms: one message
per frame holding every part, parent ``camera`` -> child ``<name>``), ``/parts/<name>/status``,
``/camera/calibration``, ``/camera/image`` (JPEG CompressedImage), ``/camera/annotations``,
``/parts/meshes`` (SceneUpdate: one frame-locked entity per part in the part's frame; deleted while the
part is lost),
``/instruments/<instrument>/joints`` (JointStates: the joint variables, radians, with their rates where
known), ``/instruments/<instrument>/joints_std`` (their standard deviations, radians, where known),
``/instruments/<instrument>/tool_tip`` and, where the tip comes from an instrument's tracked state,
``/instruments/<instrument>/tool_tip_std`` (``surftrack.PointUncertainty``, in millimetres: its
position covariance, velocity and speed standard deviation).

The file is always finished (summary, index, statistics written) by ``close()`` or on leaving the
``with`` block, including when an exception interrupts the run, so what was written stays readable.
"""

from __future__ import annotations

import base64
import json
import math
import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from mcap.writer import CompressionType, Writer
from scipy.spatial.transform import Rotation

from surftrack.jsonsafe import json_safe

__all__ = ["TrackWriter", "SCHEMAS", "time_to_ns"]

# --------------------------------------------------------------------------------------------- schemas

_TIME = {
    "type": "object",
    "title": "time",
    "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999},
    },
}
_DURATION = {
    "type": "object",
    "title": "duration",
    "properties": {
        "sec": {"type": "integer"},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999},
    },
}
_VEC2 = {"type": "object", "title": "foxglove.Point2",
         "properties": {"x": {"type": "number"}, "y": {"type": "number"}}}
_VEC3 = {"type": "object", "title": "foxglove.Vector3",
         "properties": {"x": {"type": "number"}, "y": {"type": "number"}, "z": {"type": "number"}}}
_POINT3 = dict(_VEC3, title="foxglove.Point3")
_QUAT = {"type": "object", "title": "foxglove.Quaternion",
         "properties": {k: {"type": "number"} for k in "xyzw"}}
_POSE = {"type": "object", "title": "foxglove.Pose",
         "properties": {"position": _VEC3, "orientation": _QUAT}}
_COLOR = {"type": "object", "title": "foxglove.Color",
          "properties": {k: {"type": "number", "minimum": 0, "maximum": 1} for k in "rgba"}}


def _obj(title: str, description: str, props: dict) -> dict:
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": title,
            "description": description, "type": "object", "properties": props}


_FRAME_TRANSFORM_PROPS = {
    "timestamp": _TIME,
    "parent_frame_id": {"type": "string"},
    "child_frame_id": {"type": "string"},
    "translation": _VEC3,
    "rotation": _QUAT,
}

_POINTS_ANNOTATION = {
    "type": "object",
    "title": "foxglove.PointsAnnotation",
    "properties": {
        "timestamp": _TIME,
        "type": {"type": "integer", "title": "foxglove.PointsAnnotation.Type",
                 "description": "0 UNKNOWN, 1 POINTS, 2 LINE_LOOP, 3 LINE_STRIP, 4 LINE_LIST",
                 "oneOf": [{"title": n, "const": v} for n, v in
                           (("UNKNOWN", 0), ("POINTS", 1), ("LINE_LOOP", 2), ("LINE_STRIP", 3),
                            ("LINE_LIST", 4))]},
        "points": {"type": "array", "items": _VEC2},
        "outline_color": _COLOR,
        "outline_colors": {"type": "array", "items": _COLOR},
        "fill_color": _COLOR,
        "thickness": {"type": "number", "minimum": 0},
    },
}
_CIRCLE_ANNOTATION = {
    "type": "object",
    "title": "foxglove.CircleAnnotation",
    "properties": {
        "timestamp": _TIME, "position": _VEC2, "diameter": {"type": "number"},
        "thickness": {"type": "number"}, "fill_color": _COLOR, "outline_color": _COLOR,
    },
}
_TEXT_ANNOTATION = {
    "type": "object",
    "title": "foxglove.TextAnnotation",
    "properties": {
        "timestamp": _TIME, "position": _VEC2, "text": {"type": "string"},
        "font_size": {"type": "number"}, "text_color": _COLOR, "background_color": _COLOR,
    },
}
_TRIANGLE_LIST = {
    "type": "object",
    "title": "foxglove.TriangleListPrimitive",
    "properties": {
        "pose": _POSE,
        "points": {"type": "array", "items": _POINT3},
        "color": _COLOR,
        "colors": {"type": "array", "items": _COLOR},
        "indices": {"type": "array", "items": {"type": "integer", "minimum": 0}},
    },
}
_ENTITY = {
    "type": "object",
    "title": "foxglove.SceneEntity",
    "properties": {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "id": {"type": "string"},
        "lifetime": _DURATION,
        "frame_locked": {"type": "boolean"},
        "metadata": {"type": "array", "items": {
            "type": "object", "title": "foxglove.KeyValuePair",
            "properties": {"key": {"type": "string"}, "value": {"type": "string"}}}},
        **{k: {"type": "array", "items": {"type": "object"}} for k in
           ("arrows", "cubes", "spheres", "cylinders", "lines", "texts", "models")},
        "triangles": {"type": "array", "items": _TRIANGLE_LIST},
    },
}

SCHEMAS: dict[str, dict] = {
    "foxglove.PoseInFrame": _obj("foxglove.PoseInFrame", "A timestamped pose in a named frame (metres)", {
        "timestamp": _TIME, "frame_id": {"type": "string"}, "pose": _POSE}),
    "foxglove.FrameTransforms": _obj("foxglove.FrameTransforms", "An array of FrameTransform messages", {
        "transforms": {"type": "array", "items": {"type": "object", "title": "foxglove.FrameTransform",
                                                  "properties": _FRAME_TRANSFORM_PROPS}}}),
    "foxglove.CameraCalibration": _obj("foxglove.CameraCalibration", "Camera calibration parameters", {
        "timestamp": _TIME, "frame_id": {"type": "string"},
        "width": {"type": "integer", "minimum": 0}, "height": {"type": "integer", "minimum": 0},
        "distortion_model": {"type": "string"},
        "D": {"type": "array", "items": {"type": "number"}},
        "K": {"type": "array", "items": {"type": "number"}, "minItems": 9, "maxItems": 9},
        "R": {"type": "array", "items": {"type": "number"}, "minItems": 9, "maxItems": 9},
        "P": {"type": "array", "items": {"type": "number"}, "minItems": 12, "maxItems": 12}}),
    "foxglove.CompressedImage": _obj("foxglove.CompressedImage", "A compressed image", {
        "timestamp": _TIME, "frame_id": {"type": "string"},
        "data": {"type": "string", "contentEncoding": "base64"},
        "format": {"type": "string"}}),
    "foxglove.ImageAnnotations": _obj("foxglove.ImageAnnotations", "Annotations drawn on an image (pixels)", {
        "circles": {"type": "array", "items": _CIRCLE_ANNOTATION},
        "points": {"type": "array", "items": _POINTS_ANNOTATION},
        "texts": {"type": "array", "items": _TEXT_ANNOTATION}}),
    "foxglove.SceneUpdate": _obj("foxglove.SceneUpdate", "An update to the entities in a 3D scene", {
        "deletions": {"type": "array", "items": {
            "type": "object", "title": "foxglove.SceneEntityDeletion",
            "properties": {"timestamp": _TIME, "type": {"type": "integer"}, "id": {"type": "string"}}}},
        "entities": {"type": "array", "items": _ENTITY}}),
    "foxglove.JointStates": dict(_obj("foxglove.JointStates", "The state of a set of joints at a given time", {
        "timestamp": _TIME,
        "joints": {"type": "array", "items": {
            "type": "object", "title": "foxglove.JointState",
            "description": "The state of a single joint (revolute or prismatic)",
            "properties": {
                "name": {"type": "string"},
                "position": {"type": "number", "description": "rad (revolute) or m (prismatic)"},
                "velocity": {"type": "number", "description": "rad/s or m/s"},
                "acceleration": {"type": "number", "description": "rad/s^2 or m/s^2"},
                "effort": {"type": "number", "description": "Nm or N"}},
            "required": ["name"]}}}), required=["timestamp", "joints"]),
    "surftrack.PartStatus": _obj("surftrack.PartStatus", "Tracking status of one part", {
        "timestamp": _TIME, "part": {"type": "string"}, "status": {"type": "string"},
        "confidence": {"type": "number"}, "extra": {"type": "object"}}),
    "surftrack.PointUncertainty": _obj(
        "surftrack.PointUncertainty", "Uncertainty of a tracked point (e.g. the tool tip), millimetres", {
            "timestamp": _TIME, "frame_id": {"type": "string"},
            "position_std_mm": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
            "position_covariance_mm2": {"type": "array", "items": {"type": "number"}, "minItems": 9, "maxItems": 9},
            "velocity_mm_s": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
            "speed_std_mm_s": {"type": "number"}}) | {
        "required": ["timestamp", "frame_id", "position_std_mm", "position_covariance_mm2", "velocity_mm_s",
                     "speed_std_mm_s"]},
}

_JOINT_FIELDS = ("velocity", "acceleration", "effort")
_POINTS_TYPES = {"unknown": 0, "points": 1, "line_loop": 2, "line_strip": 3, "line_list": 4}

# --------------------------------------------------------------------------------------------- helpers


def time_to_ns(time_s: float) -> int:
    """Seconds -> integer nanoseconds (rounded); must be finite and >= 0."""
    t = float(time_s)
    if not math.isfinite(t) or t < 0:
        raise ValueError(f"time must be finite and >= 0 seconds, got {time_s!r}")
    return int(round(t * 1e9))


def _stamp(ns: int) -> dict:
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _vec3(v) -> dict:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def _quat(R) -> dict:
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise ValueError(f"rotation must be a finite 3x3 matrix, got shape {R.shape}")
    q = Rotation.from_matrix(R).as_quat(canonical=True)
    return {"x": float(q[0]), "y": float(q[1]), "z": float(q[2]), "w": float(q[3])}


def _t_metres(t_mm) -> dict:
    t = np.asarray(t_mm, dtype=np.float64).reshape(-1)
    if t.shape != (3,) or not np.all(np.isfinite(t)):
        raise ValueError(f"translation must be 3 finite values (mm), got {t_mm!r}")
    return _vec3(t / 1000.0)


def _color(c) -> dict:
    c = [float(x) for x in c]
    if len(c) == 3:
        c.append(1.0)
    if len(c) != 4:
        raise ValueError(f"colour must be (r, g, b) or (r, g, b, a) in [0, 1], got {c!r}")
    return dict(zip("rgba", c))


def _check_name(name: str) -> str:
    if not isinstance(name, str) or not name or "/" in name or name.strip() != name:
        raise ValueError(f"part name must be a non-empty string without '/' or surrounding spaces: {name!r}")
    return name


def _pts2(points) -> list:
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    return [{"x": float(x), "y": float(y)} for x, y in p]


# --------------------------------------------------------------------------------------------- writer


class TrackWriter:
    """Context manager writing a tracking run to an MCAP file (chunked, zstd) for Foxglove.

    ``TrackWriter(path, metadata)`` opens ``path`` (an unwritable path raises ``OSError`` naming it)
    and writes a metadata record named ``"surftrack"`` holding ``metadata`` (values stored as strings;
    non-strings JSON-encoded). Schemas and channels are registered the first time a topic is used.
    Poses are model-to-camera ``(R 3x3, t in mm)`` and are written in METRES with (x, y, z, w)
    quaternions. All times are seconds; each message's log_time, publish_time and JSON timestamp are
    the same ``round(time_s * 1e9)`` nanoseconds. Chunks of ``chunk_size`` bytes (uncompressed): what a
    run killed outright can lose is the chunk being filled (256 KiB: about half a second of the demo's
    video; 1 MiB held 1.5-2 s and a short run's whole log), for 2 % more bytes than 1 MiB chunks.
    """

    def __init__(self, path: str | os.PathLike, metadata: Mapping[str, Any] | None = None, *,
                 chunk_size: int = 1 << 18, camera_frame: str = "camera"):
        self.path = Path(path)
        self.camera_frame = camera_frame
        try:
            self._file = open(self.path, "wb")
        except OSError as e:
            raise OSError(e.errno, f"cannot open MCAP output file {str(self.path)!r} for writing: "
                                   f"{e.strerror}", str(self.path)) from e
        self._closed = False
        try:
            self._writer = Writer(self._file, chunk_size=chunk_size, compression=CompressionType.ZSTD)
            self._writer.start(profile="", library="surftrack")
            meta = {str(k): (v if isinstance(v, str) else json.dumps(v, default=str))
                    for k, v in (metadata or {}).items()}
            self._writer.add_metadata("surftrack", meta)
        except BaseException:
            self._file.close()
            self._closed = True
            raise
        self._schema_ids: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}  # topic -> (channel id, schema name)
        self._seq: dict[int, int] = {}

    # ---------------------------------------------------------------- plumbing
    def __enter__(self) -> "TrackWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        self.close()
        return False

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Finish the MCAP file (summary, indexes, statistics) and close it; safe to call twice."""
        if self._closed:
            return
        self._closed = True
        try:
            self._writer.finish()
        finally:
            self._file.close()

    def _channel(self, topic: str, schema_name: str) -> int:
        if topic in self._channels:
            cid, sname = self._channels[topic]
            if sname != schema_name:
                raise ValueError(f"topic {topic!r} already carries {sname}, not {schema_name}")
            return cid
        if schema_name not in self._schema_ids:
            self._schema_ids[schema_name] = self._writer.register_schema(
                name=schema_name, encoding="jsonschema",
                data=json.dumps(SCHEMAS[schema_name]).encode())
        cid = self._writer.register_channel(topic=topic, message_encoding="json",
                                            schema_id=self._schema_ids[schema_name])
        self._channels[topic] = (cid, schema_name)
        return cid

    def _write(self, topic: str, schema_name: str, ns: int, msg: dict) -> None:
        if self._closed:
            raise ValueError(f"TrackWriter for {str(self.path)!r} is closed")
        cid = self._channel(topic, schema_name)
        seq = self._seq.get(cid, 0)
        self._seq[cid] = seq + 1
        self._writer.add_message(channel_id=cid, log_time=ns, publish_time=ns, sequence=seq,
                                 data=json.dumps(msg, separators=(",", ":"), allow_nan=False).encode())

    # ---------------------------------------------------------------- messages
    def pose(self, topic_part_name: str, time_s: float, R, t_mm, frame_id: str | None = None) -> None:
        """PoseInFrame of part ``topic_part_name`` on ``/parts/<name>/pose``: model-to-camera pose,
        ``t_mm`` in millimetres written as metres, ``R`` as an (x, y, z, w) quaternion, in ``frame_id``
        (default the camera frame). Does not write ``/tf``; use :meth:`transforms` (or :meth:`poses`)."""
        name = _check_name(topic_part_name)
        ns = time_to_ns(time_s)
        self._write(f"/parts/{name}/pose", "foxglove.PoseInFrame", ns, {
            "timestamp": _stamp(ns), "frame_id": frame_id or self.camera_frame,
            "pose": {"position": _t_metres(t_mm), "orientation": _quat(R)}})

    def tool_tip(self, time_s: float, instrument_name: str, R, t_mm) -> None:
        """PoseInFrame on ``/instruments/<instrument_name>/tool_tip``: the tool tip (between the jaw tips)
        with the wrist's orientation, in the camera frame, ``t_mm`` written as metres."""
        inst = _check_name(instrument_name)
        ns = time_to_ns(time_s)
        self._write(f"/instruments/{inst}/tool_tip", "foxglove.PoseInFrame", ns, {
            "timestamp": _stamp(ns), "frame_id": self.camera_frame,
            "pose": {"position": _t_metres(t_mm), "orientation": _quat(R)}})

    def tool_tip_std(self, time_s: float, instrument_name: str, cov_mm2, velocity_mm_s, speed_std_mm_s: float) -> None:
        """``surftrack.PointUncertainty`` on ``/instruments/<instrument_name>/tool_tip_std``: the tool tip's
        position covariance ``cov_mm2`` (3x3, mm^2, camera frame; row-major, with the per-axis standard
        deviations), its velocity (3,) mm/s and its speed's standard deviation (mm/s). Millimetres: our
        own schema, read by ``surftrack analyze``."""
        inst = _check_name(instrument_name)
        ns = time_to_ns(time_s)
        C, v = np.asarray(cov_mm2, np.float64), np.asarray(velocity_mm_s, np.float64)
        if C.shape != (3, 3) or v.shape != (3,):
            raise ValueError(f"tool_tip_std: a 3x3 covariance and a 3-vector velocity, got {C.shape} and {v.shape}")
        self._write(f"/instruments/{inst}/tool_tip_std", "surftrack.PointUncertainty", ns, {
            "timestamp": _stamp(ns), "frame_id": self.camera_frame,
            "position_std_mm": [_finite(math.sqrt(max(x, 0.0)), "position std") for x in np.diag(C)],
            "position_covariance_mm2": [_finite(float(x), "position covariance") for x in C.ravel()],
            "velocity_mm_s": [_finite(float(x), "velocity") for x in v],
            "speed_std_mm_s": _finite(float(speed_std_mm_s), "speed std")})

    def transforms(self, time_s: float, poses: Mapping[str, tuple]) -> None:
        """One FrameTransforms message on ``/tf`` holding ``camera -> <name>`` for every part in
        ``poses`` ({name: (R 3x3, t_mm)}); translations written in metres."""
        ns = time_to_ns(time_s)
        tfs = [{"timestamp": _stamp(ns), "parent_frame_id": self.camera_frame,
                "child_frame_id": _check_name(name), "translation": _t_metres(t),
                "rotation": _quat(R)} for name, (R, t) in poses.items()]
        self._write("/tf", "foxglove.FrameTransforms", ns, {"transforms": tfs})

    def poses(self, time_s: float, poses: Mapping[str, tuple]) -> None:
        """Convenience: :meth:`pose` for every part plus one batched :meth:`transforms` message."""
        for name, (R, t) in poses.items():
            self.pose(name, time_s, R, t)
        self.transforms(time_s, poses)

    def status(self, time_s: float, part: str, status: str, confidence: float,
               extra: Mapping[str, Any] | None = None) -> None:
        """``surftrack.PartStatus`` on ``/parts/<name>/status`` (status e.g. "tracking"/"lost")."""
        name = _check_name(part)
        ns = time_to_ns(time_s)
        self._write(f"/parts/{name}/status", "surftrack.PartStatus", ns, {
            "timestamp": _stamp(ns), "part": name, "status": str(status),
            "confidence": _finite(float(confidence), "confidence"),
            # through JSON first, so that arrays and other objects in ``extra`` become JSON values
            "extra": json_safe(json.loads(json.dumps(dict(extra or {}), default=_jsonable)))})

    def joint_states(self, time_s: float, instrument_name: str, names: Sequence[str],
                     positions: Sequence[float | None],
                     extra: Mapping[str, Sequence[float | None]] | None = None, kind: str = "joints") -> None:
        """``foxglove.JointStates`` on ``/instruments/<instrument_name>/joints``: one entry per joint
        ``{name, position}``, positions in RADIANS (revolute joints, like ROS ``sensor_msgs/JointState``;
        the jaw opening too). ``extra`` optionally maps ``"velocity"`` (rad/s), ``"acceleration"``
        (rad/s^2) or ``"effort"`` to one value per joint. A None or NaN value leaves that field out for
        that joint (the fields are optional in Foxglove's schema; JSON has no NaN). E.g. for a
        :class:`~surftrack.instruments.JointFit` ``fit``:
        ``w.joint_states(t, "lnd", JOINT_NAMES, [getattr(fit.joints, n) for n in JOINT_NAMES])``.
        ``kind="joints_std"`` writes the joints' standard deviations (radians, as positions) on
        ``/instruments/<instrument_name>/joints_std`` instead."""
        if kind not in ("joints", "joints_std"):
            raise ValueError(f"joint_states: kind must be 'joints' or 'joints_std', got {kind!r}")
        inst = _check_name(instrument_name)
        names = [_check_name(n) for n in names]
        positions = list(positions)
        if len(positions) != len(names):
            raise ValueError(f"joint_states: {len(names)} names but {len(positions)} positions")
        extra = dict(extra or {})
        bad = sorted(set(extra) - set(_JOINT_FIELDS))
        if bad:
            raise ValueError(f"joint_states: unknown extra field(s) {bad}; allowed: {list(_JOINT_FIELDS)}")
        for key, vals in extra.items():
            if len(vals) != len(names):
                raise ValueError(f"joint_states: {len(names)} names but {len(vals)} {key} values")
        joints = []
        for i, name in enumerate(names):
            entry = {"name": name}
            for key, vals in (("position", positions), *extra.items()):
                v = vals[i]
                if v is not None and math.isfinite(float(v)):
                    entry[key] = float(v)
            joints.append(entry)
        ns = time_to_ns(time_s)
        self._write(f"/instruments/{inst}/{kind}", "foxglove.JointStates", ns,
                    {"timestamp": _stamp(ns), "joints": joints})

    def camera_calibration(self, time_s: float, K, width: int, height: int, dist=None,
                           distortion_model: str | None = None) -> None:
        """CameraCalibration on ``/camera/calibration``: ``K`` 3x3 in pixels, ``dist`` the OpenCV
        coefficients (5 -> "plumb_bob", 8 -> "rational_polynomial"; None -> five zeros), R = I,
        P = [K | 0]."""
        ns = time_to_ns(time_s)
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"K must be 3x3, got shape {K.shape}")
        D = [0.0] * 5 if dist is None else [float(x) for x in np.asarray(dist).reshape(-1)]
        if distortion_model is None:
            distortion_model = "rational_polynomial" if len(D) == 8 else "plumb_bob"
        P = np.hstack([K, np.zeros((3, 1))])
        self._write("/camera/calibration", "foxglove.CameraCalibration", ns, {
            "timestamp": _stamp(ns), "frame_id": self.camera_frame,
            "width": int(width), "height": int(height), "distortion_model": distortion_model,
            "D": D, "K": K.reshape(-1).tolist(), "R": np.eye(3).reshape(-1).tolist(),
            "P": P.reshape(-1).tolist()})

    def image_jpeg(self, time_s: float, jpeg_bytes: bytes) -> None:
        """CompressedImage (format "jpeg", data base64 in the JSON) on ``/camera/image``."""
        ns = time_to_ns(time_s)
        self._write("/camera/image", "foxglove.CompressedImage", ns, {
            "timestamp": _stamp(ns), "frame_id": self.camera_frame,
            "data": base64.b64encode(bytes(jpeg_bytes)).decode("ascii"), "format": "jpeg"})

    def annotations(self, time_s: float, points: Sequence[Mapping] = (),
                    circles: Sequence[Mapping] = (), texts: Sequence[Mapping] = ()) -> None:
        """ImageAnnotations on ``/camera/annotations`` (pixel coordinates).

        ``points``: dicts ``{"points": (N, 2), "type": "points"|"line_loop"|"line_strip"|"line_list"
        (or the int enum), "color": rgba, "colors": [rgba per point] (optional), "fill_color": rgba
        (optional), "thickness": px}`` -- e.g. projected axes as a line_list, boxes as a line_loop.
        ``circles``: ``{"center": (x, y), "diameter", "thickness", "color", "fill_color"}``.
        ``texts``: ``{"position": (x, y), "text", "font_size", "color", "background_color"}``.
        Colours are (r, g, b[, a]) in [0, 1]."""
        ns = time_to_ns(time_s)
        ts = _stamp(ns)
        pts = []
        for p in points:
            typ = p.get("type", "line_strip")
            typ = _POINTS_TYPES[typ.lower()] if isinstance(typ, str) else int(typ)
            pts.append({
                "timestamp": ts, "type": typ, "points": _pts2(p["points"]),
                "outline_color": _color(p.get("color", (0, 1, 0, 1))),
                "outline_colors": [_color(c) for c in p.get("colors", ())],
                "fill_color": _color(p.get("fill_color", (0, 0, 0, 0))),
                "thickness": float(p.get("thickness", 2.0))})
        circ = [{"timestamp": ts, "position": _pts2(c["center"])[0],
                 "diameter": float(c.get("diameter", 6.0)), "thickness": float(c.get("thickness", 2.0)),
                 "fill_color": _color(c.get("fill_color", (0, 0, 0, 0))),
                 "outline_color": _color(c.get("color", (1, 1, 0, 1)))} for c in circles]
        txt = [{"timestamp": ts, "position": _pts2(t["position"])[0], "text": str(t["text"]),
                "font_size": float(t.get("font_size", 12.0)),
                "text_color": _color(t.get("color", (1, 1, 1, 1))),
                "background_color": _color(t.get("background_color", (0, 0, 0, 0.5)))} for t in texts]
        self._write("/camera/annotations", "foxglove.ImageAnnotations", ns,
                    {"circles": circ, "points": pts, "texts": txt})

    def scene_meshes(self, time_s: float, meshes: Mapping[str, tuple]) -> None:
        """SceneUpdate on ``/parts/meshes``: one frame-locked entity per part (id = frame_id = part
        name, lifetime 0 = forever) carrying a TriangleListPrimitive of its mesh. ``meshes`` is
        {name: (vertices_mm (V, 3), faces (F, 3) int, color rgba)}; vertices are written in metres in the
        part's own frame, so the mesh follows the part's ``/tf`` transform."""
        ns = time_to_ns(time_s)
        ts = _stamp(ns)
        ents = []
        for name, (verts, faces, color) in meshes.items():
            name = _check_name(name)
            v = np.asarray(verts, dtype=np.float64).reshape(-1, 3) / 1000.0
            f = np.asarray(faces).reshape(-1, 3)
            if f.size and (f.min() < 0 or f.max() >= len(v)):
                raise ValueError(f"mesh {name!r}: face indices out of range [0, {len(v)})")
            ents.append({
                "timestamp": ts, "frame_id": name, "id": name, "lifetime": {"sec": 0, "nsec": 0},
                "frame_locked": True, "metadata": [{"key": "part", "value": name}],
                "arrows": [], "cubes": [], "spheres": [], "cylinders": [], "lines": [], "texts": [],
                "models": [],
                "triangles": [{
                    "pose": {"position": _vec3((0, 0, 0)),
                             "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
                    "points": [_vec3(p) for p in v], "color": _color(color), "colors": [],
                    "indices": f.astype(np.int64).reshape(-1).tolist()}]})
        self._write("/parts/meshes", "foxglove.SceneUpdate", ns, {"deletions": [], "entities": ents})

    def scene_deletions(self, time_s: float, names: Sequence[str]) -> None:
        """SceneUpdate on ``/parts/meshes`` deleting the entities of the parts ``names`` (type 0: matching
        id). A lost part's mesh would otherwise stay at its last pose; :meth:`scene_meshes` shows it again."""
        ns = time_to_ns(time_s)
        dels = [{"timestamp": _stamp(ns), "type": 0, "id": _check_name(n)} for n in names]
        self._write("/parts/meshes", "foxglove.SceneUpdate", ns, {"deletions": dels, "entities": []})


def _finite(v: float, what: str) -> float:
    if not math.isfinite(v):
        raise ValueError(f"{what} must be finite, got {v!r}")
    return v


def _jsonable(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    return str(o)
