"""3-D pseudo-labels and voxel image embeddings for a dataset: the driver and the file format.

`build_sample(key, lifted_frames, num_classes, config)` -> `PseudoSample` (one keyframe, in memory):
superimposes the lifted frames in the keyframe's ego frame, votes one label per voxel, casts rays
for free space and averages point features per voxel.

`generate(ds, indices, out_dir, ...)` writes, resumably (samples whose files exist are skipped;
an existing folder made with other settings is refused):

    <out>/meta.json                                   settings (see `PseudoLabelDir`)
    <out>/label_space.txt                             copy of the prompt file
    <out>/<scene>/<sample_token>/labels.npz           semantics, mask_lidar, mask_camera: (X, Y, Z) uint8
    <out>/<scene>/<sample_token>/embeds.npz           index (M,) int32, embeds (M, C) float16  (with an embedder)

semantics: 0..K-1 = label-space class index, 17 = free, 255 = unknown (never observed, or
occupied without a label). mask_lidar: voxels observed by the LiDAR (crossed by a ray or hit;
without ray casting every voxel). mask_camera: observed and with its centre inside some keyframe
camera's image. index: flat C-order indices into the (X, Y, Z) grid of the occupied voxels whose
points were seen by a camera; embeds: the mean image feature of those points (E_3D), by default
from the keyframe's own LiDAR points and images only (embed_all_frames=False: aggregated frames
would smear moving objects' features too, and cost one embedding pass per frame per sample).
"""

from __future__ import annotations

import json
import time
from collections import OrderedDict
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ago_runtime.atomic import save_npz, write_bytes, write_json
from ago_runtime.geometry.camera import Rig
from ago_runtime.classes import FREE, IGNORE, table_record
from ago_runtime.errors import AgoInputError
from ago_runtime.readers import read_json
from ago_runtime.formats.frame import Frame
from ago_runtime.formats.nuscenes_boxes import BOX_TABLES, DatasetBoxes, box_tables_missing, inside_box
from ago_runtime.geometry.grid import Grid
from ago_runtime.readers import read_npz
from ago_runtime.progress import track

from .aggregate import EGO_BOX, LiftedFrame, attach_features, frames_to_aggregate, lift_frame_and_sweeps, warp_to
from .backends import embedder_encoder_id
from .lift import feature_sums_per_voxel
from .raycast import GrazingRule, grazing_stops, occupied_keys, traverse, unique_rays
from .voting import FeatureMean, vote

FORMAT_VERSION = 1


@dataclass
class PseudoLabelConfig:
    grid: Grid = field(default_factory=Grid)
    num_keyframes: int = 1     # keyframes superimposed, the keyframe included (CLI --keyframes; paper: 30)
    interval: int = 1          # keyframe stride between them (paper: 2)
    nonkey_sweeps: int = 0     # non-key LiDAR sweeps added per superimposed keyframe, those recorded just
                               # before it, labelled with its images (CLI --sweeps; real nuScenes has ~9)
    raycast: bool = True       # free = crossed by a ray; else free = every voxel without a hit
    embed_all_frames: bool = False  # E_3D from every aggregated frame (default: the keyframe's own images)
    dedupe_rays: bool = True   # one ray per (sweep, hit voxel)
    ego_box: tuple | None = EGO_BOX
    carve: GrazingRule | None = None   # CLI --carve: None = `all` (every ray carves up to its hit voxel);
                                       # a GrazingRule = `grazing` (raycast.py: rays grazing the ground stop short),
                                       # the CLI's default; None here keeps the library benchmarks' committed tables
    moving: str = "aggregate"   # CLI --moving: "aggregate" = points of every class from every superimposed keyframe
                                # (static world); "keyframe" = points of the moving classes (`moving_classes`) only
                                # from the sample's own keyframe and its own sweeps: the others' track smears;
                                # "track" = the other keyframes' moving-class points carried along their objects'
                                # annotated box tracks (`follow_tracks`), the rest dropped as with "keyframe"

    def to_dict(self) -> dict:
        d = asdict(self)
        d["grid"] = self.grid.to_dict()
        d["ego_box"] = None if self.ego_box is None else [list(map(float, c)) for c in self.ego_box]
        d["carve"] = None if self.carve is None else self.carve.to_dict()
        return d

    def __post_init__(self):
        if self.moving not in MOVING_RULES:
            raise AgoInputError("--moving", f"must be one of {', '.join(MOVING_RULES)}, got {self.moving!r}")

    @property
    def separates_moving(self) -> bool:
        """Whether the moving classes' points of the other keyframes are treated apart (keyframe, track)."""
        return self.moving != "aggregate"

    @property
    def carve_name(self) -> str:
        """The --carve choice these settings are: all or grazing."""
        return "all" if self.carve is None else "grazing"


