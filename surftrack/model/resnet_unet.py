"""ResNet18 encoder + U-Net decoder(s) predicting a mask logit and E query channels per pixel.

The encoder keeps torchvision's parameter names (``conv1``, ``bn1``, ``layer1.0.conv1``, ...,
``layer4.1.bn2``, ``layerN.0.downsample.0/1``) so ImageNet weights load from a local torchvision
``resnet18`` state dict file (:func:`load_imagenet_weights`); nothing is downloaded. Decoders follow
SurfEmb: bilinear x2 upsampling, skip concatenation, 3x3 conv + ReLU, output at the crop resolution.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn


class BasicBlock(nn.Module):
    expansion = 1

    def __init__(self, cin: int, cout: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.downsample = None
        if stride != 1 or cin != cout:
            self.downsample = nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        idt = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + idt)


class ResNet18Encoder(nn.Module):
    """ResNet18 without the classifier; returns the five feature maps (strides 2, 4, 8, 16, 32)."""

    channels = (64, 64, 128, 256, 512)

    def __init__(self):
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        self.layer1 = nn.Sequential(BasicBlock(64, 64), BasicBlock(64, 64))
        self.layer2 = nn.Sequential(BasicBlock(64, 128, 2), BasicBlock(128, 128))
        self.layer3 = nn.Sequential(BasicBlock(128, 256, 2), BasicBlock(256, 256))
        self.layer4 = nn.Sequential(BasicBlock(256, 512, 2), BasicBlock(512, 512))
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        f1 = self.relu(self.bn1(self.conv1(x)))
        f2 = self.layer1(self.maxpool(f1))
        f3 = self.layer2(f2)
        f4 = self.layer3(f3)
        f5 = self.layer4(f4)
        return [f1, f2, f3, f4, f5]


def load_imagenet_weights(encoder: ResNet18Encoder, path: str | Path) -> list[str]:
    """Load a torchvision ``resnet18`` state dict file (``fc.*`` ignored); returns the keys not found."""
    state = torch.load(path, map_location="cpu", weights_only=True)
    state = {k: v for k, v in state.items() if not k.startswith("fc.")}
    missing, unexpected = encoder.load_state_dict(state, strict=False)
    if unexpected:
        raise ValueError(f"{path}: not a torchvision resnet18 state dict (unexpected keys {unexpected[:5]})")
    return list(missing)


class Decoder(nn.Module):
    """U-Net decoder: from the stride-32 features up to full resolution, with skips at every scale
    (the input image itself is the last skip)."""

    def __init__(self, widths: tuple[int, ...], out_channels: int, enc_channels: tuple[int, ...] = ResNet18Encoder.channels):
        super().__init__()
        if len(widths) != 5:
            raise ValueError(f"decoder needs 5 widths (strides 16, 8, 4, 2, 1), got {widths}")
        skips = list(enc_channels[:-1][::-1]) + [3]  # 256, 128, 64, 64, image
        cin = enc_channels[-1]
        self.blocks = nn.ModuleList()
        for w, s in zip(widths, skips):
            self.blocks.append(nn.Sequential(nn.Conv2d(cin + s, w, 3, 1, 1), nn.ReLU(inplace=True)))
            cin = w
        self.head = nn.Conv2d(cin, out_channels, 1)

    def forward(self, feats: list[torch.Tensor], image: torch.Tensor) -> torch.Tensor:
        x = feats[-1]
        for block, skip in zip(self.blocks, [*feats[-2::-1], image]):
            x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            x = block(torch.cat([x, skip], dim=1))
        return self.head(x)


class ResNetUNet(nn.Module):
    """Shared ResNet18 encoder, one decoder per part (or one shared decoder with per-part heads).

    ``forward(images (B, 3, S, S), part_index (B,))`` -> ``(mask_logit (B, S, S), query (B, E, S, S))``.
    """

    def __init__(self, n_parts: int, emb_dim: int = 12, widths: tuple[int, ...] = (256, 128, 64, 64, 64),
                 single_decoder: bool = False):
        super().__init__()
        self.n_parts, self.emb_dim, self.single_decoder = n_parts, emb_dim, single_decoder
        self.encoder = ResNet18Encoder()
        if single_decoder:
            self.decoders = nn.ModuleList([Decoder(widths, n_parts * (1 + emb_dim))])
        else:
            self.decoders = nn.ModuleList([Decoder(widths, 1 + emb_dim) for _ in range(n_parts)])

    def forward(self, images: torch.Tensor, part_index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        feats = self.encoder(images)
        B, _, H, W = images.shape
        out = images.new_empty((B, 1 + self.emb_dim, H, W))
        if self.single_decoder:
            full = self.decoders[0](feats, images).view(B, self.n_parts, 1 + self.emb_dim, H, W)
            out = full[torch.arange(B, device=images.device), part_index]
        else:
            for p in torch.unique(part_index).tolist():
                sel = (part_index == p).nonzero(as_tuple=True)[0]
                out[sel] = self.decoders[p]([f[sel] for f in feats], images[sel]).to(out.dtype)
        return out[:, 0], out[:, 1:]
