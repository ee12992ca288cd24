"""SIREN surface fields: per part, a map from normalised surface coordinates to key embeddings.

3 -> 256 -> 256 -> 256 (sine activations, w0 = 30, the SIREN initialisation of Sitzmann et al. 2020)
-> linear E. Inputs are ``(p - c) / r`` with c, r the part's bounding-sphere centre and radius.
"""

from __future__ import annotations

import math

import torch
from torch import nn


class SineLayer(nn.Module):
    def __init__(self, cin: int, cout: int, w0: float = 30.0, first: bool = False):
        super().__init__()
        self.w0 = w0
        self.linear = nn.Linear(cin, cout)
        bound = 1.0 / cin if first else math.sqrt(6.0 / cin) / w0
        nn.init.uniform_(self.linear.weight, -bound, bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.sin(self.w0 * self.linear(x))


class Siren(nn.Module):
    """(N, 3) normalised coordinates -> (N, E) keys."""

    def __init__(self, emb_dim: int = 12, hidden: int = 256, layers: int = 3, w0: float = 30.0):
        super().__init__()
        mods = [SineLayer(3, hidden, w0, first=True)] + [SineLayer(hidden, hidden, w0) for _ in range(layers - 1)]
        self.net = nn.Sequential(*mods)
        self.out = nn.Linear(hidden, emb_dim)
        bound = math.sqrt(6.0 / hidden) / w0
        nn.init.uniform_(self.out.weight, -bound, bound)

    def forward(self, coords: torch.Tensor) -> torch.Tensor:
        return self.out(self.net(coords))


class KeyFields(nn.Module):
    """One :class:`Siren` per part; ``forward(part, coords)`` evaluates part ``part``'s field."""

    def __init__(self, n_parts: int, emb_dim: int = 12, hidden: int = 256, layers: int = 3, w0: float = 30.0):
        super().__init__()
        self.fields = nn.ModuleList([Siren(emb_dim, hidden, layers, w0) for _ in range(n_parts)])

    def forward(self, part: int, coords: torch.Tensor) -> torch.Tensor:
        return self.fields[part](coords)
