"""The bundle's camera-to-voxel encoder, run slab by slab (onnxruntime + numpy/OpenCV; no torch).

Bundle format 5 (ago_runtime/predict/contract.py):

- `planes.onnx` runs once per frame,
      images (1,V,3,H,W) + ego2img (1,V,4,4) -> plane_xy (X,Y,Dh), plane_xz (X,Z,Dh), plane_yz (Y,Z,Dh)
  (the three TPV planes at the grid's resolution, already multiplied by the decoder's first linear
  layer, channels last);
- per slab of x rows [x0, x1) (n = (x1-x0)*Y*Z voxels in C order over [x, y, z], so slabs follow each
  other in the flat order): a = plane_xy[x, y] + plane_xz[x, z] + plane_yz[y, z], x = softplus(a), computed
  as x = log(1 + E_xy[x, y] * E_xz[x, z] * E_yz[y, z]) from the planes' exponentials, taken once a frame
  (`PlaneMaps`; e^a is the product of the three, so the per-voxel work is two products, an add and a log
  instead of two sums, a clamp, an exp, an add, a log and a max); a frame whose planes could overflow or
  underflow that product takes the direct form, softplus(a) (`softplus_`). Then the voxel stages
  `voxels_<i>.onnx`, each y = x W^T + b (the softplus between layers runs here in numpy + OpenCV). The
  decoder's stages (branch "main") give h (`hidden_slab`, every voxel); the adapter's stages (branch
  "adapted") give g from h (`adapted_hidden`, for any subset of voxels).
- the folded bank's products s = A x^T run in ago_runtime.predict.bank_product (`scores`).

The slab loop that puts these together is ago_runtime.predict.classifier.VoxelClassifier.

Sessions (ago_runtime.cache.open_session): the first session of a graph saves onnxruntime's optimised
graph in the cache, later sessions load it with graph optimisation off. Each session then runs once on
dummy inputs of the real shapes (`warm_up`), so the first frame runs at the steady-state speed.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np
import onnxruntime as ort

from ago_runtime.cache import open_session
from ago_runtime.providers import Device, Precision, check_int8, stage_target
from ago_runtime.errors import AgoInputError
from ago_runtime.geometry.grid import Grid
from ago_runtime.predict.bank_product import BankProduct
from ago_runtime.predict.contract import (PLANES_INPUTS, PLANES_OUTPUTS, STAGE_INPUT, STAGE_OUTPUT, VoxelStageSpec,
                                          check_graph, planes_signature, planes_width, stage_signature)
from ago_runtime.predict.decision import Branch
from ago_runtime.predict.heads import SCORE_BUDGET_BYTES

INT8 = "int8"         # the variant `--int8` picks (bundle.json "variants")
SLAB_BYTES = 7 << 20   # a slab's widest per-voxel array (n voxels x its width, float32) stays near this size
                       # (whole x-rows of Y*Z voxels; benchmarks/results/slab_size.md)


@dataclass
class StageGraph:
    """One voxel stage of a bundle folder: its contract entry, its file and the file's sha256."""

    spec: VoxelStageSpec
    path: Path
    sha256: str | None = None


def load_session(path: Path, threads: int | None, signature, what: str, sha256: str | None = None,
                 device: Device = Device.CPU, precision: Precision = Precision.FP32) -> ort.InferenceSession:
    """The graph's session, its inputs and outputs checked against the contract's `signature` (check_graph)
    before it runs."""
    sess = open_session(path, threads, sha256, device, precision)
    check_graph(sess, signature, path, what)
    return sess


def row_view(a: np.ndarray) -> np.ndarray | None:
    """a as one row (1, a.size) sharing its memory, for OpenCV's element-wise functions in place; None where that is
    not safe: a not C-contiguous (reshape would copy), or 4 elements or fewer (OpenCV's bindings may read such an
    array as a scalar and then leave dst unwritten). One row: a 3-D array would be read as an image whose last axis
    is its channels, and a scalar operand then applies to the first channel only."""
    return a.reshape(1, -1) if a.flags.c_contiguous and a.size > 4 else None


