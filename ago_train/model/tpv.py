"""The tri-perspective-view (TPV) encoder (after TPVFormer), written to export to ONNX.

Planes (ego frame, x forward, y left, z up), each a grid of learnable queries of width D:
- plane_xy: the top view, (tpv_h, tpv_w) cells along (x, y), tokens in C order over [x, y];
- plane_xz: a side view, (tpv_h, tpv_z) cells along (x, z);
- plane_yz: a side view, (tpv_w, tpv_z) cells along (y, z).
A plane is also viewed as a map (B, D, rows, cols) whose rows/cols are its first/second axis.

Each layer = cross-view hybrid attention -> LayerNorm -> image cross-attention -> LayerNorm ->
FFN -> LayerNorm (post-norm, residual each time).

Image cross-attention: a query owns a pillar of 3-D reference points through its cell along the
plane's missing axis (z for plane_xy, y for plane_xz, x for plane_yz). The points are projected
into the V cameras of the rig with the `ego2img` INPUT (B, V, 4, 4) (ego -> (u*d, v*d, d, 1) for the
resized images), normalised to [-1, 1] (align_corners=False convention: pixel u spans [u, u+1)).
Around each projected point the query predicts `num_sampling_offsets` offsets (in pixels of the
level) and attention weights per head / level; features are read with 4-D `F.grid_sample`
(bilinear, zero padding) from every FPN level of every camera, weighted by a FLOAT validity mask
(depth > eps and inside the image), summed, and divided by the number of cameras that see any
point of the pillar (clamped to >= 1). No nonzero(), no boolean indexing, no data-dependent
shapes: either every camera is sampled densely, or (cameras_per_query < 6) each query keeps its k
most visible cameras by a static-size TopK and samples them from a side-by-side "atlas" of the
camera maps (identical result whenever no more than k cameras see the pillar; a nuScenes rig sees
a vertical pillar with at most 2 cameras and a side pillar with at most 4). (That is this reference
arithmetic; the canvas layout, which training and `ago export` run, samples only the entries whose
validity weight is non-zero, a frame-dependent number: tpv_canvas.image_attention.)

Cross-view hybrid attention: a query samples its own plane at learned offsets around itself and
each other plane at `num_cross_view_points` points along the shared axis (plus learned offsets),
with one softmax over all sampled points per head.

The classes here hold the parameters and compute this arithmetic plainly ("reference" layout, the
oracle); `TPVEncoder` runs it by default in the "canvas" layout of tpv_canvas.py (the same function,
restructured for a CPU, shared with `ago export`); `ModelConfig.tpv_layout` picks.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ago_runtime.geometry.grid import Grid

from .tpv_canvas import PLANES, CanvasGeometry, encode_frame

if TYPE_CHECKING:   # annotations only: ModelConfig.build() imports this module
    from .config import ModelConfig


# --------------------------------------------------------------------------- geometry (numpy, constant)
class TPVGeometry:
    """Constant reference points of the three planes for one grid and TPV size.

    All arrays are float32. `norm(v, axis)` maps ego metres to [-1, 1] over the grid range.
    """

    def __init__(self, grid: Grid, tpv_shape: tuple[int, int, int], pillar_top: int, pillar_side: int,
                 cross_points: int, self_points: int):
        self.grid, self.shape = grid, tpv_shape
        lo, hi = np.asarray(grid.range_min, np.float64), np.asarray(grid.range_max, np.float64)
        self.lo, self.hi = lo, hi
        # cell centres of the TPV along each axis and evenly spaced samples along each axis
        self.centres = [lo[a] + (hi[a] - lo[a]) * (np.arange(n) + 0.5) / n for a, n in enumerate(tpv_shape)]
        even = lambda a, n: lo[a] + (hi[a] - lo[a]) * (np.arange(n) + 0.5) / n  # noqa: E731
        X, Y, Z = tpv_shape
        cx, cy, cz = self.centres

        # --- pillars (Q, P, 3) ego points for image cross-attention
        def pillar(first, second, axes, along, n):
            a, b = np.meshgrid(first, second, indexing="ij")
            pts = np.zeros((a.size, n, 3))
            pts[:, :, axes[0]] = a.reshape(-1, 1)
            pts[:, :, axes[1]] = b.reshape(-1, 1)
            pts[:, :, along] = even(along, n)[None, :]
            return pts.astype(np.float32)

        self.pillars = {
            "xy": pillar(cx, cy, (0, 1), 2, pillar_top),
            "xz": pillar(cx, cz, (0, 2), 1, pillar_side),
            "yz": pillar(cy, cz, (1, 2), 0, pillar_side),
        }
        # --- cross-view references: for query plane p and source plane s, (Q_p, K_s, 2) grid_sample
        # points (col_norm, row_norm) in the source plane's map.
        n = [self.norm(c, a) for a, c in enumerate(self.centres)]        # query cell centres, normalised
        e = [self.norm(even(a, cross_points), a) for a in range(3)]      # samples along an axis, normalised
        axes = {"xy": (0, 1), "xz": (0, 2), "yz": (1, 2)}
        self.cross_refs: dict[str, list[np.ndarray]] = {}
        for p in PLANES:
            pa, pb = axes[p]
            qa, qb = np.meshgrid(n[pa], n[pb], indexing="ij")
            qa, qb = qa.reshape(-1), qb.reshape(-1)          # query's own normalised coords on its axes
            coords = {pa: qa, pb: qb}
            refs = []
            for s in PLANES:
                sa, sb = axes[s]
                if s == p:
                    row = np.repeat(qa[:, None], self_points, 1)
                    col = np.repeat(qb[:, None], self_points, 1)
                else:
                    # the shared axis comes from the query, the other axis is sampled evenly
                    def axis_vals(ax):
                        if ax in coords:
                            return np.repeat(coords[ax][:, None], cross_points, 1)
                        return np.repeat(e[ax][None, :], qa.size, 0)
                    row, col = axis_vals(sa), axis_vals(sb)
                refs.append(np.stack([col, row], -1).astype(np.float32))
            self.cross_refs[p] = refs

    def norm(self, v, axis: int) -> np.ndarray:
        return 2.0 * (np.asarray(v, np.float64) - self.lo[axis]) / (self.hi[axis] - self.lo[axis]) - 1.0

    def plane_hw(self, p: str) -> tuple[int, int]:
        X, Y, Z = self.shape
        return {"xy": (X, Y), "xz": (X, Z), "yz": (Y, Z)}[p]


def project_to_cameras(points: torch.Tensor, ego2img: torch.Tensor, width: int, height: int, eps: float = 1e-2):
    """Ego points (Q, P, 3) and ego2img (B, V, 4, 4) ->
    normalised image coords (B, V, Q, P, 2) in [-1, 1] (clamped to [-2, 2]) and a float mask (B, V, Q, P)
    that is 1 where the point is in front of the camera (depth > eps) and inside the image."""
    Q, P, _ = points.shape
    hom = torch.cat([points, torch.ones_like(points[..., :1])], -1).reshape(Q * P, 4)
    cam = torch.matmul(hom, ego2img.transpose(-1, -2))              # (B, V, Q*P, 4): (u*d, v*d, d, 1)
    depth = cam[..., 2]
    safe = torch.clamp(depth, min=eps)
    un = cam[..., 0] / safe / width * 2.0 - 1.0
    vn = cam[..., 1] / safe / height * 2.0 - 1.0
    mask = (depth > eps) & (un >= -1.0) & (un <= 1.0) & (vn >= -1.0) & (vn <= 1.0)
    uv = torch.stack([un.clamp(-2.0, 2.0), vn.clamp(-2.0, 2.0)], -1)
    B, V = ego2img.shape[:2]
    return uv.reshape(B, V, Q, P, 2), mask.to(points.dtype).reshape(B, V, Q, P)


def _ring_bias(heads: int, groups: int, points: int, first_radius: float = 1.0) -> torch.Tensor:
    """Initial sampling offsets (heads, groups, points, 2): one direction per head, radius
    first_radius, first_radius + 1, ... per point."""
    ang = torch.arange(heads, dtype=torch.float32) * (2 * math.pi / heads)
    d = torch.stack([ang.cos(), ang.sin()], -1)                       # (heads, 2)
    r = torch.arange(points, dtype=torch.float32) + first_radius      # (points,)
    return (d[:, None, None, :] * r[None, None, :, None]).expand(heads, groups, points, 2).clone()


# --------------------------------------------------------------------------- image cross-attention
class ImageCrossAttention(nn.Module):
    """Queries (B, Q, D) read the per-camera FPN maps around their projected pillar points.

    Two equivalent ways to read the cameras (same parameters, same result where a query's pillar is
    seen by at most `k` cameras):
    - dense (`forward`): every camera, one grid_sample per level over the (B*V*heads) maps;
    - top-k atlas (`forward_atlas`): the six maps of a level sit side by side in one wide "atlas"
      (each camera padded by one zero column on both sides) and every query samples only its k most
      visible cameras. Horizontal sample positions are clamped into the camera's padded strip, which
      reproduces zero padding exactly, so nothing bleeds between cameras.
    """

    def __init__(self, dim: int, heads: int, levels: int, pillar: int, offsets: int):
        super().__init__()
        self.dim, self.heads, self.levels, self.pillar, self.offsets_n = dim, heads, levels, pillar, offsets
        self.sampling_offsets = nn.Linear(dim, heads * levels * pillar * offsets * 2)
        self.attention_weights = nn.Linear(dim, heads * levels * pillar * offsets)
        self.output_proj = nn.Linear(dim, dim)
        nn.init.zeros_(self.sampling_offsets.weight)
        with torch.no_grad():
            ring = _ring_bias(heads, levels * pillar, offsets, first_radius=0.0)  # first offset on the point
            self.sampling_offsets.bias.copy_(ring.reshape(-1))
        nn.init.zeros_(self.attention_weights.weight)
        nn.init.zeros_(self.attention_weights.bias)

    def _offsets_and_weights(self, query):
        B, Q, _ = query.shape
        h, L, P, S = self.heads, self.levels, self.pillar, self.offsets_n
        off = self.sampling_offsets(query).view(B, Q, h, L, P, S, 2)
        w = self.attention_weights(query).view(B, Q, h, L * P * S).softmax(-1).view(B, 1, Q, h, L, P, S)
        return off, w

    def forward(self, query, values, ref_uv, mask, count):
        """Dense. query (B, Q, D); values: per level (B*V*heads, D/heads, H_l, W_l); ref_uv (B, V, Q, P, 2);
        mask (B, V, Q, P) float; count (B, Q) float -> (B, Q, D)."""
        B, Q, D = query.shape
        V = ref_uv.shape[1]
        h, P, S = self.heads, self.pillar, self.offsets_n
        off, w = self._offsets_and_weights(query)
        w = w * mask.view(B, V, Q, 1, 1, P, 1)                            # (B, V, Q, h, L, P, S)
        out = None
        for l, v in enumerate(values):
            Hl, Wl = int(v.shape[-2]), int(v.shape[-1])
            scale = off.new_tensor([2.0 / Wl, 2.0 / Hl])
            loc = ref_uv.view(B, V, Q, 1, P, 1, 2) + (off[:, :, :, l] * scale).view(B, 1, Q, h, P, S, 2)
            loc = loc.permute(0, 1, 3, 2, 4, 5, 6).reshape(B * V * h, Q, P * S, 2)
            sampled = F.grid_sample(v, loc, mode="bilinear", padding_mode="zeros", align_corners=False)
            wl = w[:, :, :, :, l].permute(0, 1, 3, 2, 4, 5).reshape(B * V * h, 1, Q, P * S)
            part = (sampled * wl).sum(-1)                                   # (B*V*h, D/h, Q)
            out = part if out is None else out + part
        out = out.view(B, V, D, Q).sum(1) / count.clamp(min=1.0).view(B, 1, Q)
        return self.output_proj(out.transpose(1, 2))

    def forward_atlas(self, query, atlases, level_sizes, ref_uv, mask, cam, count, num_cameras: int):
        """Top-k. atlases: per level (B*heads, D/heads, H_l, V*(W_l+2)); level_sizes: per level (H_l, W_l);
        ref_uv (B, k, Q, P, 2), mask (B, k, Q, P) and cam (B, k, Q) float camera ids of the k chosen
        cameras; count (B, Q) -> (B, Q, D)."""
        B, Q, D = query.shape
        k = ref_uv.shape[1]
        h, P, S, V = self.heads, self.pillar, self.offsets_n, num_cameras
        off, w = self._offsets_and_weights(query)
        w = w * mask.view(B, k, Q, 1, 1, P, 1)                            # (B, k, Q, h, L, P, S)
        out = None
        for l, (atlas, (Hl, Wl)) in enumerate(zip(atlases, level_sizes)):
            scale = off.new_tensor([2.0 / Wl, 2.0 / Hl])
            loc = ref_uv.view(B, k, Q, 1, P, 1, 2) + (off[:, :, :, l] * scale).view(B, 1, Q, h, P, S, 2)
            px = ((loc[..., 0] + 1.0) * (Wl / 2.0)).clamp(-0.5, Wl + 0.5)   # pixels in the camera's map
            ax = (cam.view(B, k, Q, 1, 1, 1) * (Wl + 2) + 1.0 + px) * (2.0 / (V * (Wl + 2))) - 1.0
            loc = torch.stack([ax, loc[..., 1]], -1)                         # (B, k, Q, h, P, S, 2)
            loc = loc.permute(0, 3, 2, 1, 4, 5, 6).reshape(B * h, Q, k * P * S, 2)
            sampled = F.grid_sample(atlas, loc, mode="bilinear", padding_mode="zeros", align_corners=False)
            wl = w[:, :, :, :, l].permute(0, 3, 2, 1, 4, 5).reshape(B * h, 1, Q, k * P * S)
            part = (sampled * wl).sum(-1)                                   # (B*h, D/h, Q)
            out = part if out is None else out + part
        out = out.view(B, D, Q) / count.clamp(min=1.0).view(B, 1, Q)
        return self.output_proj(out.transpose(1, 2))


def camera_atlas(v: torch.Tensor, batch: int, heads: int) -> torch.Tensor:
    """(B*V, D, H, W) per-camera maps -> (B*heads, D/heads, H, V*(W+2)): side by side, each camera
    framed by one zero column left and right."""
    BV, D, H, W = v.shape
    V = BV // batch
    v = F.pad(v, (1, 1)).view(batch, V, D, H, W + 2).permute(0, 2, 3, 1, 4)
    return v.reshape(batch * heads, D // heads, H, V * (W + 2))


def select_cameras(uv: torch.Tensor, mask: torch.Tensor, k: int):
    """Keep each query's k most visible cameras: uv (B, V, Q, P, 2), mask (B, V, Q, P) ->
    uv (B, k, Q, P, 2), mask (B, k, Q, P), cam (B, k, Q) float camera ids. Static shapes (TopK)."""
    B, V, Q, P = mask.shape
    score = mask.amax(-1) + mask.mean(-1) * 0.5                           # seen at all, then how much
    idx = torch.topk(score, k, dim=1).indices                             # (B, k, Q)
    m = torch.gather(mask, 1, idx.unsqueeze(-1).expand(B, k, Q, P))
    u = torch.gather(uv, 1, idx.view(B, k, Q, 1, 1).expand(B, k, Q, P, 2))
    return u, m, idx.to(uv.dtype)


# --------------------------------------------------------------------------- cross-view hybrid attention
class CrossViewHybridAttention(nn.Module):
    """Queries of one plane (B, Q, D) read all three planes at reference points + learned offsets."""

    def __init__(self, dim: int, heads: int, points: tuple[int, int, int]):
        super().__init__()
        self.dim, self.heads, self.points = dim, heads, tuple(points)
        total = sum(points)
        self.sampling_offsets = nn.Linear(dim, heads * total * 2)
        self.attention_weights = nn.Linear(dim, heads * total)
        self.output_proj = nn.Linear(dim, dim)
        nn.init.zeros_(self.sampling_offsets.weight)
        with torch.no_grad():
            bias = torch.cat([_ring_bias(heads, 1, k)[:, 0] * 0.5 for k in points], 1)  # (heads, total, 2)
            self.sampling_offsets.bias.copy_(bias.reshape(-1))
        nn.init.zeros_(self.attention_weights.weight)
        nn.init.zeros_(self.attention_weights.bias)

    def forward(self, query, maps, refs):
        """query (B, Q, D); maps: 3 x (B*heads, D/heads, rows, cols); refs: 3 x (Q, K_s, 2) -> (B, Q, D)."""
        B, Q, D = query.shape
        h, total = self.heads, sum(self.points)
        off = self.sampling_offsets(query).view(B, Q, h, total, 2)
        w = self.attention_weights(query).view(B, Q, h, total).softmax(-1)
        out, start = None, 0
        for m, ref, k in zip(maps, refs, self.points):
            rows, cols = int(m.shape[-2]), int(m.shape[-1])
            scale = off.new_tensor([2.0 / cols, 2.0 / rows])
            loc = ref.view(1, Q, 1, k, 2) + off[:, :, :, start:start + k] * scale    # (B, Q, h, k, 2)
            loc = loc.permute(0, 2, 1, 3, 4).reshape(B * h, Q, k, 2)
            sampled = F.grid_sample(m, loc, mode="bilinear", padding_mode="zeros", align_corners=False)
            wk = w[:, :, :, start:start + k].permute(0, 2, 1, 3).reshape(B * h, 1, Q, k)
            part = (sampled * wk).sum(-1)                                             # (B*h, D/h, Q)
            out = part if out is None else out + part
            start += k
        return self.output_proj(out.view(B, D, Q).transpose(1, 2))


class TPVLayer(nn.Module):
    def __init__(self, cfg: ModelConfig, levels: int):
        super().__init__()
        D, h = cfg.tpv_dim, cfg.num_heads
        self.heads = h
        pillars = {"xy": cfg.num_points_in_pillar, "xz": cfg.num_points_in_pillar_side,
                   "yz": cfg.num_points_in_pillar_side}
        self.plane_value = nn.Linear(D, D)                    # shared value projection of the planes
        self.image_value = nn.Conv2d(D, D, 1)                 # shared value projection of the FPN maps
        self.cross_view = nn.ModuleDict()
        self.image_attn = nn.ModuleDict()
        self.ffn = nn.ModuleDict()
        self.norms = nn.ModuleDict()
        for p in PLANES:
            pts = tuple(cfg.num_self_points if s == p else cfg.num_cross_view_points for s in PLANES)
            self.cross_view[p] = CrossViewHybridAttention(D, h, pts)
            self.image_attn[p] = ImageCrossAttention(D, h, levels, pillars[p], cfg.num_sampling_offsets)
            self.ffn[p] = nn.Sequential(nn.Linear(D, cfg.ffn_dim), nn.GELU(), nn.Linear(cfg.ffn_dim, D))
            self.norms[p] = nn.ModuleList(nn.LayerNorm(D) for _ in range(3))

    def forward(self, queries: dict, plane_hw: dict, feats: list, cams: dict, cross_refs: dict) -> dict:
        B = queries["xy"].shape[0]
        h = self.heads
        D = queries["xy"].shape[-1]
        maps = []
        for s in PLANES:
            rows, cols = plane_hw[s]
            v = self.plane_value(queries[s])                       # (B, rows*cols, D)
            maps.append(v.transpose(1, 2).reshape(B * h, D // h, rows, cols))
        projected = [self.image_value(f) for f in feats]           # (B*V, D, H_l, W_l)
        need_dense = any(c[0] == "dense" for c in cams.values())
        need_atlas = any(c[0] == "atlas" for c in cams.values())
        values = [v.reshape(v.shape[0] * h, D // h, v.shape[-2], v.shape[-1]) for v in projected] \
            if need_dense else []
        atlases = [camera_atlas(v, B, h) for v in projected] if need_atlas else []
        sizes = [(int(v.shape[-2]), int(v.shape[-1])) for v in projected]
        V = projected[0].shape[0] // B
        out = {}
        for p in PLANES:
            q = queries[p]
            n1, n2, n3 = self.norms[p]
            q = n1(q + self.cross_view[p](q, maps, cross_refs[p]))
            mode, uv, mask, cam, count = cams[p]
            if mode == "dense":
                read = self.image_attn[p](q, values, uv, mask, count)
            else:
                read = self.image_attn[p].forward_atlas(q, atlases, sizes, uv, mask, cam, count, V)
            q = n2(q + read)
            q = n3(q + self.ffn[p](q))
            out[p] = q
        return out


class TPVEncoder(nn.Module):
    """FPN maps of the V cameras + ego2img -> three TPV planes as maps (B, D, rows, cols)."""

    def __init__(self, cfg: ModelConfig, levels: int = 3):
        super().__init__()
        self.cfg = cfg
        geo = TPVGeometry(cfg.grid_obj(), cfg.tpv_shape(), cfg.num_points_in_pillar, cfg.num_points_in_pillar_side,
                          cfg.num_cross_view_points, cfg.num_self_points)
        self.geometry = geo
        self.plane_hw = {p: geo.plane_hw(p) for p in PLANES}
        D = cfg.tpv_dim
        self.queries = nn.ParameterDict({
            p: nn.Parameter(torch.randn(r * c, D) * 0.1) for p, (r, c) in self.plane_hw.items()
        })
        for p in PLANES:  # constant geometry, derived from the config (not saved in checkpoints)
            self.register_buffer(f"pillar_{p}", torch.from_numpy(geo.pillars[p]), persistent=False)
            for s, ref in zip(PLANES, geo.cross_refs[p]):
                self.register_buffer(f"cross_{p}_from_{s}", torch.from_numpy(ref), persistent=False)
        self.layers = nn.ModuleList(TPVLayer(cfg, levels) for _ in range(cfg.num_layers))
        self.cameras_per_query = {"xy": cfg.cameras_per_query, "xz": cfg.cameras_per_query_side,
                                  "yz": cfg.cameras_per_query_side}
        points = {p: self.layers[0].cross_view[p].points for p in PLANES}   # samples per source plane
        # constant buffers of the canvas layout (tpv_canvas.py; used by the export whatever the layout)
        self.canvas = CanvasGeometry(geo, self.plane_hw, self.cameras_per_query, points, cfg.num_cameras,
                                     cfg.image_width, cfg.image_height)

    def forward(self, feats: list[torch.Tensor], ego2img: torch.Tensor) -> dict[str, torch.Tensor]:
        """feats: per level (B*V, D, H_l, W_l); ego2img (B, V, 4, 4) -> {"xy"|"xz"|"yz": (B, D, rows, cols)}.
        `cfg.tpv_layout` picks the arithmetic: "canvas" (tpv_canvas.py, frame by frame) or "reference"."""
        if self.cfg.tpv_layout == "canvas":
            return self.forward_canvas(feats, ego2img)
        return self.forward_reference(feats, ego2img)

    def forward_canvas(self, feats: list[torch.Tensor], ego2img: torch.Tensor,
                       compact: bool | None = None) -> dict[str, torch.Tensor]:
        """Frame by frame through tpv_canvas.encode_frame (compact: see there; None = unless tracing)."""
        B, V = ego2img.shape[:2]
        frames = [encode_frame(self, [f.view(B, V, *f.shape[1:])[b] for f in feats], ego2img[b], compact)
                  for b in range(B)]
        out = {}
        for p in PLANES:
            rows, cols = self.plane_hw[p]
            out[p] = torch.stack([q[p] for q in frames]).transpose(1, 2).reshape(B, -1, rows, cols)
        return out

    def forward_reference(self, feats: list[torch.Tensor], ego2img: torch.Tensor) -> dict[str, torch.Tensor]:
        B = ego2img.shape[0]
        cams = {}
        for p in PLANES:
            uv, mask = project_to_cameras(getattr(self, f"pillar_{p}"), ego2img,
                                          self.cfg.image_width, self.cfg.image_height)
            count = mask.amax(-1).sum(1)                                # (B, Q): cameras seeing the pillar
            k = self.cameras_per_query[p]
            if k >= mask.shape[1]:
                cams[p] = ("dense", uv, mask, None, count)
            else:
                cams[p] = ("atlas", *select_cameras(uv, mask, k), count)
        cross_refs = {p: [getattr(self, f"cross_{p}_from_{s}") for s in PLANES] for p in PLANES}
        queries = {p: self.queries[p].unsqueeze(0).expand(B, -1, -1) for p in PLANES}
        for i, layer in enumerate(self.layers):
            if i and self.cfg.query_pos:
                queries = {p: queries[p] + self.queries[p].unsqueeze(0) for p in PLANES}
            queries = layer(queries, self.plane_hw, feats, cams, cross_refs)
        out = {}
        for p in PLANES:
            rows, cols = self.plane_hw[p]
            out[p] = queries[p].transpose(1, 2).reshape(B, -1, rows, cols)
        return out
