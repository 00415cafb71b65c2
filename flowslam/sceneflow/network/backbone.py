"""MambaFlow's spatio-temporal U-Net in bird's-eye view + time, pure PyTorch.

Tensors are (B, T, H, W, C), channels last (see ``voxelize.py``): time t = 0 is the
oldest frame, t = T-1 the newest. MambaFlow's 4D kernels map onto this BEV+time
layout as follows (its z axis is folded into the pillar features):

- spatial 3x3x3x1 kernel  -> a 3x3 convolution over (H, W) at each timestep
  (``nn.Conv2d`` on the (B*T, C, H, W) channels-last view; identical to a Conv3d with
  kernel (1, 3, 3) on (B, C, T, H, W));
- local temporal 1x1x1x3  -> ``TemporalConv`` with kernel 3 over T, dilation 1;
- cross-timestep temporal -> ``TemporalConv`` with kernel 3 over T, dilation 2
  (frames t-2, t, t+2; with T = 2 only the centre tap sees data);
- 1x1x1x1 kernels         -> ``nn.Linear`` on the channel axis.

Spatio-temporal Deep Coupling Block (``STDCB``): the three branches run on the same
input; Soft Feature Selection (SFS) pools their sum over (T, H, W) into one
descriptor per sample, a small MLP turns it into per-channel logits for each branch,
and a softmax over the branches weighs them; the Temporal Gated Block (TGB) computes
a sigmoid gate from the fused features with a temporal kernel-3 convolution and
multiplies it in; a 1x1 projection plus a (projected) residual gives the output.

``separable=True`` (the CPU preset) factorises every STDCB: a pointwise conv, then
depthwise spatial / temporal branches and gate (see ``STDCB``). ``fold_bn_into`` folds
the eval-mode BatchNorms into the preceding layers for inference.

Fused inference (``fusable``): with folded BatchNorms, float32 CPU tensors and no
autograd, each convolution / linear layer runs together with the activation after it
(LeakyReLU, the gate's sigmoid, the residual add) as one oneDNN kernel
(``torch.ops.mkldnn._convolution_pointwise`` / ``_linear_pointwise``, the kernels
``torch.compile`` uses on CPU): one pass over the activations instead of two, same
arithmetic (LeakyReLU and the add bit-identical, the sigmoid to 1e-7). Elsewhere, or
where this torch build lacks the ops, the plain layers run. In a separable STDCB the
steps between the expansion / 3x3 convolution and the projection (temporal branches,
pooling, branch weighting, gate) run as two compiled passes instead
(``COMPILED_BLOCKS``, :mod:`compiled_stdcb`): the same numbers to float32 rounding.

U-Net: ``levels`` resolutions (stride 1, 2, 4, ...), encoder level i runs
``encoder_depths[i]`` STDCBs then a 2x2 stride-2 convolution down (per timestep, time
is never pooled); the decoder goes up with 2x2 stride-2 transposed convolutions,
concatenates the skip and runs ``decoder_depths`` STDCBs per level. The output keeps
the time axis; the model picks the timesteps it needs (see ``model.py``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["TemporalConv", "STDCB", "STUNet", "spatial_conv", "fold_bn_into", "fusable"]

PostOp = tuple[str, list]
"""An activation fused into a oneDNN kernel: its attribute name and scalars."""
LEAKY: PostOp = ("leaky_relu", [0.1])
IDENTITY: PostOp = ("none", [])
SIGMOID: PostOp = ("sigmoid", [])
RELU: PostOp = ("relu", [])


def _has_fused_ops() -> bool:
    """Whether this torch build has oneDNN and its fused conv/linear + post-op kernels."""
    try:
        return bool(torch.backends.mkldnn.is_available()) and all(
            hasattr(torch.ops.mkldnn, op) for op in ("_convolution_pointwise", "_linear_pointwise")
        )
    except (AttributeError, RuntimeError):
        return False


_FUSED_OPS = _has_fused_ops()
COMPILED_BLOCKS = True
"""Fused inference of a separable STDCB runs its temporal branches, pooling and gate as two
compiled passes (:mod:`flowslam.sceneflow.network.compiled_stdcb`); False: torch kernels only."""


def fusable(x: Tensor) -> bool:
    """Whether the fused oneDNN kernels may run on ``x``: float32 CPU inference (no autograd)."""
    return _FUSED_OPS and x.device.type == "cpu" and x.dtype == torch.float32 and not torch.is_grad_enabled()


def _post(y: Tensor, post: PostOp | None) -> Tensor:
    """The activation ``post`` applied in place (the unfused path)."""
    if post is None or post[0] == "none":
        return y
    if post[0] == "leaky_relu":
        return F.leaky_relu_(y, *post[1])
    if post[0] == "sigmoid":
        return torch.sigmoid_(y)
    if post[0] == "relu":
        return torch.relu_(y)
    raise ValueError(f"unknown post-op {post[0]!r}")


def linear(x: Tensor, layer: nn.Linear, post: PostOp | None = None) -> Tensor:
    """``layer`` on the channel axis of (..., C), then ``post``; one oneDNN kernel when
    ``post`` is given and ``fusable(x)``."""
    if post is None or not fusable(x):
        return _post(layer(x), post)
    y = torch.ops.mkldnn._linear_pointwise(x.reshape(-1, x.shape[-1]), layer.weight, layer.bias, post[0], post[1], "")
    return y.view(x.shape[:-1] + (y.shape[-1],))


def linear_add(x: Tensor, layer: nn.Linear, other: Tensor) -> Tensor:
    """``layer(x) + other`` on the channel axis, one oneDNN kernel when ``fusable(x)``."""
    if not fusable(x):
        return layer(x).add_(other)
    flat = x.reshape(-1, x.shape[-1])
    y = torch.ops.mkldnn._linear_pointwise.binary(
        flat, other.reshape(flat.shape[0], -1), layer.weight, layer.bias, "add"
    )
    return y.view(x.shape[:-1] + (y.shape[-1],))


def _conv2d(x: Tensor, weight: Tensor, bias: Tensor | None, stride, padding, dilation, groups: int,
            post: PostOp | None) -> Tensor:
    """``F.conv2d`` then ``post``; one oneDNN kernel when ``post`` is given and ``fusable(x)``."""
    if post is None or not fusable(x):
        return _post(F.conv2d(x, weight, bias, stride, padding, dilation, groups), post)
    return torch.ops.mkldnn._convolution_pointwise(
        x, weight, bias, list(padding), list(stride), list(dilation), groups, post[0], post[1], ""
    )


def spatial_conv(x: Tensor, conv: nn.Module, post: PostOp | None = None) -> Tensor:
    """Apply a 2D conv (or transposed conv) to every timestep of (B, T, H, W, C), then
    ``post`` (fused into an ``nn.Conv2d``'s kernel where possible)."""
    B, T, H, W, C = x.shape
    view = x.reshape(B * T, H, W, C).permute(0, 3, 1, 2)  # channels-last view, no copy
    if isinstance(conv, nn.Conv2d) and conv.padding_mode == "zeros":
        y = _conv2d(view, conv.weight, conv.bias, conv.stride, conv.padding, conv.dilation, conv.groups, post)
    else:
        y = _post(conv(view), post)
    return y.permute(0, 2, 3, 1).reshape(B, T, y.shape[2], y.shape[3], y.shape[1])


class TemporalConv(nn.Module):
    """Kernel-3 convolution along T of (B, T, H, W, C), zero-padded, with a dilation.

    ``out[t] = W0 x[t - d] + W1 x[t] + W2 x[t + d] (+ bias)``: the Conv3d kernel
    (3, 1, 1) with dilation (d, 1, 1). Dense (``depthwise=False``): the W are
    (cout, cin) matrices, computed as one matmul for the three taps. Depthwise
    (``depthwise=True``, cin == cout, Conv3d ``groups=cin``): the W are per-channel
    scales, computed as a depthwise (3, 1) ``conv2d`` over the channels-last (T, H*W)
    view of each sample.
    """

    def __init__(self, cin: int, cout: int, dilation: int = 1, bias: bool = False, depthwise: bool = False):
        super().__init__()
        if depthwise and cin != cout:
            raise ValueError("a depthwise temporal conv needs cin == cout")
        self.dilation = int(dilation)
        self.depthwise = depthwise
        fan_in = 3 if depthwise else 3 * cin
        self.weight = nn.Parameter(torch.empty((3, cout) if depthwise else (3, cout, cin)))
        self.bias = nn.Parameter(torch.zeros(cout)) if bias else None
        bound = 1.0 / math.sqrt(fan_in)
        nn.init.uniform_(self.weight, -bound, bound)

    def forward(self, x: Tensor, post: PostOp | None = None) -> Tensor:
        """(B, T, H, W, cin) -> (B, T, H, W, cout), then the activation ``post`` (fused
        into the depthwise kernel where possible)."""
        d, T = self.dilation, x.shape[1]
        w = self.weight
        if self.depthwise:  # a depthwise (3, 1) conv over the (T, H*W) image of each sample
            B, T, H, W, C = x.shape
            view = x.reshape(B, T, H * W, C).permute(0, 3, 1, 2)  # channels-last view, no copy
            k = w.t().reshape(C, 1, 3, 1)
            y = _conv2d(view, k, self.bias, (1, 1), (d, 0), (d, 1), C, post)
            return y.permute(0, 2, 3, 1).reshape(B, T, H, W, C)
        return _post(self._dense(x, w, d, T), post)

    def _dense(self, x: Tensor, w: Tensor, d: int, T: int) -> Tensor:
        cout = w.shape[1]
        # one matmul for the three taps: (..., 3, cout), tap-major like the weight
        y = F.linear(x, w.reshape(3 * cout, -1)).view(x.shape[:-1] + (3, cout))
        out = y[..., 1, :].clone() if self.bias is None else y[..., 1, :] + self.bias
        if T > d:
            out[:, d:] += y[:, :-d, ..., 0, :]
            out[:, :-d] += y[:, d:, ..., 2, :]
        return out


@torch.no_grad()
def fold_bn_into(layer: nn.Module, bn: nn.BatchNorm1d) -> None:
    """Fold an eval-mode BatchNorm that follows ``layer`` into the layer's weight and bias.

    Handles ``nn.Linear``, ``nn.Conv2d``, ``nn.ConvTranspose2d`` and ``TemporalConv``
    (BN acts on their output channels).
    """
    scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
    shift = bn.bias - bn.running_mean * scale
    w = layer.weight
    if isinstance(layer, nn.ConvTranspose2d):  # (in, out / groups, kh, kw)
        w.mul_(scale.view(1, -1, 1, 1))
    elif isinstance(layer, (nn.Conv2d, nn.Linear)):  # (out, ...)
        w.mul_(scale.view((-1,) + (1,) * (w.dim() - 1)))
    elif isinstance(layer, TemporalConv):  # (3, out) or (3, out, in)
        w.mul_(scale.view((1, -1) + (1,) * (w.dim() - 2)))
    else:
        raise TypeError(f"cannot fold a BatchNorm into {type(layer).__name__}")
    if layer.bias is None:
        layer.bias = nn.Parameter(shift.clone())
    else:
        layer.bias.mul_(scale).add_(shift)


class _NormAct(nn.Module):
    """BatchNorm over the channel axis of a channels-last tensor, then LeakyReLU (optional).

    After ``fold(layer)`` (inference only) the normalisation lives in the preceding
    layer's weights and only the activation is left.
    """

    def __init__(self, channels: int, act: bool = True):
        super().__init__()
        self.norm = nn.BatchNorm1d(channels)
        self.act = act
        self.folded = False

    def fold(self, layer: nn.Module) -> None:
        if not self.folded:
            fold_bn_into(layer, self.norm)
            self.folded = True

    def forward(self, x: Tensor) -> Tensor:
        y = x if self.folded else self.norm(x.reshape(-1, x.shape[-1])).view(x.shape)
        return F.leaky_relu(y, 0.1, inplace=True) if self.act else y

    def after(self, layer: Callable[[PostOp | None], Tensor], fuse: bool) -> Tensor:
        """``self(layer(None))``; with ``fuse`` and a folded norm the activation is handed
        to the layer as its post-op instead (``layer(post)``: one fused kernel)."""
        if fuse and self.folded:
            return layer(LEAKY if self.act else IDENTITY)
        return self(layer(None))


class STDCB(nn.Module):
    """Spatio-temporal Deep Coupling Block on (B, T, H, W, cin) -> (B, T, H, W, cout).

    See the module doc for the branches, SFS and TGB. ``separable=True`` is the CPU
    form: a pointwise conv (cin -> mid) first, then every branch and the gate are
    depthwise (3x3 spatial per channel, kernel-3 temporal per channel), so the block
    costs ~2 mid^2 instead of ~19 mid^2 multiply-adds per cell; the structure (three
    branches, SFS, TGB, projection, residual) is the same.
    """

    def __init__(
        self,
        cin: int,
        cout: int,
        mid: int | None = None,
        dilation: int = 2,
        reduction: int = 4,
        separable: bool = False,
    ):
        super().__init__()
        mid = mid or cout
        self.mid = mid
        self.separable = separable
        if separable:
            self.expand = nn.Linear(cin, mid, bias=False)
            self.norm_e = _NormAct(mid)
            self.spatial = nn.Conv2d(mid, mid, 3, padding=1, groups=mid, bias=False)
            self.local_t = TemporalConv(mid, mid, 1, depthwise=True)
            self.cross_t = TemporalConv(mid, mid, dilation, depthwise=True)
            self.gate = TemporalConv(mid, mid, 1, bias=True, depthwise=True)
        else:
            self.spatial = nn.Conv2d(cin, mid, 3, padding=1, bias=False)
            self.local_t = TemporalConv(cin, mid, 1)
            self.cross_t = TemporalConv(cin, mid, dilation)
            self.gate = TemporalConv(mid, mid, 1, bias=True)
        self.norm_s, self.norm_l, self.norm_c = _NormAct(mid), _NormAct(mid), _NormAct(mid)
        hidden = max(mid // reduction, 4)
        self.sfs = nn.Sequential(nn.Linear(mid, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, 3 * mid))
        self.proj = nn.Linear(mid, cout, bias=False)
        self.norm_o = _NormAct(cout, act=False)
        self.shortcut = nn.Linear(cin, cout, bias=False) if cin != cout else nn.Identity()

    def fold_batchnorm(self) -> None:
        """Fold every BatchNorm into its layer (eval/inference only)."""
        if self.separable:
            self.norm_e.fold(self.expand)
        self.norm_s.fold(self.spatial)
        self.norm_l.fold(self.local_t)
        self.norm_c.fold(self.cross_t)
        self.norm_o.fold(self.proj)

    def forward(self, x: Tensor) -> Tensor:
        fuse = fusable(x) and self.norm_s.folded  # layer + activation as one kernel (folded, CPU inference)
        h = self.norm_e.after(lambda post: linear(x, self.expand, post), fuse) if self.separable else x
        s = self.norm_s.after(lambda post: spatial_conv(h, self.spatial, post), fuse)
        if fuse and self.separable and COMPILED_BLOCKS and h.is_contiguous() and s.is_contiguous():
            out = self._compiled_branches(x, h, s)
        else:
            out = self._branches(x, h, s, fuse)
        return F.leaky_relu(out, 0.1, inplace=True)

    def _compiled_branches(self, x: Tensor, h: Tensor, s: Tensor) -> Tensor:
        """:meth:`_branches` of a folded separable block, its temporal branches, pooling and
        gate as two compiled passes (:mod:`compiled_stdcb`)."""
        from flowslam.sceneflow.network.compiled_stdcb import gated, temporal_branches

        loc, cross, desc = temporal_branches(self, h, s)
        w = torch.softmax(self.sfs(desc).view(x.shape[0], 3, self.mid), 1)
        return linear_add(gated(self, s, loc, cross, w), self.proj, self.shortcut(x))

    def _branches(self, x: Tensor, h: Tensor, s: Tensor, fuse: bool) -> Tensor:
        """The block before its final LeakyReLU: temporal branches of ``h``, Soft Feature
        Selection with the spatial branch ``s``, temporal gate, projection plus the shortcut
        of ``x`` (``fuse``: each layer with its activation as one kernel)."""
        B = x.shape[0]
        inplace = not torch.is_grad_enabled()  # inference: reuse buffers, no autograd to upset
        loc = self.norm_l.after(lambda post: self.local_t(h, post), fuse)
        cross = self.norm_c.after(lambda post: self.cross_t(h, post), fuse)
        # Soft Feature Selection: per-sample, per-channel softmax over the three branches
        desc = s.mean((1, 2, 3)) + loc.mean((1, 2, 3)) + cross.mean((1, 2, 3))  # (B, mid)
        w = torch.softmax(self.sfs(desc).view(B, 3, 1, 1, 1, self.mid), 1)
        if inplace:
            fused = s.mul_(w[:, 0]).addcmul_(loc, w[:, 1]).addcmul_(cross, w[:, 2])
            fused.mul_(self.gate(fused, SIGMOID) if fuse else torch.sigmoid_(self.gate(fused)))
            if fuse:  # the projection and the residual add in one kernel
                return linear_add(fused, self.proj, self.shortcut(x))
            out = self.norm_o(self.proj(fused))
            return out.add_(self.shortcut(x))
        fused = torch.addcmul(torch.addcmul(s * w[:, 0], loc, w[:, 1]), cross, w[:, 2])
        # Temporal Gated Block: a sigmoid gate from the fused features' temporal context
        fused = fused * torch.sigmoid(self.gate(fused))
        return self.norm_o(self.proj(fused)) + self.shortcut(x)


class _Down(nn.Module):
    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, 2, stride=2, bias=False)
        self.norm = _NormAct(cout)

    def fold_batchnorm(self) -> None:
        self.norm.fold(self.conv)

    def forward(self, x: Tensor) -> Tensor:
        return self.norm.after(lambda post: spatial_conv(x, self.conv, post), fusable(x))


class _Up(nn.Module):
    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.conv = nn.ConvTranspose2d(cin, cout, 2, stride=2, bias=False)
        self.norm = _NormAct(cout)

    def fold_batchnorm(self) -> None:
        self.norm.fold(self.conv)

    def forward(self, x: Tensor) -> Tensor:
        return self.norm(spatial_conv(x, self.conv))


class STUNet(nn.Module):
    """U-Net of STDCBs over (B, T, H, W, C); H and W must be divisible by 2**(levels-1).

    Args:
        in_channels: channels of the pillar grid.
        widths: channels per level, finest first (its length is the number of levels).
        encoder_depths: STDCBs per encoder level (same length as ``widths``; the last is
            the bottleneck).
        decoder_depths: STDCBs per decoder level, finest first (``len(widths) - 1``).
        dilation: dilation of the cross-timestep branch.
        separable: depthwise-separable STDCBs (the CPU form, see ``STDCB``).
    """

    def __init__(
        self,
        in_channels: int,
        widths: Sequence[int] = (16, 32, 64, 64, 64),
        encoder_depths: Sequence[int] = (2, 2, 2, 2, 2),
        decoder_depths: Sequence[int] = (1, 1, 1, 1),
        dilation: int = 2,
        separable: bool = False,
    ):
        super().__init__()
        widths, enc, dec = list(widths), list(encoder_depths), list(decoder_depths)
        if len(enc) != len(widths) or len(dec) != len(widths) - 1:
            raise ValueError(
                f"need len(encoder_depths) == len(widths) and len(decoder_depths) == len(widths) - 1, "
                f"got {enc}, {dec}, {widths}"
            )
        if min(enc) < 1 or min(dec, default=1) < 1:
            raise ValueError("every level needs at least one STDCB")
        self.levels = len(widths)
        self.out_channels = widths[0]
        self.encoders = nn.ModuleList()
        self.downs = nn.ModuleList()
        cin = in_channels
        for i, (w, depth) in enumerate(zip(widths, enc)):
            blocks = [STDCB(cin if k == 0 else w, w, dilation=dilation, separable=separable) for k in range(depth)]
            self.encoders.append(nn.Sequential(*blocks))
            cin = w
            if i < self.levels - 1:
                self.downs.append(_Down(w, widths[i + 1]))
                cin = widths[i + 1]
        self.ups = nn.ModuleList()
        self.decoders = nn.ModuleList()
        for i in reversed(range(self.levels - 1)):  # from the coarsest skip up to the finest
            self.ups.append(_Up(widths[i + 1], widths[i]))
            blocks = [
                STDCB(2 * widths[i] if k == 0 else widths[i], widths[i], dilation=dilation, separable=separable)
                for k in range(dec[i])
            ]
            self.decoders.append(nn.Sequential(*blocks))

    @property
    def stride(self) -> int:
        return 2 ** (self.levels - 1)

    def forward(self, x: Tensor) -> Tensor:
        """(B, T, H, W, in_channels) -> (B, T, H, W, widths[0])."""
        if x.shape[2] % self.stride or x.shape[3] % self.stride:
            raise ValueError(f"grid {x.shape[2]}x{x.shape[3]} is not divisible by {self.stride}")
        skips = []
        for i, enc in enumerate(self.encoders):
            x = enc(x)
            if i < self.levels - 1:
                skips.append(x)
                x = self.downs[i](x)
        for up, dec in zip(self.ups, self.decoders):
            x = dec(torch.cat([up(x), skips.pop()], -1))
        return x
