"""The torch modules `ago export` traces into the bundle's ONNX graphs (bundle format 4).

They compute the trained model's function (ago_train.model) with the same weights, restructured
for onnxruntime on a CPU; tests/test_export.py checks them against the torch model itself.

`PlanesGraph` (planes.onnx): images (1, V, 3, H, W) + ego2img (1, V, 4, 4) ->
    plane_xy (X, Y, Dh), plane_xz (X, Z, Dh), plane_yz (Y, Z, Dh): the three TPV planes, upsampled
    to the grid and already multiplied by the decoder's first linear layer (its bias is in
    plane_xy), channels last. The first linear commutes with the plane sum
    (W (xy + xz + yz) + b = (W xy + b) + W xz + W yz) and with bilinear upsampling (its weights sum
    to one), so it runs on the ~11 600 plane cells instead of on every voxel.
`VoxelStageGraph` (voxels_<i>.onnx, one per `voxel_stages(model)`): the per-voxel MLP's linear
    layers after the planes, one graph per layer. The runtime sums the planes of a slab of voxels,
    applies the softplus activations between the stages itself (numpy + OpenCV's vectorised exp / log)
    and runs each stage's GEMM in onnxruntime; the folded bank's products are the runtime's own
    (ago_runtime.predict.bank_product), so no graph holds a bank.

The TPV encoder runs in its "canvas" layout (one grid_sample per attention over zero-framed canvases,
queries last, fused offset/weight products, per-frame camera geometry): ago_train/model/tpv_canvas.py,
the same code training runs, traced here.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from ago_runtime.predict.contract import VoxelStageSpec
from ago_runtime.predict.decision import Branch
from ago_train.model.tpv_canvas import PLANES, encode_frame


class LogSigmoidSoftplus(nn.Module):
    """softplus(x) = relu(x) - log(sigmoid(|x|)): the same function (sigmoid(|x|) is in [0.5, 1], so
    no underflow). Marks the activations of the exported MLP (the runtime computes them outside the
    graphs); as an ONNX graph it was measured faster than onnxruntime's Softplus op and than
    relu(x) + log1p(exp(-|x|)) (benchmarks/results/runtime_rewrites.md)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.relu(x) - torch.log(torch.sigmoid(torch.abs(x)))


def export_activations(seq: nn.Sequential) -> nn.Sequential:
    """A copy of a Linear/Softplus Sequential whose nn.Softplus(beta=1) layers are LogSigmoidSoftplus."""
    mods = []
    for m in seq:
        if isinstance(m, nn.Softplus):
            if m.beta != 1:
                raise ValueError("only softplus with beta 1 is exported")
            mods.append(LogSigmoidSoftplus())
        else:
            mods.append(m)
    return nn.Sequential(*mods)


def fused_adapter(model) -> nn.Sequential:
    """The adapter's hidden layers with decoder_out folded into the first linear:
    g = adapter(decoder_out(h)) = softplus(W1 (W_dec h + b_dec) + b1) ... , so W = W1 W_dec, b = W1 b_dec + b1
    (float64 product). Adapter depth 1 (g = F_3D) keeps decoder_out as its only layer."""
    net = model.adapter.net
    dec = model.decoder_out
    if len(net) == 0:
        return nn.Sequential(dec)
    first = net[0]
    with torch.no_grad():
        fused = nn.Linear(dec.in_features, first.out_features)
        fused.weight.copy_((first.weight.double() @ dec.weight.double()).float())
        fused.bias.copy_((first.weight.double() @ dec.bias.double() + first.bias.double()).float())
    return export_activations(nn.Sequential(fused, *list(net)[1:]))


