"""Choosing `ago infer --unexplained-threshold` for a prompt file on labelled frames (`ago choose-threshold`).

`ago infer --save-volumes` flags a voxel as an unexplained obstacle when it is occupied (p_occ > 0.5) and its
score, 1 - the largest probability a prompted class gets, is above a threshold (`predictor.unexplained_mask`).
How high the voxels of the prompted classes themselves score depends on the model and on the prompt file, so
one fixed threshold does not suit every pair. The rule here: the lowest threshold that flags at most
`false_rate` (default 5 %) of the voxels labelled with a class the prompt file names ("explained" voxels).

    choice = choose_for_prompts(Predictor(bundle), bank, frames, labels, false_rate=0.05)
    choice.threshold          # give it to `ago infer --unexplained-threshold`

The labels are what a user has: an `ago pseudo-labels` folder (its meta.json names the classes, the free and
ignore labels and the grid), or Occ3D ground truth (`<scene>/<token>/labels.npz`, the Occ3D-nuScenes classes).
A label class counts as explained when the prompt file names it: a class of the file of that name, or an
Occ3D class one of its classes maps to (`vehicle [car, bus, ...]`). Only labelled voxels are counted (not
free, not ignored; inside the camera mask when the file has one). Predictions and labels meet at the finer of
the two grids (the coarser one repeated by an integer factor per axis; other shapes are refused).
Choose on frames other than those the threshold will be judged on (e.g. the training split).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ago_runtime.errors import AgoInputError
from ago_runtime.predict.predictor import UNEXPLAINED_THRESHOLD, unexplained_mask

__all__ = ["LabelFolder", "ThresholdChoice", "choose_threshold", "explained_names", "frame_voxels",
           "choose_for_prompts"]

MAX_LABEL_FILES = 1_000_000   # a label folder holding more is refused before anything is read


def choose_threshold(scores: np.ndarray, occupancy: np.ndarray, explained: np.ndarray, false_rate: float) -> float:
    """The lowest mask threshold t (score > t and occupancy > 0.5 flags a voxel) that flags at most `false_rate`
    of the `explained` voxels; scores, occupancy, explained: per voxel. Ties at t stay unflagged (the mask is
    strict), so the rate holds exactly. Nothing forces t >= 0.5: a prompt file that explains its classes well
    gets a threshold below 0.5."""
    if not 0.0 <= false_rate < 1.0:
        raise ValueError(f"false_rate must be in [0, 1), got {false_rate}")
    n = int(explained.sum())
    if n == 0:
        raise ValueError("no explained voxels to choose a threshold on")
    could = unexplained_mask(scores, occupancy, -np.inf)            # flagged at some threshold: the occupied ones
    cand = np.sort(scores[explained & could])[::-1]
    allowed = int(np.floor(false_rate * n))
    if allowed >= len(cand):
        return 0.0
    return float(cand[allowed])    # flags only scores > cand[allowed]: at most `allowed` voxels


@dataclass
class LabelFolder:
    """A folder of per-frame labels, `<scene>/<token>/labels.npz` (a Waymo scene is `<split>/<scene>`): `files`
    sample token -> file, the label classes (`class_names[i]` is label i), the free and ignore labels, and the grid's
    range when the folder says it (an `ago pseudo-labels` meta.json, checked against the bundle's; Occ3D GT says
    nothing)."""

    root: Path
    files: dict[str, Path]
    class_names: list[str]
    free_index: int
    ignore_index: int = 255
    grid_range: tuple[tuple[float, ...], tuple[float, ...]] | None = None
    kind: str = "Occ3D ground truth"

    @classmethod
    def open(cls, root: str | Path, option: str = "--labels") -> "LabelFolder":
        from ago_runtime.classes import FREE, OCC3D_CLASSES
        from ago_runtime.readers import read_json

        root = Path(root)
        if not root.is_dir():
            raise AgoInputError(root, f"{option}: label folder not found")
        files: dict[str, Path] = {}
        for f in root.rglob("labels.npz"):   # <scene>/<token>/, or <split>/<scene>/<token>/ (an Occ3D-Waymo dataset's)
            if len(files) >= MAX_LABEL_FILES:
                raise AgoInputError(root, f"{option}: more than {MAX_LABEL_FILES} label files")
            token = f.parent.name
            if token in files:
                raise AgoInputError(f, f"{option}: sample token {token} appears twice (also {files[token]})")
            files[token] = f
        if not files:
            raise AgoInputError(root, f"{option}: no <scene>/<token>/labels.npz (an `ago pseudo-labels` folder or "
                                "an Occ3D gts folder)")
        files = dict(sorted(files.items(), key=lambda kv: str(kv[1])))   # by scene, then token
        if not (root / "meta.json").is_file():
            return cls(root, files, list(OCC3D_CLASSES), FREE)
        meta = read_json(root / "meta.json")
        try:
            classes = meta["label_space"]["classes"]
            if not isinstance(classes, list) or not all(isinstance(c, str) for c in classes):
                raise TypeError(f"label_space.classes is {type(classes).__name__}, not a list of names")
            names = list(classes)
            free = int(meta.get("free_index", len(names)))
            ignore = int(meta.get("ignore_index", 255))
            grid = meta.get("grid") or {}
            rng = (tuple(float(v) for v in grid["range_min"]), tuple(float(v) for v in grid["range_max"])) \
                if "range_min" in grid and "range_max" in grid else None
        except (KeyError, TypeError, ValueError) as e:
            raise AgoInputError(root / "meta.json", f"{option}: no label_space.classes / free_index ({e})") from None
        if not 0 < len(names) < 255 or not 0 <= free <= 255 or not 0 <= ignore <= 255 or free == ignore:
            raise AgoInputError(root / "meta.json", f"{option}: {len(names)} classes, free label {free}, ignore "
                                f"label {ignore}: not a label space (1-254 classes, two different labels in 0-255)")
        if rng is not None and (len(rng[0]) != 3 or len(rng[1]) != 3):
            raise AgoInputError(root / "meta.json", f"{option}: grid range {rng} is not (x, y, z)")
        return cls(root, files, names, free, ignore, rng, "pseudo-labels")

    def load(self, token: str) -> tuple[np.ndarray, np.ndarray]:
        """(labels (X, Y, Z) uint8, the voxels to count: labelled with a class, inside the camera mask if any)."""
        from ago_runtime.formats.occ3d import load_semantics

        sem, mask = load_semantics(self.files[token])
        counted = (sem < len(self.class_names)) & (sem != self.free_index) & (sem != self.ignore_index)
        if mask is not None:
            counted &= mask
        return sem, counted


def explained_names(bank) -> set[str]:
    """The label class names a bank's classes explain: each class's own name and the names of the table classes
    (Occ3D) it maps to."""
    names = set(bank.class_names)
    for ids in bank.occ3d_ids:
        names |= {bank.class_table.name_of(i) for i in ids}
    return names


def _common_shape(a: tuple[int, ...], b: tuple[int, ...], what: str) -> tuple[int, ...]:
    """The finer of two grid shapes, when each axis of the coarser divides it; else one AgoInputError."""
    fine = tuple(max(x, y) for x, y in zip(a, b))
    if len(a) != 3 or len(b) != 3 or any(f % x or f % y for f, x, y in zip(fine, a, b)):
        raise AgoInputError(what, f"label grid {tuple(b)} and prediction grid {tuple(a)}: neither is an integer "
                            "multiple of the other along every axis")
    return fine


def _repeat_to(volume: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    from ago_runtime.volumes import upsample_nearest

    return upsample_nearest(volume, [s // v for s, v in zip(shape, volume.shape)])


def frame_voxels(pred, labels: np.ndarray, counted: np.ndarray, explained_ids: np.ndarray, source) \
        -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One frame's counted voxels at the finer grid: (unexplained score, occupancy, explained?)."""
    shape = _common_shape(pred.unexplained.shape, labels.shape, source)
    keep = _repeat_to(counted, shape)
    lab = _repeat_to(labels, shape)[keep]
    return (_repeat_to(pred.unexplained, shape)[keep].astype(np.float32),
            _repeat_to(pred.occupancy, shape)[keep].astype(np.float32), np.isin(lab, explained_ids))


