"""The bundle's camera-to-voxel encoder, delivered in chunks of voxels (onnxruntime + numpy/OpenCV; no torch).

Bundle format 3 (ago_runtime/predict/bundle.py):

- `planes.onnx` runs once per frame,
      images (1,6,3,H,W) + ego2img (1,6,4,4) -> plane_xy (X,Y,Dh), plane_xz (X,Z,Dh), plane_yz (Y,Z,Dh)
  (the three TPV planes at the grid's resolution, already multiplied by the decoder's first linear
  layer, channels last);
- then per slab of x rows [x0, x1) (n = (x1-x0)*Y*Z voxels in C order over [x, y, z], so slabs
  follow each other in the flat order): a = plane_xy[x, y] + plane_xz[x, z] + plane_yz[y, z] (numpy
  broadcasting), x = softplus(a), and the voxel stages `voxels_<i>.onnx` one after the other: each
  gives y = x W^T + b (the next layer's pre-activation; the softplus between layers runs here in
  numpy + OpenCV, ~2x faster than onnxruntime's Log kernel) and, where x is h or g, the bank scores
  s_main = bank_main h^T / s_adapted = bank_adapted g^T (P', n). bank_* are the bank folded into the
  linear heads (ago_runtime.predict.heads.FoldedHeads), fed at run time, so the heads' matrix product runs in
  onnxruntime's GEMM and any bank works without re-export.
  Memory scales with the slab, not the grid (SLAB_VOXELS voxels; docs/runtime.md has the slab sizes
  measured).

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
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np
import onnxruntime as ort

from ago_runtime.errors import AgoInputError
from ago_runtime.geometry.grid import Grid
from ago_runtime.predict.heads import SCORE_BUDGET_BYTES

PLANE_OUTPUTS = ["plane_xy", "plane_xz", "plane_yz"]
SLAB_VOXELS = 4096    # target voxels per slab (whole x-rows of Y*Z voxels)
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
    from ago_runtime.vocab.text_encoder import ago_cache_dir

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


def softplus_(x: np.ndarray, tmp: np.ndarray) -> np.ndarray:
    """x <- softplus(x) = max(log(1 + exp(min(x, 20))), x), in place; tmp: scratch of x's shape.

    The same function as torch's softplus to float32 rounding (softplus(x) > x always, and for x > 20
    log(1 + e^x) = x to float32; absolute error <= 1e-6, tests/test_runtime.py). OpenCV's vectorised
    cv2.exp / cv2.log are ~6x faster than numpy's and than onnxruntime's Log kernel here."""
    np.minimum(x, 20.0, out=tmp)
    cv2.exp(tmp, tmp)
    tmp += 1.0
    cv2.log(tmp, tmp)
    np.maximum(tmp, x, out=x)
    return x


class Softplus:
    """softplus_ on (n, d) float32 arrays, in place, split over `threads` threads by rows (numpy and OpenCV
    release the GIL)."""

    def __init__(self, threads: int | None = None):
        self.threads = max(1, int(threads or os.cpu_count() or 1))
        self.pool = ThreadPoolExecutor(self.threads, thread_name_prefix="ago-softplus") if self.threads > 1 else None

    def __call__(self, x: np.ndarray) -> np.ndarray:
        tmp = np.empty_like(x)
        if self.pool is None or x.shape[0] < 2 * self.threads:
            return softplus_(x, tmp)
        cuts = np.linspace(0, x.shape[0], self.threads + 1).astype(int)
        parts = [slice(a, b) for a, b in zip(cuts[:-1], cuts[1:])]
        list(self.pool.map(lambda sl: softplus_(x[sl], tmp[sl]), parts))
        return x


class SplitEncoder:
    """Format-3 bundles: planes once, then the per-voxel MLP slab by slab.

    stages: the bundle's "voxel_stages" (ago_export.graphs.voxel_stages), each with its "path" (and
    optionally "sha256"). Per slab: a = plane_xy + plane_xz + plane_yz (numpy), x = softplus(a), then
    per stage its graph (onnxruntime: y = x W^T + b, and s = bank x^T where x is h or g) and the
    softplus of y (numpy + OpenCV). sha256: {"planes": hex} for the optimised-graph cache (the stages
    carry their own); warm_up: run the graphs once on dummy inputs when opened."""

    PLANES = PLANE_OUTPUTS

    def __init__(self, planes_path: Path, stages: list[dict], grid: Grid, threads: int | None = None,
                 slab_voxels: int = SLAB_VOXELS, sha256: dict | None = None, warm_up: bool = True):
        self.grid = grid
        self.planes_path = planes_path
        self.planes = load_session(planes_path, threads, ["images", "ego2img"], self.PLANES,
                                   (sha256 or {}).get("planes"))
        self.stages = []
        for st in stages:
            ins = ["x"] + (["bank"] if st.get("bank") else [])
            outs = (["y"] if st.get("linear") else []) + (["s"] if st.get("bank") else [])
            self.stages.append({**st, "session": load_session(Path(st["path"]), threads, ins, outs, st.get("sha256")),
                                "outputs": outs})
        roles = [st.get("bank") for st in self.stages]
        if roles.count("main") != 1 or roles[-1] != "adapted" or roles.count("adapted") != 1:
            raise AgoInputError(planes_path.parent, f"voxel stages {roles} are not decoder ... h ... g; re-export")
        self.hidden_dim = int(self.stages[0]["input_dim"])
        self.widths = {st["bank"]: int(st["input_dim"]) for st in self.stages if st.get("bank")}
        self.no_bank = {"main": np.zeros((1, self.widths["main"]), np.float32),
                        "adapted": np.zeros((1, self.widths["adapted"]), np.float32)}
        self.softplus = Softplus(threads)
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
        rows = min(self.slab, planes[0].shape[0])
        bank = {k: np.zeros((phrases, v.shape[1]), np.float32) for k, v in self.no_bank.items()}
        self._slab(planes, 0, rows, bank, want=("s_main", "s_adapted"))

    def plane_maps(self, images: np.ndarray, ego2img: np.ndarray) -> list[np.ndarray]:
        xy, xz, yz = self.planes.run(self.PLANES, {"images": images, "ego2img": ego2img})
        X, Y, Z = self.grid.shape
        D = self.hidden_dim
        if xy.shape != (X, Y, D) or xz.shape != (X, Z, D) or yz.shape != (Y, Z, D):
            raise AgoInputError(self.planes_path, f"planes {xy.shape}, {xz.shape}, {yz.shape} do not fit the "
                                f"bundle grid {X}x{Y}x{Z} and width {D}")
        return [np.ascontiguousarray(xy), np.ascontiguousarray(xz), np.ascontiguousarray(yz)]

    def _slab(self, planes, x0: int, x1: int, bank: dict, want) -> dict:
        """One slab of x rows [x0, x1): -> {"h", "g", "s_main", "s_adapted"} (those in `want`, plus h/g)."""
        xy, xz, yz = planes
        a = xy[x0:x1, :, None, :] + xz[x0:x1, None, :, :]
        a += yz
        x = self.softplus(a.reshape(-1, a.shape[-1]))
        out: dict = {}
        adapted = "s_adapted" in want or "g" in want
        for st in self.stages:
            role = st.get("bank")
            feeds = {"x": x}
            if role:
                out["h" if role == "main" else "g"] = x
                feeds["bank"] = bank[role]
            names = st["outputs"] if adapted else [n for n in st["outputs"] if n == "s"]
            res = dict(zip(names, st["session"].run(names, feeds))) if names else {}
            if role:
                out["s_main" if role == "main" else "s_adapted"] = res.get("s")
            if role == "main" and not adapted:
                break
            if "y" in res:
                x = self.softplus(res["y"]) if st["activation"] == "softplus" else res["y"]
        n = (x1 - x0) * self.grid.shape[1] * self.grid.shape[2]
        if out["h"].shape[0] != n:
            raise AgoInputError(self.planes_path, f"voxel stages give {out['h'].shape[0]} voxels for a slab of {n}")
        return out

    def _slabs(self, images: np.ndarray, ego2img: np.ndarray, want, bank: dict, rows: int):
        planes = self.plane_maps(images, ego2img)
        X, Y, Z = self.grid.shape
        row = Y * Z
        for x0 in range(0, X, rows):
            x1 = min(X, x0 + rows)
            yield x0 * row, x1 * row, self._slab(planes, x0, x1, bank, want)

    def chunks(self, images: np.ndarray, ego2img: np.ndarray) -> Iterator[tuple[int, int, np.ndarray, np.ndarray]]:
        for start, stop, out in self._slabs(images, ego2img, ("h", "g"), self.no_bank, self.slab):
            yield start, stop, out["h"], out["g"]

    def score_chunks(self, images, ego2img, folded, adapted: bool = True):
        """(start, stop, s_main (P', n), s_adapted (P', n) | None) per slab, from the stages' GEMMs.
        adapted=False skips the adapter's stages."""
        if folded.A_main_T.shape[1] != self.widths["main"] or folded.A_ad_T.shape[1] != self.widths["adapted"]:
            raise AgoInputError(self.planes_path, "folded bank widths do not match the voxel stages' hidden widths")
        bank = {"main": folded.A_main_T, "adapted": folded.A_ad_T}
        want = ("s_main", "s_adapted") if adapted else ("s_main",)
        # a large bank gets thinner slabs: each (P', n) score block stays within the heads' budget
        rows = self.rows_per_slab(min(self.slab_voxels, SCORE_BUDGET_BYTES // (4 * folded.num_rows)))
        for start, stop, out in self._slabs(images, ego2img, want, bank, rows):
            yield start, stop, out["s_main"], out["s_adapted"] if adapted else None

    def hidden(self, images: np.ndarray, ego2img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        parts = list(self.chunks(images, ego2img))
        return np.concatenate([p[2] for p in parts]), np.concatenate([p[3] for p in parts])


def open_encoder(bundle, int8: bool = False, threads: int | None = None, slab_voxels: int = SLAB_VOXELS) -> "SplitEncoder":
    """The encoder of a loaded `Bundle`; int8 picks the quantised graphs."""
    paths = bundle.encoder_paths(int8)
    planes_sha = bundle.meta["files"]["planes_int8" if int8 else "planes"].get("sha256")
    return SplitEncoder(paths["planes"], paths["voxels"], bundle.grid, threads, slab_voxels,
                        sha256={"planes": planes_sha})
