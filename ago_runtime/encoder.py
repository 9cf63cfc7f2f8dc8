"""The bundle's camera-to-voxel encoder in onnxruntime, delivered in chunks of voxels. No torch.

The bundle's encoder is split in two graphs (bundle format 2, ago_runtime/bundle.py):

- `planes.onnx` runs once per frame,
      images (1,6,3,H,W) + ego2img (1,6,4,4) -> plane_xy (D,X,Y), plane_xz (D,X,Z), plane_yz (D,Y,Z)
  (the three TPV planes already at the grid's resolution), and `voxels.onnx` runs per slab of x,
      plane_xy[:, x0:x1], plane_xz[:, x0:x1], plane_yz, bank_main (P',Dh), bank_adapted (P',Da)
        -> h (n,Dh), g (n,Da), s_main (P',n), s_adapted (P',n),   n = (x1-x0)*Y*Z,
  the voxels of that slab in C order over [x, y, z] (so slabs follow each other in the flat order);
  bank_* are the bank folded into the linear heads (ago_runtime.heads.FoldedHeads), fed at run time,
  so the heads' matrix product runs in onnxruntime's GEMM and any bank works without re-export.
  Memory then scales with the slab, not the grid: at 200x200x16 the monolithic graph held
  640 000 x (64 + 128 + 384 + ...) float32 intermediates at once (peak RSS ~4.4 GB); a slab of
  ~65 000 voxels holds a few hundred MB at most and stays in cache between the MLPs and the heads.

`open_encoder(bundle, int8=False, threads=None)` -> a SplitEncoder with
- `score_chunks(images, ego2img, folded, adapted=True)`: yields (start, stop, s_main, s_adapted), the
  bias-free class-major phrase scores (P', n) of each slab (s_adapted None when not asked for);
- `chunks(images, ego2img)`: yields (start, stop, h, g) over the flat voxel index, in order;
- `hidden(images, ego2img)`: the whole (N,Dh), (N,Da) (retrieval, parity checks).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterator

import numpy as np
import onnxruntime as ort

from .errors import AgoInputError
from .grid import Grid
from .heads import SCORE_BUDGET_BYTES

VOXEL_INPUTS = ["plane_xy", "plane_xz", "plane_yz", "bank_main", "bank_adapted"]
VOXEL_OUTPUTS = ["h", "g", "s_main", "s_adapted"]
SLAB_VOXELS = 65536   # target voxels per slab of the split encoder (whole x-rows of Y*Z voxels)


def session_options(threads: int | None = None) -> ort.SessionOptions:
    so = ort.SessionOptions()
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    if threads:
        so.intra_op_num_threads = int(threads)
    # onnxruntime's idle worker threads spin by default; between the slabs they then steal the cores
    # that numpy's heads need (measured on 2 cores: 2.6 s -> 2.2 s per 200x200x16 frame, and
    # 0.43 -> 0.37 s at 100x100x8, with spinning off). AGO_ORT_SPIN=1 turns spinning back on.
    if os.environ.get("AGO_ORT_SPIN", "0") != "1":
        so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.log_severity_level = 3
    return so


def load_session(path: Path, threads: int | None, inputs: list[str], outputs: list[str]) -> ort.InferenceSession:
    try:
        sess = ort.InferenceSession(str(path), session_options(threads), providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own Fail/InvalidProtobuf types
        raise AgoInputError(path, f"onnxruntime cannot load the graph ({str(e).splitlines()[0][:200]})") from None
    names_in = [i.name for i in sess.get_inputs()]
    names_out = [o.name for o in sess.get_outputs()]
    if names_in != inputs or names_out != outputs:
        raise AgoInputError(path, f"graph has inputs {names_in} and outputs {names_out}; expected {inputs} -> {outputs}")
    return sess


class SplitEncoder:
    """Format-2 bundles: planes once, then the per-voxel MLPs slab by slab."""

    PLANES = ["plane_xy", "plane_xz", "plane_yz"]

    def __init__(self, planes_path: Path, voxels_path: Path, grid: Grid, threads: int | None = None,
                 slab_voxels: int = SLAB_VOXELS):
        self.grid = grid
        self.planes_path, self.voxels_path = planes_path, voxels_path
        self.planes = load_session(planes_path, threads, ["images", "ego2img"], self.PLANES)
        self.voxels = load_session(voxels_path, threads, VOXEL_INPUTS, VOXEL_OUTPUTS)
        self.no_bank = {"bank_main": np.zeros((1, self.voxels.get_inputs()[3].shape[1]), np.float32),
                        "bank_adapted": np.zeros((1, self.voxels.get_inputs()[4].shape[1]), np.float32)}
        self.slab_voxels = slab_voxels
        self.slab = self.rows_per_slab(slab_voxels)

    def rows_per_slab(self, voxels: int) -> int:
        X, Y, Z = self.grid.shape
        return int(max(1, min(X, voxels // (Y * Z))))   # whole x-rows of Y*Z voxels

    def plane_maps(self, images: np.ndarray, ego2img: np.ndarray) -> list[np.ndarray]:
        xy, xz, yz = self.planes.run(self.PLANES, {"images": images, "ego2img": ego2img})
        X, Y, Z = self.grid.shape
        if xy.shape[1:] != (X, Y) or xz.shape[1:] != (X, Z) or yz.shape[1:] != (Y, Z):
            raise AgoInputError(self.planes_path, f"planes {xy.shape}, {xz.shape}, {yz.shape} do not fit the "
                                f"bundle grid {X}x{Y}x{Z}")
        return [np.ascontiguousarray(xy), np.ascontiguousarray(xz), np.ascontiguousarray(yz)]

    def _slabs(self, images: np.ndarray, ego2img: np.ndarray, outputs: list[str], bank: dict, rows: int):
        xy, xz, yz = self.plane_maps(images, ego2img)
        X, Y, Z = self.grid.shape
        row = Y * Z
        for x0 in range(0, X, rows):
            x1 = min(X, x0 + rows)
            res = self.voxels.run(outputs, {"plane_xy": np.ascontiguousarray(xy[:, x0:x1]),
                                            "plane_xz": np.ascontiguousarray(xz[:, x0:x1]), "plane_yz": yz, **bank})
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
    return SplitEncoder(paths["planes"], paths["voxels"], bundle.grid, threads)
