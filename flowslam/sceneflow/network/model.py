"""``SceneFlowNet``: MambaFlow's architecture in pure, device-agnostic PyTorch.

Input contract (``forward(batch)``)
-----------------------------------
``batch["points"][b][t]``: (N_bt, 3) float tensors, metres, for sample ``b`` and frame
``t`` (oldest first, ``config.num_frames`` frames, newest last), **all expressed in the
sensor frame of the newest scan**, the older scans moved there with the ego-motion the
caller estimated itself (the network never sees poses). Point counts may differ per
frame and per sample. A plain list of T tensors is accepted as a batch of one.

Which points get flow (MambaFlow's convention)
----------------------------------------------
Flow is predicted for the points of the **second-newest** frame (t = T-2, the
"source", scan *t*) towards the newest (t = T-1, scan *t+1*), using frames
t-(T-2) .. t+1 as context (T = 5: t-3 .. t+1; T = 2: just the pair).

Output (``dict``)
-----------------
- ``"flow"``: (sum_b N_b, 3) **residual** flow in metres, newest sensor frame, one row
  per source point, samples concatenated in order, points in their input order:
  ``compensated_source_point + flow`` is where the point is at t+1, in the newest frame.
  It is zero for a static point when the ego-motion estimate is right.
- ``"dynamic_logit"``: (sum_b N_b,) logit of "this point moves in the world".
- ``"batch_index"``: (sum_b N_b,) long, the sample of each row.
- ``"valid"``: (sum_b N_b,) bool, the point fell inside the grid (outside: flow 0,
  logit ``OUTSIDE_LOGIT``).

Time collapse: the U-Net keeps the time axis; the decoder reads the U-Net output and the
pillar grid only at frames t and t+1 (concatenated per point), as MambaFlow keeps the
source frame's slice of its 4D output.

Presets (``ModelConfig.preset``): ``"tiny"`` (alias ``"cpu"``) for CPU inference and
CPU training: 0.4 m pillars over +-51.2 m, U-Net from 0.8 m cells, depthwise-separable
STDCBs, one unidirectional FlowSSM layer; ``"full"``: MambaFlow's 0.2 m voxels, dense
STDCBs at full resolution, two bidirectional FlowSSM layers, ~3.1 M parameters (GPU).
Every field can be overridden (``ModelConfig.preset("tiny", widths=[...])``).

Residual-flow convention: with ``p`` a source point in its own sensor frame and
``T_new_src`` the caller's ego-motion estimate (``T_{t+1,t}``), the network saw
``q = T_new_src p`` and the full Argoverse-2-convention flow is
``(q - p) + residual`` (``full_flow`` below): the caller adds the ego prior back.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Literal

import torch
from pydantic import BaseModel, ConfigDict, Field, model_validator
from torch import Tensor, nn

from flowslam.sceneflow.network.backbone import STUNet, _Down
from flowslam.sceneflow.network.flowssm import FlowSSMDecoder, bilinear_gather, morton_code
from flowslam.sceneflow.network.voxelize import BEVGrid, PillarEncoder, index_points

COMPILED_PILLARS = True
"""CPU float32 inference runs the pillar PointNet, its pooling and the stride-2 stem on the
occupied pillars only (:mod:`flowslam.sceneflow.network.compiled_pillars`); False: torch."""

__all__ = [
    "ModelConfig", "SceneFlowNet", "full_flow", "tune_cpu_allocator", "release_free_heap", "malloc_in_use_bytes",
    "default_cpu_threads", "OUTSIDE_LOGIT", "PRESETS",
]

OUTSIDE_LOGIT = -20.0
"""Dynamic logit given to source points outside the grid (they get zero residual flow)."""

MORTON_SUBDIVISION = 8
"""The Z-order serialisation quantises points at ``voxel_size / MORTON_SUBDIVISION``."""

OFFSET_FEATURES = 8
"""Raw offset inputs per point: offsets to the fine and coarse cell centres (2 + 2),
to the pillar's point mean (3), normalised height (1)."""


