"""Shared fixtures: a small synthetic tracking clip and an untrained checkpoint with the LND's parts."""

import json

import pytest
import torch

from surftrack.model import save_checkpoint
from surftrack.model.config import ModelCfg, TrainConfig
from surftrack.model.surfsurg6d import PartInfo, SurfSurg6D
from surftrack.synth.clip import ClipConfig, make_clip


@pytest.fixture(scope="session")
def clip(tmp_path_factory):
    """A 1.5 s, 10 fps, 320x256 clip: LND crossed by a second tool (which the models here do not know)."""
    out = tmp_path_factory.mktemp("clip")
    make_clip(out, "lnd", ClipConfig(seconds=1.5, fps=10, width=320, height=256, hfov_deg=70.0), seed=4,
              progress=False)
    return out


@pytest.fixture(scope="session")
def lnd_parts(clip):
    det = json.loads((clip / "det.json").read_text())
    return {d["part"]: int(k) for k, d in det["parts"].items() if d["instrument"] == "large_needle_driver"}


@pytest.fixture(scope="session")
def tiny_ckpt(tmp_path_factory):
    """An untrained model with the LND's parts: its poses are arbitrary, the plumbing is real."""
    from surftrack.instruments import load_instrument

    lnd = load_instrument("lnd")
    parts = [PartInfo.from_part(i + 1, lnd.name, lnd.parts[n]) for i, n in enumerate(lnd.part_names)]
    torch.manual_seed(0)
    cfg = TrainConfig.from_dict({"model": {"decoder_widths": [16, 16, 16, 16, 16], "siren_hidden": 32},
                                 "data": {"crop": 64}})
    model = SurfSurg6D(parts, ModelCfg(decoder_widths=(16, 16, 16, 16, 16), siren_hidden=32))
    return save_checkpoint(tmp_path_factory.mktemp("model") / "tiny.pt", model, cfg, step=0)