MOVING_RULES = ("aggregate", "keyframe", "track")
# the classes that move (class-table names: Occ3D-nuScenes and Occ3D-Waymo); a label-space class is moving when every
# table class it maps to is (a class of no table class, an open-vocabulary one, is not)
MOVING_TABLE_CLASSES = frozenset({"bicycle", "bus", "car", "construction_vehicle", "motorcycle", "pedestrian",
                                  "trailer", "truck", "vehicle", "bicyclist"})


def moving_classes(label_space) -> np.ndarray:
    """Indices of the label space's moving classes (MOVING_TABLE_CLASSES), for --moving keyframe and track."""
    table = label_space.class_table
    return np.array([k for k, c in enumerate(label_space.classes)
                     if c.occ3d_ids and all(table.name_of(i) in MOVING_TABLE_CLASSES for i in c.occ3d_ids)], np.int64)


@dataclass
class PseudoSample:
    semantics: np.ndarray      # (X, Y, Z) uint8
    mask_lidar: np.ndarray     # (X, Y, Z) uint8 0/1
    mask_camera: np.ndarray    # (X, Y, Z) uint8 0/1
    embed_index: np.ndarray | None = None   # (M,) int32
    embeds: np.ndarray | None = None        # (M, C) float16
    stats: dict = field(default_factory=dict)


Track = dict[str, tuple[np.ndarray, np.ndarray]]   # instance token -> (box2ego 4x4, size wlh): DatasetBoxes.by_instance


def follow_tracks(pts: np.ndarray, movable: np.ndarray, then: Track, now: Track) -> tuple[np.ndarray, np.ndarray]:
    """`--moving track`: another keyframe's moving-class points carried to where their objects are at the sample.

    pts (N, 3): that keyframe's points in the sample's ego frame, as the static warp (`warp_to`) puts them;
    movable (N,) bool: the points labelled with a moving class; then / now: the boxes annotated at that keyframe /
    at the sample, both in the sample's ego frame (`DatasetBoxes.by_instance`). A movable point inside a box of
    `then` (grown by BOX_MARGIN) whose object is annotated at the sample too moves with the box
    (now_box @ then_box^-1, a rigid motion); a movable point in no box, or in the box of an object not annotated at
    the sample, is dropped, as `--moving keyframe` drops it. A parked object's box does not move between
    keyframes, so its points stay where aggregation puts them. Gives (points, dropped (N,) bool); the other points
    are returned unchanged. A point inside two boxes goes with the first."""
    out = np.array(pts, np.float64, copy=True)
    dropped = np.asarray(movable, bool).copy()
    todo = np.flatnonzero(dropped)
    for inst, (box_then, wlh) in then.items():
        if todo.size == 0:
            break
        inside = inside_box(out[todo], box_then, wlh)
        if not inside.any():
            continue
        sel = todo[inside]
        if inst in now:
            motion = now[inst][0] @ np.linalg.inv(box_then)
            out[sel] = out[sel] @ motion[:3, :3].T + motion[:3, 3]
            dropped[sel] = False
        todo = todo[~inside]
    return out, dropped


_FRUSTUM_CACHE: OrderedDict = OrderedDict()


def frustum_mask(grid: Grid, rig: Rig) -> np.ndarray:
    """(X*Y*Z,) bool: voxel centres inside some camera's image (in front of it)."""
    key = (json.dumps(grid.to_dict()), rig.ego2img().tobytes(),
           tuple((c.width, c.height) for c in rig))
    if key in _FRUSTUM_CACHE:
        return _FRUSTUM_CACHE[key]
    centres = grid.centres().reshape(-1, 3)
    inside = np.zeros(len(centres), dtype=bool)
    for cam in rig:
        inside |= cam.project(centres)[2]
    _FRUSTUM_CACHE[key] = inside
    while len(_FRUSTUM_CACHE) > 4:
        _FRUSTUM_CACHE.popitem(last=False)
    return inside


