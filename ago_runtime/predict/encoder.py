"""The bundle's camera-to-voxel encoder, delivered in chunks of voxels (onnxruntime + numpy/OpenCV; no torch).

Bundle format 3 (ago_runtime/predict/bundle.py):

- `planes.onnx` runs once per frame,
      images (1,6,3,H,W) + ego2img (1,6,4,4) -> plane_xy (X,Y,Dh), plane_xz (X,Z,Dh), plane_yz (Y,Z,Dh)
  (the three TPV planes at the grid's resolution, already multiplied by the decoder's first linear
  layer, channels last);
- then per slab of x rows [x0, x1) (n = (x1-x0)*Y*Z voxels in C order over [x, y, z], so slabs
  follow each other in the flat order): a = plane_xy[x, y] + plane_xz[x, z] + plane_yz[y, z] (numpy
  broadcasting), x = softplus(a), and the voxel stages `voxels_<i>.onnx`: each gives y = x W^T + b (the
  next layer's pre-activation; the softplus between layers runs here in numpy + OpenCV, ~2x faster than
  onnxruntime's Log kernel). The stages before the bundle's "main" one give h (`hidden_slab`, every
  voxel); the stages from it on give g from h (`adapted_hidden`, for any subset of voxels: the runtime
  runs them only on the voxels the main branch calls occupied, ago_runtime/predict/predictor.py::
  classify_slabs).
- the bank scores s_main = bank_main h^T / s_adapted = bank_adapted g^T (P', n) run in the generic graph
  BANK_SCORES_GRAPH (`scores`; onnxruntime's GEMM, any width, any subset of voxels); bank_* are the bank
  folded into the linear heads (ago_runtime.predict.heads.FoldedHeads), so any bank works without
  re-export. The stages' own bank products (format 3 graphs hold them) are fed one zero row, unused.
  Memory scales with the slab, not the grid (SLAB_VOXELS voxels; docs/runtime.md has the slab sizes
  measured).

Sessions (ago_runtime.cache.open_session): the first session of a graph saves onnxruntime's optimised
graph in the cache (`~/.cache/ago/ort/`, or $AGO_CACHE_DIR/ort; keyed by the graph's sha256, the
onnxruntime version and the CPU), and later sessions load that file with graph optimisation off
(measured 0.26 s -> ~0.05 s to open planes.onnx). Each session then runs once on dummy inputs of the real
shapes (`warm_up`), so the first frame of a process runs at the steady-state speed.

`open_encoder(bundle, int8=False, threads=None)` -> a SplitEncoder with
- `plane_maps(images, ego2img)`, `slabs(rows)`, `hidden_slab(planes, x0, x1)`, `adapted_hidden(h)`,
  `scores(bank, x)`: the parts classify_slabs puts together;
- `score_chunks(images, ego2img, folded, adapted=True)`: yields (start, stop, s_main, s_adapted), the
  bias-free class-major phrase scores (P', n) of each slab, both branches on every voxel (parity checks);
- `chunks(images, ego2img)`: yields (start, stop, h, g) over the flat voxel index, in order;
- `hidden(images, ego2img)`: the whole (N,Dh), (N,Da) (retrieval, parity checks).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np
import onnxruntime as ort

from ago_runtime.cache import ENV_NO_ORT_CACHE, open_session, optimized_cache_path, session_options  # noqa: F401
from ago_runtime.errors import AgoInputError
from ago_runtime.geometry.grid import Grid
from ago_runtime.predict.heads import SCORE_BUDGET_BYTES

PLANE_OUTPUTS = ["plane_xy", "plane_xz", "plane_yz"]
SLAB_VOXELS = 4096    # target voxels per slab (whole x-rows of Y*Z voxels)
# s = bank x^T for any x (n, d) and bank (P', d): the folded bank's scores of any subset of voxels
# (written by ago_export.graphs.write_bank_scores; no weights)
BANK_SCORES_GRAPH = Path(__file__).resolve().parents[1] / "assets" / "graphs" / "bank_scores.onnx"


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
    optionally "sha256"). Per slab: a = plane_xy + plane_xz + plane_yz (numpy), x = softplus(a), then the
    decoder's stages up to h (`hidden_slab`); the adapter's stages from h to g (`adapted_hidden`), on all
    of the slab's voxels or on a subset of them; each stage's graph gives y = x W^T + b (onnxruntime) and
    the softplus of y runs here (numpy + OpenCV). The bank products s = bank x^T run in the generic graph
    BANK_SCORES_GRAPH (`scores`), on whichever voxels are asked for; the stages' own bank products (format
    3 bundles hold them) are fed one zero row and not used. sha256: {"planes": hex} for the
    optimised-graph cache (the stages carry their own); warm_up: run the graphs once on dummy inputs when
    opened."""

    PLANES = PLANE_OUTPUTS

    def __init__(self, planes_path: Path, stages: list[dict], grid: Grid, threads: int | None = None,
                 slab_voxels: int = SLAB_VOXELS, sha256: dict | None = None, warm_up: bool = True):
        self.grid = grid
        self.planes_path = planes_path
        self.planes = load_session(planes_path, threads, ["images", "ego2img"], self.PLANES,
                                   (sha256 or {}).get("planes"))
        self.bank_session = load_session(BANK_SCORES_GRAPH, threads, ["x", "bank"], ["s"])
        self.stages = []
        for st in stages:
            ins = ["x"] + (["bank"] if st.get("bank") else [])
            outs = (["y"] if st.get("linear") else []) + (["s"] if st.get("bank") else [])
            self.stages.append({**st, "session": load_session(Path(st["path"]), threads, ins, outs, st.get("sha256")),
                                "outputs": outs})
        roles = [st.get("bank") for st in self.stages]
        if roles.count("main") != 1 or roles[-1] != "adapted" or roles.count("adapted") != 1:
            raise AgoInputError(planes_path.parent, f"voxel stages {roles} are not decoder ... h ... g; re-export")
        self.main_index = roles.index("main")      # stages before it: decoder (all voxels); from it: adapter
        self.hidden_dim = int(self.stages[0]["input_dim"])
        self.widths = {st["bank"]: int(st["input_dim"]) for st in self.stages if st.get("bank")}
        # the stages' own bank input: one zero row (their bank product is not used, see the class doc)
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

    def slab_rows(self, folded=None) -> int:
        """x rows per slab; a large bank gets thinner slabs, so that each (P', n) score block stays within
        the heads' budget."""
        if folded is None:
            return self.slab
        return self.rows_per_slab(min(self.slab_voxels, SCORE_BUDGET_BYTES // (4 * folded.num_rows)))

    def slabs(self, rows: int) -> Iterator[tuple[int, int]]:
        """(x0, x1) of each slab of `rows` x rows; its voxels are [x0 * Y * Z, x1 * Y * Z) in the flat order."""
        X = self.grid.shape[0]
        for x0 in range(0, X, rows):
            yield x0, min(X, x0 + rows)

    def warm_up(self, phrases: int = 64) -> None:
        """One run of each graph on dummy inputs of the real shapes (onnxruntime's first run of a
        session allocates its buffers and is ~2x slower than later runs)."""
        shape = [d if isinstance(d, int) else 1 for d in self.planes.get_inputs()[0].shape]
        ego2img = np.tile(np.eye(4, dtype=np.float32), (1, shape[1], 1, 1))
        ego2img[..., 2, 3] = 10.0                     # points in front of every camera: real sampling work
        planes = self.planes.run(self.PLANES, {"images": np.zeros(shape, np.float32), "ego2img": ego2img})
        rows = min(self.slab, planes[0].shape[0])
        h = self.hidden_slab(planes, 0, rows)
        self.scores(np.zeros((phrases, h.shape[1]), np.float32), h)
        g = self.adapted_hidden(h)
        self.scores(np.zeros((phrases, g.shape[1]), np.float32), g)

    def plane_maps(self, images: np.ndarray, ego2img: np.ndarray) -> list[np.ndarray]:
        xy, xz, yz = self.planes.run(self.PLANES, {"images": images, "ego2img": ego2img})
        X, Y, Z = self.grid.shape
        D = self.hidden_dim
        if xy.shape != (X, Y, D) or xz.shape != (X, Z, D) or yz.shape != (Y, Z, D):
            raise AgoInputError(self.planes_path, f"planes {xy.shape}, {xz.shape}, {yz.shape} do not fit the "
                                f"bundle grid {X}x{Y}x{Z} and width {D}")
        return [np.ascontiguousarray(xy), np.ascontiguousarray(xz), np.ascontiguousarray(yz)]

    def _linear(self, st: dict, x: np.ndarray) -> np.ndarray:
        """One stage's y = x W^T + b, then its activation."""
        feeds = {"x": x}
        if st.get("bank"):
            feeds["bank"] = self.no_bank[st["bank"]]
        (y,) = st["session"].run(["y"], feeds)
        return self.softplus(y) if st["activation"] == "softplus" else y

    def hidden_slab(self, planes, x0: int, x1: int) -> np.ndarray:
        """h (n, Dh) of the slab of x rows [x0, x1) (n = (x1-x0)*Y*Z voxels, C order over [x, y, z])."""
        xy, xz, yz = planes
        a = xy[x0:x1, :, None, :] + xz[x0:x1, None, :, :]
        a += yz
        x = self.softplus(a.reshape(-1, a.shape[-1]))
        for st in self.stages[:self.main_index]:
            x = self._linear(st, x)
        n = (x1 - x0) * self.grid.shape[1] * self.grid.shape[2]
        if x.shape != (n, self.widths["main"]):
            raise AgoInputError(self.planes_path, f"voxel stages give h {x.shape} for a slab of {n} voxels")
        return x

    def adapted_hidden(self, h: np.ndarray) -> np.ndarray:
        """g (m, Da) of any m voxels from their h (m, Dh): the adapter's stages (decoder_out folded in)."""
        x = h
        for st in self.stages[self.main_index:]:
            if st.get("linear"):
                x = self._linear(st, x)
        return x

    def scores(self, bank: np.ndarray, x: np.ndarray) -> np.ndarray:
        """bank (P', d) x (m, d) -> s = bank x^T (P', m), class-major, in onnxruntime's GEMM."""
        if x.shape[0] == 0:
            return np.zeros((bank.shape[0], 0), np.float32)
        (s,) = self.bank_session.run(["s"], {"x": x, "bank": bank})
        return s

    def check_folded(self, folded) -> None:
        if folded.A_main_T.shape[1] != self.widths["main"] or folded.A_ad_T.shape[1] != self.widths["adapted"]:
            raise AgoInputError(self.planes_path, "folded bank widths do not match the voxel stages' hidden widths")

    def chunks(self, images: np.ndarray, ego2img: np.ndarray) -> Iterator[tuple[int, int, np.ndarray, np.ndarray]]:
        """(start, stop, h, g) per slab over the flat voxel index, in order; g of every voxel."""
        planes = self.plane_maps(images, ego2img)
        row = self.grid.shape[1] * self.grid.shape[2]
        for x0, x1 in self.slabs(self.slab):
            h = self.hidden_slab(planes, x0, x1)
            yield x0 * row, x1 * row, h, self.adapted_hidden(h)

    def score_chunks(self, images, ego2img, folded, adapted: bool = True):
        """(start, stop, s_main (P', n), s_adapted (P', n) | None) per slab, both branches on EVERY voxel
        (parity checks; `Predictor.predict_arrays` runs the adapted branch on the occupied voxels only).
        adapted=False skips the adapter's stages."""
        self.check_folded(folded)
        planes = self.plane_maps(images, ego2img)
        row = self.grid.shape[1] * self.grid.shape[2]
        for x0, x1 in self.slabs(self.slab_rows(folded)):
            h = self.hidden_slab(planes, x0, x1)
            s_ad = self.scores(folded.A_ad_T, self.adapted_hidden(h)) if adapted else None
            yield x0 * row, x1 * row, self.scores(folded.A_main_T, h), s_ad

    def hidden(self, images: np.ndarray, ego2img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        parts = list(self.chunks(images, ego2img))
        return np.concatenate([p[2] for p in parts]), np.concatenate([p[3] for p in parts])


def open_encoder(bundle, int8: bool = False, threads: int | None = None, slab_voxels: int = SLAB_VOXELS,
                 warm_up: bool = True) -> "SplitEncoder":
    """The encoder of a loaded `Bundle`; int8 picks the quantised graphs; warm_up: see SplitEncoder."""
    paths = bundle.encoder_paths(int8)
    planes_sha = bundle.meta["files"]["planes_int8" if int8 else "planes"].get("sha256")
    return SplitEncoder(paths["planes"], paths["voxels"], bundle.grid, threads, slab_voxels,
                        sha256={"planes": planes_sha}, warm_up=warm_up)
