"""One self-contained HTML file per frame: its occupancy in 3-D, to turn, hide classes and hover, with no network.

`write_viewer(path, views, images, title)` writes the page; `view_from_arrays(arrays, source)` makes a view of the
arrays of a prediction or labels file (`ago infer`'s npz: semantics, class_names, free_index, class_table +
class_colors, entropy, unexplained; an Occ3D labels.npz: semantics). What the page holds:

- the occupied voxels only (at most MAX_DRAWN_VOXELS per view: beyond that the ones farthest from the ego are
  dropped, with a `note:`), as base64 typed arrays: which voxels (a bitmask of the grid, or uint32 flat indices
  when that is smaller), one uint8 class per voxel, and per scalar volume (entropy, the unexplained-obstacle score,
  the similarity of `ago retrieve`) one uint16 per voxel quantised over its range;
- the class table's names and colours (drawn unlit: a cube's top face is exactly the class colour);
- the frame's camera images as JPEG, at most MAX_IMAGE_WIDTH pixels wide;
- three.js (`assets/viewer/three_bundle.min.js`, rebuilt by scripts/build_viewer.sh; licence THREE_LICENSE) and
  the viewer's own script (`assets/viewer/viewer.js`, API `window.agoViewer`), both inlined: no CDN.

Several views (a prediction and its ground truth) share one camera. The demo frame's page (200 x 200 x 16, six
images) is about 1.2 MB (docs/metric_and_pictures.md, "The 3-D page").
"""

from __future__ import annotations

import base64
import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import cv2
import numpy as np

from ago_runtime.atomic import write_text
from ago_runtime.classes import IGNORE, OCC3D_NUSCENES, ClassTable
from ago_runtime.errors import AgoInputError, AgoNote
from ago_runtime.geometry.grid import Grid
from ago_runtime.pictures.render import mosaic_layout, palette_for

ASSET_DIR = Path(__file__).resolve().parents[1] / "assets" / "viewer"
MAX_DRAWN_VOXELS = 400_000     # cubes per view: more makes a page too big to write and too slow to turn
MAX_IMAGE_WIDTH = 800          # camera images are downscaled to this width
JPEG_QUALITY = 80
HTML_SUFFIXES = (".html", ".htm")


@dataclass
class Scalar:
    """A float volume shown on hover and as heat colours: `threshold` is where the page's slider starts."""
    name: str
    volume: np.ndarray            # (X, Y, Z)
    unit: str = ""
    threshold: float | None = None


@dataclass
class View:
    """One grid to draw: dense labels (class k = 0..K-1, K = free, 255 = unknown; free and unknown not drawn)."""
    title: str
    semantics: np.ndarray
    names: list[str]
    colors: np.ndarray            # (K, 3) uint8 RGB
    grid: Grid
    scalars: list[Scalar] = field(default_factory=list)


def recorded_table(arrays: Mapping[str, np.ndarray], source) -> ClassTable | None:
    """The class table an `ago infer` file records when it is not Occ3D-nuScenes (keys class_table, class_names,
    class_colors: its dense order, free last), else None. A class_table without colours is an AgoInputError."""
    if "class_table" not in arrays:
        return None
    if not {"class_names", "class_colors"} <= set(arrays):
        raise AgoInputError(source, f"names class table {str(arrays['class_table'])!r} but has no class_names and "
                                    "class_colors to draw it in (give --classes TABLE)")
    names, colors = [str(c) for c in np.atleast_1d(arrays["class_names"])], np.asarray(arrays["class_colors"])
    if names[-1:] != ["free"] or colors.shape != (len(names), 3):
        raise AgoInputError(source, "class_names must end with 'free' and class_colors give one RGB per name")
    try:
        return ClassTable(str(arrays["class_table"]), tuple(names[:-1]), tuple(range(len(names) - 1)), len(names) - 1,
                          tuple(tuple(int(c) for c in row) for row in colors))
    except ValueError as e:
        raise AgoInputError(source, str(e)) from None