# --------------------------------------------------------------------------- the TPV encoder
class ExportTPV(nn.Module):
    """The trained TPVEncoder in its canvas layout (ago_train/model/tpv_canvas.py: the same code
    training runs): FPN maps per level (V, D, H_l, W_l), ego2img (V, 4, 4) -> queries
    {"xy" | "xz" | "yz": (Q_p, D)} after the last layer (C order over the plane's rows, cols).

    static_sampling=False (the default) traces the image attentions' compact sampling, as training runs
    it: only the (camera, pillar point, query) entries that a camera sees are sampled, so the graph holds
    NonZero and ScatterElements(add) and the sample count depends on the frame (at the paper's scale on a
    nuScenes rig 55 % of the top plane's entries and 27 % of a side plane's). static_sampling=True traces
    the static form: every entry is sampled (the others weighted by 0), no data-dependent shapes, for
    runtimes that need static shapes. Both compute the same function (tests/test_model.py,
    tests/test_export.py)."""

    def __init__(self, encoder, static_sampling: bool = False):
        super().__init__()   # encode_frame checks the FPN map sizes against the encoder's canvas layout
        self.encoder = encoder
        self.plane_hw = dict(encoder.plane_hw)
        self.static_sampling = static_sampling

    def forward(self, feats: list[torch.Tensor], ego2img: torch.Tensor) -> dict:
        return encode_frame(self.encoder, feats, ego2img, compact=not self.static_sampling)


# --------------------------------------------------------------------------- the two graphs
def interpolation_matrix(n_in: int, n_out: int) -> torch.Tensor:
    """(n_out, n_in): linear interpolation along one axis as F.interpolate(mode="bilinear", align_corners=False)
    does it (output i reads the input at (i + 0.5) * n_in / n_out - 0.5, clamped to [0, n_in - 1]; two taps).
    Bilinear upsampling of a map is A_rows @ map @ A_cols^T."""
    src = ((torch.arange(n_out, dtype=torch.float64) + 0.5) * (n_in / n_out) - 0.5).clamp(min=0.0)
    i0 = src.floor().long().clamp(max=n_in - 1)
    i1 = (i0 + 1).clamp(max=n_in - 1)
    w1 = src - i0
    a = torch.zeros(n_out, n_in, dtype=torch.float64)
    rows = torch.arange(n_out)
    a.index_put_((rows, i0), 1.0 - w1, accumulate=True)
    a.index_put_((rows, i1), w1, accumulate=True)
    return a.float()


class PlanesGraph(nn.Module):
    """planes.onnx: images (1, V, 3, H, W), ego2img (1, V, 4, 4) -> plane_xy (X, Y, Dh), plane_xz (X, Z, Dh),
    plane_yz (Y, Z, Dh): the TPV planes times the decoder's first linear layer (bias in plane_xy only),
    bilinearly upsampled to the grid (align_corners=False, as ago_train.model.aggregate.upsample_planes),
    channels last. The upsampling runs channels last too, as two matrix products with `interpolation_matrix`
    (the queries' (rows, cols) order is already channels last): F.interpolate's channels-first Resize and the
    transpose behind it cost more in onnxruntime and far more in OpenVINO
    (benchmarks/results/planes_upsampling.md). (Running the backbone one camera at a time instead of on the
    batch of six was measured and did not pay: benchmarks/results/runtime_rewrites.md.)"""

    def __init__(self, model, grid_shape: tuple[int, int, int] | None = None, static_sampling: bool = False):
        """grid_shape: the read-out grid the planes are upsampled to (default the model's grid; a finer one
        over the same range reads the same planes at finer voxel centres, as AGOModel.forward(grid_shape=)).
        static_sampling: see ExportTPV."""
        super().__init__()
        self.backbone, self.fpn = model.backbone, model.fpn
        self.tpv = ExportTPV(model.encoder, static_sampling)
        first = model.decoder.net[0]
        if not isinstance(first, nn.Linear):
            raise ValueError("the decoder must start with a linear layer")
        self.first = first
        self.grid_shape = tuple(grid_shape) if grid_shape is not None else model.grid_shape
        X, Y, Z = self.grid_shape
        target = {"xy": (X, Y), "xz": (X, Z), "yz": (Y, Z)}
        for p in PLANES:     # per plane and axis, the interpolation matrix where the size changes
            for axis, n_in, n_out in (("rows", self.tpv.plane_hw[p][0], target[p][0]),
                                      ("cols", self.tpv.plane_hw[p][1], target[p][1])):
                self.register_buffer(f"up_{p}_{axis}", interpolation_matrix(n_in, n_out) if n_in != n_out else None,
                                     persistent=False)

    def forward(self, images: torch.Tensor, ego2img: torch.Tensor):
        # flatten, not images[0]: a Reshape onnxruntime runs in place, where [0] is a Gather that copies the images
        return self.from_features(self.fpn(self.backbone(images.flatten(0, 1))), ego2img)

    def from_features(self, feats: list[torch.Tensor], ego2img: torch.Tensor):
        """FPN maps per level (V, D, H_l, W_l), ego2img (1, V, 4, 4) -> the three planes (see the class)."""
        queries = self.tpv(feats, ego2img[0])
        out = []
        for p in PLANES:
            rows, cols = self.tpv.plane_hw[p]
            f = F.linear(queries[p], self.first.weight, self.first.bias if p == "xy" else None)   # (Q, Dh)
            m = f.reshape(rows, cols, -1)                       # queries are C order over (rows, cols)
            up_rows, up_cols = getattr(self, f"up_{p}_rows"), getattr(self, f"up_{p}_cols")
            if up_rows is not None:                             # (R, rows) @ (rows, cols * Dh)
                m = torch.matmul(up_rows, m.reshape(rows, -1)).reshape(up_rows.shape[0], cols, -1)
            if up_cols is not None:                             # (C, cols) @ (R, cols, Dh) -> (R, C, Dh)
                m = torch.matmul(up_cols, m)
            out.append(m)
        return tuple(out)