class ModelConfig(BaseModel):
    """Every size knob of ``SceneFlowNet`` (metres for lengths); the defaults are the
    ``"tiny"`` preset. See ``PRESETS``."""

    model_config = ConfigDict(extra="forbid")

    num_frames: int = Field(5, ge=2, description="frames per sample, oldest first; flow for frame T-2")
    half_extent: float = Field(51.2, gt=0, description="grid covers [-half_extent, half_extent) in x and y (m)")
    voxel_size: float = Field(0.4, gt=0, description="pillar size (m)")
    z_min: float = Field(-3.0, description="points below are ignored (m, sensor frame)")
    z_max: float = Field(5.0, description="points at or above are ignored (m)")
    pillar_channels: int = Field(16, ge=1)
    pooling: Literal["amax", "mean"] = "amax"
    stem_stride: Literal[1, 2] = Field(2, description="U-Net input stride w.r.t. the pillar grid")
    widths: list[int] = Field(default_factory=lambda: [16, 24, 32, 48, 64], description="U-Net channels, finest first")
    encoder_depths: list[int] = Field(default_factory=lambda: [2, 2, 2, 2, 2])
    decoder_depths: list[int] = Field(default_factory=lambda: [1, 1, 1, 1])
    temporal_dilation: int = Field(2, ge=1, description="dilation of the cross-timestep branch")
    separable: bool = Field(True, description="depthwise-separable STDCBs (CPU form)")
    d_model: int = Field(32, ge=1, description="FlowSSM point feature width")
    d_inner: int = Field(16, ge=1, description="FlowSSM scanned channels")
    d_state: int = Field(8, ge=1, description="selective-scan state size per channel")
    d_offset: int = Field(16, ge=1, description="offset-feature width (drives Delta, B, C)")
    ssm_layers: int = Field(1, ge=1)
    bidirectional: bool = Field(False, description="also scan the reversed sequence")
    conv_kernel: int = Field(4, ge=0, description="causal depthwise conv before the scan (0/1: none)")
    chunk_size: int = Field(128, ge=1, description="selective-scan chunk length")
    head_hidden: int = Field(32, ge=1)

    @model_validator(mode="after")
    def _check(self) -> ModelConfig:
        if self.z_max <= self.z_min:
            raise ValueError("z_max must be above z_min")
        if len(self.encoder_depths) != len(self.widths) or len(self.decoder_depths) != len(self.widths) - 1:
            raise ValueError("need len(encoder_depths) == len(widths) == len(decoder_depths) + 1")
        n = self.grid.size
        stride = self.stem_stride * 2 ** (len(self.widths) - 1)
        if abs(n * self.voxel_size - 2 * self.half_extent) > 1e-6 * self.half_extent or n % stride:
            raise ValueError(
                f"2*half_extent/voxel_size = {2 * self.half_extent / self.voxel_size:g} cells must be an integer "
                f"divisible by {stride} (stem_stride * 2**(levels-1))"
            )
        z_cells = (self.z_max - self.z_min) / self.voxel_size
        if max(n, z_cells) * MORTON_SUBDIVISION >= 2**21:
            raise ValueError("grid too large for 21-bit Morton codes")
        return self

    @property
    def grid(self) -> BEVGrid:
        return BEVGrid(self.half_extent, self.voxel_size, self.z_min, self.z_max)

    @classmethod
    def preset(cls, name: str, **overrides) -> ModelConfig:
        """A named preset (``"tiny"`` / ``"cpu"``, ``"full"``) with optional field overrides."""
        if name not in PRESETS:
            raise ValueError(f"unknown preset {name!r}, choose from {sorted(PRESETS)}")
        return cls(**{**PRESETS[name], **overrides})