def _classes(arrays, source, table: ClassTable | None) -> tuple[np.ndarray, list[str], np.ndarray]:
    """(dense labels, class names, (K, 3) colours) of a file's semantics: --classes TABLE (labels are its file ids),
    else the table the file records, else its class_names (bank classes: render.palette_for, as the PNG draws them),
    else Occ3D-nuScenes."""
    sem = np.asarray(arrays["semantics"])
    table = table or recorded_table(arrays, source)
    if table is None and "class_names" in arrays:
        names = [str(c) for c in np.atleast_1d(arrays["class_names"])]
        free = int(arrays["free_index"]) if "free_index" in arrays else len(names) - 1
        if not 0 <= free < len(names) or names[free] != "free" or free != len(names) - 1:
            raise AgoInputError(source, f"class_names must end with 'free' at free_index ({free}), got {names[-3:]}")
        names = names[:-1]
        dense, colors = sem.astype(np.uint8), palette_for(names)
        bad = np.unique(sem[(sem > len(names)) & (sem != IGNORE)])
        if bad.size:
            raise AgoInputError(source, f"'semantics' holds values {bad[:8].tolist()} beyond its {len(names)} "
                                        "classes and free")
        return dense, names, colors
    table = table or OCC3D_NUSCENES
    try:
        dense = table.to_dense(sem, "'semantics'")
    except ValueError as e:
        raise AgoInputError(source, str(e)) from None
    return dense, list(table.names), table.dense_colors()[:-1]


def view_from_arrays(arrays: Mapping[str, np.ndarray], source, title: str, grid: Grid | None = None,
                     table: ClassTable | None = None) -> View:
    """A View of a prediction or labels file's arrays (a dict; `source` names it in errors). `grid`: default the
    Occ3D range cut into the file's shape; `table`: the class table of the labels (default: the file's own).
    Scalars: entropy, the unexplained-obstacle score, an `ago retrieve` similarity, where present."""
    if "semantics" not in arrays:
        raise AgoInputError(source, f"not a prediction or labels file: no 'semantics' array (found {sorted(arrays)})")
    sem = np.asarray(arrays["semantics"])
    if sem.ndim != 3 or not np.issubdtype(sem.dtype, np.integer) or 0 in sem.shape:
        raise AgoInputError(source, f"'semantics' must be a non-empty 3-D (X, Y, Z) integer array, got {sem.dtype} "
                                    f"{sem.shape}")
    if sem.min() < 0 or sem.max() > 255:
        raise AgoInputError(source, f"'semantics' labels must lie in 0..255, found {sem.min()}..{sem.max()}")
    grid = grid or Grid.with_shape(sem.shape)
    if tuple(grid.shape) != tuple(sem.shape):
        raise AgoInputError(source, f"'semantics' shape {sem.shape} != the grid's {grid.shape}")
    dense, names, colors = _classes(arrays, source, table)
    scalars = []
    for key, unit, thr_key in (("entropy", "nats", None), ("unexplained", "", "unexplained_threshold"),
                               ("similarity", "cosine", None)):
        if key not in arrays:
            continue
        vol = np.asarray(arrays[key])
        if vol.shape != sem.shape or not np.issubdtype(vol.dtype, np.floating):
            raise AgoInputError(source, f"'{key}' must be a float array of the shape of 'semantics' {sem.shape}, "
                                        f"got {vol.dtype} {vol.shape}")
        threshold = float(arrays[thr_key]) if thr_key and thr_key in arrays else None
        scalars.append(Scalar(key, vol, unit, threshold))
    return View(title, dense, names, np.asarray(colors, np.uint8).reshape(-1, 3), grid, scalars)


def _b64(a: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(a).tobytes()).decode("ascii")