def softplus_(x: np.ndarray, tmp: np.ndarray) -> np.ndarray:
    """x <- softplus(x) = max(log(1 + exp(min(x, 20))), x), in place; tmp: scratch of x's shape.

    The same function as torch's softplus to float32 rounding (softplus(x) > x always, and for x > 20
    log(1 + e^x) = x to float32; absolute error <= 1e-6, tests/test_runtime.py). OpenCV's vectorised
    cv2.exp / cv2.log are faster than numpy's and than onnxruntime's Log kernel here, and its min / add / max
    than numpy's; they run on `row_view`s. A NaN stays NaN."""
    x2, t2 = row_view(x), row_view(tmp)
    if x2 is None or t2 is None:
        np.minimum(x, 20.0, out=tmp)
        np.exp(tmp, out=tmp)
        tmp += 1.0
        np.log(tmp, out=tmp)
        np.maximum(tmp, x, out=x)
        return x
    cv2.min(x2, 20.0, dst=t2)
    cv2.exp(t2, t2)
    cv2.add(t2, 1.0, dst=t2)
    cv2.log(t2, t2)
    cv2.max(t2, x2, dst=x2)        # its first operand NaN (x NaN) gives NaN
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


EXP_RANGE = 80.0   # |a| bound under which e^a and every partial product of the three exponentials is a normal float32


class PlaneMaps(tuple):
    """A frame's three planes (plane_xy, plane_xz, plane_yz), a tuple, with `exps`: their exponentials
    (float32, same shapes), or None when the product form of the plane sum's softplus is not safe on this
    frame (some a could leave [-EXP_RANGE, EXP_RANGE], or a plane holds a NaN or an infinity)."""

    exps: tuple[np.ndarray, np.ndarray, np.ndarray] | None

    def __new__(cls, planes):
        self = super().__new__(cls, planes)
        high = sum(float(np.maximum(0.0, p.max())) for p in self)    # np.maximum: a NaN stays NaN,
        low = sum(float(np.minimum(0.0, p.min())) for p in self)     # and the test below fails on it
        safe = high <= EXP_RANGE and low >= -EXP_RANGE
        self.exps = tuple(cv2.exp(p.reshape(-1, p.shape[-1])).reshape(p.shape) for p in self) if safe else None
        return self


def softplus_of_sum_(exps, x0: int, x1: int, ys: slice, out: np.ndarray) -> None:
    """out (x1-x0, len(ys), Z, D) <- softplus(plane_xy[x, y] + plane_xz[x, z] + plane_yz[y, z]) for x in [x0, x1),
    y in ys, as log(1 + E_xy E_xz E_yz) from the planes' exponentials `exps` (PlaneMaps.exps); out is
    C-contiguous."""
    e_xy, e_xz, e_yz = exps
    for i, x in enumerate(range(x0, x1)):     # one x row at a time: its (Y, Z, D) block stays in the core's cache
        row = out[i]
        np.multiply(e_yz[ys], e_xz[x, None], out=row)     # E_xz[x] repeats over y: numpy runs it as long rows
        row *= e_xy[x, ys, None, :]                        # E_xy[x] repeats over z: rows of D
        flat = row_view(row)
        if flat is None:
            row += 1.0
            np.log(row, out=row)
        else:
            cv2.add(flat, 1.0, dst=flat)
            cv2.log(flat, flat)


