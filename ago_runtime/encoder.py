"""The bundle's camera-to-voxel encoder in onnxruntime, delivered in chunks of voxels. No torch.

The bundle's encoder is split in two graphs (bundle format 3, ago_runtime/bundle.py):

- `planes.onnx` runs once per frame,
      images (1,6,3,H,W) + ego2img (1,6,4,4) -> plane_xy (X,Y,Dh), plane_xz (X,Z,Dh), plane_yz (Y,Z,Dh)
  (the three TPV planes at the grid's resolution, already multiplied by the decoder's first linear
  layer, channels last), and `voxels.onnx` runs per slab of x rows,
      plane_xy[x0:x1], plane_xz[x0:x1], plane_yz, bank_main (P',Dh), bank_adapted (P',Da)
        -> h (n,Dh), g (n,Da), s_main (P',n), s_adapted (P',n),   n = (x1-x0)*Y*Z,
  the voxels of that slab in C order over [x, y, z] (so slabs follow each other in the flat order);
  bank_* are the bank folded into the linear heads (ago_runtime.heads.FoldedHeads), fed at run time,
  so the heads' matrix product runs in onnxruntime's GEMM and any bank works without re-export.
  Memory scales with the slab, not the grid; slabs of ~8 000 voxels keep each slab's
  (n, 384) intermediates (12 MB) near the cache (measured faster than 65 000-voxel slabs,
  docs/runtime.md).

Sessions: the first session of a graph saves onnxruntime's optimised graph in the cache
(`~/.cache/ago/ort/`, or $AGO_CACHE_DIR/ort; keyed by the graph's sha256, the onnxruntime version
and the CPU), and later sessions load that file with graph optimisation off (measured 0.26 s ->
~0.05 s to open planes.onnx). Each session then runs once on dummy inputs of the real shapes
(`warm_up`), so the first frame of a process runs at the steady-state speed.

`open_encoder(bundle, int8=False, threads=None)` -> a SplitEncoder with
- `score_chunks(images, ego2img, folded, adapted=True)`: yields (start, stop, s_main, s_adapted), the
  bias-free class-major phrase scores (P', n) of each slab (s_adapted None when not asked for);
- `chunks(images, ego2img)`: yields (start, stop, h, g) over the flat voxel index, in order;
- `hidden(images, ego2img)`: the whole (N,Dh), (N,Da) (retrieval, parity checks).
"""

from __future__ import annotations

import hashlib
import os
import platform
import tempfile
from pathlib import Path
from typing import Iterator

import numpy as np
import onnxruntime as ort

from .errors import AgoInputError
from .grid import Grid
from .heads import SCORE_BUDGET_BYTES

VOXEL_INPUTS = ["plane_xy", "plane_xz", "plane_yz", "bank_main", "bank_adapted"]
VOXEL_OUTPUTS = ["h", "g", "s_main", "s_adapted"]
PLANE_OUTPUTS = ["plane_xy", "plane_xz", "plane_yz"]
SLAB_VOXELS = 8192    # target voxels per slab of the split encoder (whole x-rows of Y*Z voxels)
ENV_NO_ORT_CACHE = "AGO_NO_ORT_CACHE"   # =1: never read or write cached optimised graphs


def session_options(threads: int | None = None, optimize: bool = True) -> ort.SessionOptions:
    so = ort.SessionOptions()
    so.graph_optimization_level = (ort.GraphOptimizationLevel.ORT_ENABLE_ALL if optimize
                                   else ort.GraphOptimizationLevel.ORT_DISABLE_ALL)
    if threads:
        so.intra_op_num_threads = int(threads)
    # onnxruntime's idle worker threads spin by default; between the slabs they then steal the cores
    # that numpy's heads need (measured on 2 cores: 2.6 s -> 2.2 s per 200x200x16 frame, and
    # 0.43 -> 0.37 s at 100x100x8, with spinning off). AGO_ORT_SPIN=1 turns spinning back on.
    if os.environ.get("AGO_ORT_SPIN", "0") != "1":
        so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.log_severity_level = 3
    return so


def _cpu_tag() -> str:
    """A short tag of this CPU (model and instruction-set flags): optimised graphs hold CPU-specific
    layouts (onnxruntime's NCHWc blocks), so the cache never shares them across CPUs."""
    text = platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                if line.startswith(("model name", "flags", "Features")):
                    text += line
                if line.strip() == "":
                    break
    except OSError:
        pass
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def optimized_cache_path(sha256: str) -> Path:
    from .text_encoder import ago_cache_dir

    return ago_cache_dir() / "ort" / f"{sha256[:32]}-ort{ort.__version__}-{_cpu_tag()}.onnx"