def build_sample(key: Frame, lifted: list[LiftedFrame], num_classes: int, config: PseudoLabelConfig,
                 own: int = 1, moving: np.ndarray | None = None,
                 tracks: list[tuple[Track, Track] | None] | None = None) -> PseudoSample:
    """Pseudo-labels of keyframe `key` from lifted frames (lifted[0] = the keyframe's own; the first `own` are the
    keyframe's own sweeps). With config.moving "keyframe", points labelled with a class of `moving` (label indices)
    count only from those first `own` frames: elsewhere they neither occupy nor vote (their rays still carve, to
    where the point was). With "track", tracks[f] = (the boxes at lifted[f]'s keyframe, the boxes at `key`) carries
    lifted[f]'s moving-class points along their objects' tracks instead (`follow_tracks`); a frame whose
    tracks[f] is None (another keyframe's non-key sweeps: no boxes at their times) has them dropped."""
    grid = config.grid
    if num_classes > FREE:
        raise AgoInputError(None, f"a label space for pseudo-labels has at most {FREE} classes "
                            f"(index {FREE} means free), got {num_classes}")
    V = grid.num_voxels
    hit = np.zeros(V, dtype=bool)
    crossed = np.zeros(V, dtype=bool)
    vox_parts, lab_parts = [], []
    fmean = FeatureMean()
    n_points = n_labelled = rays = 0
    ray_sets, columns = [], []   # (origin, ends) per sweep; occupied lattice keys per sweep (--carve grazing)
    drop_moving = config.separates_moving and moving is not None and len(moving) > 0
    for f_i, lf in enumerate(lifted):
        pts, origin = warp_to(lf, key.ego2global)
        hits, dropped = pts, None   # where the points occupy and vote; the rays end at pts
        if drop_moving and f_i >= own:   # moving, another time
            movable = np.isin(lf.labels, moving)
            boxes = tracks[f_i] if config.moving == "track" and tracks is not None else None
            hits, dropped = follow_tracks(pts, movable, *boxes) if boxes is not None else (pts, movable)
        idx, inside = grid.points_to_index(hits)
        flat = grid.flat_index(idx)
        stays = inside if dropped is None else inside & ~dropped
        hit[flat[stays]] = True
        ok = stays & (lf.labels != IGNORE)
        vox_parts.append(flat[ok])
        lab_parts.append(lf.labels[ok])
        n_points += int(inside.sum())
        n_labelled += int(ok.sum())
        if config.raycast:
            ends = unique_rays(origin, pts, grid) if config.dedupe_rays else pts
            rays += len(ends)
            if config.carve is None:
                crossed |= traverse(origin[None], ends, grid)
            else:   # the stops need every sweep's hits first (a wall's other hits may come from another sweep)
                ray_sets.append((origin, ends))
                columns.append(occupied_keys(hits if dropped is None else hits[~dropped], grid))
        if lf.feature_maps is not None and (config.embed_all_frames or f_i == 0):
            for ci, fmap in enumerate(lf.feature_maps):
                sel = np.flatnonzero(inside & (lf.cam_idx == ci))
                if fmap is not None and sel.size:
                    fmean.add_sums(*feature_sums_per_voxel(flat[sel], lf.uv[sel], fmap, lf.image_sizes[ci]))
    if ray_sets:
        occupied = np.unique(np.concatenate(columns))
        for origin, ends in ray_sets:
            crossed |= traverse(origin[None], ends, grid, grazing_stops(origin, ends, grid, config.carve, occupied))
    voxels, labels = vote(np.concatenate(vox_parts), np.concatenate(lab_parts), num_classes)
    sem = np.full(V, IGNORE, dtype=np.uint8)
    if config.raycast:
        sem[crossed & ~hit] = FREE
        mask_lidar = crossed | hit
    else:
        sem[~hit] = FREE
        mask_lidar = np.ones(V, dtype=bool)
    sem[voxels] = labels.astype(np.uint8)
    mask_camera = mask_lidar & frustum_mask(grid, key.rig)
    shape = grid.shape
    out = PseudoSample(sem.reshape(shape), mask_lidar.reshape(shape).astype(np.uint8),
                       mask_camera.reshape(shape).astype(np.uint8))
    channels = [lf.channels for lf in lifted if lf.channels is not None]
    if channels:
        index, mean = fmean.result()
        c = channels[0]
        out.embed_index = index.astype(np.int32)
        out.embeds = (mean if len(index) else np.zeros((0, c), np.float32)).astype(np.float16)
    out.stats = {"frames": len(lifted), "points": n_points, "labelled_points": n_labelled, "rays": rays,
                 "occupied_voxels": int(hit.sum()), "labelled_voxels": int(len(voxels)),
                 "free_voxels": int((sem == FREE).sum())}
    return out


