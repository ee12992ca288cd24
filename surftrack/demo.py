"""``surftrack demo``: the end-to-end job on built-in data.

For now (renderer stage): pose an instrument under a remote-centre-of-motion constraint over procedural
tissue, render every modality, and write the RGB frame and a modality panel as PNGs.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from PIL import Image

from surftrack.geometry import PinholeCamera, quat_xyzw_from_matrix, rotation_about, se3
from surftrack.instruments import JointState, load_instrument, rcm_base_pose
from surftrack.render import Light, Renderer, add_instrument, endoscope_light, gl_info
from surftrack.render.visualize import modality_panel
from surftrack.synth import procedural_tissue


def run_demo(out_dir: Path, instrument: str = "lnd", seed: int = 0) -> dict:
    """Render the demo scene into ``out_dir``; returns a summary (paths, part poses, timings)."""
    t0 = time.perf_counter()
    out_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    inst = load_instrument(instrument)
    camera = PinholeCamera.from_fov(640, 512, hfov_deg=70.0)
    tissue = procedural_tissue(rng)
    tissue_pose = se3(rotation_about([1.0, 0.3, 0.0], np.radians(18.0)), [0.0, 0.0, 105.0])
    trocar = np.array([-75.0, -60.0, 15.0])            # outside the view, up and to the left
    pitch_point = np.array([-6.0, -4.0, 62.0])         # wrist, ~40 mm above the tissue
    base = rcm_base_pose(trocar, pitch_point)
    q = JointState.from_degrees(roll=20.0, pitch=25.0, yaw=-30.0, opening=35.0)
    part_poses = inst.forward(base, q)

    renderer = Renderer(camera.width, camera.height)
    tissue_id = tissue.add_to(renderer)
    handles = add_instrument(renderer, inst)
    poses = {tissue_id: tissue_pose, **handles.poses(part_poses)}
    lights = [endoscope_light(0.9), Light(position=(25.0, -10.0, 0.0), direction=(-0.2, 0.1, 1.0), intensity=0.35)]
    t1 = time.perf_counter()
    result = renderer.render(camera, poses, lights)
    t_render = time.perf_counter() - t1

    rgb_path, panel_path = out_dir / "demo_rgb.png", out_dir / "demo_modalities.png"
    Image.fromarray(result.rgb).save(rgb_path)
    Image.fromarray(modality_panel(result)).save(panel_path)
    parts = {}
    for pname, iid in handles.parts.items():
        T = part_poses[pname]
        parts[pname] = {
            "t_mm": np.round(T[:3, 3], 3).tolist(),
            "q_xyzw": np.round(quat_xyzw_from_matrix(T[:3, :3]), 6).tolist(),
            "visible_px": int((result.instance == iid).sum()),
            "silhouette_px": int(result.amodal[iid].sum()),
        }
    summary = {
        "instrument": inst.name, "rgb": str(rgb_path), "modalities": str(panel_path),
        "camera": camera.to_dict(), "joints_deg": {k: float(np.degrees(v)) for k, v in q.as_dict().items()},
        "trocar_mm": trocar.tolist(), "parts": parts, "render_ms": round(1000 * t_render, 1),
        "total_s": round(time.perf_counter() - t0, 2), "gl": gl_info(),
    }
    (out_dir / "demo.json").write_text(json.dumps(summary, indent=2))
    renderer.release()
    return summary