def _create(path: Path, so: ort.SessionOptions) -> ort.InferenceSession:
    try:
        return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own Fail/InvalidProtobuf types
        raise AgoInputError(path, f"onnxruntime cannot load the graph ({str(e).splitlines()[0][:200]})") from None


def open_session(path: Path, threads: int | None, sha256: str | None = None) -> ort.InferenceSession:
    """An onnxruntime session of `path`. With the graph's sha256 (from bundle.json, already checked by
    Bundle.load) the optimised graph is cached: read when present (optimisation off), else written
    while this session is made (written to a temporary name, then renamed). A cache file that
    onnxruntime cannot read is removed and remade. AGO_NO_ORT_CACHE=1 disables the cache."""
    if not sha256 or os.environ.get(ENV_NO_ORT_CACHE) == "1":
        return _create(path, session_options(threads))
    cached = optimized_cache_path(sha256)
    if cached.is_file():
        try:
            return ort.InferenceSession(str(cached), session_options(threads, optimize=False),
                                        providers=["CPUExecutionProvider"])
        except Exception:
            cached.unlink(missing_ok=True)
    so = session_options(threads)
    tmp = None
    try:
        cached.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{cached.stem}.", suffix=".tmp.onnx", dir=cached.parent)
        os.close(fd)
        so.optimized_model_filepath = tmp
    except OSError:
        tmp = None          # no writable cache: just optimise in memory
    try:
        sess = _create(path, so)
        if tmp is not None and os.path.getsize(tmp) > 0:
            os.replace(tmp, cached)
        return sess
    finally:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)


def load_session(path: Path, threads: int | None, inputs: list[str], outputs: list[str],
                 sha256: str | None = None) -> ort.InferenceSession:
    sess = open_session(path, threads, sha256)
    names_in = [i.name for i in sess.get_inputs()]
    names_out = [o.name for o in sess.get_outputs()]
    if names_in != inputs or names_out != outputs:
        raise AgoInputError(path, f"graph has inputs {names_in} and outputs {names_out}; expected {inputs} -> {outputs}")
    return sess


