"""`Predictor`: a bundle + camera images + their rig + a prompt bank -> an occupancy prediction. No torch.

    p = Predictor("bundle_dir")                       # or Predictor(Bundle.load(...))
    pred = p.predict(images, rig, bank)               # one frame; images: dict camera -> (H, W, 3) uint8 RGB
    pred.semantics                                    # (X, Y, Z) uint8 bank class index, free = K
    for frame, pred in p.predict_many(open_frames("DATAROOT")):   # many frames (ago_runtime.predict.frames)
        ...                                           # runs while the next frames are read and predicted

Steps: Preprocess (resize to the model's input size, ImageNet normalisation; intrinsics scaled to
match) -> the ONNX encoder (onnxruntime; ago_runtime/predict/encoder.py: the TPV planes once, then the
per-voxel MLPs slab by slab) -> the slab loop (ago_runtime.predict.classifier.VoxelClassifier): the bank
folded into the linear heads (ago_runtime.predict.heads.FoldedHeads, data), class scores, and the voxel decision
(ago_runtime.predict.decision: free, identifier, entropy, label); every prediction, `predict_hidden` included,
goes through that slab loop. The whole grid's (N, Dh) and (N, Da)
features never exist at once, so memory follows the slab, not the grid.

Swapping the bank (a new prompt file) changes the classes with no retraining and no re-export:
folding a bank costs one (P+1, C) x (C, Dh) product, cached per bank.

The user's entry points are `predict` and `predict_many`; `prepare`, `encode_arrays`, `predict_arrays`,
`predict_hidden`, `fold` and `fold_with_reference` are the steps, for parity checks, retrieval and benchmarks.
"""

from __future__ import annotations

import hashlib
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator, Sized

import numpy as np

from ago_runtime.classes import OCC3D_NUSCENES, ClassTable
from ago_runtime.errors import AgoInputError
from ago_runtime.formats.calibration import fit_rig_to_images
from ago_runtime.geometry.camera import Rig
from ago_runtime.geometry.grid import Grid
from ago_runtime.predict.bundle import Bundle
from ago_runtime.predict.classifier import FrameFeatures, VoxelClassifier
from ago_runtime.predict.contract import check_bank_fits
from ago_runtime.predict.decision import Identifier
from ago_runtime.predict.encoder import open_encoder
from ago_runtime.predict.frames import InputFrame
from ago_runtime.predict.heads import FoldedHeads
from ago_runtime.providers import Device, Precision, check_device, parse_device, parse_precision
from ago_runtime.vocab.bank import check_class_count

__all__ = ["Predictor", "Prediction", "FrameFeatures", "prepare_inputs", "table_id_lookup", "UNEXPLAINED_THRESHOLD",
           "unexplained_mask"]


# A voxel is flagged as an unexplained obstacle when it is occupied (p_occ > 0.5) and its score
# 1 - (best prompted-class probability) exceeds this (decision.decide with volumes, against the
# prompted + reference classes: fold_with_reference): no branch gives any prompted class more than half
# of its probability. Measured in benchmarks/unexplained_obstacles.py (AUROC, share flagged at 0.5); a prompt
# file whose classes explain their voxels weakly needs a higher one (`ago infer --unexplained-threshold`, chosen
# on labelled frames by `ago choose-threshold`, ago_runtime/predict/threshold.py).
UNEXPLAINED_THRESHOLD = 0.5


def unexplained_mask(unexplained: np.ndarray, occupancy: np.ndarray, threshold: float) -> np.ndarray:
    """The unexplained-obstacle mask's rule: occupied (p_occ > 0.5) and score above `threshold` (any shapes)."""
    return (occupancy > 0.5) & (unexplained > threshold)


