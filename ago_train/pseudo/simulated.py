"""SIMULATED 2-D vision-language backends for synthetic data (no neural network involved).

Synthetic frames (`ago synth`) carry per-pixel truth: `frame.extras["semantic"][cam]` ((H, W) uint8
label id of the dataset's class table: Occ3D-nuScenes ids in the nuScenes layout, Occ3D-Waymo ids in the
Occ3D-Waymo layout; 255 = sky / nothing) and `frame.extras["depth"][cam]` ((H, W) float32 metres, 0 = none).
These classes turn that truth into what a real model would give, with its typical failures:

- `SimulatedSegmenter(label_space, SimSegmenterConfig())`: stands in for Grounded SAM. Label ids (of
  the label space's table, `@table`: the pixels must be of that table, `formats.datasets.check_label_table`)
  -> label-space classes (ids outside the label space: no label), then, in this order:
  confusions between related classes (whole instance for object classes, a blob for surfaces;
  only when both classes are in the label space and differ there), missed instances (connected
  components dropped with a probability rising for small and far ones), boundary errors (each
  class eroded or dilated by a random radius), false positives (random elliptic blobs of random
  classes). Output: (H, W) uint8 class index, 255 = no label.
- `SimulatedImageEmbedder(class_text, SimEmbedderConfig())`: stands in for MaskCLIP+ / FeatUp.
  Each pixel's feature is the text embedding of its true Occ3D class passed through a fixed
  modality gap (a fixed random rotation by `rotation_deg` of every vector, plus a shared offset
  that adds the same amount to every class's similarity and dilutes all of them),
  averaged over ViT-like patches (a `patch_grid` of 27 x 48 patches, as MaskCLIP at 432 x 768), plus
  per-patch noise, then upsampled bilinearly x `upsample` (FeatUp's role). Output (C, h, w) float32.

Randomness is seeded per image from sha256("<scene>/<token>/<camera>/<image file name>|<seed>"),
so a given image always gets the same result, whichever order frames are processed in.
"""

from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from ago_runtime.classes import NUM_SEMANTIC, OCC3D_CLASSES, ClassTable, name_key, shipped_name
from ago_runtime.errors import AgoInputError
from ago_runtime.formats.frame import Frame
from ago_runtime.vocab.prompts import LabelSpace

NO_LABEL = 255
THING_IDS = frozenset(range(1, 11))  # barrier .. truck: countable objects; the rest are surfaces/stuff
# the countable objects of each shipped class table, by name (Occ3D-nuScenes: THING_IDS)
THING_NAMES = {
    "occ3d_nuscenes": tuple(OCC3D_CLASSES[i] for i in sorted(THING_IDS)),
    "occ3d_waymo": ("general_object", "vehicle", "pedestrian", "sign", "bicyclist", "traffic_light", "pole",
                    "construction_cone", "bicycle", "motorcycle"),
}


def thing_names(table: ClassTable) -> tuple[str, ...]:
    """The countable-object classes of `table`: a shipped table's THING_NAMES; for any other table, its classes whose
    name is an object class of a shipped table ("car", "pedestrian", "vehicle", ...); the rest are surfaces."""
    name = shipped_name(table)
    if name is not None:
        return THING_NAMES[name]
    objects = {name_key(n) for names in THING_NAMES.values() for n in names}
    return tuple(n for n in table.names if name_key(n) in objects)


DEFAULT_CONFUSIONS: tuple[tuple[str, str], ...] = (
    ("driveable_surface", "sidewalk"),
    ("sidewalk", "other_flat"),
    ("driveable_surface", "other_flat"),
    ("terrain", "vegetation"),
    ("terrain", "sidewalk"),
    ("manmade", "vegetation"),
    ("car", "truck"),
    ("truck", "construction_vehicle"),
    ("truck", "trailer"),
    ("bus", "truck"),
    ("bicycle", "motorcycle"),
    ("barrier", "traffic_cone"),
    ("others", "manmade"),
)
# the same kinds of mix-ups between Occ3D-Waymo classes (ours: Waymo has one vehicle class, walkable covers
# sidewalk and terrain, and it splits poles, signs, traffic lights and tree trunks off)
WAYMO_CONFUSIONS: tuple[tuple[str, str], ...] = (
    ("road", "walkable"),
    ("walkable", "vegetation"),
    ("building", "vegetation"),
    ("vegetation", "tree_trunk"),
    ("pole", "tree_trunk"),
    ("sign", "traffic_light"),
    ("bicycle", "motorcycle"),
    ("bicyclist", "pedestrian"),
    ("general_object", "construction_cone"),
    ("general_object", "building"),
)
CONFUSIONS = {"occ3d_nuscenes": DEFAULT_CONFUSIONS, "occ3d_waymo": WAYMO_CONFUSIONS}


