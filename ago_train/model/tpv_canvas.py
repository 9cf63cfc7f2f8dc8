"""The TPV encoder's arithmetic in the "canvas" layout: the fast path of training and the export.

`TPVEncoder` (tpv.py) holds the parameters and two ways to run them that compute the same function
(tests/test_model.py checks values and gradients against each other):
- "reference" (tpv.py): per level and per camera set, tensors laid out (B, cameras, Q, heads, points);
  the plain reading of TPVFormer's attention, kept as the oracle;
- "canvas" (this module; the default, `ModelConfig.tpv_layout`): one frame at a time, restructured
  for a CPU (its cost against the reference: benchmarks/results/train_step_speed.md); `ago export`
  traces this same code into planes.onnx.

What is restructured:
- queries kept as (Q, D); every per-sample tensor is laid out (heads, points, Q) with the Q queries
  last, so elementwise ops and reductions run over long contiguous rows;
- the offsets and attention-weight linears of an attention run as one matrix product, their rows
  reordered (x offsets, y offsets, weights) by `fused_linear` (differentiable: training updates the
  original linears; the export's constant folding turns the reorder into one weight);
- the image attentions sample only the (camera, pillar point, query) entries a camera sees (compact
  form; `ago export` traces it too; the static form samples every entry, see `image_attention`);
- one grid_sample per attention: the V cameras' FPN levels sit in one zero-framed "camera canvas"
  (per level a strip of six maps, each with a one-pixel zero frame; strips stacked vertically) and
  the three TPV value maps in one "plane canvas"; sample positions are clamped into their map's
  frame, which reproduces grid_sample's zero padding exactly, values and gradients (nothing bleeds
  between maps);
- the image value projection (1x1 conv with bias) runs on the canvas with an extra all-ones
  channel on the real pixels, so the frame stays zero;
- the camera geometry (projection, top-k cameras, reference pixels, validity / count weights) is
  computed once per frame, not per layer.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

PLANES = ("xy", "xz", "yz")
LEVEL_STRIDES = (8, 16, 32)   # the backbone's three maps (ago_train.model.backbone)

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
        f = torch.cat([f, torch.ones(V, 1, H, W, dtype=f.dtype, device=f.device)], 1)
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
            cam_id = torch.arange(V, dtype=un.dtype, device=un.device).view(1, V, 1, 1, 1)
        weight = (mask / count.clamp(min=1.0)).view(1, 1, k, P, 1, Q)
        ref_x = ((un.view(1, k, P, 1, Q) + 1.0) * self.half_w).unsqueeze(0)        # (1, L, k, P, 1, Q)
        ref_y = ((vn.view(1, k, P, 1, Q) + 1.0) * self.half_h).unsqueeze(0)
        base_x = (cam_id * self.strip + 1.0).unsqueeze(0)                            # (1, L, k|V, 1, 1, Q|1)
        return {"ref_x": ref_x, "ref_y": ref_y, "weight": weight, "base_x": base_x, "base_y": self.base_y,
                "hi_x": self.hi_x, "hi_y": self.hi_y}


def fused_linear(offsets: nn.Linear, weights: nn.Linear, heads: int, points: int):
    """The offsets and attention-weight linears of an attention as one (3 * heads * points, D) weight
    and bias. The offsets linear's rows are (heads, points, 2) in C order; they are reordered to an x
    block (heads, points), then a y block, then the weights' rows. Differentiable."""
    W_off = offsets.weight.view(heads, points, 2, -1)
    b_off = offsets.bias.view(heads, points, 2)
    W = torch.cat([W_off[:, :, 0].reshape(heads * points, -1), W_off[:, :, 1].reshape(heads * points, -1),
                   weights.weight], 0)
    b = torch.cat([b_off[:, :, 0].reshape(-1), b_off[:, :, 1].reshape(-1), weights.bias], 0)
    return W, b


class CrossViewRefs(nn.Module):
    """Constant reference pixels of one query plane's cross-view attention in the plane canvas:
    buffers (1, J, Q | 1) over the J = sum(points) samples (its own plane first or in PLANES order,
    as `TPVGeometry.cross_refs`)."""

    def __init__(self, geometry, plane: str, points: tuple, plane_hw: dict, layout: CanvasLayout):
        super().__init__()
        ex, ey, hx, hy, bx = [], [], [], [], []
        for s, ref, k in zip(PLANES, geometry.cross_refs[plane], points):
            rows, cols = plane_hw[s]
            r = torch.from_numpy(ref).double()                       # (Q, k, 2) (col_norm, row_norm)
            ex.append(((r[..., 0] + 1.0) * (cols / 2.0)).t())         # (k, Q) edge pixels
            ey.append(((r[..., 1] + 1.0) * (rows / 2.0)).t())
            hx.append(torch.full((k, 1), cols + 0.5, dtype=torch.float64))
            hy.append(torch.full((k, 1), rows + 0.5, dtype=torch.float64))
            _, col0, _, _ = layout.blocks[s]
            bx.append(torch.full((k, 1), col0 + 1.0, dtype=torch.float64))
        for name, parts in (("ref_x", ex), ("ref_y", ey), ("hi_x", hx), ("hi_y", hy), ("base_x", bx)):
            self.register_buffer(name, torch.cat(parts).float().unsqueeze(0), persistent=False)