@dataclass
class Prediction:
    """One frame's prediction over the grid (axis order [x, y, z])."""

    semantics: np.ndarray          # (X, Y, Z) uint8: bank class index 0..K-1, free = free_index (= K)
    class_names: list[str]         # K names, bank order
    free_index: int
    entropy: np.ndarray            # (X, Y, Z) float32, nats, of the chosen branch
    confidence: np.ndarray         # (X, Y, Z) float32, max softmax probability of the chosen branch
    branch: np.ndarray             # (X, Y, Z) uint8: 0 = original (main) branch, 1 = adapted branch
    identifier: Identifier
    grid: Grid
    table_ids: np.ndarray | None = None   # (X, Y, Z) uint8 in `class_table`'s dense order (Occ3D-nuScenes: its ids,
                                          # free = 17) when every class is one class of the table
    class_table: ClassTable = OCC3D_NUSCENES   # the bank's class table (ago_runtime.classes)
    timings: dict = field(default_factory=dict)   # seconds: preprocess, encoder, heads
    unexplained: np.ndarray | None = None   # (X, Y, Z) float32 unexplained-obstacle score (volumes=True)
    occupancy: np.ndarray | None = None     # (X, Y, Z) float32 p_occ against prompted + reference classes
    unexplained_threshold: float = UNEXPLAINED_THRESHOLD   # the mask's score threshold

    @property
    def unexplained_mask(self) -> np.ndarray | None:
        """(X, Y, Z) bool: occupied (p_occ > 0.5) and no prompt explains it (score > unexplained_threshold)."""
        if self.unexplained is None:
            return None
        return unexplained_mask(self.unexplained, self.occupancy, self.unexplained_threshold)

    @property
    def label_names(self) -> list[str]:
        """Names of the values in `semantics`: classes then "free"."""
        return list(self.class_names) + ["free"]

    def output_arrays(self, volumes: bool = False) -> dict[str, np.ndarray]:
        """The arrays of an Occ3D-format prediction file (see docs/runtime.md)."""
        if self.table_ids is not None:
            table = self.class_table
            out = {"semantics": self.table_ids, "class_names": np.array(table.label_names, dtype=str),
                   "free_index": np.array(table.free_index, np.int64), "bank_semantics": self.semantics,
                   "bank_class_names": np.array(self.label_names, dtype=str)}
            if table != OCC3D_NUSCENES:   # (nuScenes files stay as they were)
                out["class_table"] = np.array(table.name)
                out["class_colors"] = table.dense_colors()   # RGB per dense label: `ago show` draws in them
        else:
            out = {"semantics": self.semantics, "class_names": np.array(self.label_names, dtype=str),
                   "free_index": np.array(self.free_index, np.int64)}
        if volumes:
            out.update(entropy=self.entropy, confidence=self.confidence, branch=self.branch)
            if self.unexplained is not None:
                out.update(unexplained=self.unexplained, occupancy=self.occupancy,
                           unexplained_mask=self.unexplained_mask.astype(np.uint8),
                           unexplained_threshold=np.array(self.unexplained_threshold, np.float32))
        return out


def table_id_lookup(bank) -> np.ndarray | None:
    """(K+1,) uint8 bank index -> the class's index in the bank's class table, dense order (`ClassTable.label_names`:
    the table's classes, then free; for Occ3D-nuScenes the Occ3D ids, free = 17; for Occ3D-Waymo its ids 0..14,
    free = 15 where the files store 23) when every bank class is exactly one class of the table."""
    table = bank.class_table
    dense = table.dense_lut()
    ids = []
    for ids_k in bank.occ3d_ids:
        if len(ids_k) != 1 or dense[int(ids_k[0])] < 0:
            return None
        ids.append(int(dense[int(ids_k[0])]))
    return np.array(ids + [table.free_index], dtype=np.uint8)


def bank_key(bank) -> str:
    h = hashlib.sha256(np.ascontiguousarray(bank.embeddings).tobytes())
    h.update(np.ascontiguousarray(bank.phrase_class).tobytes())
    return h.hexdigest()


def prepare_inputs(bundle: Bundle, images: dict[str, np.ndarray], rig: Rig, source=None) -> tuple[np.ndarray, np.ndarray]:
    """A frame's images + its rig -> a bundle's model inputs: images (1, V, 3, H, W) float32, ego2img (1, V, 4, 4)
    float32 (needs the bundle only, no sessions: `ago infer` reads its first frame while they open). A frame
    whose cameras are not the bundle's rig's is refused, naming the camera."""
    bundle.contract.rig.check_cameras(images.keys(), source)
    rig = rig.ordered_as(bundle.contract.rig.names, source)   # the model's camera order (refuses another rig)
    rig.validate(source)
    rig = fit_rig_to_images(rig, images)
    pre = bundle.preprocess
    x = pre.images(images, rig, source)[None]
    m = pre.ego2img(rig)[None]
    if not np.isfinite(m).all():
        raise AgoInputError(source, "calibration gives non-finite projection matrices")
    return x, m


