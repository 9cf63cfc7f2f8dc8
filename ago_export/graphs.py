"""The torch modules `ago export` traces into the bundle's two ONNX graphs (bundle format 3).

They compute the trained model's function (ago_train.model) with the same weights, restructured
for onnxruntime on a CPU; tests/test_export.py checks them against the torch model itself.

`PlanesGraph` (planes.onnx): images (1, V, 3, H, W) + ego2img (1, V, 4, 4) ->
    plane_xy (X, Y, Dh), plane_xz (X, Z, Dh), plane_yz (Y, Z, Dh): the three TPV planes, upsampled
    to the grid and already multiplied by the decoder's first linear layer (its bias is in
    plane_xy), channels last. The first linear commutes with the plane sum
    (W (xy + xz + yz) + b = (W xy + b) + W xz + W yz) and with bilinear upsampling (its weights sum
    to one), so it runs on the ~11 600 plane cells instead of on every voxel.
`VoxelStageGraph` (voxels_<i>.onnx, one per `voxel_stages(model)`): the per-voxel MLP's linear
    layers and the folded bank's products, one graph per layer. The runtime sums the planes of a
    slab of voxels, applies the softplus activations between the stages itself (numpy + OpenCV's
    vectorised exp / log: measured ~2x faster than onnxruntime's Log in a graph, docs/runtime.md)
    and runs each stage's GEMMs in onnxruntime.

What is restructured in the TPV encoder (ExportTPV; the trained ago_train.model.tpv.TPVEncoder
does the same arithmetic in another order):
- batch 1, queries kept as (Q, D); every per-sample tensor is laid out (heads, points, Q) with the
  Q queries last, so elementwise ops and reductions run over long contiguous rows (onnxruntime is
  slow on tensors whose last axis is 1 or 2);
- the offsets and attention-weight linears of an attention are one Gemm (rows reordered at export
  time so that x offsets, y offsets and weights are contiguous blocks);
- one GridSample per attention: the six cameras' FPN levels sit in one zero-framed "camera canvas"
  (per level a strip of six maps, each with a one-pixel zero frame; strips stacked vertically) and
  the three TPV value maps in one "plane canvas"; sample positions are clamped into their map's
  frame, which reproduces grid_sample's zero padding exactly (nothing bleeds between maps);
- the image value projection (1x1 conv with bias) runs on the canvas with an extra all-ones
  channel on the real pixels, so the frame stays zero;
- the camera geometry (projection, top-k cameras, reference pixels, validity / count weights) is
  computed once per frame, not per layer.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

PLANES = ("xy", "xz", "yz")


class LogSigmoidSoftplus(nn.Module):
    """softplus(x) = relu(x) - log(sigmoid(|x|)): the same function (sigmoid(|x|) is in [0.5, 1], so
    no underflow). Marks the activations of the exported MLP (the runtime computes them outside the
    graphs); as an ONNX graph it was measured faster than onnxruntime's Softplus op and than
    relu(x) + log1p(exp(-|x|)) (docs/runtime.md)."""

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


# --------------------------------------------------------------------------- canvases
class CanvasLayout:
    """Maps placed in one zero-framed 2-D canvas. blocks: name -> (row0, col0, rows, cols), where
    (row0, col0) is the block's top-left zero-frame pixel and the map's pixel (i, j) sits at
    (row0 + 1 + i, col0 + 1 + j)."""

    def __init__(self, blocks: dict, height: int, width: int):
        self.blocks, self.height, self.width = blocks, height, width

    @classmethod
    def cameras(cls, level_sizes: list[tuple[int, int]], num_cameras: int) -> "CanvasLayout":
        """Per level a strip of the V camera maps side by side; strips stacked top to bottom."""
        blocks, row = {}, 0
        width = max(num_cameras * (w + 2) for _, w in level_sizes)
        for lvl, (h, w) in enumerate(level_sizes):
            for v in range(num_cameras):
                blocks[(lvl, v)] = (row, v * (w + 2), h, w)
            row += h + 2
        return cls(blocks, row, width)

    @classmethod
    def planes(cls, plane_hw: dict) -> "CanvasLayout":
        """The three TPV maps side by side (rows aligned at the top)."""
        blocks, col = {}, 0
        height = max(r for r, _ in plane_hw.values()) + 2
        for p in PLANES:
            r, c = plane_hw[p]
            blocks[p] = (0, col, r, c)
            col += c + 2
        return cls(blocks, height, col)


def camera_canvas(feats: list[torch.Tensor], layout: CanvasLayout) -> torch.Tensor:
    """Per level (V, C, H_l, W_l) maps -> (C + 1, Hc, Wc) canvas; the extra last channel is 1 on real
    pixels and 0 on the zero frame (it carries the value projection's bias)."""
    strips = []
    for f in feats:
        V, C, H, W = f.shape
        f = torch.cat([f, torch.ones(V, 1, H, W, dtype=f.dtype)], 1)
        f = F.pad(f, (1, 1, 1, 1))                                            # (V, C+1, H+2, W+2)
        s = f.permute(1, 2, 0, 3).reshape(C + 1, H + 2, V * (W + 2))
        strips.append(F.pad(s, (0, layout.width - V * (W + 2))))
    return torch.cat(strips, 1)


def plane_canvas(maps: list[torch.Tensor], layout: CanvasLayout) -> torch.Tensor:
    """(C, rows_p, cols_p) maps of xy, xz, yz -> (C, Hp, Wp)."""
    parts = []
    for m in maps:
        parts.append(F.pad(m, (1, 1, 1, layout.height - m.shape[1] - 1)))
    return torch.cat(parts, 2)


def canvas_coords(px: torch.Tensor, py: torch.Tensor, lo_x: float, hi_x: torch.Tensor, lo_y: float,
                  hi_y: torch.Tensor, base_x, base_y, layout: CanvasLayout) -> torch.Tensor:
    """Sample positions in a map's "edge" pixel units (pixel i spans [i, i+1)) -> grid_sample
    coordinates in the canvas, clamped into the map's zero frame; px, py (..., Q) -> (..., Q, 2).
    base_*: the canvas column / row of the map's first pixel edge (block origin + 1)."""
    x = torch.minimum(px.clamp(min=lo_x), hi_x) + base_x
    y = torch.minimum(py.clamp(min=lo_y), hi_y) + base_y
    return torch.stack([x * (2.0 / layout.width) - 1.0, y * (2.0 / layout.height) - 1.0], -1)


# --------------------------------------------------------------------------- attentions
def _fused_linear(offsets: nn.Linear, weights: nn.Linear, heads: int, points: int):
    """One (3 * heads * points, D) weight for offsets and attention logits. The offsets linear's rows
    are (heads, points, 2) in C order; they are reordered to x block (heads, points), then y block."""
    W_off = offsets.weight.detach().view(heads, points, 2, -1)
    b_off = offsets.bias.detach().view(heads, points, 2)
    W = torch.cat([W_off[:, :, 0].reshape(heads * points, -1), W_off[:, :, 1].reshape(heads * points, -1),
                   weights.weight.detach()], 0)
    b = torch.cat([b_off[:, :, 0].reshape(-1), b_off[:, :, 1].reshape(-1), weights.bias.detach()], 0)
    return nn.Parameter(W.clone(), requires_grad=False), nn.Parameter(b.clone(), requires_grad=False)


class ExportCrossView(nn.Module):
    """CrossViewHybridAttention of one query plane over the plane canvas."""

    def __init__(self, attn, plane: str, geometry, layout: CanvasLayout, plane_hw: dict):
        super().__init__()
        self.heads, self.dim = attn.heads, attn.dim
        self.total = sum(attn.points)
        self.weight, self.bias = _fused_linear(attn.sampling_offsets, attn.attention_weights, self.heads, self.total)
        self.output_proj = attn.output_proj
        self.layout = layout
        ex, ey, hx, hy, bx = [], [], [], [], []
        for s, ref, k in zip(PLANES, geometry.cross_refs[plane], attn.points):
            rows, cols = plane_hw[s]
            r = torch.from_numpy(ref).double()                       # (Q, k, 2) (col_norm, row_norm)
            ex.append(((r[..., 0] + 1.0) * (cols / 2.0)).t())         # (k, Q) edge pixels
            ey.append(((r[..., 1] + 1.0) * (rows / 2.0)).t())
            hx.append(torch.full((k, 1), cols + 0.5, dtype=torch.float64))
            hy.append(torch.full((k, 1), rows + 0.5, dtype=torch.float64))
            row0, col0, _, _ = layout.blocks[s]
            bx.append(torch.full((k, 1), col0 + 1.0, dtype=torch.float64))
        for name, parts in (("ref_x", ex), ("ref_y", ey), ("hi_x", hx), ("hi_y", hy), ("base_x", bx)):
            self.register_buffer(name, torch.cat(parts).float().unsqueeze(0), persistent=False)   # (1, J, Q|1)

    def forward(self, q: torch.Tensor, canvas: torch.Tensor) -> torch.Tensor:
        """q (Q, D), canvas (heads, D/heads, Hp, Wp) -> (Q, D)."""
        h, J = self.heads, self.total
        Q = q.shape[0]
        o = torch.addmm(self.bias.unsqueeze(1), self.weight, q.t())             # (3*h*J, Q)
        off_x = o[: h * J].view(h, J, Q)
        off_y = o[h * J: 2 * h * J].view(h, J, Q)
        w = torch.softmax(o[2 * h * J:].view(h, J, Q), 1)
        grid = canvas_coords(self.ref_x + off_x, self.ref_y + off_y, -0.5, self.hi_x, -0.5, self.hi_y,
                             self.base_x, 1.0, self.layout)                     # (h, J, Q, 2)
        sampled = F.grid_sample(canvas, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        out = (sampled * w.unsqueeze(1)).sum(2)                                 # (h, D/h, Q)
        return self.output_proj(out.reshape(self.dim, Q).t())


class ExportImageAttention(nn.Module):
    """ImageCrossAttention of one plane over the camera canvas, with the frame's camera geometry."""

    def __init__(self, attn, layout: CanvasLayout, level_sizes: list[tuple[int, int]]):
        super().__init__()
        self.heads, self.dim = attn.heads, attn.dim
        self.L, self.P, self.S = attn.levels, attn.pillar, attn.offsets_n
        self.points = self.L * self.P * self.S
        self.weight, self.bias = _fused_linear(attn.sampling_offsets, attn.attention_weights, self.heads, self.points)
        self.output_proj = attn.output_proj
        self.layout = layout

    def forward(self, q: torch.Tensor, canvas: torch.Tensor, geo: dict) -> torch.Tensor:
        """q (Q, D); canvas (heads, D/heads, Hc, Wc); geo: this plane's frame geometry (FrameGeometry)
        -> (Q, D)."""
        h, L, P, S = self.heads, self.L, self.P, self.S
        Q = q.shape[0]
        n = h * self.points
        o = torch.addmm(self.bias.unsqueeze(1), self.weight, q.t())              # (3*n, Q)
        off_x = o[:n].view(h, L, 1, P, S, Q)
        off_y = o[n: 2 * n].view(h, L, 1, P, S, Q)
        w = torch.softmax(o[2 * n:].view(h, self.points, Q), 1).view(h, L, 1, P, S, Q)
        w = (w * geo["weight"]).reshape(h, 1, -1, Q)                              # (h, 1, L*k*P*S, Q)
        grid = canvas_coords(geo["ref_x"] + off_x, geo["ref_y"] + off_y, -0.5, geo["hi_x"], -0.5, geo["hi_y"],
                             geo["base_x"], geo["base_y"], self.layout)           # (h, L, k, P, S, Q, 2)
        grid = grid.reshape(h, -1, Q, 2)
        sampled = F.grid_sample(canvas, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        out = (sampled * w).sum(2)                                                 # (h, D/h, Q)
        return self.output_proj(out.reshape(self.dim, Q).t())


class FrameGeometry(nn.Module):
    """Per frame and plane: project the plane's pillars into the cameras, keep each query's k most
    visible cameras (static-size TopK, as ago_train.model.tpv.select_cameras), and give the
    reference pixels per level, the validity / camera-count weights and the canvas origins.
    Layout (levels L, cameras k, pillar points P, offsets 1, queries Q)."""

    def __init__(self, pillar, k: int, num_cameras: int, width: int, height: int,
                 level_sizes: list[tuple[int, int]], layout: CanvasLayout, eps: float = 1e-2):
        super().__init__()
        Q, P, _ = pillar.shape
        pts = torch.from_numpy(pillar).permute(1, 0, 2).reshape(P * Q, 3)          # P-major
        self.register_buffer("hom", torch.cat([pts, torch.ones(P * Q, 1)], 1).t().contiguous(), persistent=False)
        self.Q, self.P, self.k, self.V = Q, P, min(k, num_cameras), num_cameras
        self.width, self.height, self.eps = width, height, eps
        L = len(level_sizes)
        sz = torch.tensor(level_sizes, dtype=torch.float32)                          # (L, 2) (H, W)
        shape = (1, L, 1, 1, 1, 1)
        self.register_buffer("half_w", (sz[:, 1] / 2).view(L, 1, 1, 1, 1), persistent=False)
        self.register_buffer("half_h", (sz[:, 0] / 2).view(L, 1, 1, 1, 1), persistent=False)
        self.register_buffer("hi_x", (sz[:, 1] + 0.5).view(shape), persistent=False)
        self.register_buffer("hi_y", (sz[:, 0] + 0.5).view(shape), persistent=False)
        self.register_buffer("strip", (sz[:, 1] + 2).view(L, 1, 1, 1, 1), persistent=False)
        rows = torch.tensor([layout.blocks[(lvl, 0)][0] + 1.0 for lvl in range(L)])
        self.register_buffer("base_y", rows.view(shape), persistent=False)

    def forward(self, ego2img: torch.Tensor) -> dict:
        """ego2img (V, 4, 4) -> dict of tensors broadcastable to (heads, L, k, P, S, Q)."""
        V, P, Q, k = self.V, self.P, self.Q, self.k
        cam = torch.matmul(ego2img, self.hom)                                       # (V, 4, P*Q)
        depth = cam[:, 2]
        safe = torch.clamp(depth, min=self.eps)
        un = cam[:, 0] / safe / self.width * 2.0 - 1.0
        vn = cam[:, 1] / safe / self.height * 2.0 - 1.0
        mask = ((depth > self.eps) & (un >= -1.0) & (un <= 1.0) & (vn >= -1.0) & (vn <= 1.0)).float()
        mask = mask.view(V, P, Q)
        un = un.clamp(-2.0, 2.0).view(V, P, Q)
        vn = vn.clamp(-2.0, 2.0).view(V, P, Q)
        seen = mask.amax(1)                                                           # (V, Q)
        count = seen.sum(0)                                                           # (Q,)
        if k < V:
            idx = torch.topk(seen + mask.mean(1) * 0.5, k, dim=0).indices              # (k, Q)
            full = idx.unsqueeze(1).expand(k, P, Q)
            mask, un, vn = torch.gather(mask, 0, full), torch.gather(un, 0, full), torch.gather(vn, 0, full)
            cam_id = idx.to(un.dtype).view(1, k, 1, 1, Q)
        else:
            cam_id = torch.arange(V, dtype=un.dtype).view(1, V, 1, 1, 1)
        weight = (mask / count.clamp(min=1.0)).view(1, 1, k, P, 1, Q)
        ref_x = ((un.view(1, k, P, 1, Q) + 1.0) * self.half_w).unsqueeze(0)        # (1, L, k, P, 1, Q)
        ref_y = ((vn.view(1, k, P, 1, Q) + 1.0) * self.half_h).unsqueeze(0)
        base_x = (cam_id * self.strip + 1.0).unsqueeze(0)                            # (1, L, k|V, 1, 1, Q|1)
        return {"ref_x": ref_x, "ref_y": ref_y, "weight": weight, "base_x": base_x, "base_y": self.base_y,
                "hi_x": self.hi_x, "hi_y": self.hi_y}


class ExportTPVLayer(nn.Module):
    def __init__(self, layer, geometry, plane_hw: dict, cam_layout: CanvasLayout, plane_layout: CanvasLayout,
                 level_sizes):
        super().__init__()
        self.heads = layer.heads
        self.plane_hw = plane_hw
        self.plane_layout = plane_layout
        self.plane_value = layer.plane_value
        conv = layer.image_value
        with torch.no_grad():   # 1x1 conv with the bias as the weight of the canvas's ones channel
            w = torch.cat([conv.weight.detach(), conv.bias.detach().view(-1, 1, 1, 1)], 1)
        self.image_value = nn.Parameter(w.clone(), requires_grad=False)
        self.cross = nn.ModuleDict({p: ExportCrossView(layer.cross_view[p], p, geometry, plane_layout, plane_hw)
                                    for p in PLANES})
        self.image = nn.ModuleDict({p: ExportImageAttention(layer.image_attn[p], cam_layout, level_sizes)
                                    for p in PLANES})
        self.ffn = layer.ffn
        self.norms = layer.norms

    def forward(self, queries: dict, cam_canvas: torch.Tensor, geo: dict) -> dict:
        h = self.heads
        D = queries["xy"].shape[1]
        maps = []
        for s in PLANES:
            rows, cols = self.plane_hw[s]
            maps.append(self.plane_value(queries[s]).t().reshape(D, rows, cols))
        planes = plane_canvas(maps, self.plane_layout)
        planes = planes.reshape(h, D // h, planes.shape[1], planes.shape[2])
        values = F.conv2d(cam_canvas.unsqueeze(0), self.image_value)               # (1, D, Hc, Wc), frame 0
        values = values.reshape(h, D // h, values.shape[2], values.shape[3])
        out = {}
        for p in PLANES:
            q = queries[p]
            n1, n2, n3 = self.norms[p]
            q = n1(q + self.cross[p](q, planes))
            q = n2(q + self.image[p](q, values, geo[p]))
            out[p] = n3(q + self.ffn[p](q))
        return out


class ExportTPV(nn.Module):
    """TPVEncoder restructured (module docstring): FPN maps per level (V, D, H_l, W_l), ego2img (V, 4, 4)
    -> queries {"xy" | "xz" | "yz": (Q_p, D)} after the last layer (C order over the plane's rows, cols)."""

    def __init__(self, encoder, level_sizes: list[tuple[int, int]]):
        super().__init__()
        cfg = encoder.cfg
        geometry = encoder.geometry
        self.plane_hw = dict(encoder.plane_hw)
        V = cfg.num_cameras
        self.cam_layout = CanvasLayout.cameras(level_sizes, V)
        self.plane_layout = CanvasLayout.planes(self.plane_hw)
        self.geometry = nn.ModuleDict({
            p: FrameGeometry(geometry.pillars[p], encoder.cameras_per_query[p], V, cfg.image_width,
                             cfg.image_height, level_sizes, self.cam_layout) for p in PLANES})
        self.queries = encoder.queries
        self.layers = nn.ModuleList(ExportTPVLayer(layer, geometry, self.plane_hw, self.cam_layout,
                                                   self.plane_layout, level_sizes) for layer in encoder.layers)

    def forward(self, feats: list[torch.Tensor], ego2img: torch.Tensor) -> dict:
        geo = {p: self.geometry[p](ego2img) for p in PLANES}
        canvas = camera_canvas(feats, self.cam_layout)
        queries = {p: self.queries[p] for p in PLANES}
        for layer in self.layers:
            queries = layer(queries, canvas, geo)
        return queries


# --------------------------------------------------------------------------- the two graphs
class PlanesGraph(nn.Module):
    """planes.onnx: images (1, V, 3, H, W), ego2img (1, V, 4, 4) -> plane_xy (X, Y, Dh), plane_xz (X, Z, Dh),
    plane_yz (Y, Z, Dh): the TPV planes times the decoder's first linear layer (bias in plane_xy only),
    bilinearly upsampled to the grid (align_corners=False, as ago_train.model.aggregate.upsample_planes),
    channels last. (Running the backbone one camera at a time instead of on the batch of six was
    measured and did not pay: docs/runtime.md.)"""

    def __init__(self, model):
        super().__init__()
        cfg = model.cfg
        self.backbone, self.fpn = model.backbone, model.fpn
        with torch.no_grad():
            dummy = torch.zeros(1, 3, cfg.image_height, cfg.image_width)
            sizes = [tuple(int(s) for s in f.shape[-2:]) for f in model.fpn(model.backbone(dummy))]
        self.tpv = ExportTPV(model.encoder, sizes)
        first = model.decoder.net[0]
        if not isinstance(first, nn.Linear):
            raise ValueError("the decoder must start with a linear layer")
        self.first = first
        self.grid_shape = model.grid_shape

    def forward(self, images: torch.Tensor, ego2img: torch.Tensor):
        return self.from_features(self.fpn(self.backbone(images[0])), ego2img)

    def from_features(self, feats: list[torch.Tensor], ego2img: torch.Tensor):
        """FPN maps per level (V, D, H_l, W_l), ego2img (1, V, 4, 4) -> the three planes (see the class)."""
        queries = self.tpv(feats, ego2img[0])
        X, Y, Z = self.grid_shape
        target = {"xy": (X, Y), "xz": (X, Z), "yz": (Y, Z)}
        out = []
        for p in PLANES:
            rows, cols = self.tpv.plane_hw[p]
            f = F.linear(queries[p], self.first.weight, self.first.bias if p == "xy" else None)   # (Q, Dh)
            m = f.t().reshape(1, -1, rows, cols)
            if (rows, cols) != target[p]:
                m = F.interpolate(m, size=target[p], mode="bilinear", align_corners=False)
            out.append(m[0].permute(1, 2, 0))
        return tuple(out)


@dataclass
class VoxelStage:
    """One ONNX graph of the per-voxel MLP (voxels_<i>.onnx). Input x (n, d_in), the activation of the
    previous layer (the runtime applies the softplus between stages, ago_runtime.predict.encoder.Softplus);
    outputs y = x W^T + b (n, d_out), the next layer's pre-activation (no linear: no y), and, for the
    stages whose input is h (bank "main") or g (bank "adapted"), s = bank x^T (P', n) with the folded
    bank fed as the input "bank". activation: whether the runtime applies softplus to y."""

    linear: nn.Linear | None
    activation: bool
    bank: str | None

    def spec(self) -> dict:
        return {"linear": None if self.linear is None else [self.linear.in_features, self.linear.out_features],
                "activation": "softplus" if self.activation else "none", "bank": self.bank}


def voxel_stages(model) -> list[VoxelStage]:
    """The per-voxel MLP after the planes as stages: the decoder's remaining layers (each Linear +
    softplus; the first linear is in the planes and its softplus is applied to the plane sum), then
    from h the adapter's layers with decoder_out folded into the first (fused_adapter; adapter depth 1:
    g = decoder_out(h), no activation), then the adapted bank's product on g."""
    stages = [VoxelStage(m, True, None) for m in list(model.decoder.net)[1:] if isinstance(m, nn.Linear)]
    mods = list(fused_adapter(model))
    i, bank = 0, "main"
    while i < len(mods):
        act = i + 1 < len(mods) and isinstance(mods[i + 1], LogSigmoidSoftplus)
        stages.append(VoxelStage(mods[i], act, bank))
        bank = None
        i += 2 if act else 1
    stages.append(VoxelStage(None, False, "adapted"))
    return stages


class VoxelStageGraph(nn.Module):
    """voxels_<i>.onnx for one VoxelStage: inputs x (n, d_in) [, bank (P', d_in)] -> [y (n, d_out)] [, s (P', n)]."""

    def __init__(self, stage: VoxelStage):
        super().__init__()
        self.linear, self.bank = stage.linear, stage.bank

    def io_names(self) -> tuple[list[str], list[str]]:
        return (["x"] + (["bank"] if self.bank else []),
                (["y"] if self.linear is not None else []) + (["s"] if self.bank else []))

    def forward(self, x, bank=None):
        out = []
        if self.linear is not None:
            out.append(self.linear(x))
        if self.bank:
            out.append(torch.matmul(bank, x.t()))
        return tuple(out)


class VoxelsReference(nn.Module):
    """The whole per-voxel stage in torch, as the runtime runs it slab by slab (tests): a slab of x rows
    plane_xy (x, Y, Dh), plane_xz (x, Z, Dh), plane_yz (Y, Z, Dh), bank_main (P', Dh), bank_adapted
    (P', Da) -> h (n, Dh), g (n, Da), s_main (P', n), s_adapted (P', n); n = x*Y*Z in C order."""

    def __init__(self, model):
        super().__init__()
        self.stages = voxel_stages(model)
        self.act = LogSigmoidSoftplus()

    def forward(self, plane_xy, plane_xz, plane_yz, bank_main, bank_adapted):
        a = plane_xy.unsqueeze(2) + plane_xz.unsqueeze(1) + plane_yz.unsqueeze(0)      # (x, Y, Z, Dh)
        x = self.act(a.reshape(-1, a.shape[-1]))
        out = {}
        for st in self.stages:
            if st.bank == "main":
                out["h"], out["s_main"] = x, torch.matmul(bank_main, x.t())
            if st.bank == "adapted":
                out["g"], out["s_adapted"] = x, torch.matmul(bank_adapted, x.t())
            if st.linear is not None:
                x = st.linear(x)
                x = self.act(x) if st.activation else x
        return out["h"], out["g"], out["s_main"], out["s_adapted"]


def bank_scores_model():
    """The runtime's generic bank-product graph (ago_runtime/assets/graphs/bank_scores.onnx): inputs
    x (n, d) and bank (P', d), output s = bank x^T (P', n), every dimension symbolic, no weights. The
    runtime computes both branches' folded-bank scores with it (onnxruntime's GEMM; numpy's OpenBLAS was
    3-20x slower for this skinny shape here), so it can score any subset of voxels of any bundle.
    Rewrite the file with `write_bank_scores()`; tests/test_runtime.py checks it."""
    from onnx import TensorProto, helper

    graph = helper.make_graph(
        [helper.make_node("Transpose", ["x"], ["xt"], perm=[1, 0]), helper.make_node("MatMul", ["bank", "xt"], ["s"])],
        "ago_bank_scores",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["voxels", "width"]),
         helper.make_tensor_value_info("bank", TensorProto.FLOAT, ["phrases", "width"])],
        [helper.make_tensor_value_info("s", TensorProto.FLOAT, ["phrases", "voxels"])])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8,
                              producer_name="ago_export.graphs.bank_scores_model")
    return model


def write_bank_scores(path=None):
    """Write bank_scores_model() to the runtime's asset (or `path`)."""
    import onnx
    from pathlib import Path

    from ago_runtime.predict.encoder import BANK_SCORES_GRAPH

    path = Path(path or BANK_SCORES_GRAPH)
    path.parent.mkdir(parents=True, exist_ok=True)
    model = bank_scores_model()
    onnx.checker.check_model(model, full_check=True)
    onnx.save(model, str(path))
    return path
