"""XFeat's network (Potje et al., CVPR 2024) as a PyTorch module: the PyTorch runtime and the ONNX export.

The layers are the paper's detector and descriptor network (Fig. 2): a
backbone of 3 x 3 convolutions with batch normalisation and ReLU that reaches
1/32 of the input, a fusion of the 1/8, 1/16 and 1/32 maps at 1/8, and three
heads at 1/8 of the input:

* ``descriptors`` (B, 64, H/8, W/8): dense local features, not normalised;
* ``keypoint_logits`` (B, 65, H/8, W/8): for each 8 x 8 cell the logits of its
  64 pixels and of a "no keypoint" bin, computed from the cell's raw pixels;
* ``reliability`` (B, 1, H/8, W/8): the sigmoid reliability map.

Parameter names follow the authors' release so that its state dict loads as
it is (the fine matcher of the dense "XFeat*" mode is not part of this module:
topoloc uses the sparse mode only).  The 8 x 8 cells of the keypoint head are
cut with :func:`torch.nn.functional.pixel_unshuffle`, which orders a cell's
pixels row by row as the release does, and which the ONNX exporter writes as
reshapes that accept inputs of any size (the release's ``Tensor.unfold``
exported for one fixed size only).

Only :mod:`topoloc.features.xfeat.runtimes` (the PyTorch runtime) and
``scripts/export_xfeat_onnx.py`` import this module: it imports PyTorch.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

#: Names of the network's outputs, in order (also the ONNX graph's output names).
OUTPUTS = ("descriptors", "keypoint_logits", "reliability")


class _ConvBlock(nn.Module):
    """Convolution (no bias), batch normalisation without affine parameters, ReLU."""

    def __init__(self, c_in: int, c_out: int, kernel: int = 3, stride: int = 1, padding: int = 1) -> None:
        super().__init__()
        self.layer = nn.Sequential(nn.Conv2d(c_in, c_out, kernel, stride=stride, padding=padding, bias=False),
                                   nn.BatchNorm2d(c_out, affine=False), nn.ReLU(inplace=True))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.layer(x)


def _pointwise(c_in: int, c_out: int) -> _ConvBlock:
    return _ConvBlock(c_in, c_out, kernel=1, padding=0)


class XFeatNet(nn.Module):
    """XFeat's backbone and heads; ``forward`` takes gray images (B, 1, H, W), H and W multiples of 32."""

    def __init__(self) -> None:
        super().__init__()
        self.norm = nn.InstanceNorm2d(1)
        self.skip1 = nn.Sequential(nn.AvgPool2d(4, stride=4), nn.Conv2d(1, 24, 1))
        self.block1 = nn.Sequential(_ConvBlock(1, 4), _ConvBlock(4, 8, stride=2), _ConvBlock(8, 8),
                                    _ConvBlock(8, 24, stride=2))
        self.block2 = nn.Sequential(_ConvBlock(24, 24), _ConvBlock(24, 24))
        self.block3 = nn.Sequential(_ConvBlock(24, 64, stride=2), _ConvBlock(64, 64), _pointwise(64, 64))
        self.block4 = nn.Sequential(_ConvBlock(64, 64, stride=2), _ConvBlock(64, 64), _ConvBlock(64, 64))
        self.block5 = nn.Sequential(_ConvBlock(64, 128, stride=2), _ConvBlock(128, 128), _ConvBlock(128, 128),
                                    _pointwise(128, 64))
        self.block_fusion = nn.Sequential(_ConvBlock(64, 64), _ConvBlock(64, 64), nn.Conv2d(64, 64, 1))
        self.heatmap_head = nn.Sequential(_pointwise(64, 64), _pointwise(64, 64), nn.Conv2d(64, 1, 1), nn.Sigmoid())
        self.keypoint_head = nn.Sequential(_pointwise(64, 64), _pointwise(64, 64), _pointwise(64, 64),
                                           nn.Conv2d(64, 65, 1))

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        x = self.norm(image)
        x1 = self.block1(x)
        x2 = self.block2(x1 + self.skip1(x))
        x3 = self.block3(x2)
        x4 = self.block4(x3)
        x5 = self.block5(x4)
        size = (x3.shape[-2], x3.shape[-1])
        fused = x3 + F.interpolate(x4, size, mode="bilinear") + F.interpolate(x5, size, mode="bilinear")
        descriptors = self.block_fusion(fused)
        reliability = self.heatmap_head(descriptors)
        logits = self.keypoint_head(F.pixel_unshuffle(x, 8))
        return descriptors, logits, reliability


def load_state(net: XFeatNet, state: dict[str, torch.Tensor]) -> XFeatNet:
    """``net`` with the weights of ``state`` (the release's keys; extra keys such as the fine matcher's ignored)."""
    own = net.state_dict()
    missing = [k for k in own if k not in state and not k.endswith("num_batches_tracked")]
    if missing:
        raise ValueError(f"XFeat weights lack {len(missing)} tensors, e.g. {missing[0]}")
    net.load_state_dict({k: state[k] for k in own if k in state}, strict=False)
    return net.eval()