class Predictor:
    def __init__(self, bundle: Bundle | str | Path, *, device: Device | str = Device.CPU,
                 precision: Precision | str = Precision.FP32, int8: bool = False, workers: int = 1,
                 warm_up: bool = True):
        """bundle: a bundle folder or a loaded Bundle (checked on load).
        device, precision: where the graphs run (`cpu`, `cuda`, `tensorrt`, `openvino`; `fp16` through
        TensorRT or OpenVINO; ago_runtime/providers.py); the heads and bank products stay on the CPU.
        int8: the bundle's int8 encoder graphs (`ago export --int8`; on a CPU: providers.check_int8).
        workers: frames `predict_many` predicts at once; with more than one, each gets cpu_count // workers
        onnxruntime threads (`pipeline.auto_workers` is `ago infer`'s choice), with one, every core.
        warm_up: run each graph once on dummy inputs now, so that the first frame runs at the steady-state
        speed; False lets the first frame pay onnxruntime's first-run allocations instead (`ago infer` runs without
        it, benchmarks/results/infer_warm_up.md)."""
        if not 1 <= int(workers) <= 64:
            raise AgoInputError("workers", f"must be between 1 and 64, got {workers}")
        self.bundle = bundle if isinstance(bundle, Bundle) else Bundle.load(bundle)
        self.workers = int(workers)
        device, precision = parse_device(device), parse_precision(precision)
        check_device(device, precision)   # before any session is made
        threads = max(1, (os.cpu_count() or 1) // self.workers) if self.workers > 1 else None
        self.encoder = open_encoder(self.bundle, int8, threads, warm_up=warm_up, device=device, precision=precision)
        self.classifier = VoxelClassifier(self.encoder)
        self._folded: dict[str, FoldedHeads] = {}

    @property
    def grid(self) -> Grid:
        return self.bundle.grid

    # ---- banks -----------------------------------------------------------------------------
    def fold(self, bank) -> FoldedHeads:
        """The bank folded into the heads (cached per bank content)."""
        key = bank_key(bank)
        if key not in self._folded:
            check_bank_fits(bank, self.bundle.contract.text_encoder, self.bundle.root)
            self._folded[key] = FoldedHeads.fold(self.bundle.heads, bank.embeddings, bank.phrase_class,
                                                 bank.num_classes)
        return self._folded[key]

    def fold_with_reference(self, bank) -> FoldedHeads:
        """The bank folded with REFERENCE classes appended (cached): the bundle's own training classes that
        no class of `bank` covers (by Occ3D ids; by identical phrases for classes without ids). Used for the
        unexplained-obstacle score only (`volumes=True`): with a 5-class prompt file, a building voxel
        would otherwise look free (no prompt matches it better than the learnt free embedding) or be
        forced onto the best of 5 wrong classes; against the reference classes it is seen as occupied and
        as something no prompt explains. Labels are unchanged (FoldedHeads ignores the reference rows)."""
        key = bank_key(bank) + "+reference"   # the bundle's training bank is fixed: one entry per user bank
        if key not in self._folded:
            check_bank_fits(bank, self.bundle.contract.text_encoder, self.bundle.root)
            train = self.bundle.load_bank()
            covered = {i for ids in bank.occ3d_ids for i in ids}
            user_phrases = set(bank.phrases)
            ref = []
            for k in range(train.num_classes):
                ids = set(train.occ3d_ids[k]) if k < len(train.occ3d_ids) else set()
                phrases = {p for p, c in zip(train.phrases, train.phrase_class) if c == k}
                if not (ids <= covered if ids else bool(user_phrases & phrases)):
                    ref.append(k)
            keep = np.isin(train.phrase_class, ref)
            remap = {k: bank.num_classes + i for i, k in enumerate(ref)}
            emb = np.concatenate([bank.embeddings, train.embeddings[keep]])
            pc = np.concatenate([bank.phrase_class, [remap[int(c)] for c in train.phrase_class[keep]]]).astype(np.int64)
            self._folded[key] = FoldedHeads.fold(self.bundle.heads, emb, pc, bank.num_classes + len(ref),
                                                 reference_classes=len(ref))
        return self._folded[key]

    # ---- encoder ---------------------------------------------------------------------------
    def prepare(self, images: dict[str, np.ndarray], rig: Rig, source=None) -> tuple[np.ndarray, np.ndarray]:
        """-> model inputs: images (1, 6, 3, H, W) float32, ego2img (1, 6, 4, 4) float32."""
        return prepare_inputs(self.bundle, images, rig, source)

    def encode_arrays(self, x: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The whole grid's h (N, Dh), g (N, Da) (retrieval, parity; `predict` streams slabs instead)."""
        return self.encoder.hidden(x, m)

    # ---- prediction ------------------------------------------------------------------------
    def predict(self, images: dict[str, np.ndarray], rig: Rig, bank=None, identifier: Identifier | str | None = None,
                source=None, volumes: bool = False) -> Prediction:
        """A frame's images (dict camera -> RGB uint8) + their rig + a bank (default: the bundle's) -> Prediction."""
        bank = bank if bank is not None else self.bundle.load_bank()
        identifier = Identifier.parse(identifier, "identifier") if identifier else self.bundle.identifier_for(bank)
        folded = self.fold_with_reference(bank) if volumes else self.fold(bank)
        t0 = time.perf_counter()
        x, m = self.prepare(images, rig, source)
        t1 = time.perf_counter()
        pred = self.predict_arrays(x, m, bank, identifier, folded, volumes)
        pred.timings = {"preprocess": t1 - t0, **pred.timings}
        return pred

    def predict_many(self, frames: Iterable[InputFrame | tuple], bank=None, identifier: Identifier | str | None = None,
                     volumes: bool = False, progress: str | None = None) -> Iterator[tuple[InputFrame, Prediction]]:
        """(frame, Prediction) for each frame of `frames`, in order: `open_frames(...)`, or any iterable of
        InputFrame / (name, images, rig[, source]) tuples. A reader thread decodes and preprocesses the next
        frames and `workers` threads predict them while the caller's loop body handles the previous one
        (ago_runtime/predict/pipeline.py). bank, identifier, volumes: as `predict`, checked and folded once,
        before the first frame is read. A frame that cannot be read or predicted ends the iteration with its
        error (AgoInputError naming its source) after the frames before it. `progress`: a progress bar's
        label (stderr), None for none."""
        from ago_runtime.predict.pipeline import overlapped

        bank = bank if bank is not None else self.bundle.load_bank()
        identifier = Identifier.parse(identifier, "identifier") if identifier else self.bundle.identifier_for(bank)
        folded = self.fold_with_reference(bank) if volumes else self.fold(bank)
        total = len(frames) if isinstance(frames, Sized) else None

        def read(frame) -> tuple[InputFrame, np.ndarray, np.ndarray, float]:
            frame = InputFrame(*frame)
            t = time.perf_counter()
            x, m = self.prepare(frame.images, frame.rig, frame.source)
            return frame, x, m, time.perf_counter() - t

        def predict(item) -> tuple[InputFrame, Prediction]:
            frame, x, m, t_pre = item
            pred = self.predict_arrays(x, m, bank, identifier, folded, volumes)
            pred.timings = {"preprocess": t_pre, **pred.timings}
            return frame, pred

        return overlapped(frames, read, predict, self.workers, progress, total)

    def predict_arrays(self, x: np.ndarray, m: np.ndarray, bank, identifier: Identifier = Identifier.MIN_ENTROPY,
                       folded: FoldedHeads | None = None, volumes: bool = False,
                       planes: list[np.ndarray] | None = None, features: FrameFeatures | None = None) -> Prediction:
        """Preprocessed inputs -> Prediction, slab by slab: the main branch on every voxel, then the
        adapted branch only on the voxels that need it (VoxelClassifier).

        folded: `self.fold(bank)` (or, with volumes, `self.fold_with_reference(bank)`) when the caller has it;
        None folds here.

        planes: this frame's `self.encoder.plane_maps(x, m)` when the caller already has them (re-querying
        the same frame with another bank skips the planes graph); None runs it.
        features: a `FrameFeatures` of this frame, filled by the first call given it; later calls with it skip the
        planes graph and the decoder's stages (a re-query with another bank: bank products, adapter on the
        voxels that need it, heads).
        timings: "encoder" = the graphs (planes, voxel stages and the bank products) and the numpy glue
        between them (plane sums, softplus, gathers), "heads" = the numpy heads (class max, softmax,
        entropy, identifier)."""
        identifier = Identifier(identifier)
        if folded is None:
            # the unexplained-obstacle score needs the reference classes (fold_with_reference); labels are the same
            folded = self.fold_with_reference(bank) if volumes else self.fold(bank)
        check_class_count(bank.num_classes, None)
        out, timings = self.classifier.classify(x, m, folded, identifier, volumes, planes, features)
        pred = self._prediction(out, bank, identifier)
        pred.timings = timings
        return pred

    def predict_hidden(self, h: np.ndarray, g: np.ndarray, bank, identifier: Identifier = Identifier.MIN_ENTROPY,
                       folded: FoldedHeads | None = None) -> Prediction:
        """Whole-grid hidden features -> Prediction (the slab loop's `classify_hidden`: `ago retrieve`, benchmarks
        and tests)."""
        folded = folded or self.fold(bank)
        check_class_count(bank.num_classes, None)
        identifier = Identifier(identifier)
        return self._prediction(self.classifier.classify_hidden(h, g, folded, identifier), bank, identifier)

    def _prediction(self, out: dict, bank, identifier: Identifier) -> Prediction:
        shape = self.grid.shape
        K = bank.num_classes
        sem = out["label"].reshape(shape)
        lut = table_id_lookup(bank)
        return Prediction(
            semantics=sem, class_names=list(bank.class_names), free_index=K,
            entropy=out["entropy"].reshape(shape), confidence=out["confidence"].reshape(shape),
            branch=out["branch"].reshape(shape), identifier=identifier, grid=self.grid,
            table_ids=lut[sem] if lut is not None else None, class_table=bank.class_table,
            unexplained=out["unexplained"].reshape(shape) if "unexplained" in out else None,
            occupancy=out["occupancy"].reshape(shape) if "occupancy" in out else None)