@dataclass
class VoxelStage:
    """One ONNX graph of the per-voxel MLP (voxels_<i>.onnx): x (n, d_in), the activation of the previous
    layer (the runtime applies the softplus between stages, ago_runtime.predict.encoder.Softplus) -> y =
    x W^T + b (n, d_out), the next layer's pre-activation. activation: whether the runtime applies softplus
    to y. branch: MAIN for the decoder's layers (toward h, every voxel), ADAPTED for the adapter's (from h
    toward g)."""

    linear: nn.Linear
    activation: bool
    branch: Branch

    def spec(self, file: str) -> VoxelStageSpec:
        return VoxelStageSpec(file, self.linear.in_features, self.linear.out_features,
                              "softplus" if self.activation else "none", self.branch)


def voxel_stages(model) -> list[VoxelStage]:
    """The per-voxel MLP after the planes as stages: the decoder's remaining layers (each Linear +
    softplus; the first linear is in the planes and its softplus is applied to the plane sum), then
    from h the adapter's layers with decoder_out folded into the first (fused_adapter; adapter depth 1:
    g = decoder_out(h), no activation)."""
    stages = [VoxelStage(m, True, Branch.MAIN) for m in list(model.decoder.net)[1:] if isinstance(m, nn.Linear)]
    mods = list(fused_adapter(model))
    i = 0
    while i < len(mods):
        act = i + 1 < len(mods) and isinstance(mods[i + 1], LogSigmoidSoftplus)
        stages.append(VoxelStage(mods[i], act, Branch.ADAPTED))
        i += 2 if act else 1
    return stages


class VoxelStageGraph(nn.Module):
    """voxels_<i>.onnx for one VoxelStage: x (n, d_in) -> y (n, d_out)."""

    def __init__(self, stage: VoxelStage):
        super().__init__()
        self.linear = stage.linear

    def forward(self, x):
        return self.linear(x)


class VoxelsReference(nn.Module):
    """The whole per-voxel stage in torch, as the runtime runs it slab by slab (tests): a slab of x rows
    plane_xy (x, Y, Dh), plane_xz (x, Z, Dh), plane_yz (Y, Z, Dh) -> h (n, Dh), g (n, Da); n = x*Y*Z in C order."""

    def __init__(self, model):
        super().__init__()
        self.stages = voxel_stages(model)
        self.act = LogSigmoidSoftplus()

    def forward(self, plane_xy, plane_xz, plane_yz):
        a = plane_xy.unsqueeze(2) + plane_xz.unsqueeze(1) + plane_yz.unsqueeze(0)      # (x, Y, Z, Dh)
        x = self.act(a.reshape(-1, a.shape[-1]))
        h = None
        for st in self.stages:
            if st.branch == Branch.ADAPTED and h is None:
                h = x
            x = st.linear(x)
            x = self.act(x) if st.activation else x
        return h, x