PRESETS: dict[str, dict] = {
    # CPU: 0.4 m pillars over +-51.2 m (256x256), U-Net from 0.8 m (128x128); see the benchmark
    "tiny": dict(
        voxel_size=0.4, pillar_channels=16, stem_stride=2, widths=[16, 24, 32, 48, 64], separable=True,
        d_model=32, d_inner=16, d_state=8, d_offset=16, ssm_layers=1, bidirectional=False, head_hidden=32,
    ),
    # GPU: MambaFlow's 0.2 m voxels (512x512), U-Net at full resolution, ~3 M parameters
    "full": dict(
        voxel_size=0.2, pillar_channels=32, stem_stride=1, widths=[32, 64, 96, 116, 116],
        separable=False, d_model=96, d_inner=192, d_state=16, d_offset=32, ssm_layers=2, bidirectional=True,
        head_hidden=64, chunk_size=256,
    ),
}
PRESETS["cpu"] = PRESETS["tiny"]


class SceneFlowNet(nn.Module):
    """Pillar PointNet -> BEV+time STDCB U-Net -> FlowSSM decoder (see the module doc)."""

    def __init__(self, config: ModelConfig | None = None):
        super().__init__()
        self.config = config = config or ModelConfig()
        self.grid = config.grid
        self.pillars = PillarEncoder(self.grid, config.pillar_channels, config.pooling)
        cp = config.pillar_channels
        if config.stem_stride == 2:
            self.stem: nn.Module = _Down(cp, config.widths[0])
            unet_in = config.widths[0]
        else:
            self.stem = nn.Identity()
            unet_in = cp
        self.backbone = STUNet(
            unet_in, config.widths, config.encoder_depths, config.decoder_depths, config.temporal_dilation,
            config.separable,
        )
        # per point: U-Net features at t and t+1, pillar features at t and t+1, own PointNet feature
        point_in = 2 * config.widths[0] + 3 * cp
        self.decoder = FlowSSMDecoder(
            point_in, OFFSET_FEATURES, config.d_model, config.d_inner, config.d_state, config.d_offset,
            config.ssm_layers, config.chunk_size, config.bidirectional, config.conv_kernel, config.head_hidden,
        )

    # ------------------------------------------------------------------ size
    def count_parameters(self) -> int:
        """Trainable parameters."""
        return sum(p.numel() for p in self.parameters() if p.requires_grad)

    def size_mb(self) -> float:
        """Parameters + buffers in MB (1e6 bytes), as in MambaFlow's Table V."""
        n = sum(p.numel() * p.element_size() for p in self.parameters())
        n += sum(b.numel() * b.element_size() for b in self.buffers())
        return n / 1e6

    def crop_grid(self, half_extent: float | None) -> SceneFlowNet:
        """Run on the square ``[-half_extent, half_extent)`` around the sensor instead of the
        trained grid (``BEVGrid.crop``; None: the trained grid again). The crop must take
        whole cells of the U-Net's coarsest level off each side (``coarsest_cell_m``), so
        that every level's cells stay where they were; points beyond it get no residual flow
        and the logit ``OUTSIDE_LOGIT`` (static). Inference only: the convolutions of a
        cropped grid see zeros where the trained grid had the cells beyond, so the outputs
        change a little everywhere (not a training option)."""
        full = self.config.half_extent
        if half_extent is not None:
            cells = (full - half_extent) / self.coarsest_cell_m
            if not (0 < half_extent <= full) or abs(cells - round(cells)) > 1e-6:
                raise ValueError(
                    f"grid crop {half_extent:g} m: must be in (0, {full:g}] and take a multiple of "
                    f"{self.coarsest_cell_m:g} m (the coarsest U-Net cell) off the trained {full:g} m"
                )
            if abs(half_extent - full) < 1e-9:
                half_extent = None
        self.grid = dataclasses.replace(self.config.grid, crop=half_extent)
        self.pillars.grid = self.grid
        return self

    @property
    def coarsest_cell_m(self) -> float:
        """Side (m) of a cell of the U-Net's coarsest level."""
        return self.config.voxel_size * self.config.stem_stride * self.backbone.stride

    def fold_batchnorm(self) -> SceneFlowNet:
        """Switch to eval mode and fold every BatchNorm into the layer before it (faster
        inference, same outputs up to float rounding). Irreversible: do not train afterwards."""
        self.eval()
        for m in self.modules():
            if m is not self and hasattr(m, "fold_batchnorm"):
                m.fold_batchnorm()
        self.folded = True
        return self

    def train(self, mode: bool = True) -> SceneFlowNet:
        if mode and getattr(self, "folded", False):
            raise RuntimeError("this SceneFlowNet has folded BatchNorms (inference only); rebuild it to train")
        return super().train(mode)

    # ------------------------------------------------------------------ forward
    def forward(self, batch: dict | list) -> dict[str, Tensor]:
        """See the module doc for the input/output contract."""
        frames = batch["points"] if isinstance(batch, dict) else batch
        if frames and isinstance(frames[0], Tensor):
            frames = [frames]
        T = self.config.num_frames
        if not frames or any(len(f) != T for f in frames):
            raise ValueError(f"every sample needs {T} frames (config.num_frames)")
        w = self.pillars.linear.weight
        frames = [[p.to(device=w.device, dtype=w.dtype) for p in sample] for sample in frames]
        index, inside = index_points(frames, self.grid)
        if self._compiled_pillars(w):  # CPU inference: the occupied pillars only
            from flowslam.sceneflow.network.compiled_pillars import pillars_and_stem

            pillars = pillars_and_stem(self.pillars, self.stem, index)
            point_feats, raw, table, row_of = pillars.point_feats, pillars.raw, pillars.table, pillars.row_of
            feats = self.backbone(pillars.stem)  # (B, T, h, w, C0)
        else:
            dense, point_feats, raw = self.pillars(index)  # (B, T, H, W, Cp), (P, Cp), (P, 9)
            table, row_of = dense.reshape(-1, dense.shape[-1]), None
            feats = self.backbone(self.stem(dense))  # (B, T, h, w, C0)
        src = T - 2
        sel = torch.nonzero(index.time == src).squeeze(1)  # in-grid points of the source frame
        point_in, offset_in, code = self._source_inputs(index, sel, table, row_of, feats, point_feats, raw)
        out = self.decoder(point_in, offset_in, index.batch[sel], code, index.batch_size)  # (P_src, 4)

        # back to one row per input source point, samples concatenated
        counts = torch.tensor([len(sample[src]) for sample in frames], device=w.device)
        starts = torch.cumsum(counts, 0) - counts
        rows = starts[index.batch[sel]] + index.frame_index[sel]
        total = int(counts.sum())
        flow = out.new_zeros(total, 3).index_copy(0, rows, out[:, :3])
        logit = out.new_full((total,), OUTSIDE_LOGIT).index_copy(0, rows, out[:, 3])
        valid = torch.cat([sample_inside[src] for sample_inside in inside])
        batch_index = torch.repeat_interleave(torch.arange(len(frames), device=w.device), counts)
        return {"flow": flow, "dynamic_logit": logit, "batch_index": batch_index, "valid": valid}

    def _compiled_pillars(self, weight: Tensor) -> bool:
        """Whether the pillar stage and the stem run compiled (:mod:`compiled_pillars`):
        float32 CPU inference with folded BatchNorms, ``amax`` pooling and a stride-2 stem."""
        return (
            COMPILED_PILLARS and weight.device.type == "cpu" and weight.dtype == torch.float32
            and not torch.is_grad_enabled() and self.pillars.folded and self.pillars.pooling == "amax"
            and isinstance(self.stem, _Down) and self.stem.norm.folded
        )

    def _source_inputs(
        self, index, sel: Tensor, table: Tensor, row_of: Tensor | None, feats: Tensor, point_feats: Tensor,
        raw: Tensor,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Per source point: voxel-to-point inputs, raw offset inputs and Z-order code.

        The time axis is collapsed here: only frames t (source) and t+1 (target) of the
        U-Net output and of the pillar grid are read, at the point's position. The pooled
        pillar feature of grid cell ``c`` is ``table[row_of[c]]`` (``row_of`` None: ``table[c]``,
        the dense grid's rows).
        """
        cfg, g = self.config, self.grid
        pts = index.points[sel]
        cell = cfg.voxel_size * cfg.stem_stride
        u = (pts[:, 0] + g.extent) / cell - 0.5  # continuous U-Net cell coordinates (centres at integers)
        v = (pts[:, 1] + g.extent) / cell - 0.5
        if row_of is not None:  # the compiled pillar stage ran: the same inputs in one compiled pass
            from flowslam.sceneflow.network.compiled_decoder_inputs import decoder_inputs

            point_in, offset_in = decoder_inputs(feats, index.num_frames - 2, g.size, index.batch[sel], index.ix[sel],
                                                 index.iy[sel], u, v, table, row_of, point_feats, sel, raw)
        else:
            point_in, offset_in = self._gathered_inputs(index, sel, table, feats, point_feats, raw, u, v)
        # Z-order at 1/8 of the pillar size, so that ties (and with them any dependence on
        # the input order) are rare; from the trained grid's corner, cropped or not
        origin = pts.new_tensor([-g.half_extent, -g.half_extent, g.z_min])
        q = torch.floor((pts - origin) / (cfg.voxel_size / MORTON_SUBDIVISION)).long().clamp(min=0)
        return point_in, offset_in, morton_code(q[:, 0], q[:, 1], q[:, 2])

    @staticmethod
    def _gathered_inputs(
        index, sel: Tensor, table: Tensor, feats: Tensor, point_feats: Tensor, raw: Tensor, u: Tensor, v: Tensor,
    ) -> tuple[Tensor, Tensor]:
        """The torch form of :meth:`_source_inputs`' voxel-to-point and offset inputs, on the
        dense pillar grid's rows ``table`` (``u``, ``v``: the points' U-Net cell coordinates)."""
        B, T, n = index.batch_size, index.num_frames, index.grid.size
        src, tgt = T - 2, T - 1
        b, ix, iy = index.batch[sel], index.ix[sel], index.iy[sel]
        unet = feats.reshape(B * T, feats.shape[2], feats.shape[3], feats.shape[4])
        point_in = torch.cat(
            [
                bilinear_gather(unet, b * T + src, u, v),  # U-Net features at t and t+1
                bilinear_gather(unet, b * T + tgt, u, v),
                table[((b * T + src) * n + iy) * n + ix],  # the point's own pillar at t and t+1
                table[((b * T + tgt) * n + iy) * n + ix],
                point_feats[sel],  # its PointNet feature
            ],
            1,
        )
        raw = raw[sel]
        offset_in = torch.cat(  # pillar-centre offsets, U-Net-cell offsets, pillar-mean offsets, height
            [raw[:, 3:5], torch.stack([u - u.round(), v - v.round()], 1), raw[:, 5:8], raw[:, 2:3]], 1
        )
        return point_in, offset_in


@functools.lru_cache(maxsize=1)
def _glibc():
    """The C library as a ``ctypes.CDLL`` on Linux, else None; looked up once (the
    lookup runs ``ldconfig``, and the heap trims below come every few scans)."""
    import ctypes
    import ctypes.util
    import sys

    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None


def tune_cpu_allocator(mmap_threshold: int = 256 << 20, trim_threshold: int = 512 << 20) -> bool:
    """Opt-in: stop glibc from returning freed multi-MB blocks to the OS (Linux only).

    PyTorch's CPU allocator is plain ``malloc``; by default glibc serves every block of a
    few MB with a fresh ``mmap`` and unmaps it on free, so each large activation of the
    network is page-faulted in again (measured: an STDCB at 128x128x5x16 takes 21 ms
    instead of 7-9 ms). Raising ``M_MMAP_THRESHOLD`` / ``M_TRIM_THRESHOLD`` keeps such
    blocks in the heap for reuse, at the price of a process that keeps its peak heap.
    This changes the whole process, so the library never calls it by itself: the
    application (frontend, benchmark) does, once. Returns whether it took effect.
    """
    libc = _glibc()
    if libc is None:
        return False
    M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameter numbers
    try:
        ok = libc.mallopt(M_MMAP_THRESHOLD, int(mmap_threshold)) == 1
        return bool(ok and libc.mallopt(M_TRIM_THRESHOLD, int(trim_threshold)) == 1)
    except AttributeError:  # a C library without mallopt
        return False


def release_free_heap() -> bool:
    """Hand the heap's whole free pages back to the OS, in every arena (glibc ``malloc_trim``;
    Linux only): the counterpart of :func:`tune_cpu_allocator`, whose thresholds otherwise
    let the resident set ratchet up to the peak heap plus its fragmentation (measured: 1.8 GB
    after 500 scans of a 64-beam ``ssf`` run; ~550 MB, flat, with a trim every 25 scans, at
    ~16 ms a trim). Returns whether it ran."""
    libc = _glibc()
    if libc is None:
        return False
    try:
        libc.malloc_trim(0)
    except AttributeError:  # a C library without malloc_trim
        return False
    return True


def malloc_in_use_bytes() -> int | None:
    """Bytes glibc's malloc hands out now, every arena, mmapped blocks included
    (``mallinfo2``: ``uordblks`` + ``hblkhd``; glibc >= 2.33, Linux only), else None. Unlike
    the resident set it leaves out the free heap that glibc keeps (between the trims of
    :func:`release_free_heap`), so it shows what the process holds."""
    fn = _mallinfo2()
    if fn is None:
        return None
    info = fn()
    return int(info.uordblks + info.hblkhd)


@functools.lru_cache(maxsize=1)
def _mallinfo2():
    """glibc's ``mallinfo2`` with its result type, or None; set up once."""
    import ctypes

    libc = _glibc()
    if libc is None or not hasattr(libc, "mallinfo2"):
        return None

    class MallInfo2(ctypes.Structure):
        _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                         "fsmblks", "uordblks", "fordblks", "keepcost")]

    fn = libc.mallinfo2
    fn.restype = MallInfo2
    return fn