# ------------------------------------------------------------------------------------------------
# Output folder
# ------------------------------------------------------------------------------------------------
def sample_dir(out_dir: str | Path, scene: str, token: str) -> Path:
    return Path(out_dir) / scene / token


def save_sample(out_dir: str | Path, scene: str, token: str, sample: PseudoSample) -> None:
    """Write embeds.npz (if any) then labels.npz, each atomically; labels.npz last marks the sample done."""
    d = sample_dir(out_dir, scene, token)
    if sample.embeds is not None:
        save_npz(d / "embeds.npz", index=sample.embed_index.astype(np.int32),
                 embeds=sample.embeds.astype(np.float16))
    save_npz(d / "labels.npz", semantics=sample.semantics, mask_lidar=sample.mask_lidar,
             mask_camera=sample.mask_camera)


def load_pseudo_labels(out_dir: str | Path, scene: str, token: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(semantics, mask_lidar, mask_camera), each (X, Y, Z) uint8 (masks 0/1: use as bool)."""
    path = sample_dir(out_dir, scene, token) / "labels.npz"
    z = read_npz(path, ("semantics", "mask_lidar", "mask_camera"), what="pseudo-label file")
    shapes = {k: v.shape for k, v in z.items()}
    if len(set(shapes.values())) != 1 or z["semantics"].ndim != 3:
        raise AgoInputError(path, f"arrays must share one 3-D shape, got {shapes}")
    return z["semantics"].astype(np.uint8), z["mask_lidar"].astype(np.uint8), z["mask_camera"].astype(np.uint8)


def load_voxel_embeds(out_dir: str | Path, scene: str, token: str) -> tuple[np.ndarray, np.ndarray]:
    """(index (M,) int32 flat C-order voxel indices, embeds (M, C) float16)."""
    path = sample_dir(out_dir, scene, token) / "embeds.npz"
    z = read_npz(path, ("index", "embeds"), what="pseudo-label file")
    if z["index"].ndim != 1 or z["embeds"].ndim != 2 or len(z["index"]) != len(z["embeds"]):
        raise AgoInputError(path, f"index {z['index'].shape} and embeds {z['embeds'].shape} do not match")
    return z["index"].astype(np.int32), z["embeds"].astype(np.float16)


class PseudoLabelDir:
    """A pseudo-label output folder: its meta.json and readers.

    meta keys: format_version, label_space {name, classes, sha256, prompt_file[, class_table]}, grid (Grid.to_dict),
    segmenter {name, config}, embedder {name, config} or null, num_keyframes, interval, nonkey_sweeps,
    raycast, carve (all | grazing; its rule in config.carve), config (PseudoLabelConfig), free_index 17,
    ignore_index 255, created_by. (Folders written before non-key sweeps were read say `num_sweeps` for
    num_keyframes and have no nonkey_sweeps (= 0); folders from before --carve have no carve (= all); they
    are read and resumed as such.)
    """

    def __init__(self, out_dir: str | Path):
        self.root = Path(out_dir)
        path = self.root / "meta.json"
        self.meta = read_json(path, missing="not a pseudo-label folder (no meta.json); make one with `ago pseudo-labels`")

    @property
    def grid(self) -> Grid:
        return Grid.from_dict(self.meta["grid"])

    @property
    def class_names(self) -> list[str]:
        return list(self.meta["label_space"]["classes"])

    @property
    def label_space_path(self) -> Path:
        return self.root / "label_space.txt"

    def label_space(self):
        """The label space of these pseudo-labels: label_space.txt (a copy of the prompt file) with the class table
        meta.json records for it (a table file the prompt file names need not be beside the copy)."""
        from ago_runtime.classes import table_from_ref
        from ago_runtime.vocab.prompts import parse_prompt_text

        ls = self.meta["label_space"]
        table = table_from_ref(ls["class_table"], self.root / "meta.json") if "class_table" in ls else None
        return parse_prompt_text(self.label_space_path.read_bytes(), name=ls.get("name"), source=self.label_space_path,
                                 table=table)

    @property
    def has_embeds(self) -> bool:
        return self.meta.get("embedder") is not None

    @property
    def embed_channels(self) -> int | None:
        e = self.meta.get("embedder")
        return None if e is None else e.get("channels")

    def samples(self) -> list[tuple[str, str]]:
        """(scene, token) of every finished sample (labels.npz present), sorted."""
        return sorted((p.parent.parent.relative_to(self.root).as_posix(), p.parent.name)   # a Waymo scene: split/scene
                      for p in self.root.rglob("labels.npz"))

    def has(self, scene: str, token: str) -> bool:
        d = sample_dir(self.root, scene, token)
        return (d / "labels.npz").is_file() and (not self.has_embeds or (d / "embeds.npz").is_file())

    def sample_problem(self, scene: str, token: str, full: bool = True) -> str | None:
        """None when the sample's files are there and sound, else what is wrong (e.g. a labels.npz cut short
        by a kill). full=True reads the arrays (shapes against the grid, embedding index range); full=False
        only opens the zip directories and looks for the arrays' names (fast: for `ago train`'s check)."""
        d = sample_dir(self.root, scene, token)
        needed = [("labels.npz", ("semantics", "mask_lidar", "mask_camera"))]
        if self.has_embeds:
            needed.append(("embeds.npz", ("index", "embeds")))
        for name, keys in needed:
            path = d / name
            if not path.is_file():
                return f"{path}: missing"
            if not full:
                problem = _zip_members_problem(path, keys)
                if problem:
                    return f"{path}: {problem}"
        if not full:
            return None
        try:
            sem, ml, mc = load_pseudo_labels(self.root, scene, token)
            if sem.shape != tuple(self.grid.shape):
                return f"{d / 'labels.npz'}: shape {sem.shape}, the folder's grid is {tuple(self.grid.shape)}"
            if self.has_embeds:
                index, emb = load_voxel_embeds(self.root, scene, token)
                if index.size and (index.min() < 0 or index.max() >= self.grid.num_voxels):
                    return f"{d / 'embeds.npz'}: voxel indices outside the grid"
                ch = self.embed_channels
                if ch is not None and emb.shape[1] != ch:
                    return f"{d / 'embeds.npz'}: {emb.shape[1]} channels, the folder's embedder has {ch}"
        except AgoInputError as e:
            return str(e)
        return None

    def check_files(self, samples: list[tuple[str, str]], full: bool = False) -> None:
        """Refuse (one AgoInputError naming the first bad file, with the count) before training when any of
        `samples` (scene, token) has a missing or damaged pseudo-label file."""
        bad = []
        for scene, token in samples:
            problem = self.sample_problem(scene, token, full=full)
            if problem:
                bad.append(problem)
        if bad:
            first_path, _, what = bad[0].partition(": ")
            raise AgoInputError(first_path, f"{what} ({len(bad)} of {len(samples)} pseudo-label samples are missing "
                                "or damaged; rerun the same `ago pseudo-labels` command: it remakes them)")

    def labels(self, scene: str, token: str):
        return load_pseudo_labels(self.root, scene, token)

    def embeds(self, scene: str, token: str):
        return load_voxel_embeds(self.root, scene, token)


def _zip_members_problem(path: Path, keys) -> str | None:
    """What is wrong with an .npz's zip directory (truncated file, missing arrays), or None."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as z:
            names = set(z.namelist())
    except (zipfile.BadZipFile, OSError) as e:
        return f"not a readable npz file ({e.__class__.__name__}: {e}); truncated?"
    missing = [k for k in keys if f"{k}.npy" not in names]
    return f"missing arrays {missing}" if missing else None