def image_seed(frame: Frame, camera: str, seed: int) -> int:
    """A 64-bit seed for one image that does not depend on where the dataset lives on disk."""
    name = Path(frame.image_paths.get(camera, "")).name
    key = f"{frame.scene}/{frame.token}/{camera}/{name}|{seed}".encode()
    return int.from_bytes(hashlib.sha256(key).digest()[:8], "little")


def _synthetic_maps(frame: Frame, camera: str, need_depth: bool) -> tuple[np.ndarray, np.ndarray | None]:
    sem = frame.extras.get("semantic", {}).get(camera) if isinstance(frame.extras, dict) else None
    if sem is None:
        raise AgoInputError(f"{frame.scene}/{frame.token}", f"no synthetic per-pixel semantics for {camera}: the "
                            "simulated backends only work on `ago synth` data (use the file backends for real data)")
    depth = frame.extras.get("depth", {}).get(camera) if need_depth else None
    if need_depth and depth is None:
        raise AgoInputError(f"{frame.scene}/{frame.token}", f"no synthetic depth map for {camera}")
    return np.asarray(sem), (None if depth is None else np.asarray(depth, dtype=np.float32))


# ---------------------------------------------------------------------------------------------
# Segmenter
# ---------------------------------------------------------------------------------------------
@dataclass
class SimSegmenterConfig:
    """Knobs of the simulated segmenter. Probabilities are per connected component / per blob."""

    seed: int = 0
    confusion_rate: float = 0.15          # chance that an instance / a surface blob takes a related class
    confusion_pairs: tuple[tuple[str, str], ...] = DEFAULT_CONFUSIONS  # symmetric, Occ3D names
    confusion_blob: float = 0.12          # radius of a confused surface blob, fraction of image width
    miss_object: float = 0.08             # base chance an object instance is missed
    miss_surface: float = 0.02            # base chance a surface component is missed
    miss_small: float = 0.35              # extra chance for components smaller than `small_area`
    small_area: float = 0.0005            # fraction of the image area (720 px at 1600 x 900)
    miss_far_per_m: float = 0.012         # extra chance per metre of mean depth beyond `far_start_m`
    far_start_m: float = 15.0
    miss_max: float = 0.9
    boundary_px: float = 6.0              # max erode/dilate radius, in pixels of a 1600-wide image
    false_positive_blobs: float = 1.0     # mean number of spurious blobs per image (Poisson)
    false_positive_size: float = 0.03     # blob radius, fraction of image width

    def to_dict(self) -> dict:
        d = asdict(self)
        d["confusion_pairs"] = [list(p) for p in self.confusion_pairs]
        return d

    @classmethod
    def for_table(cls, table: ClassTable, seed: int = 0) -> "SimSegmenterConfig":
        """The defaults with the confusion pairs of a shipped class table (`LabelSpace.class_table`); a table that is
        not shipped has none (nothing says which of its classes look alike)."""
        return cls(seed=seed, confusion_pairs=CONFUSIONS.get(shipped_name(table) or "", ()))

    @classmethod
    def perfect(cls, seed: int = 0) -> "SimSegmenterConfig":
        """No degradation at all: the rendered truth mapped to the label space (an upper bound)."""
        return cls(seed=seed, confusion_rate=0.0, miss_object=0.0, miss_surface=0.0, miss_small=0.0,
                   miss_far_per_m=0.0, boundary_px=0.0, false_positive_blobs=0.0)