class CanvasGeometry(nn.Module):
    """Everything constant the canvas layout needs for one encoder config (non-persistent buffers
    only: nothing of it is in a checkpoint): the two canvas layouts, per plane the pillar projection
    (`FrameGeometry`) and the cross-view reference pixels."""

    def __init__(self, geometry, plane_hw: dict, cameras_per_query: dict, points: dict, num_cameras: int,
                 width: int, height: int):
        super().__init__()
        self.level_sizes = [(height // s, width // s) for s in LEVEL_STRIDES]
        self.cam_layout = CanvasLayout.cameras(self.level_sizes, num_cameras)
        self.plane_layout = CanvasLayout.planes(plane_hw)
        self.frames = nn.ModuleDict({
            p: FrameGeometry(geometry.pillars[p], cameras_per_query[p], num_cameras, width, height,
                             self.level_sizes, self.cam_layout) for p in PLANES})
        self.cross = nn.ModuleDict({p: CrossViewRefs(geometry, p, points[p], plane_hw, self.plane_layout)
                                    for p in PLANES})


# --------------------------------------------------------------------------- attentions, one frame
def weighted_samples(canvas: torch.Tensor, grid: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """The attentions' read-out: bilinear samples (zero padding) of the canvas (heads, C, H, W) at grid
    (heads, S, Q, 2), weighted by w (heads, S, Q) and summed over the S samples -> (heads, C, Q).

    This form (samples-major, Mul + sum) is the fastest of those measured in onnxruntime at the paper's
    scale: an einsum or a batched MatMul over the samples, and a query-major layout (heads, Q, S), were
    slower there (benchmarks/results/tpv_sampling_forms.md)."""
    sampled = F.grid_sample(canvas, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    return (sampled * w.unsqueeze(1)).sum(2)


def cross_view(attn, refs: CrossViewRefs, q: torch.Tensor, canvas: torch.Tensor, layout: CanvasLayout):
    """CrossViewHybridAttention `attn` of one query plane: q (Q, D), plane canvas (heads, D/heads, Hp, Wp)
    -> (Q, D)."""
    h, J = attn.heads, sum(attn.points)
    Q = q.shape[0]
    W, b = fused_linear(attn.sampling_offsets, attn.attention_weights, h, J)
    o = torch.addmm(b.unsqueeze(1), W, q.t())                                # (3*h*J, Q)
    off_x, off_y, logits = o.view(3, h, J, Q).unbind(0)    # unbind, not slices: no zero-filled grads
    w = torch.softmax(logits, 1)
    grid = canvas_coords(refs.ref_x + off_x, refs.ref_y + off_y, -0.5, refs.hi_x, -0.5, refs.hi_y,
                         refs.base_x, 1.0, layout)                             # (h, J, Q, 2)
    out = weighted_samples(canvas, grid, w)                                    # (h, D/h, Q)
    return attn.output_proj(out.reshape(attn.dim, Q).t())


def image_attention(attn, q: torch.Tensor, canvas: torch.Tensor, geo: dict, layout: CanvasLayout,
                    compact: bool = False):
    """ImageCrossAttention `attn` of one plane: q (Q, D), camera canvas (heads, D/heads, Hc, Wc), geo:
    the plane's `FrameGeometry` of this frame -> (Q, D).

    compact: sample only the (camera, pillar point, query) entries whose validity weight is > 0 and
    add them into their queries (the same sum: the others are multiplied by 0). Their number depends
    on the frame (nonzero): traced to ONNX it gives NonZero / Gather / ScatterElements(add) and a
    data-dependent sample count (what `ago export` writes; `--static-sampling` traces the static form,
    compact=False). On the `cpu` and `full` presets with a nuScenes rig 54-55 % of the top plane's
    entries and 27 % of a side plane's are valid; grid_sample's backward is the largest part of a
    training step and GridSample the largest part of the exported encoder."""
    h, L, P, S = attn.heads, attn.levels, attn.pillar, attn.offsets_n
    points = L * P * S
    Q = q.shape[0]
    n = h * points
    W, b = fused_linear(attn.sampling_offsets, attn.attention_weights, h, points)
    o = torch.addmm(b.unsqueeze(1), W, q.t())                                 # (3*n, Q)
    off_x, off_y, logits = o.view(3, n, Q).unbind(0)
    off_x, off_y = off_x.view(h, L, 1, P, S, Q), off_y.view(h, L, 1, P, S, Q)
    w = torch.softmax(logits.view(h, points, Q), 1).view(h, L, 1, P, S, Q)
    if compact:
        # the valid (camera, pillar point, query) entries are selected BEFORE the offsets are broadcast
        # over the k cameras: the sample positions are computed for those entries only (the same
        # arithmetic per entry as the static form below)
        k = geo["weight"].shape[2]
        valid = (geo["weight"] > 0).reshape(-1)                               # over (k, P, Q)
        sel = valid.nonzero().squeeze(1)
        pq = sel % (P * Q)                                                     # its (pillar point, query)

        def per_entry(t: torch.Tensor) -> torch.Tensor:   # (1, L, k|1, P|1, 1, Q|1) geometry -> (1, L, 1, n)
            return t.expand(1, L, k, P, 1, Q).reshape(L, k * P * Q).index_select(1, sel).view(1, L, 1, -1)

        def per_offset(t: torch.Tensor) -> torch.Tensor:  # (h, L, 1, P, S, Q) -> (h, L, S, n)
            return t.squeeze(2).permute(0, 1, 3, 2, 4).reshape(h, L, S, P * Q).index_select(3, pq)

        grid = canvas_coords(per_entry(geo["ref_x"]) + per_offset(off_x), per_entry(geo["ref_y"]) + per_offset(off_y),
                             -0.5, geo["hi_x"].view(1, L, 1, 1), -0.5, geo["hi_y"].view(1, L, 1, 1),
                             per_entry(geo["base_x"]), geo["base_y"].view(1, L, 1, 1), layout)   # (h, L, S, n, 2)
        grid = grid.view(h, L * S, -1, 2)
        w = (per_offset(w) * geo["weight"].reshape(-1).index_select(0, sel)).view(h, L * S, -1)
        part = weighted_samples(canvas, grid, w)                                # (h, D/h, n_valid)
        to_query = (sel % Q).view(1, 1, -1).expand_as(part)   # scatter_add: ONNX ScatterElements(add)
        out = part.new_zeros(h, part.shape[1], Q).scatter_add(2, to_query, part)   # (h, D/h, Q)
    else:
        grid = canvas_coords(geo["ref_x"] + off_x, geo["ref_y"] + off_y, -0.5, geo["hi_x"], -0.5, geo["hi_y"],
                             geo["base_x"], geo["base_y"], layout)             # (h, L, k, P, S, Q, 2)
        w = (w * geo["weight"]).reshape(h, -1, Q)                              # (h, L*k*P*S, Q)
        out = weighted_samples(canvas, grid.reshape(h, -1, Q, 2), w)           # (h, D/h, Q)
    return attn.output_proj(out.reshape(attn.dim, Q).t())


def layer_forward(layer, queries: dict, cam_canvas: torch.Tensor, geo: dict, c: CanvasGeometry,
                  plane_hw: dict, compact: bool = False) -> dict:
    """One TPVLayer (tpv.py) on one frame: queries {plane: (Q_p, D)}, the frame's camera canvas
    (C + 1, Hc, Wc) and geometry -> the layer's output queries."""
    h = layer.heads
    D = queries["xy"].shape[1]
    maps = []
    for s in PLANES:
        rows, cols = plane_hw[s]
        maps.append(layer.plane_value(queries[s]).t().reshape(D, rows, cols))
    planes = plane_canvas(maps, c.plane_layout)
    planes = planes.reshape(h, D // h, planes.shape[1], planes.shape[2])
    conv = layer.image_value      # 1x1 conv; its bias is the weight of the canvas's ones channel
    weight = torch.cat([conv.weight, conv.bias.view(-1, 1, 1, 1)], 1)
    values = F.conv2d(cam_canvas.unsqueeze(0), weight)                         # (1, D, Hc, Wc), frame 0
    values = values.reshape(h, D // h, values.shape[2], values.shape[3])
    out = {}
    for p in PLANES:
        q = queries[p]
        n1, n2, n3 = layer.norms[p]
        q = n1(q + cross_view(layer.cross_view[p], c.cross[p], q, planes, c.plane_layout))
        q = n2(q + image_attention(layer.image_attn[p], q, values, geo[p], c.cam_layout, compact))
        out[p] = n3(q + layer.ffn[p](q))
    return out


def encode_frame(encoder, feats: list[torch.Tensor], ego2img: torch.Tensor, compact: bool | None = None) -> dict:
    """TPVEncoder `encoder` on one frame: FPN maps per level (V, D, H_l, W_l), ego2img (V, 4, 4) ->
    queries {"xy" | "xz" | "yz": (Q_p, D)} after the last layer (C order over the plane's rows, cols).
    compact (`image_attention`): None = whenever no trace is running (ago_export.graphs.ExportTPV
    passes it explicitly)."""
    if compact is None:
        compact = not (torch.jit.is_tracing() or torch.onnx.is_in_onnx_export())
    c = encoder.canvas
    sizes = [tuple(int(s) for s in f.shape[-2:]) for f in feats]
    if sizes != [tuple(s) for s in c.level_sizes]:
        raise ValueError(f"FPN map sizes {sizes} differ from the canvas layout's {c.level_sizes}")
    geo = {p: c.frames[p](ego2img) for p in PLANES}
    canvas = camera_canvas(feats, c.cam_layout)
    queries = {p: encoder.queries[p] for p in PLANES}
    for i, layer in enumerate(encoder.layers):
        if i and encoder.cfg.query_pos:
            queries = {p: queries[p] + encoder.queries[p] for p in PLANES}
        queries = layer_forward(layer, queries, canvas, geo, c, encoder.plane_hw, compact)
    return queries
