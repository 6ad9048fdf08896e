"""The pose network (torch): a tiny fully-convolutional centre-heatmap net (CenterNet-style).

Input, output, layers and cost: docs/perception.md, "Training".
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

HEAT_PRIOR_BIAS = -2.19  # sigmoid(-2.19) = 0.1: the heatmap starts near "no part" (CenterNet)


def _cbr(cin: int, cout: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride=stride, padding=dilation, dilation=dilation, bias=False),
        nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class PoseNet(nn.Module):
    def __init__(self, in_ch: int = 5, width: int = 16) -> None:
        super().__init__()
        c1, c2 = width, 2 * width
        self.stem = _cbr(in_ch, c1, stride=2)
        self.b1 = _cbr(c1, c1)
        self.down = _cbr(c1, c2, stride=2)
        self.b2 = _cbr(c2, c2)
        self.b3 = _cbr(c2, c2, dilation=2)
        self.b4 = _cbr(c2, c2, dilation=4)
        self.lat = nn.Conv2d(c2, c1, 1)
        self.fuse = _cbr(2 * c1, 24)
        self.head = nn.Conv2d(24, 4, 1)
        bias = self.head.bias
        assert bias is not None
        with torch.no_grad():
            bias.zero_()
            bias[0] = HEAT_PRIOR_BIAS
            bias[3] = 0.6  # a 6 cm part

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        a = self.b1(self.stem(x))
        b = self.b4(self.b3(self.b2(self.down(a))))
        up = F.interpolate(self.lat(b), size=a.shape[-2:], mode="bilinear", align_corners=False)
        return self.head(self.fuse(torch.cat([a, up], dim=1)))


def focal_loss(logit: torch.Tensor, target: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """CenterNet's penalty-reduced focal loss on the heatmap (alpha 2, beta 4), per positive."""
    p = torch.sigmoid(logit).clamp(1e-4, 1 - 1e-4)
    pos = target.ge(0.999).float()
    pos_loss = -torch.log(p) * (1 - p) ** 2 * pos
    neg_loss = -torch.log(1 - p) * p**2 * (1 - target) ** 4 * (1 - pos)
    n = pos.sum().clamp(min=1.0)
    return ((pos_loss + neg_loss) * weight).sum() / n