class SplitEncoder:
    """Planes once per frame, then the per-voxel MLP slab by slab (see the module doc).

    stages: the bundle's voxel stages (StageGraph), decoder stages first; hidden_dim, adapted_dim: the widths
    of h and g. slab_voxels: voxels per slab (None: `slab_rows` sizes slabs from SLAB_BYTES). sha256: of
    planes.onnx, for the optimised-graph cache; warm_up: run the graphs once on dummy inputs when opened;
    image_input: (cameras, height, width) of planes.onnx's images input, when known. Every graph's inputs and
    outputs are checked against the contract's signatures when it is opened."""

    PLANES = list(PLANES_OUTPUTS)

    def __init__(self, planes_path: Path, stages: list[StageGraph], grid: Grid, hidden_dim: int, adapted_dim: int,
                 threads: int | None = None, slab_voxels: int | None = None, sha256: str | None = None,
                 warm_up: bool = True, device: Device = Device.CPU, precision: Precision = Precision.FP32,
                 image_input: tuple[int, int, int] | None = None):
        self.grid = grid
        self.planes_path = planes_path
        self.device = device
        signature = planes_signature(*(image_input or (None, None, None)), grid.shape,
                                     planes_width([st.spec for st in stages], hidden_dim))
        self.planes = load_session(planes_path, threads, signature, "planes", sha256, device, precision)
        self.bank_product = BankProduct(threads)   # the bank products stay on the CPU (docs/runtime.md, Devices)
        self.threads = max(1, int(threads or os.cpu_count() or 1))
        stage_device, stage_precision = stage_target(device, precision)
        self.slab_pool = (ThreadPoolExecutor(self.threads, thread_name_prefix="ago-slab")
                          if self.threads > 1 and stage_device is Device.CPU else None)
        self._local = threading.local()     # in a slab worker: .single = True, .bank_product (one thread)
        self.sessions = {Branch.MAIN: [], Branch.ADAPTED: []}
        self.widths = {Branch.MAIN: int(hidden_dim), Branch.ADAPTED: int(adapted_dim)}
        widest = dict(self.widths)
        for i, st in enumerate(stages):
            sess = load_session(Path(st.path), threads, stage_signature(st.spec), f"voxel_stages[{i}]", st.sha256,
                                stage_device, stage_precision)
            self.sessions[st.spec.branch].append((sess, st.spec.activation == "softplus"))
            widest[st.spec.branch] = max(widest[st.spec.branch], int(st.spec.output_dim))
        # the widest per-voxel array of a slab: the main branch's, and the adapted branch's where it runs on every voxel
        self.widest = (widest[Branch.MAIN], max(widest.values()))
        self.softplus = Softplus(threads)
        self.slab_voxels = slab_voxels
        self.slab = self.slab_rows(every_voxel_adapted=True)
        if warm_up:
            self.warm_up()

    @property
    def hidden_dim(self) -> int:
        return self.widths[Branch.MAIN]

    def rows_per_slab(self, voxels: int) -> int:
        X, Y, Z = self.grid.shape
        return int(max(1, min(X, voxels // (Y * Z))))   # whole x-rows of Y*Z voxels

    def slab_rows(self, num_rows: int | None = None, every_voxel_adapted: bool = False) -> int:
        """x rows per slab: the slab_voxels given when opened, else as many voxels as keep the slab's widest
        per-voxel array near SLAB_BYTES (the adapted branch's widths count when it runs on every voxel: volumes,
        `hidden`); a bank of many score rows (num_rows = P + 1) gets thinner slabs, so that each (P+1, n) score
        block stays within the heads' budget."""
        voxels = self.slab_voxels or SLAB_BYTES // (4 * self.widest[1 if every_voxel_adapted else 0])
        if num_rows is not None:
            voxels = min(voxels, SCORE_BUDGET_BYTES // (4 * num_rows))
        return self.rows_per_slab(voxels)

    def map_slabs(self, fn, slabs: list[tuple[int, int]]) -> list:
        """[fn(x0, x1) for each slab], in order. With several threads on the CPU the slabs run in parallel, one
        slab per thread at a time, and everything a slab worker calls here (first activation, softplus, bank
        products) runs on that worker's one thread: whole slabs in parallel beat splitting each small slab's
        arrays over the threads (benchmarks/results/infer_speed.md). fn must write only its own slab's outputs."""
        if self.slab_pool is None or len(slabs) < 2:
            return [fn(x0, x1) for x0, x1 in slabs]

        def run(slab):
            self._local.single = True
            return fn(*slab)

        return list(self.slab_pool.map(run, slabs))

    def _single(self) -> bool:
        """Whether this thread is a slab worker (map_slabs): its work then stays on it."""
        return getattr(self._local, "single", False)

    def slabs(self, rows: int) -> Iterator[tuple[int, int]]:
        """(x0, x1) of each slab of `rows` x rows; its voxels are [x0 * Y * Z, x1 * Y * Z) in the flat order."""
        X = self.grid.shape[0]
        for x0 in range(0, X, rows):
            yield x0, min(X, x0 + rows)

    def warm_up(self, phrases: int = 64) -> None:
        """One run of each graph on dummy inputs of the real shapes (onnxruntime's first run of a
        session allocates its buffers and is slower than later runs)."""
        shape = [d if isinstance(d, int) else 1 for d in self.planes.get_inputs()[0].shape]
        ego2img = np.tile(np.eye(4, dtype=np.float32), (1, shape[1], 1, 1))
        ego2img[..., 2, 3] = 10.0                     # points in front of every camera: real sampling work
        planes = PlaneMaps(self.planes.run(self.PLANES, dict(zip(PLANES_INPUTS, (np.zeros(shape, np.float32),
                                                                            ego2img)))))
        rows = min(self.slab, planes[0].shape[0])
        h = self.hidden_slab(planes, 0, rows)
        self.scores(np.zeros((phrases, h.shape[1]), np.float32), h)
        g = self.adapted_hidden(h)
        self.scores(np.zeros((phrases, g.shape[1]), np.float32), g)

    def plane_maps(self, images: np.ndarray, ego2img: np.ndarray) -> list[np.ndarray]:
        xy, xz, yz = self.planes.run(self.PLANES, dict(zip(PLANES_INPUTS, (images, ego2img))))
        X, Y, Z = self.grid.shape
        D = xy.shape[-1]
        if xy.shape != (X, Y, D) or xz.shape != (X, Z, D) or yz.shape != (Y, Z, D):
            raise AgoInputError(self.planes_path, f"planes {xy.shape}, {xz.shape}, {yz.shape} do not fit the "
                                f"bundle grid {X}x{Y}x{Z}")
        return PlaneMaps([np.ascontiguousarray(xy), np.ascontiguousarray(xz), np.ascontiguousarray(yz)])

    def _run(self, branch: Branch, x: np.ndarray) -> np.ndarray:
        """The branch's stages on x: each y = x W^T + b (onnxruntime), then softplus when the stage has it."""
        for sess, softplus in self.sessions[branch]:
            (x,) = sess.run([STAGE_OUTPUT], {STAGE_INPUT: x})
            if softplus:
                x = softplus_(x, np.empty_like(x)) if self._single() else self.softplus(x)
        return x

    def hidden_slab(self, planes, x0: int, x1: int) -> np.ndarray:
        """h (n, Dh) of the slab of x rows [x0, x1) (n = (x1-x0)*Y*Z voxels, C order over [x, y, z]).
        planes: `plane_maps`'s PlaneMaps (the product form when its exps are there), or any three arrays
        (the direct form)."""
        h = self._run(Branch.MAIN, self.first_activation(planes, x0, x1))
        n = (x1 - x0) * self.grid.shape[1] * self.grid.shape[2]
        if h.shape != (n, self.hidden_dim):
            raise AgoInputError(self.planes_path, f"planes and decoder stages give h {h.shape} for a slab of {n} "
                                f"voxels; bundle.json says width {self.hidden_dim}")
        return h

    def first_activation(self, planes, x0: int, x1: int) -> np.ndarray:
        """softplus(a) (n, Dh) of the slab's plane sums a (see the module doc), split over the threads."""
        xy, xz, yz = planes
        exps = getattr(planes, "exps", None)
        single = self._single()
        if exps is None:                                   # the direct form
            a = xy[x0:x1, :, None, :] + xz[x0:x1, None, :, :]
            a += yz
            a = a.reshape(-1, a.shape[-1])
            return softplus_(a, np.empty_like(a)) if single else self.softplus(a)
        Y, Z, D = yz.shape
        out = np.empty((x1 - x0, Y, Z, D), np.float32)
        pool = None if single else self.softplus.pool
        if pool is None:
            softplus_of_sum_(exps, x0, x1, slice(None), out)
        elif x1 - x0 >= 2:                                 # whole x rows per thread (contiguous parts)
            cuts = np.linspace(x0, x1, min(self.softplus.threads, x1 - x0) + 1).astype(int)
            list(pool.map(lambda ab: softplus_of_sum_(exps, ab[0], ab[1], slice(None), out[ab[0] - x0:ab[1] - x0]),
                          zip(cuts[:-1], cuts[1:])))
        else:                                              # one x row: split it by y
            cuts = np.linspace(0, Y, min(self.softplus.threads, Y) + 1).astype(int)
            list(pool.map(lambda ab: softplus_of_sum_(exps, x0, x1, slice(ab[0], ab[1]), out[:, ab[0]:ab[1]]),
                          zip(cuts[:-1], cuts[1:])))
        return out.reshape(-1, D)

    def adapted_hidden(self, h: np.ndarray) -> np.ndarray:
        """g (m, Da) of any m voxels from their h (m, Dh): the adapter's stages (decoder_out folded in)."""
        return self._run(Branch.ADAPTED, h)

    def scores(self, bank: np.ndarray, x: np.ndarray) -> np.ndarray:
        """bank (P', d) x (m, d) -> s = bank x^T (P', m), class-major (in a slab worker on its one thread)."""
        if not self._single():
            return self.bank_product(bank, x)
        if not hasattr(self._local, "bank_product"):
            self._local.bank_product = BankProduct(1)
        return self._local.bank_product(bank, x)

    def check_folded(self, folded) -> None:
        if any(folded.width(branch) != self.widths[branch] for branch in Branch):
            raise AgoInputError(self.planes_path, "folded bank widths do not match the voxel stages' hidden widths")

    def chunks(self, images: np.ndarray, ego2img: np.ndarray) -> Iterator[tuple[int, int, np.ndarray, np.ndarray]]:
        """(start, stop, h, g) per slab over the flat voxel index, in order; g of every voxel."""
        planes = self.plane_maps(images, ego2img)
        row = self.grid.shape[1] * self.grid.shape[2]
        for x0, x1 in self.slabs(self.slab):
            h = self.hidden_slab(planes, x0, x1)
            yield x0 * row, x1 * row, h, self.adapted_hidden(h)

    def hidden(self, images: np.ndarray, ego2img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The whole grid's h (N, Dh), g (N, Da) (retrieval, parity checks)."""
        parts = list(self.chunks(images, ego2img))
        return np.concatenate([p[2] for p in parts]), np.concatenate([p[3] for p in parts])


def open_encoder(bundle, int8: bool = False, threads: int | None = None, slab_voxels: int | None = None,
                 warm_up: bool = True, device: Device = Device.CPU,
                 precision: Precision = Precision.FP32) -> "SplitEncoder":
    """The encoder of a loaded `Bundle`; int8 picks the bundle's "int8" variant (contract "variants"; on a CPU:
    `providers.check_int8`); device/precision: the execution provider of the graphs (ago_runtime/providers.py;
    the voxel stages run where `providers.stage_target` says); warm_up: see SplitEncoder."""
    if int8:
        check_int8(device, precision)
    planes, stages = bundle.encoder_graphs(INT8 if int8 else None)
    c = bundle.contract
    return SplitEncoder(planes.path, stages, bundle.grid, c.hidden_dim, c.adapted_dim, threads, slab_voxels,
                        sha256=planes.sha256, warm_up=warm_up, device=device, precision=precision,
                        image_input=(len(c.rig.cameras), bundle.preprocess.height, bundle.preprocess.width))