class SplitEncoder:
    """Format-3 bundles: planes once, then the per-voxel MLPs slab by slab.

    sha256: {"planes": hex, "voxels": hex} of the two files (from bundle.json) to use the optimised-graph
    cache; warm_up: run both graphs once on dummy inputs when opened (see the module docstring)."""

    PLANES = PLANE_OUTPUTS

    def __init__(self, planes_path: Path, voxels_path: Path, grid: Grid, threads: int | None = None,
                 slab_voxels: int = SLAB_VOXELS, sha256: dict | None = None, warm_up: bool = True):
        self.grid = grid
        self.planes_path, self.voxels_path = planes_path, voxels_path
        sha256 = sha256 or {}
        self.planes = load_session(planes_path, threads, ["images", "ego2img"], self.PLANES, sha256.get("planes"))
        self.voxels = load_session(voxels_path, threads, VOXEL_INPUTS, VOXEL_OUTPUTS, sha256.get("voxels"))
        ins = self.voxels.get_inputs()
        self.hidden_dim = ins[0].shape[2]
        if not isinstance(self.hidden_dim, int) or ins[3].shape[1] != self.hidden_dim:
            raise AgoInputError(voxels_path, f"voxel graph inputs {[i.shape for i in ins]} are not a format-3 "
                                "graph (plane_xy (x, Y, Dh)); re-export the checkpoint with `ago export`")
        self.no_bank = {"bank_main": np.zeros((1, ins[3].shape[1]), np.float32),
                        "bank_adapted": np.zeros((1, ins[4].shape[1]), np.float32)}
        self.slab_voxels = slab_voxels
        self.slab = self.rows_per_slab(slab_voxels)
        if warm_up:
            self.warm_up()

    def rows_per_slab(self, voxels: int) -> int:
        X, Y, Z = self.grid.shape
        return int(max(1, min(X, voxels // (Y * Z))))   # whole x-rows of Y*Z voxels

    def warm_up(self, phrases: int = 64) -> None:
        """One run of each graph on dummy inputs of the real shapes (onnxruntime's first run of a
        session allocates its buffers and is ~2x slower than later runs)."""
        shape = [d if isinstance(d, int) else 1 for d in self.planes.get_inputs()[0].shape]
        ego2img = np.tile(np.eye(4, dtype=np.float32), (1, shape[1], 1, 1))
        ego2img[..., 2, 3] = 10.0                     # points in front of every camera: real sampling work
        planes = self.planes.run(self.PLANES, {"images": np.zeros(shape, np.float32), "ego2img": ego2img})
        X, Y, Z = self.grid.shape
        rows = min(self.slab, planes[0].shape[0])
        bank = {k: np.zeros((phrases, v.shape[1]), np.float32) for k, v in self.no_bank.items()}
        self.voxels.run(["s_main", "s_adapted"], {"plane_xy": planes[0][:rows], "plane_xz": planes[1][:rows],
                                                  "plane_yz": planes[2], **bank})

    def plane_maps(self, images: np.ndarray, ego2img: np.ndarray) -> list[np.ndarray]:
        xy, xz, yz = self.planes.run(self.PLANES, {"images": images, "ego2img": ego2img})
        X, Y, Z = self.grid.shape
        D = self.hidden_dim
        if xy.shape != (X, Y, D) or xz.shape != (X, Z, D) or yz.shape != (Y, Z, D):
            raise AgoInputError(self.planes_path, f"planes {xy.shape}, {xz.shape}, {yz.shape} do not fit the "
                                f"bundle grid {X}x{Y}x{Z} and width {D}")
        return [np.ascontiguousarray(xy), np.ascontiguousarray(xz), np.ascontiguousarray(yz)]

    def _slabs(self, images: np.ndarray, ego2img: np.ndarray, outputs: list[str], bank: dict, rows: int):
        xy, xz, yz = self.plane_maps(images, ego2img)
        X, Y, Z = self.grid.shape
        row = Y * Z
        for x0 in range(0, X, rows):
            x1 = min(X, x0 + rows)
            res = self.voxels.run(outputs, {"plane_xy": xy[x0:x1], "plane_xz": xz[x0:x1], "plane_yz": yz, **bank})
            got = res[0].shape[0] if outputs[0] in ("h", "g") else res[0].shape[1]
            if got != (x1 - x0) * row:
                raise AgoInputError(self.voxels_path, f"voxel graph gives {got} voxels for a slab of {(x1 - x0) * row}")
            yield x0 * row, x1 * row, res

    def chunks(self, images: np.ndarray, ego2img: np.ndarray) -> Iterator[tuple[int, int, np.ndarray, np.ndarray]]:
        for start, stop, (h, g) in self._slabs(images, ego2img, ["h", "g"], self.no_bank, self.slab):
            yield start, stop, h, g

    def score_chunks(self, images, ego2img, folded, adapted: bool = True):
        """(start, stop, s_main (P', n), s_adapted (P', n) | None) per slab, from the graph's own GEMM."""
        if folded.A_main_T.shape[1] != self.no_bank["bank_main"].shape[1] or \
                folded.A_ad_T.shape[1] != self.no_bank["bank_adapted"].shape[1]:
            raise AgoInputError(self.voxels_path, "folded bank widths do not match the voxel graph's hidden widths")
        bank = {"bank_main": folded.A_main_T, "bank_adapted": folded.A_ad_T}
        outputs = ["s_main", "s_adapted"] if adapted else ["s_main"]
        # a large bank gets thinner slabs: each (P', n) score block stays within the heads' budget
        rows = self.rows_per_slab(min(self.slab_voxels, SCORE_BUDGET_BYTES // (4 * folded.num_rows)))
        for start, stop, res in self._slabs(images, ego2img, outputs, bank, rows):
            yield start, stop, res[0], res[1] if adapted else None

    def hidden(self, images: np.ndarray, ego2img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        parts = list(self.chunks(images, ego2img))
        return np.concatenate([p[2] for p in parts]), np.concatenate([p[3] for p in parts])


def open_encoder(bundle, int8: bool = False, threads: int | None = None) -> "SplitEncoder":
    """The encoder of a loaded `Bundle`; int8 picks the quantised graphs."""
    paths = bundle.encoder_paths(int8)
    files = bundle.meta["files"]
    sha = {k: files[f"{k}_int8" if int8 else k].get("sha256") for k in paths}
    return SplitEncoder(paths["planes"], paths["voxels"], bundle.grid, threads, sha256=sha)
