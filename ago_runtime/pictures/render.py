"""Pictures of occupancy grids and camera rigs (numpy + opencv). Every image here is RGB uint8.

What it takes and gives:
- `bev_image(semantics)`: (X, Y, Z) labels -> top-down (H, W, 3) picture. Orientation: ego x
  (forward) points UP in the image and ego y (left) points LEFT, i.e. the picture is what you see
  looking down from above with the car driving up the page. Array row 0 is the largest x, column 0
  the largest y. The ego (x = y = 0 m of the grid) is marked by a small black-and-white triangle
  pointing forward.
- `voxel_view(semantics)`: an orthographic 3-D view from behind-right and above (per-pixel
  z-buffer of cube sprites, exact depth per pixel), occupied voxels only, top faces lighter
  than sides.
- `scalar_bev(volume)`: a float volume (entropy, confidence) reduced over z, colour-mapped, with a
  colour bar.
- `rig_mosaic(images)`: a rig's camera images in rows with names (nuScenes' six: the 2 x 3 layout).
- `side_by_side`, `legend`, `prediction_vs_gt`: panels assembled into one figure.
- `save_png(path, rgb)`: written atomically (cv2 wants BGR; converted here).

Label spaces: class names and colours default to Occ3D (17 classes + free = 17); any other label
space works by passing `class_names`, `free_index` and `colors` (`palette_for(names)` gives Occ3D
colours for Occ3D names and distinct deterministic colours for the rest). Label 255 is unknown
and never drawn as a class.
"""

from __future__ import annotations

import colorsys
from pathlib import Path
from typing import Mapping, Sequence

import cv2
import numpy as np

from ago_runtime.atomic import atomic_path
from ago_runtime.classes import FREE, IGNORE, OCC3D_CLASSES, OCC3D_COLORS, ClassTable
from ago_runtime.geometry.grid import Grid

FREE_GREY = (250, 250, 250)      # BEV columns seen free (near-white)
UNKNOWN_GREY = (70, 70, 70)      # BEV columns with nothing known (all 255 / outside the mask)
OUTSIDE_GREY = (215, 215, 215)   # BEV free columns not seen by any camera (mask given, mask_mode="dim")
BACKGROUND = (255, 255, 255)
TEXT = (20, 20, 20)
FONT = cv2.FONT_HERSHEY_SIMPLEX
# PNG: deflate level 1 with the "up" row filter only: the same pixels, faster to encode and smaller than with
# OpenCV's default filter choice on `ago infer`'s pictures (benchmarks/results/infer_speed.md)
PNG_OPTIONS = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_UP]

# Where nuScenes' six cameras go in `rig_mosaic` (rows top to bottom, columns left to right).
RIG_LAYOUT = (("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT"),
              ("CAM_BACK_LEFT", "CAM_BACK", "CAM_BACK_RIGHT"))
MOSAIC_COLUMNS = 3


def mosaic_layout(names) -> tuple[tuple[str, ...], ...]:
    """Rows of camera names for a picture of a rig: nuScenes' six as RIG_LAYOUT (front row, back row); any
    other rig in its own order, MOSAIC_COLUMNS to a row."""
    names = list(names)
    if sorted(names) == sorted(c for row in RIG_LAYOUT for c in row):
        return RIG_LAYOUT
    return tuple(tuple(names[i:i + MOSAIC_COLUMNS]) for i in range(0, len(names), MOSAIC_COLUMNS))