def default_cpu_threads(shares_cores: bool = False) -> int | None:
    """Intra-op threads for CPU inference when the user set none: 1 under passive OpenMP
    waiting (``OMP_WAIT_POLICY=PASSIVE``, what the CLI sets unless the user set it) or when
    the network ``shares_cores`` with other work running at the same time (``ssf.lookahead``:
    a spinning second thread would take the other thread's core), else None (keep torch's
    default).

    With passive waiting every parallel op wakes a sleeping worker; the network runs
    ~1,000 ops per scan, so a second thread gains nothing: measured on the 2-core
    machine, one thread vs two (KITTI scan, 16,384 points/frame) 113 vs 131 ms idle
    (``docs/sceneflow_evaluation.md``) and 133 vs 139 ms forward with other jobs
    running (load ~5); one thread also leaves the other core to the rest of the frame.
    With active (spinning) waiting on an idle machine two threads are faster (82 ms),
    so then torch's default is kept.
    """
    import os

    passive = os.environ.get("OMP_WAIT_POLICY", "").strip().upper() == "PASSIVE"
    return 1 if passive or shares_cores else None


def full_flow(points_src: Tensor, points_src_compensated: Tensor, residual: Tensor) -> Tensor:
    """Argoverse-2-convention flow of the source points: ``(q - p) + residual``.

    ``points_src`` (N,3) in the source sensor frame, ``points_src_compensated`` (N,3) the
    same points moved into the newest frame with the caller's ego-motion estimate (what
    the network was given), ``residual`` (N,3) the network's ``"flow"``.
    """
    return points_src_compensated - points_src + residual