# ------------------------------------------------------------------------------------------------
# Driver
# ------------------------------------------------------------------------------------------------
_COMPARED = ("format_version", "label_space", "grid", "segmenter", "embedder", "carve", "config")


def make_meta(label_space, segmenter, embedder, config: PseudoLabelConfig, command: str = "") -> dict:
    return {
        "format_version": FORMAT_VERSION,
        "label_space": {"name": label_space.name, "classes": label_space.class_names,
                        "sha256": label_space.sha256,
                        "prompt_file": str(label_space.source) if label_space.source else None,
                        **table_record(label_space.class_table)},
        "grid": config.grid.to_dict(),
        "segmenter": {"name": segmenter.name, "config": segmenter.config_dict()},
        "embedder": None if embedder is None else {"name": embedder.name, "config": embedder.config_dict(),
                                                   "channels": getattr(embedder, "channels", None),
                                                   "encoder_id": embedder_encoder_id(embedder)},
        "num_keyframes": config.num_keyframes,
        "interval": config.interval,
        "nonkey_sweeps": config.nonkey_sweeps,
        "raycast": config.raycast,
        "carve": config.carve_name,
        "config": config.to_dict(),
        "free_index": FREE,
        "ignore_index": IGNORE,
        "created_by": command,
    }


def _differences(a: dict, b: dict) -> list[str]:
    def strip(m: dict) -> dict:
        m = json.loads(json.dumps({k: m.get(k) for k in _COMPARED}))
        m["carve"] = m["carve"] or "all"            # folders from before --carve
        if isinstance(m.get("config"), dict):   # folders from before non-key sweeps: same meaning, older names
            c = m["config"]
            if "num_sweeps" in c and "num_keyframes" not in c:
                c["num_keyframes"] = c.pop("num_sweeps")
            c.setdefault("nonkey_sweeps", 0)
            c.setdefault("carve", None)           # folders from before --carve: every ray carved to its hit
            c.setdefault("moving", "aggregate")   # folders from before --moving: every class aggregated
        if m.get("label_space"):
            m["label_space"].pop("prompt_file", None)
        if m.get("embedder"):
            m["embedder"].pop("channels", None)   # files backends learn it from the first file
            m["embedder"].pop("encoder_id", None)   # folders from before encoder ids lack it
            (m["embedder"].get("config") or {}).pop("channels", None)
        return m
    sa, sb = strip(a), strip(b)
    return [k for k in _COMPARED if sa.get(k) != sb.get(k)]