class SimulatedSegmenter:
    """SIMULATION of an open-vocabulary segmenter on synthetic frames (see the module docstring)."""

    name = "simulated"

    def __init__(self, label_space: LabelSpace, config: SimSegmenterConfig | None = None):
        self.label_space = label_space
        self.config = config or SimSegmenterConfig()
        table = label_space.class_table   # the pixels' ids are this table's
        lut = label_space.gt_lut().astype(np.int64)
        self.lut2d = np.full(256, NO_LABEL, dtype=np.uint8)  # label id -> class, free/sky/unmapped -> 255
        for i in table.ids:
            if lut[i] < label_space.num_classes:
                self.lut2d[i] = lut[i]
        # directed confusions a -> b between label ids whose classes both exist and differ
        unknown = sorted({n for pair in self.config.confusion_pairs for n in pair} - set(table.names))
        if unknown:
            raise AgoInputError(label_space.source or label_space.name, f"confusion pairs name {unknown}, not classes "
                                f"of the label space's table {table.name} (SimSegmenterConfig.for_table)")
        self.confusions: list[tuple[int, int]] = []
        for a, b in self.config.confusion_pairs:
            ia, ib = table.id_of(a), table.id_of(b)
            ca, cb = self.lut2d[ia], self.lut2d[ib]
            if ca != NO_LABEL and cb != NO_LABEL and ca != cb:
                self.confusions += [(ia, ib), (ib, ia)]
        self.thing_ids = frozenset(table.id_of(n) for n in thing_names(table))
        self.is_object = np.array([bool(c.occ3d_ids) and set(c.occ3d_ids) <= self.thing_ids
                                   for c in label_space.classes] + [False], dtype=bool)

    def config_dict(self) -> dict:
        return {"simulation": True, "label_space": self.label_space.name, **self.config.to_dict()}

    def segment(self, frame: Frame, camera: str) -> np.ndarray:
        sem, depth = _synthetic_maps(frame, camera, need_depth=True)
        cfg = self.config
        rng = np.random.default_rng(image_seed(frame, camera, cfg.seed))
        h, w = sem.shape
        sem = self._confuse(sem.copy(), rng) if cfg.confusion_rate > 0 else sem
        lab = self.lut2d[sem]
        lab = self._miss(lab, depth, rng)
        if cfg.boundary_px > 0:
            lab = self._boundaries(lab, rng)
        if cfg.false_positive_blobs > 0:
            for _ in range(rng.poisson(cfg.false_positive_blobs)):
                cls = int(rng.integers(self.label_space.num_classes))
                mask = _ellipse(h, w, rng, cfg.false_positive_size * w)
                lab[mask] = cls
        return lab

    # -- degradations ---------------------------------------------------------------------------
    def _confuse(self, sem: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        cfg = self.config
        h, w = sem.shape
        orig = sem.copy()
        for a, b in self.confusions:
            mask = (orig == a).astype(np.uint8)
            if not mask.any():
                continue
            n, comp = cv2.connectedComponents(mask, connectivity=8)
            hit = rng.random(n - 1) < cfg.confusion_rate / 2   # each pair is listed in both directions
            if not hit.any():
                continue
            if a in self.thing_ids:     # a whole instance is taken for the other class
                sem[np.r_[False, hit][comp]] = b
            else:                  # a blob of the surface is
                for k in np.flatnonzero(hit) + 1:
                    ys, xs = np.nonzero(comp == k)
                    j = rng.integers(len(ys))
                    blob = _ellipse(h, w, rng, cfg.confusion_blob * w, centre=(xs[j], ys[j]))
                    sem[blob & (comp == k)] = b
        return sem

    def _miss(self, lab: np.ndarray, depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        cfg = self.config
        h, w = lab.shape
        valid = (depth > 0).ravel()
        depth_of_valid = np.where(valid, depth.ravel(), 0.0)   # the same for every class: made once
        out = lab.copy()
        out_flat = out.reshape(-1)
        for c in np.unique(lab):
            if c == NO_LABEL:
                continue
            is_c = lab == c
            n, comp, stats, _ = cv2.connectedComponentsWithStats(is_c.view(np.uint8), connectivity=8)
            if n <= 1:
                continue
            pix = np.flatnonzero(is_c)          # only this class's pixels: component 0 (the rest) is not needed
            comp_of_pix = comp.reshape(-1)[pix]
            dsum = np.bincount(comp_of_pix, weights=depth_of_valid[pix], minlength=n)
            dcnt = np.bincount(comp_of_pix, weights=valid[pix].astype(np.float64), minlength=n)
            mean_depth = np.where(dcnt > 0, dsum / np.maximum(dcnt, 1), 0.0)[1:]
            area = stats[1:, cv2.CC_STAT_AREA]
            p = (cfg.miss_object if self.is_object[c] else cfg.miss_surface) \
                + cfg.miss_small * (area < cfg.small_area * h * w) \
                + cfg.miss_far_per_m * np.maximum(mean_depth - cfg.far_start_m, 0.0)
            drop = rng.random(n - 1) < np.minimum(p, cfg.miss_max)
            if drop.any():
                out_flat[pix[np.r_[False, drop][comp_of_pix]]] = NO_LABEL
        return out

    def _boundaries(self, lab: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        w = lab.shape[1]
        scale = self.config.boundary_px * w / 1600.0
        classes = [c for c in np.unique(lab) if c != NO_LABEL]
        rng.shuffle(classes)
        for c in classes:
            r = int(np.floor(scale * rng.random() + rng.random()))   # stochastic rounding of a random radius
            if r <= 0:
                continue
            kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
            m = (lab == c).astype(np.uint8)
            if rng.random() < 0.5:
                lab[(m > 0) & (cv2.erode(m, kernel) == 0)] = NO_LABEL
            else:
                lab[cv2.dilate(m, kernel) > 0] = c
        return lab


def _ellipse(h: int, w: int, rng: np.random.Generator, radius: float, centre=None) -> np.ndarray:
    """A bool (h, w) mask of a random ellipse of about `radius` pixels."""
    mask = np.zeros((h, w), np.uint8)
    cx, cy = (int(rng.integers(w)), int(rng.integers(h))) if centre is None else (int(centre[0]), int(centre[1]))
    ax = max(1, int(radius * rng.uniform(0.4, 1.0)))
    ay = max(1, int(radius * rng.uniform(0.3, 0.8)))
    cv2.ellipse(mask, (cx, cy), (ax, ay), float(rng.uniform(0, 180)), 0, 360, 1, -1)
    return mask.astype(bool)


# ---------------------------------------------------------------------------------------------
# Image embedder
# ---------------------------------------------------------------------------------------------
@dataclass
class SimEmbedderConfig:
    """Knobs of the simulated dense image embedder (defaults calibrated on MiniLM cw.txt embeddings)."""

    seed: int = 0                          # fixes the modality gap; per-image noise is seeded per image
    rotation_deg: float = 45.0             # every vector is rotated by exactly this angle (in random planes)
    offset_text: float = 1.1               # offset part with the same cosine to every class text (raises all)
    offset_other: float = 2.5              # offset part orthogonal to every class text (shrinks the spread)
    noise: float = 3.0                     # length of the per-patch Gaussian noise vector
    patch_grid: tuple[int, int] = (27, 48)  # (rows, cols) of ViT patches over the image
    upsample: int = 2                      # bilinear upsampling of the patch features (FeatUp's role)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["patch_grid"] = list(self.patch_grid)
        return d


def class_text_from_bank(bank, num_classes: int = NUM_SEMANTIC) -> np.ndarray:
    """(K, C) float32: per class id 0..K-1 of a class table the normalised mean of its phrase embeddings in a
    PromptBank of the table's closed label space in id order (cw.txt: the 17 Occ3D-nuScenes classes;
    waymo/cw_waymo.txt: the 15 Occ3D-Waymo ones)."""
    emb = np.asarray(bank.embeddings, dtype=np.float32)
    pc = np.asarray(bank.phrase_class)
    if len(bank.class_names) != num_classes:
        raise AgoInputError(None, f"the simulated embedder needs a bank of the table's {num_classes} classes in id "
                            f"order (cw.txt, waymo/cw_waymo.txt), got {len(bank.class_names)} classes")
    out = np.stack([emb[pc == k].mean(axis=0) for k in range(num_classes)])
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def _fixed_rotation(dim: int, angle: float, rng: np.random.Generator) -> np.ndarray:
    """(C, C) orthogonal R = Q B Q^T with B rotating C/2 random planes by `angle`: cos(Rx, x) = cos(angle) for all x."""
    q, r = np.linalg.qr(rng.standard_normal((dim, dim)))
    q = q * np.sign(np.diag(r))
    b = np.eye(dim)
    c, s = np.cos(angle), np.sin(angle)
    for i in range(0, dim - 1, 2):
        b[i, i], b[i, i + 1], b[i + 1, i], b[i + 1, i + 1] = c, -s, s, c
    return q @ b @ q.T


class SimulatedImageEmbedder:
    """SIMULATION of CLIP-like dense image features on synthetic frames (see the module docstring).

    class_text: (K, C) text embeddings, one per class of the pixels' class table (17 Occ3D-nuScenes classes, 15
    Occ3D-Waymo ones), or a cw.txt PromptBank; `ids`: the label id of each row (default 0..K-1); pixels of other
    ids (free, sky, nothing) take
    sky_text: an optional (C,) embedding for sky / nothing pixels (else they carry only the offset).
    """

    name = "simulated"

    def __init__(self, class_text, config: SimEmbedderConfig | None = None, sky_text: np.ndarray | None = None,
                 ids: tuple[int, ...] | None = None):
        if not isinstance(class_text, np.ndarray):
            class_text = class_text_from_bank(class_text)
        t = np.asarray(class_text, dtype=np.float64)
        if t.ndim != 2 or t.shape[0] < 2:
            raise ValueError(f"class_text must be (K, C), one row per class, got {t.shape}")
        self.num_classes = K = t.shape[0]
        t = t / np.linalg.norm(t, axis=1, keepdims=True)
        self.config = config or SimEmbedderConfig()
        self.class_text = t.astype(np.float32)
        self.channels = t.shape[1]
        cfg = self.config
        rng = np.random.default_rng(cfg.seed)
        rot = _fixed_rotation(self.channels, np.deg2rad(cfg.rotation_deg), rng)
        # shared offset = offset_text * u + offset_other * v: u (unit) has the same cosine with every class
        # text (the least-norm solution of t @ u = 1), v (unit, random) is orthogonal to all of them
        u = np.linalg.lstsq(t, np.ones(K), rcond=None)[0]
        u /= np.linalg.norm(u)
        v = rng.standard_normal(self.channels)
        v -= t.T @ np.linalg.lstsq(t.T, v, rcond=None)[0]
        v = v / np.linalg.norm(v) if np.linalg.norm(v) > 1e-6 else np.zeros_like(v)  # (C <= K: no room)
        self.offset = cfg.offset_text * u + cfg.offset_other * v
        sky = np.zeros(self.channels) if sky_text is None else rot @ (sky_text / np.linalg.norm(sky_text))
        # rows 0..K-1: the table's classes; row K: sky / nothing. Pixel label id -> row (`ids`: row k's label id)
        self.row_of_id = np.full(256, K, dtype=np.int64)
        self.row_of_id[list(range(K)) if ids is None else list(ids)] = np.arange(K)
        self.pixel_embeddings = np.vstack([t @ rot.T, sky[None]]) + self.offset
        self.pixel_embeddings = self.pixel_embeddings.astype(np.float32)

    def config_dict(self) -> dict:
        return {"simulation": True, "channels": self.channels, **self.config.to_dict()}

    def embed(self, frame: Frame, camera: str) -> np.ndarray:
        sem, _ = _synthetic_maps(frame, camera, need_depth=False)
        cfg = self.config
        rows, cols = cfg.patch_grid
        K = self.num_classes
        cls = self.row_of_id[sem]
        # fraction of each patch covered by each class (area pooling of one-hot maps)
        frac = np.zeros((rows, cols, K + 1), dtype=np.float32)
        for k in np.unique(cls):
            frac[:, :, k] = cv2.resize((cls == k).astype(np.float32), (cols, rows), interpolation=cv2.INTER_AREA)
        feats = frac.reshape(-1, K + 1) @ self.pixel_embeddings                 # (rows*cols, C)
        rng = np.random.default_rng(image_seed(frame, camera, cfg.seed))
        feats += rng.standard_normal(feats.shape).astype(np.float32) * (cfg.noise / np.sqrt(self.channels))
        feats = feats.reshape(rows, cols, self.channels)
        if cfg.upsample > 1:
            feats = upsample_bilinear(feats, cfg.upsample)
        return np.ascontiguousarray(feats.transpose(2, 0, 1), dtype=np.float32)


def _taps(n_in: int, n_out: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bilinear source taps (i0, i1, weight of i1) per output cell, cell-centre aligned like cv2.INTER_LINEAR."""
    x = np.clip((np.arange(n_out) + 0.5) * n_in / n_out - 0.5, 0, n_in - 1)
    i0 = np.minimum(np.floor(x).astype(np.int64), max(n_in - 2, 0))
    i1 = np.minimum(i0 + 1, n_in - 1)
    return i0, i1, (x - i0).astype(np.float32)


def upsample_bilinear(feats: np.ndarray, factor: int) -> np.ndarray:
    """(h, w, C) -> (h*factor, w*factor, C) bilinear (any channel count, unlike cv2.resize)."""
    h, w, _ = feats.shape
    y0, y1, fy = _taps(h, h * factor)
    x0, x1, fx = _taps(w, w * factor)
    rows = feats[y0] * (1 - fy)[:, None, None] + feats[y1] * fy[:, None, None]
    return rows[:, x0] * (1 - fx)[None, :, None] + rows[:, x1] * fx[None, :, None]


def similarity_stats(feature_maps: list[np.ndarray], semantics: list[np.ndarray], class_text: np.ndarray) -> dict:
    """Image-text cosine statistics of feature maps against per-class text embeddings.

    feature_maps: (C, h, w) maps; semantics: the matching (H, W) Occ3D id maps (each map cell takes
    the id at its centre pixel); class_text: (17, C). Gives mean right-class cosine, mean wrong-class
    cosine, their gap, the 95th percentile of all cosines, nearest-text accuracy overall and per class.
    """
    t = np.asarray(class_text, dtype=np.float64)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    sims, truth = [], []
    for f, sem in zip(feature_maps, semantics):
        c, h, w = f.shape
        H, W = sem.shape
        ys = np.minimum(((np.arange(h) + 0.5) * H / h).astype(int), H - 1)
        xs = np.minimum(((np.arange(w) + 0.5) * W / w).astype(int), W - 1)
        lab = sem[np.ix_(ys, xs)].ravel()
        v = f.reshape(c, -1).T.astype(np.float64)
        keep = lab < NUM_SEMANTIC
        v = v[keep] / np.maximum(np.linalg.norm(v[keep], axis=1, keepdims=True), 1e-12)
        sims.append(v @ t.T)
        truth.append(lab[keep].astype(np.int64))
    s = np.concatenate(sims)
    y = np.concatenate(truth)
    right = s[np.arange(len(y)), y]
    wrong = (s.sum(axis=1) - right) / (s.shape[1] - 1)
    pred = s.argmax(axis=1)
    per_class = {}
    for k in range(NUM_SEMANTIC):
        sel = y == k
        if sel.any():
            per_class[OCC3D_CLASSES[k]] = {"cells": int(sel.sum()), "accuracy": float((pred[sel] == k).mean()),
                                           "right_cos": float(right[sel].mean()), "wrong_cos": float(wrong[sel].mean())}
    return {
        "cells": int(len(y)),
        "right_cos_mean": float(right.mean()),
        "wrong_cos_mean": float(wrong.mean()),
        "gap_mean": float((right - wrong).mean()),
        "cos_p95": float(np.percentile(s, 95)),
        "cos_p05": float(np.percentile(s, 5)),
        "accuracy": float((pred == y).mean()),
        "chance": 1.0 / NUM_SEMANTIC,
        "min_class_accuracy": float(min(v["accuracy"] for v in per_class.values())) if per_class else float("nan"),
        "per_class": per_class,
    }