# ---------------------------------------------------------------------------------------- colours
def palette_for(class_names: Sequence[str]) -> np.ndarray:
    """(len(names), 3) uint8 RGB: the Occ3D colour for an Occ3D name, otherwise a distinct colour.

    Non-Occ3D names get hues stepped by the golden ratio in list order (deterministic: the same
    list always gives the same colours), saturated and bright enough to tell apart from greys.
    """
    known = {n: OCC3D_COLORS[i] for i, n in enumerate(OCC3D_CLASSES)}
    out = np.zeros((len(class_names), 3), dtype=np.uint8)
    step = 0
    for i, name in enumerate(class_names):
        if name in known:
            out[i] = known[name]
            continue
        h = (0.07 + 0.61803398875 * step) % 1.0
        s = 0.75 if step % 2 == 0 else 0.55
        v = 0.95 if (step // 2) % 2 == 0 else 0.75
        out[i] = np.round(np.array(colorsys.hsv_to_rgb(h, s, v)) * 255).astype(np.uint8)
        step += 1
    return out


def _colors_or_default(colors, n_labels: int) -> np.ndarray:
    c = OCC3D_COLORS if colors is None else np.asarray(colors, dtype=np.uint8).reshape(-1, 3)
    if len(c) < n_labels:
        raise ValueError(f"need a colour for each of {n_labels} labels, got {len(c)}")
    return c


def _lut(colors: np.ndarray) -> np.ndarray:
    """(256, 3) float32 lookup: labels beyond the palette (255 included) map to grey."""
    lut = np.full((256, 3), 128, dtype=np.float32)
    lut[: min(len(colors), 256)] = colors[:256]
    return lut


def _check_volume(v: np.ndarray, what: str = "semantics") -> np.ndarray:
    v = np.asarray(v)
    if v.ndim != 3:
        raise ValueError(f"{what} must be an (X, Y, Z) volume, got shape {v.shape}")
    return v


# ---------------------------------------------------------------------------------------- BEV
def _ego_pixel(shape: tuple[int, int, int], grid: Grid | None, scale: int) -> tuple[float, float] | None:
    """(column, row) in the BEV picture of the ego origin, or None if it lies outside the grid."""
    grid = grid or Grid.with_shape(shape)
    X, Y = shape[0], shape[1]
    fx = (0.0 - grid.range_min[0]) / grid.voxel_size[0]  # x = 0 in voxel units
    fy = (0.0 - grid.range_min[1]) / grid.voxel_size[1]
    if not (0 <= fx <= X and 0 <= fy <= Y):
        return None
    return (Y - fy) * scale, (X - fx) * scale


def _draw_ego(img: np.ndarray, at: tuple[float, float] | None, size: int) -> None:
    """A triangle pointing up (ego forward), white with a black outline."""
    if at is None:
        return
    cx, cy = at
    s = max(size, 4)
    pts = np.array([[cx, cy - 1.3 * s], [cx - 0.8 * s, cy + 0.8 * s], [cx + 0.8 * s, cy + 0.8 * s]])
    pts = np.round(pts).astype(np.int32)
    cv2.fillConvexPoly(img, pts, (255, 255, 255), lineType=cv2.LINE_AA)
    cv2.polylines(img, [pts], True, (0, 0, 0), max(1, s // 4), lineType=cv2.LINE_AA)


def _wash(rgb: np.ndarray) -> np.ndarray:
    """Pale version of colours (float, last axis RGB) for voxels outside the mask: hue kept, mostly grey."""
    return 0.35 * rgb + 0.65 * 205.0


def _to_bev_orientation(a: np.ndarray) -> np.ndarray:
    """Array indexed [x, y, ...] -> picture rows/columns: x up, y left (a 180-degree turn)."""
    return a[::-1, ::-1]


def _table_style(table: ClassTable | None, colors, free_index: int):
    """(colors, free_index) of a class table (labels as its file ids), or the ones given when table is None."""
    if table is None:
        return colors, free_index
    return table.palette_by_id(), table.free_id


def bev_image(semantics: np.ndarray, colors: np.ndarray | None = None, free_index: int = FREE,
              scale: int = 3, mask: np.ndarray | None = None, grid: Grid | None = None,
              mark_ego: bool = True, height_shading: float = 0.35, mask_mode: str = "dim",
              table: ClassTable | None = None) -> np.ndarray:
    """Top-down picture: each (x, y) column shows the class of its highest non-free, non-255 voxel.

    semantics: (X, Y, Z) integer labels. Returns (X*scale, Y*scale, 3) uint8 RGB, x up, y left.
    The colour is darkened by up to `height_shading` for the lowest voxels (higher = brighter).
    Columns with no occupied voxel: near-white if some voxel is free, dark grey if all are unknown.
    `mask` (bool/0-1, same shape; e.g. mask_camera), two modes:
      "dim"  (default): columns whose top voxel lies outside the mask are washed out towards grey,
             free columns with no voxel inside the mask are light grey;
      "hide": voxels outside the mask count as unknown: the picture shows exactly what the metric scores.
    `grid` only places the ego marker (default: the Occ3D range cut into this shape).
    `table` (a ClassTable; labels are its file ids, e.g. Occ3D-Waymo's free = 23) sets the colours and
    the free id instead of `colors` / `free_index`.
    """
    sem = _check_volume(semantics)
    X, Y, Z = sem.shape
    colors, free_index = _table_style(table, colors, free_index)
    colors = _colors_or_default(colors, free_index + 1)
    if mask_mode not in ("dim", "hide"):
        raise ValueError(f"mask_mode must be 'dim' or 'hide', got {mask_mode!r}")
    known = sem != IGNORE
    inside = None if mask is None else np.asarray(mask).astype(bool)
    if inside is not None and mask_mode == "hide":
        known &= inside
    occupied = known & (sem != free_index)
    has_occ = occupied.any(axis=2)
    # index of the highest occupied voxel per column (argmax over reversed z finds the last True)
    top = Z - 1 - np.argmax(occupied[:, :, ::-1], axis=2)
    top_label = np.take_along_axis(sem, top[:, :, None], axis=2)[:, :, 0]
    shade = 1.0 - height_shading * (1.0 - top / max(Z - 1, 1))
    rgb = _lut(colors)[top_label] * shade[:, :, None]
    has_free = (known & (sem == free_index)).any(axis=2)
    rgb[~has_occ & has_free] = FREE_GREY
    if inside is not None and mask_mode == "dim":
        top_inside = np.take_along_axis(inside, top[:, :, None], axis=2)[:, :, 0]
        rgb = np.where((has_occ & ~top_inside)[:, :, None], _wash(rgb), rgb)
        rgb[~has_occ & has_free & ~inside.any(axis=2)] = OUTSIDE_GREY
    rgb[~has_occ & ~has_free] = UNKNOWN_GREY
    img = np.clip(np.round(_to_bev_orientation(rgb)), 0, 255).astype(np.uint8)
    if scale != 1:
        img = cv2.resize(img, (Y * scale, X * scale), interpolation=cv2.INTER_NEAREST)
    img = np.ascontiguousarray(img)
    if mark_ego:
        _draw_ego(img, _ego_pixel(sem.shape, grid, scale), size=max(3, int(round(2.5 * scale))))
    return img


# ---------------------------------------------------------------------------------------- 3-D view
# Screen offsets (u right, v down, pixels at scale 1) of one voxel step along ego x, y, z. Integer
# offsets make every voxel the same sprite, so the render is a vectorised z-buffer splat.
VIEW_BASIS = ((2, -1), (-2, -1), (0, -2))   # x -> up-right, y -> up-left, z -> up (2:1 isometric)

_FACES = {  # outward normal -> corners of the face of a unit cube at the origin
    (0, 0, 1): ((0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)),
    (0, 0, -1): ((0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)),
    (1, 0, 0): ((1, 0, 0), (1, 1, 0), (1, 1, 1), (1, 0, 1)),
    (-1, 0, 0): ((0, 0, 0), (0, 1, 0), (0, 1, 1), (0, 0, 1)),
    (0, 1, 0): ((0, 1, 0), (1, 1, 0), (1, 1, 1), (0, 1, 1)),
    (0, -1, 0): ((0, 0, 0), (1, 0, 0), (1, 0, 1), (0, 0, 1)),
}


def _sprite(basis: np.ndarray):
    """Pixels of one projected unit cube: (offsets (P, 2) int, depth offset (P,), face shade (P,), edge (P,)).

    `basis` (3, 2) int: screen offsets of unit steps in x, y, z. The view direction is the 3-D
    direction that projects to no screen motion; faces whose normal points at the viewer are drawn.
    Depth is measured along the view direction from the cube's lower corner (bigger = farther).
    """
    p = basis.T.astype(np.float64)                       # (2, 3): 3-D step -> screen
    view = np.cross(p[0], p[1])                          # null space of p
    view /= np.linalg.norm(view)
    if view[2] > 0:                                      # look down: away from viewer = -z side
        view = -view
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.float64)
    scr = corners @ p.T
    lo = np.floor(scr.min(axis=0)).astype(int) - 1
    hi = np.ceil(scr.max(axis=0)).astype(int) + 2
    w, h = hi - lo
    face_id = np.full((h, w), -1, dtype=np.int32)
    edge = np.zeros((h, w), dtype=np.uint8)
    faces = []
    for normal, quad in _FACES.items():
        if np.dot(normal, view) >= 0:                   # facing away from the viewer
            continue
        q = np.array(quad, dtype=np.float64)
        poly = np.round(q @ p.T - lo).astype(np.int32)
        cv2.fillConvexPoly(face_id, poly, len(faces))
        cv2.polylines(edge, [poly], True, 1, 1)
        faces.append((np.array(normal), q[0], q[1] - q[0], q[3] - q[0]))
    vs, us = np.nonzero(face_id >= 0)
    fid = face_id[vs, us]
    depth = np.zeros(len(us))
    shade = np.zeros(len(us))
    for f, (normal, c0, e1, e2) in enumerate(faces):
        sel = fid == f
        # 3-D point on the face under each pixel: c0 + a e1 + b e2 with p @ point = pixel
        m = np.stack([p @ e1, p @ e2], axis=1)
        rhs = np.stack([us[sel] + lo[0], vs[sel] + lo[1]], axis=0) - (p @ c0)[:, None]
        ab = np.linalg.solve(m, rhs)
        pts = c0[None] + ab[0][:, None] * e1[None] + ab[1][:, None] * e2[None]
        depth[sel] = pts @ view
        shade[sel] = 1.0 if normal[2] > 0 else (0.78 if normal[0] != 0 else 0.62)
    offsets = np.stack([us + lo[0], vs + lo[1]], axis=1)
    return offsets, depth, shade, edge[vs, us].astype(bool)


def voxel_view(semantics: np.ndarray, colors: np.ndarray | None = None, free_index: int = FREE,
               scale: int = 2, mask: np.ndarray | None = None, basis=VIEW_BASIS,
               crop: bool = True, edges: bool = True, height_shading: float = 0.25,
               grid: Grid | None = None, mark_ego: bool = True, table: ClassTable | None = None) -> np.ndarray:
    """Orthographic 3-D picture of the occupied voxels (label not free, not 255), RGB uint8.

    Viewed from behind-right and above: ego x goes up-right, y up-left, z up. Top faces are
    full colour, the x-facing sides darker, the y-facing sides darker still; cube edges are
    slightly darkened when `edges`. `mask` (e.g. mask_camera): voxels outside it are drawn
    in a pale, washed-out version of their class colour. A 200 x 200 x 16 grid takes well under a second.
    `table`: as in `bev_image`.
    """
    sem = _check_volume(semantics)
    X, Y, Z = sem.shape
    colors, free_index = _table_style(table, colors, free_index)
    colors = _colors_or_default(colors, free_index + 1)
    basis = np.asarray(basis, dtype=np.int64) * int(scale)
    occ = (sem != free_index) & (sem != IGNORE)
    offsets, d_off, f_shade, f_edge = _sprite(basis)
    p = basis.T.astype(np.float64)
    view = np.cross(p[0], p[1])
    view /= np.linalg.norm(view)
    if view[2] > 0:
        view = -view

    # Cull voxels whose visible faces are all covered by occupied neighbours (exact for cubes).
    visible = np.zeros_like(occ)
    padded = np.pad(occ, 1, constant_values=False)
    for axis in range(3):
        step = -int(np.sign(view[axis]))  # neighbour on the viewer's side along this axis
        if step == 0:
            continue
        sl = [slice(1, -1)] * 3
        sl[axis] = slice(1 + step, padded.shape[axis] - 1 + step)
        visible |= ~padded[tuple(sl)]
    ii, jj, kk = np.nonzero(occ & visible)

    # canvas: projections of the whole grid's corners
    gc = np.array([[a, b, c] for a in (0, X) for b in (0, Y) for c in (0, Z)], dtype=np.float64) @ p.T
    lo = np.floor(gc.min(axis=0)).astype(int) + offsets.min(axis=0) - 2
    hi = np.ceil(gc.max(axis=0)).astype(int) + offsets.max(axis=0) + 3
    W, H = (hi - lo)
    img = _canvas(H, W)

    if len(ii):
        vox = np.stack([ii, jj, kk], axis=1)
        base = vox @ basis - lo                            # (N, 2) integer screen position of the corner
        base_depth = vox.astype(np.float64) @ view
        u = (base[:, None, 0] + offsets[None, :, 0]).ravel()
        v = (base[:, None, 1] + offsets[None, :, 1]).ravel()
        depth = (base_depth[:, None] + d_off[None, :]).ravel()
        pix = v * W + u
        order = np.lexsort((depth, pix))                   # by pixel, nearest first
        first = np.ones(len(order), dtype=bool)
        first[1:] = pix[order][1:] != pix[order][:-1]
        win = order[first]
        n_sp = len(offsets)
        vid, sid = win // n_sp, win % n_sp

        labels = sem[ii, jj, kk]
        base_col = _lut(colors)[labels]                    # (N, 3)
        if mask is not None:
            inside = np.asarray(mask).astype(bool)[ii, jj, kk]
            base_col = np.where(inside[:, None], base_col, _wash(base_col))
        hshade = 1.0 - height_shading * (1.0 - kk / max(Z - 1, 1))
        shade = f_shade[sid] * hshade[vid]
        if edges:
            shade = shade * np.where(f_edge[sid], 0.82, 1.0)
        col = np.clip(np.round(base_col[vid] * shade[:, None]), 0, 255).astype(np.uint8)
        img.reshape(-1, 3)[pix[win]] = col

    if mark_ego:
        grid = grid or Grid.with_shape(sem.shape)
        ego = (np.array([0.0, 0.0, 0.0]) - np.asarray(grid.range_min)) / np.asarray(grid.voxel_size)
        if np.all(ego >= 0) and np.all(ego <= np.array([X, Y, Z])):
            c = ego @ p.T - lo
            tip = (ego + [6, 0, 0]) @ p.T - lo
            cv2.arrowedLine(img, tuple(int(round(t)) for t in c), tuple(int(round(t)) for t in tip), (0, 0, 0),
                            max(1, scale), tipLength=0.4, line_type=cv2.LINE_AA)
    if crop:
        img = _crop_to_content(img, margin=6 * int(scale))
    return img


def _crop_to_content(img: np.ndarray, margin: int) -> np.ndarray:
    diff = np.any(img != np.array(BACKGROUND, dtype=np.uint8), axis=2)
    if not diff.any():
        return img
    rows, cols = np.nonzero(diff.any(axis=1))[0], np.nonzero(diff.any(axis=0))[0]
    r0, r1 = max(rows[0] - margin, 0), min(rows[-1] + margin + 1, img.shape[0])
    c0, c1 = max(cols[0] - margin, 0), min(cols[-1] + margin + 1, img.shape[1])
    return np.ascontiguousarray(img[r0:r1, c0:c1])


# ---------------------------------------------------------------------------------------- scalars
def scalar_bev(volume: np.ndarray, reduce: str = "max", colormap: int = cv2.COLORMAP_VIRIDIS,
               mask: np.ndarray | None = None, scale: int = 3, vmin: float | None = None,
               vmax: float | None = None, label: str = "", grid: Grid | None = None) -> np.ndarray:
    """(X, Y, Z) float volume -> top-down colour map (x up, y left) with a colour bar on the right.

    reduce: "max" or "mean" over z of the voxels inside `mask` (all voxels when None) and finite.
    Columns with no such voxel are dark grey. vmin/vmax default to the data's range.
    """
    vol = _check_volume(volume, "volume").astype(np.float64)
    X, Y, _ = vol.shape
    valid = np.isfinite(vol)
    if mask is not None:
        valid &= np.asarray(mask).astype(bool)
    if reduce == "max":
        red = np.where(valid, vol, -np.inf).max(axis=2)
    elif reduce == "mean":
        cnt = valid.sum(axis=2)
        red = np.where(valid, vol, 0.0).sum(axis=2) / np.maximum(cnt, 1)
    else:
        raise ValueError(f"reduce must be 'max' or 'mean', got {reduce!r}")
    col_ok = valid.any(axis=2)
    vals = red[col_ok]
    lo = float(vals.min()) if vmin is None and vals.size else (0.0 if vmin is None else float(vmin))
    hi = float(vals.max()) if vmax is None and vals.size else (1.0 if vmax is None else float(vmax))
    if hi <= lo:
        hi = lo + 1e-6
    norm = np.clip((np.where(col_ok, red, lo) - lo) / (hi - lo), 0, 1)
    u8 = np.round(norm * 255).astype(np.uint8)
    rgb = cv2.cvtColor(cv2.applyColorMap(u8, colormap), cv2.COLOR_BGR2RGB)
    rgb[~col_ok] = UNKNOWN_GREY
    img = np.ascontiguousarray(_to_bev_orientation(rgb))
    img = cv2.resize(img, (Y * scale, X * scale), interpolation=cv2.INTER_NEAREST)
    _draw_ego(img, _ego_pixel(vol.shape, grid, scale), size=max(3, int(round(2.5 * scale))))
    bar = _colour_bar(img.shape[0], colormap, lo, hi, label)
    return np.concatenate([img, bar], axis=1)


def _colour_bar(height: int, colormap: int, lo: float, hi: float, label: str) -> np.ndarray:
    bar_w, text_w, pad = 18, 90, 8
    out = _canvas(height, pad + bar_w + text_w)
    top, bottom = 24, height - 12
    ramp = np.linspace(255, 0, max(bottom - top, 2)).round().astype(np.uint8)[:, None]
    ramp = cv2.cvtColor(cv2.applyColorMap(ramp, colormap), cv2.COLOR_BGR2RGB)  # (n, 1, 3)
    out[top:top + len(ramp), pad:pad + bar_w] = ramp
    cv2.rectangle(out, (pad, top), (pad + bar_w - 1, top + len(ramp) - 1), TEXT, 1)
    for frac in (0.0, 0.5, 1.0):
        y = int(round(top + (1 - frac) * (len(ramp) - 1)))
        val = lo + frac * (hi - lo)
        cv2.putText(out, f"{val:.3g}", (pad + bar_w + 4, min(max(y + 4, 10), height - 2)), FONT, 0.4, TEXT, 1,
                    cv2.LINE_AA)
    if label:
        cv2.putText(out, label[:14], (2, 15), FONT, 0.4, TEXT, 1, cv2.LINE_AA)
    return out


# ---------------------------------------------------------------------------------------- layout
def _text_size(text: str, scale: float, thick: int) -> tuple[int, int]:
    (w, h), base = cv2.getTextSize(text, FONT, scale, thick)
    return w, h + base


def _wrap(text: str, width: int, scale: float, thick: int) -> list[str]:
    """`text` cut into lines that fit `width` pixels (at word boundaries; a word longer than a line is split)."""
    lines: list[str] = []
    line = ""
    for word in text.split(" "):
        cand = f"{line} {word}" if line else word
        if _text_size(cand, scale, thick)[0] <= width or not line:
            line = cand
        else:
            lines.append(line)
            line = word
        while _text_size(line, scale, thick)[0] > width and len(line) > 1:   # one over-long word
            cut = len(line)
            while cut > 1 and _text_size(line[:cut], scale, thick)[0] > width:
                cut -= 1
            lines.append(line[:cut])
            line = line[cut:]
    if line:
        lines.append(line)
    return lines or [""]


def _title_bar(text: str, width: int, scale: float | None = None) -> np.ndarray:
    """A bar of `width` pixels with `text`, on as many lines as it needs (never cut off at the right)."""
    scale = scale or float(np.clip(width / 1000, 0.5, 0.9))
    thick = 2 if scale >= 0.7 else 1
    lines = _wrap(text, max(width - 12, 8), scale, thick)
    _, th = _text_size("Ag", scale, thick)
    bar = _canvas(len(lines) * (th + 4) + 8, width)
    for i, line in enumerate(lines):
        cv2.putText(bar, line, (6, (i + 1) * (th + 4) - 1), FONT, scale, TEXT, thick, cv2.LINE_AA)
    return bar


def with_title(img: np.ndarray, text: str) -> np.ndarray:
    """`img` with a full-width title bar above it (wrapped onto several lines when long)."""
    img = _as_rgb(img)
    return np.concatenate([_title_bar(text, img.shape[1]), img], axis=0)


def _canvas(h: int, w: int, color=BACKGROUND) -> np.ndarray:
    """An (h, w, 3) uint8 image of one RGB colour. One row is filled, then copied down: np.full with an
    RGB triple fills element by element, ~100x slower (25 ms for a 1300 x 1300 picture)."""
    row = np.empty((1, w, 3), np.uint8)
    row[...] = color
    out = np.empty((h, w, 3), np.uint8)
    out[...] = row
    return out


def _pad_to(img: np.ndarray, h: int, w: int) -> np.ndarray:
    out = _canvas(h, w)
    y0, x0 = (h - img.shape[0]) // 2, (w - img.shape[1]) // 2
    out[y0:y0 + img.shape[0], x0:x0 + img.shape[1]] = img
    return out


def _as_rgb(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) RGB image, got shape {img.shape}")
    return img.astype(np.uint8, copy=False)   # no copy of an image that is uint8 already (callers only read it)


def side_by_side(panels: Sequence[tuple[str, np.ndarray]], gap: int = 8) -> np.ndarray:
    """Panels left to right, each with its title above, padded (centred) to the tallest one."""
    if not panels:
        raise ValueError("side_by_side needs at least one panel")
    titled = []
    for title, img in panels:
        img = _as_rgb(img)
        titled.append(np.concatenate([_title_bar(title, img.shape[1]), img], axis=0) if title else img)
    h = max(t.shape[0] for t in titled)
    cols = []
    for i, t in enumerate(titled):
        cols.append(_pad_to(t, h, t.shape[1]))
        if i < len(titled) - 1:
            cols.append(_canvas(h, gap))
    return np.concatenate(cols, axis=1)


def stack_vertical(images: Sequence[np.ndarray], gap: int = 8) -> np.ndarray:
    """Images top to bottom, centred on the widest one."""
    images = [_as_rgb(i) for i in images]
    w = max(i.shape[1] for i in images)
    rows = []
    for n, i in enumerate(images):
        rows.append(_pad_to(i, i.shape[0], w))
        if n < len(images) - 1:
            rows.append(_canvas(gap, w))
    return np.concatenate(rows, axis=0)


def legend(class_names: Sequence[str], colors: np.ndarray | None = None, width: int = 900,
           font_scale: float | None = None) -> np.ndarray:
    """A strip of colour swatches with names, wrapped into rows of at most `width` pixels."""
    colors = palette_for(class_names) if colors is None else np.asarray(colors, dtype=np.uint8).reshape(-1, 3)
    font_scale = font_scale or float(np.clip(width / 2000, 0.45, 0.8))
    sw, pad = int(round(30 * font_scale)), int(round(12 * font_scale))
    _, th = _text_size("Ag", font_scale, 1)
    row_h = max(sw, th) + pad
    items, x, y = [], pad, pad
    for name, col in zip(class_names, colors):
        tw, _ = _text_size(name, font_scale, 1)
        item_w = sw + 4 + tw + 2 * pad
        if x + item_w > width and x > pad:
            x, y = pad, y + row_h
        items.append((x, y, name, col))
        x += item_w
    out = _canvas(y + row_h + pad, width)
    for x, y, name, col in items:
        cv2.rectangle(out, (x, y), (x + sw - 1, y + sw - 1), tuple(int(c) for c in col), -1)
        cv2.rectangle(out, (x, y), (x + sw - 1, y + sw - 1), (90, 90, 90), 1)
        cv2.putText(out, name, (x + sw + 4, y + sw - 2), FONT, font_scale, TEXT, 1, cv2.LINE_AA)
    return out


def prediction_vs_gt(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None,
                     class_names: Sequence[str] = OCC3D_CLASSES, colors: np.ndarray | None = None,
                     free_index: int = FREE, grid: Grid | None = None, views: str = "both",
                     titles: tuple[str, str] = ("prediction", "ground truth"),
                     table: ClassTable | None = None) -> np.ndarray:
    """One figure: BEV prediction | BEV GT (top), voxel views (below), legend of present classes.

    `mask` (e.g. mask_camera): BEV shows only voxels inside it and the voxel views grey out those
    outside it. views: "bev", "voxels" or "both". `table` (a ClassTable; both volumes in its file ids)
    sets names, colours and the free id instead of `class_names` / `colors` / `free_index`.
    """
    pred, gt = _check_volume(pred, "prediction"), _check_volume(gt, "ground truth")
    if pred.shape != gt.shape:
        raise ValueError(f"prediction shape {pred.shape} != GT shape {gt.shape}")
    if table is not None:
        colors, free_index = _table_style(table, colors, free_index)
        class_names = [table.name_of(i) if i in table.ids or i == table.free_id else str(i)
                       for i in range(len(colors))]
    colors = palette_for(class_names) if colors is None and list(class_names) != list(OCC3D_CLASSES) \
        else _colors_or_default(colors, len(class_names))
    rows = []
    if views in ("bev", "both"):
        rows.append(side_by_side([(f"{titles[0]} (BEV)", bev_image(pred, colors, free_index, 4, mask=mask, grid=grid)),
                                  (f"{titles[1]} (BEV)", bev_image(gt, colors, free_index, 4, mask=mask, grid=grid))]))
    if views in ("voxels", "both"):
        rows.append(side_by_side([(f"{titles[0]} (3-D)", voxel_view(pred, colors, free_index, mask=mask, grid=grid)),
                                  (f"{titles[1]} (3-D)", voxel_view(gt, colors, free_index, mask=mask, grid=grid))]))
    if not rows:
        raise ValueError(f"views must be 'bev', 'voxels' or 'both', got {views!r}")
    present = sorted(set(np.unique(pred).tolist()) | set(np.unique(gt).tolist()))
    ids = [i for i in present if i != free_index and i < len(class_names)]
    width = max(r.shape[1] for r in rows)
    rows.append(legend([class_names[i] for i in ids], colors[ids], width=width))
    return stack_vertical(rows)


def rig_mosaic(images: Mapping[str, np.ndarray], width: int = 1800, layout=None) -> np.ndarray:
    """A rig's camera images (RGB) in rows (`mosaic_layout`: nuScenes' 2 x 3, front row and back row) with
    camera names; `width` px wide. Each tile keeps its own image's aspect ratio (a row is as tall as its
    tallest tile, shorter ones padded dark below); a camera of `layout` with no image is a dark tile saying so.
    """
    layout = mosaic_layout(images.keys()) if layout is None else layout
    ncol = max(len(row) for row in layout)
    tile_w = width // ncol
    first = next((np.asarray(images[c]) for row in layout for c in row if c in images), None)
    default_aspect = first.shape[0] / first.shape[1] if first is not None else 9 / 16
    rows = []
    for row in layout:
        tiles = []
        for name in row:
            if name in images:
                img = _as_rgb(images[name])
                tile_h = max(1, int(round(tile_w * img.shape[0] / img.shape[1])))
                tile = cv2.resize(img, (tile_w, tile_h), interpolation=cv2.INTER_AREA)
            else:
                tile_h = int(round(tile_w * default_aspect))
                tile = np.full((tile_h, tile_w, 3), 40, dtype=np.uint8)
                cv2.putText(tile, "missing", (10, tile_h // 2), FONT, 0.8, (220, 220, 220), 2, cv2.LINE_AA)
            tile = np.ascontiguousarray(tile)
            fs = max(0.45, tile_w / 900)
            label = name.replace("CAM_", "")
            (tw, th), base = cv2.getTextSize(label, FONT, fs, 2)
            cv2.rectangle(tile, (4, 4), (4 + tw + 10, 4 + th + base + 8), (0, 0, 0), -1)
            cv2.putText(tile, label, (9, 4 + th + 4), FONT, fs, (255, 255, 255), 2, cv2.LINE_AA)
            tiles.append(tile)
        height = max(t.shape[0] for t in tiles)
        row_img = np.concatenate([np.pad(t, ((0, height - t.shape[0]), (0, 0), (0, 0)), constant_values=40)
                                  for t in tiles], axis=1)
        rows.append(np.pad(row_img, ((0, 0), (0, ncol * tile_w - row_img.shape[1]), (0, 0)), constant_values=255))
    return np.concatenate(rows, axis=0)


# ---------------------------------------------------------------------------------------- files
def save_png(path: str | Path, rgb: np.ndarray) -> Path:
    """Write an RGB uint8 image as PNG, atomically (temp file + rename). Returns the path."""
    rgb = _as_rgb(rgb)
    path = Path(path)
    with atomic_path(path, suffix=".png") as tmp:
        if not cv2.imwrite(str(tmp), cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR), PNG_OPTIONS):
            raise OSError(f"could not write {path}")
    return path