class LiftCache:
    """The last few lifted frames (labels only), so that neighbouring keyframes share the labelling work.

    Camera images are dropped once a frame is lifted; the synthetic extras are kept (the simulated
    embedder reads them when the frame becomes a keyframe).
    """

    def __init__(self, ds, segmenter, ego_box, size: int, nonkey_sweeps: int = 0):
        self.ds, self.segmenter, self.ego_box = ds, segmenter, ego_box
        self.size = max(1, size)
        self.nonkey_sweeps = nonkey_sweeps
        self.items: OrderedDict[int, tuple[Frame, list[LiftedFrame]]] = OrderedDict()

    def get(self, i: int) -> tuple[Frame, list[LiftedFrame]]:
        """(frame, [its own lifted sweep, then its non-key sweeps' lifted points])."""
        if i in self.items:
            self.items.move_to_end(i)
            return self.items[i]
        frame = self.ds[i]
        nonkey = self.ds.nonkey_sweeps(i, self.nonkey_sweeps) if self.nonkey_sweeps > 0 else []
        lifted = lift_frame_and_sweeps(frame, self.segmenter, nonkey, None, self.ego_box)
        frame.images = {}
        self.items[i] = (frame, lifted)
        while len(self.items) > self.size:
            self.items.popitem(last=False)
        return frame, lifted