def _drawn(view: View) -> tuple[np.ndarray, int, float]:
    """(sorted flat indices of the voxels a view draws, how many occupied ones it leaves out, the radius kept): the
    occupied voxels, the MAX_DRAWN_VOXELS nearest the ego (in x, y) when there are more."""
    flat = np.flatnonzero(view.semantics.ravel() < len(view.names))
    if flat.size <= MAX_DRAWN_VOXELS:
        return flat, 0, float("inf")
    _, Y, Z = view.semantics.shape
    cx, cy, _ = view.grid.axis_centres()
    dist = np.hypot(cx[flat // (Y * Z)], cy[(flat // Z) % Y])
    order = np.argsort(dist, kind="stable")
    keep = order[:MAX_DRAWN_VOXELS]
    return np.sort(flat[keep]), flat.size - keep.size, float(dist[keep[-1]])


def _view_data(view: View, source: str) -> tuple[dict, list[str]]:
    """The JSON-able record of a view that the page's viewer.js decodes, and the notes on it (each also an AgoNote:
    voxels dropped, or nothing to draw)."""
    flat, dropped, radius = _drawn(view)
    notes = []
    if dropped:
        notes.append(f"{source}: {flat.size + dropped} occupied voxels, more than the viewer draws "
                     f"({MAX_DRAWN_VOXELS}): drew those within {radius:.1f} m of the ego, dropped the {dropped} "
                     "farther ones")
    elif flat.size == 0:
        notes.append(f"{source}: every voxel is free, nothing to draw (the page says so)")
    for note in notes:
        warnings.warn(AgoNote(note))
    n_voxels = view.semantics.size
    if (n_voxels + 7) // 8 <= 4 * flat.size:
        mask = np.zeros(n_voxels, bool)
        mask[flat] = True
        index, kind = np.packbits(mask, bitorder="little"), "bitmask"
    else:
        index, kind = flat.astype("<u4"), "uint32"
    labels = view.semantics.ravel()[flat].astype(np.uint8)
    scalars = []
    for s in view.scalars:
        vals = np.nan_to_num(s.volume.ravel()[flat].astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0)
        lo, hi = (float(vals.min()), float(vals.max())) if vals.size else (0.0, 1.0)
        hi = hi if hi > lo else lo + 1.0
        q = np.round((vals - lo) / (hi - lo) * 65535).astype("<u2")
        thr = s.threshold if s.threshold is not None else (float(np.quantile(vals, 0.9)) if vals.size else lo)
        scalars.append({"name": s.name, "unit": s.unit, "lo": lo, "hi": hi, "threshold": min(max(thr, lo), hi),
                        "data": _b64(q)})
    g = view.grid
    return ({"title": view.title, "shape": list(view.semantics.shape), "range_min": list(g.range_min),
             "voxel_size": list(g.voxel_size), "classes": [{"name": n, "color": [int(c) for c in col]}
                                                            for n, col in zip(view.names, view.colors)],
             "count": int(flat.size), "index_kind": kind, "index": _b64(index), "labels": _b64(labels),
             "occupied": int(flat.size + dropped), "voxels": int(n_voxels), "scalars": scalars}, notes)


def _jpeg(rgb: np.ndarray) -> str:
    h, w = rgb.shape[:2]
    if w > MAX_IMAGE_WIDTH:
        rgb = cv2.resize(rgb, (MAX_IMAGE_WIDTH, max(1, round(h * MAX_IMAGE_WIDTH / w))), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR),
                           [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return base64.b64encode(buf.tobytes()).decode("ascii")


def viewer_html(views: Sequence[View], images: Mapping[str, np.ndarray] | None = None, title: str = "",
                mode: str = "classes", source: str = "") -> str:
    """The page's text: `views` side by side with one camera, `images` (camera name -> RGB) below in the rig's
    layout, `mode` the colouring it opens with ("classes" or a scalar's name)."""
    records, notes = [], []
    for v in views:
        record, view_notes = _view_data(v, f"{source} ({v.title})" if source else v.title)
        records.append(record)
        notes += view_notes
    rows = mosaic_layout(list(images)) if images else ()
    ordered = [name for row in rows for name in row if name in images]
    data = {"title": title, "notes": notes, "mode": mode, "views": records,
            "image_columns": max((len(r) for r in rows), default=0),
            "images": [{"name": n, "jpeg": _jpeg(np.asarray(images[n]))} for n in ordered]}
    template = (ASSET_DIR / "viewer.html").read_text(encoding="utf-8")
    parts = {"__AGO_TITLE__": _html_escape(title or "ago occupancy"),
             "__AGO_DATA__": json.dumps(data, separators=(",", ":")).replace("</", "<\\/"),
             "__AGO_THREE__": _script_text(ASSET_DIR / "three_bundle.min.js"),
             "__AGO_VIEWER__": _script_text(ASSET_DIR / "viewer.js")}
    for key, text in parts.items():   # one pass per key; no value holds another key
        template = template.replace(key, text, 1)
    return template


def _html_escape(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def _script_text(path: Path) -> str:
    text = path.read_text(encoding="utf-8")
    return text.replace("</script", "<\\/script")   # never ends the inline script early


def write_viewer(path: str | Path, views: Sequence[View], images: Mapping[str, np.ndarray] | None = None,
                 title: str = "", mode: str = "classes", source: str = "") -> Path:
    """Write `viewer_html(...)` to `path` atomically; gives the path."""
    write_text(path, viewer_html(views, images, title, mode, source))
    return Path(path)


def write_prediction_page(path: str | Path, arrays: Mapping[str, np.ndarray], grid: Grid,
                          images: Mapping[str, np.ndarray] | None, title: str, mode: str = "classes") -> Path:
    """`ago infer|demo|retrieve --html`: the page of one prediction (the arrays its npz holds, volumes included;
    `ago retrieve` adds `similarity`) with the frame's camera images."""
    view = view_from_arrays(arrays, title, "prediction", grid=grid)
    return write_viewer(path, [view], images, title, mode, source=title)
