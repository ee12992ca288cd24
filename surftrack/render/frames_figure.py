"""A picture of an instrument's joint frames, to check a description against its CAD at a glance.

Two views of the instrument rendered by the project's own renderer: the rest configuration (all joints
zero) and a bent one. On each, every part's frame (x red, y green, z blue, at the joint origin), its joint
axis (yellow, labelled with the joint variables that turn it) and its ``tip`` keypoints (white dots).
"""

from __future__ import annotations

import cv2
import numpy as np

from surftrack.geometry import PinholeCamera, se3
from surftrack.instruments import Instrument, JointState
from surftrack.render.lights import endoscope_light
from surftrack.render.renderer import Renderer
from surftrack.render.scene import add_instrument

_AXIS_BGR = ((60, 60, 230), (60, 200, 60), (230, 120, 40))  # x, y, z
_JOINT_RGB = (255, 220, 0)


def _view_pose(instrument: Instrument, q: JointState, distance_mm: float) -> np.ndarray:
    """A base pose that shows the wrist from three quarters: the shaft running left to right and away."""
    z = np.array([1.0, 0.15, 0.45])
    z /= np.linalg.norm(z)
    x = np.array([0.0, 0.0, -1.0]) - z * (-z[2])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z], axis=1)
    # Centre the view on the middle of the distal parts at this configuration.
    poses = instrument.forward(se3(R, np.zeros(3)), q)
    pts = np.concatenate([poses[n][:3, :3] @ p.mesh.bounds.mean(axis=0)[:, None] + poses[n][:3, 3:4]
                          for n, p in instrument.parts.items()], axis=1)
    centre = pts.mean(axis=1)
    return se3(R, np.array([0.0, 0.0, distance_mm]) - centre)


def _label(img: np.ndarray, text: str, at: tuple[int, int], color: tuple[int, int, int], scale: float = 0.45) -> None:
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    cv2.rectangle(img, (at[0] - 2, at[1] - h - 2), (at[0] + w + 2, at[1] + base), (25, 25, 25), -1)
    cv2.putText(img, text, at, cv2.FONT_HERSHEY_SIMPLEX, scale, color, 1, cv2.LINE_AA)


def joint_frames_figure(instrument: Instrument, bent: JointState | None = None, width: int = 640,
                        height: int = 480, hfov_deg: float = 40.0) -> np.ndarray:
    """RGB image (height, 2 * width, 3) uint8: the rest configuration and ``bent`` (default: 30 deg of
    pitch and yaw, jaws open 40 deg, within the limits) side by side, frames and joint axes drawn."""
    rest = instrument.rest
    bent = instrument.limits.clip(bent or JointState.from_degrees(pitch=30.0, yaw=30.0, opening=40.0))
    distal = [p.diameter_bbox_diagonal for n, p in instrument.parts.items() if instrument.chain.joints[n].parent]
    size = max(distal) if distal else next(iter(instrument.parts.values())).diameter_bbox_diagonal
    distance = max(60.0, 4.0 * size)
    camera = PinholeCamera.from_fov(width, height, hfov_deg)
    renderer = Renderer(width, height)
    try:
        handles = add_instrument(renderer, instrument)
        panels = []
        for title, q in (("rest (all joints 0)", rest), ("bent", bent)):
            poses = instrument.forward(_view_pose(instrument, rest, distance), q)
            res = renderer.render(camera, handles.poses(poses), [endoscope_light(1.2)], ambient=(0.25, 0.25, 0.25),
                                  background=(0.12, 0.13, 0.16), modalities={"rgb"})
            panels.append(_annotate(res.rgb.copy(), instrument, poses, camera, q, title, 0.25 * size))
    finally:
        renderer.release()
    return np.concatenate(panels, axis=1)


def _annotate(img: np.ndarray, instrument: Instrument, poses: dict[str, np.ndarray], camera: PinholeCamera,
              q: JointState, title: str, axis_mm: float) -> np.ndarray:
    bgr = np.ascontiguousarray(img[..., ::-1])
    labelled: list[np.ndarray] = []
    for name in instrument.chain.order:
        T, joint = poses[name], instrument.chain.joints[name]
        ends = T[:3, 3:4] + T[:3, :3] * axis_mm
        o, *axes = camera.project(np.concatenate([T[:3, 3:4], ends], axis=1).T)
        for end, color in zip(axes, _AXIS_BGR):
            cv2.arrowedLine(bgr, tuple(np.round(o).astype(int)), tuple(np.round(end).astype(int)), color, 2,
                            cv2.LINE_AA, tipLength=0.2)
        a = np.asarray(joint.axis, dtype=np.float64)
        a = T[:3, :3] @ (a / np.linalg.norm(a)) * axis_mm * 1.4
        p0, p1 = camera.project(np.stack([T[:3, 3] - a, T[:3, 3] + a]))
        cv2.line(bgr, tuple(np.round(p0).astype(int)), tuple(np.round(p1).astype(int)), _JOINT_RGB[::-1], 1,
                 cv2.LINE_AA)
        terms = [("- " if c < 0 else "+ ") + (k if abs(c) == 1 else f"{abs(c):g} {k}")
                 for k, c in joint.coefficients.items() if c]
        angle = " ".join(terms).removeprefix("+ ") or "fixed"
        at = p1 + (4, -4)
        while any(abs(at[1] - o[1]) < 16 and abs(at[0] - o[0]) < 150 for o in labelled):  # parts on one joint: stack labels
            at = at + (0, 16)
        labelled.append(at)
        _label(bgr, f"{name}: {angle}", tuple(np.round(at).astype(int)), _JOINT_RGB[::-1])
        for kname, kp in instrument.parts[name].keypoints.items():
            if kname == "tip":
                uv = camera.project((T[:3, :3] @ kp + T[:3, 3])[None])[0]
                cv2.circle(bgr, tuple(np.round(uv).astype(int)), 3, (255, 255, 255), -1, cv2.LINE_AA)
    deg = {k: round(float(np.degrees(v))) for k, v in q.as_dict().items()}
    _label(bgr, f"{instrument.name}, {title}: " + ", ".join(f"{k} {v}" for k, v in deg.items()), (8, 20),
           (255, 255, 255), 0.5)
    _label(bgr, "frames: x red, y green, z blue; joint axes yellow; tips white", (8, camera.height - 10),
           (220, 220, 220), 0.42)
    return bgr[..., ::-1]