def check_track_tables(ds) -> None:
    """`--moving track` needs the dataset's box tables: refused with one line naming --moving when it lacks them."""
    root = getattr(ds, "root", None)
    missing = list(BOX_TABLES) if root is None else box_tables_missing(root)
    if missing:
        where = f" in {root}" if root is not None else ""
        raise AgoInputError("--moving", f"track needs the dataset's box tables ({', '.join(missing)} missing{where}); "
                            "use --moving keyframe or aggregate")


def dataset_tracks(ds, config: PseudoLabelConfig) -> DatasetBoxes | None:
    """The dataset's annotated boxes when config.moving is "track" (check_track_tables first), else None."""
    if config.moving != "track":
        return None
    check_track_tables(ds)
    return DatasetBoxes(ds.root, "--moving track")


def pseudo_sample(ds, i: int, label_space, segmenter, embedder, config: PseudoLabelConfig,
                  cache: LiftCache | None = None, boxes: DatasetBoxes | None = None) -> PseudoSample:
    """Pseudo-labels (and voxel embeddings) of dataset index i, in memory. boxes: `dataset_tracks(ds, config)`
    when the caller has it (--moving track; None loads it here)."""
    cache = cache or LiftCache(ds, segmenter, config.ego_box, config.num_keyframes * config.interval + 1,
                               config.nonkey_sweeps)
    ids = frames_to_aggregate(ds, i, config.num_keyframes, config.interval)
    pairs = [cache.get(j) for j in ids]
    moving = moving_classes(label_space) if config.separates_moving else None
    boxes = boxes if boxes is not None else dataset_tracks(ds, config)
    key = pairs[0][0]
    now = boxes.by_instance(key.token, key.ego2global) if boxes is not None else None
    lifted: list[LiftedFrame] = []   # keyframe i's own sweep first (build_sample embeds from lifted[0])
    tracks: list = []                # per lifted frame: (its keyframe's boxes, the sample's), or None
    for k, (frame, parts) in enumerate(pairs):
        own = parts[0]
        if embedder is not None and (k == 0 or config.embed_all_frames):
            own = attach_features(frame, own, embedder)
        lifted += [own] + list(parts[1:])
        then = boxes.by_instance(frame.token, key.ego2global) if boxes is not None and k > 0 else None
        tracks += [None if then is None else (then, now)] + [None] * (len(parts) - 1)
    return build_sample(key, lifted, label_space.num_classes, config, own=len(pairs[0][1]), moving=moving,
                        tracks=tracks)


def _cache_for(ds, segmenter, config: PseudoLabelConfig) -> LiftCache:
    """A LiftCache spanning the window of keyframes one sample aggregates (capped in memory)."""
    return LiftCache(ds, segmenter, config.ego_box,
                     min(config.num_keyframes * config.interval + config.interval + 1, 64), config.nonkey_sweeps)


def _label_and_save(job: dict, indices: list[int], cache: LiftCache) -> int:
    for i in indices:
        sample = pseudo_sample(job["ds"], i, job["label_space"], job["segmenter"], job["embedder"], job["config"],
                               cache, job.get("boxes"))
        save_sample(job["out"], job["ds"].scene_of(i), job["ds"].sample_tokens[i], sample)
    return len(indices)


_WORKER_JOB: dict | None = None   # set once per worker process by _init_worker


def _init_worker(job: dict) -> None:
    global _WORKER_JOB
    _WORKER_JOB = job


def _label_scene(indices: list[int]) -> int:
    """One scene's samples in a worker process (its own cache: scenes share no frames)."""
    job = _WORKER_JOB
    return _label_and_save(job, indices, _cache_for(job["ds"], job["segmenter"], job["config"]))


def scene_groups(ds, indices: list[int]) -> list[list[int]]:
    """Dataset indices (sorted) -> runs of consecutive indices of one scene, in order."""
    groups: list[list[int]] = []
    for i in indices:
        if groups and ds.scene_of(groups[-1][-1]) == ds.scene_of(i):
            groups[-1].append(i)
        else:
            groups.append([i])
    return groups