@dataclass
class ThresholdChoice:
    """What `choose_for_prompts` found: the threshold, and over the counted voxels of the frames used the share
    of explained voxels and of other labelled voxels (classes the prompt file does not name) the mask flags at
    that threshold and at the default one."""

    threshold: float
    false_rate: float
    frames: list[str] = field(default_factory=list)
    explained_voxels: int = 0
    other_voxels: int = 0
    explained_classes: list[str] = field(default_factory=list)
    other_classes: list[str] = field(default_factory=list)
    flagged_explained: float = 0.0
    flagged_other: float | None = None
    default_flagged_explained: float = 0.0
    default_flagged_other: float | None = None

    def to_dict(self) -> dict:
        return dict(self.__dict__, default_threshold=UNEXPLAINED_THRESHOLD)


def choose_for_prompts(predictor, bank, frames, labels: LabelFolder, false_rate: float = 0.05,
                       progress: str | None = "choosing the threshold") -> ThresholdChoice:
    """Predict `frames` (InputFrames whose names are tokens of `labels`) with `bank` (volumes on) and choose the
    threshold on their counted voxels (see the module doc)."""
    if labels.grid_range is not None:
        g = predictor.bundle.grid
        if not (np.allclose(labels.grid_range[0], g.range_min) and np.allclose(labels.grid_range[1], g.range_max)):
            raise AgoInputError(labels.root / "meta.json", f"the labels cover {labels.grid_range}, the bundle's grid "
                                f"{(tuple(g.range_min), tuple(g.range_max))}: not the same space")
    covered = explained_names(bank)
    explained_ids = np.array([i for i, n in enumerate(labels.class_names) if n in covered and i != labels.free_index],
                             dtype=np.int64)
    if explained_ids.size == 0:
        raise AgoInputError(labels.root, f"none of the label classes ({', '.join(labels.class_names)}) is a class "
                            "of the prompt file: nothing to choose the threshold on")
    scores, occs, expl, names = [], [], [], []
    with_volumes = predictor.predict_many(frames, bank, volumes=True, progress=progress)
    try:
        for frame, pred in with_volumes:
            sem, counted = labels.load(frame.name)
            s, o, e = frame_voxels(pred, sem, counted, explained_ids, labels.files[frame.name])
            scores.append(s)
            occs.append(o)
            expl.append(e)
            names.append(frame.name)
    finally:
        with_volumes.close()
    s, o, e = np.concatenate(scores), np.concatenate(occs), np.concatenate(expl)
    if not e.any():
        raise AgoInputError(labels.root, "the frames used hold no labelled voxel of a class the prompt file names")
    t = choose_threshold(s, o, e, false_rate)

    def rate(mask: np.ndarray, sel: np.ndarray) -> float | None:
        return float(mask[sel].mean()) if sel.any() else None

    at_t, at_default = unexplained_mask(s, o, t), unexplained_mask(s, o, UNEXPLAINED_THRESHOLD)
    named = set(explained_ids.tolist())
    return ThresholdChoice(
        threshold=t, false_rate=false_rate, frames=names, explained_voxels=int(e.sum()), other_voxels=int((~e).sum()),
        explained_classes=[n for i, n in enumerate(labels.class_names) if i in named],
        other_classes=[n for i, n in enumerate(labels.class_names) if i not in named and i != labels.free_index],
        flagged_explained=rate(at_t, e), flagged_other=rate(at_t, ~e),
        default_flagged_explained=rate(at_default, e), default_flagged_other=rate(at_default, ~e))