def generate(ds, indices: list[int], out_dir: str | Path, label_space, segmenter, embedder,
             config: PseudoLabelConfig, command: str = "", progress: bool = True, jobs: int = 1) -> dict:
    """Write pseudo-labels for dataset `indices` into out_dir; resumable. Gives counts and timing.

    jobs > 1 labels whole scenes in that many worker processes (the samples are the same for any
    value: every random draw of the simulated backends is seeded per image, not per run).

    A new folder gets nothing (no meta.json) until the first sample has been computed in memory: bad
    settings (a simulated segmenter on real images, a missing mask file, ...) fail with nothing written.
    On resume, each existing sample is checked (its arrays read back against the grid); a damaged one
    (e.g. a labels.npz cut short by a kill) is made again, and counted in "remade"."""
    out = Path(out_dir)
    meta = make_meta(label_space, segmenter, embedder, config, command)
    boxes = dataset_tracks(ds, config)   # --moving track: the boxes, or its one-line refusal, before any work
    meta_path = out / "meta.json"
    indices = sorted(set(int(i) for i in indices))
    if not indices:
        raise AgoInputError(out, "no samples to label (empty split or --limit)")
    remade = 0
    if meta_path.is_file():
        old = PseudoLabelDir(out).meta
        diff = _differences(old, meta)
        if diff:
            raise AgoInputError(meta_path, f"this folder holds pseudo-labels made with other settings "
                                f"({', '.join(diff)} differ); use another --out or delete it")
        folder = PseudoLabelDir(out)
        existing = [i for i in indices if folder.has(ds.scene_of(i), ds.sample_tokens[i])]
        checked = track(existing, "checking existing", total=len(existing)) if progress and existing else existing
        damaged = {i for i in checked if folder.sample_problem(ds.scene_of(i), ds.sample_tokens[i]) is not None}
        remade = len(damaged)
        todo = [i for i in indices if i in damaged or i not in set(existing)]
        first = None
    else:
        if label_space.source is None or not Path(label_space.source).is_file():
            raise AgoInputError(label_space.source, "prompt file not found (it is copied into the output)")
        todo = list(indices)
        # the window of keyframes one sample uses spans num_keyframes * interval keyframes; cap the memory
        first_cache = LiftCache(ds, segmenter, config.ego_box, 4, config.nonkey_sweeps)
        first = pseudo_sample(ds, todo[0], label_space, segmenter, embedder, config, first_cache, boxes)  # settings work
        out.mkdir(parents=True, exist_ok=True)
        write_bytes(out / "label_space.txt", Path(label_space.source).read_bytes())
        write_json(meta_path, meta)
    folder = PseudoLabelDir(out)

    t0 = time.perf_counter()
    rest = list(todo)
    if first is not None:
        save_sample(out, ds.scene_of(rest[0]), ds.sample_tokens[rest[0]], first)
        rest = rest[1:]
    job = {"ds": ds, "label_space": label_space, "segmenter": segmenter, "embedder": embedder, "config": config,
           "out": str(out), "boxes": boxes}
    # neighbouring keyframes share lifted frames: process in dataset (scene, time) order
    groups = scene_groups(ds, rest)
    if jobs > 1 and len(groups) > 1:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor, as_completed

        with ProcessPoolExecutor(max_workers=min(jobs, len(groups)), mp_context=mp.get_context("spawn"),
                                 initializer=_init_worker, initargs=(job,)) as ex:
            futures = {ex.submit(_label_scene, g): len(g) for g in groups}

            def frames_done():   # the bar counts frames: a finished scene advances it by its frames
                for fut in as_completed(futures):
                    fut.result()
                    yield from range(futures[fut])
            for _ in (track(frames_done(), "pseudo-labels (frames)", total=len(rest)) if progress else frames_done()):
                pass
    else:
        cache = _cache_for(ds, segmenter, config)
        items = track(rest, "pseudo-labels", total=len(rest)) if progress else rest
        for i in items:
            _label_and_save(job, [i], cache)
    seconds = time.perf_counter() - t0
    channels = getattr(embedder, "channels", None)
    if embedder is not None and channels is not None and folder.meta.get("embedder", {}).get("channels") is None:
        folder.meta["embedder"]["channels"] = int(channels)   # file backends learn it from the first file
        write_json(meta_path, folder.meta)
    return {"requested": len(indices), "written": len(todo), "skipped": len(indices) - len(todo),
            "remade": remade, "seconds": round(seconds, 3),
            "frames_per_s": round(len(todo) / seconds, 3) if todo and seconds > 0 else None}
