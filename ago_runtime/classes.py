"""The Occ3D-nuScenes class table: ids, names, colours.

Ids 0..16 follow nuScenes-lidarseg's 16+1 challenge classes (0 = others), 17 = free.
Colours are the palette Occ3D / SurroundOcc / the AGO paper use in their figures (RGB).

The label table from data (`ClassTable`, `OCC3D_NUSCENES`, `OCC3D_WAYMO`, `load_class_table`):
class names, the id each class has in the files, the free id, colours.

Occ3D-nuScenes stores 17 classes as ids 0..16 and free as 17; Occ3D-Waymo stores 15 classes as ids
0..14 and free as 23 (docs/dataset_format.md, "Occ3D-Waymo"). A `ClassTable` says which, so the
metric and the pictures need not assume one dataset:

- `names[k]`, `ids[k]`: class k and the label value it has in the ground-truth files;
- `free_id`: the label value of free voxels; `ignore_ids`: values that are never scored (255);
- `colors`: one RGB colour per class, then one for free.

The *dense* order is the classes in table order, then free: dense index k for class k and
`num_classes` for free (Occ3D-nuScenes: dense index == file id). `dense_lut()` maps file ids to it.

Shipped: `OCC3D_NUSCENES` (the ids and colours of `ago_runtime.classes`, unchanged) and
`OCC3D_WAYMO`. `load_class_table(name_or_path)` takes a shipped name or a JSON file:

    {"name": "my_table", "free_id": 23, "ignore_ids": [255],
     "classes": [{"name": "vehicle", "id": 1, "color": [0, 150, 245]}, ...],
     "free_color": [240, 240, 240]}

("color" and "free_color" are optional: a class without one gets a distinct hue from a fixed series,
free gets light grey.) Reading is bounded (MAX_TABLE_BYTES, MAX_CLASSES) and every problem is one
AgoInputError naming the file.

Where a table comes from: a dataset folder's `class_table.json` (TABLE_FILE), else its layout's; a prompt file's
`@table:` line (a shipped name or a JSON file). Banks, checkpoints, pseudo-label folders and bundles record it with
`table_record` (nothing for Occ3D-nuScenes, a shipped table by name, any other as its JSON form) and read it back
with `table_from_ref`.
"""

from __future__ import annotations

import colorsys
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ago_runtime.errors import AgoInputError
from ago_runtime.readers import read_json

OCC3D_CLASSES: tuple[str, ...] = (
    "others",                # 0
    "barrier",               # 1
    "bicycle",               # 2
    "bus",                   # 3
    "car",                   # 4
    "construction_vehicle",  # 5
    "motorcycle",            # 6
    "pedestrian",            # 7
    "traffic_cone",          # 8
    "trailer",               # 9
    "truck",                 # 10
    "driveable_surface",     # 11
    "other_flat",            # 12
    "sidewalk",              # 13
    "terrain",               # 14
    "manmade",               # 15
    "vegetation",            # 16
    "free",                  # 17
)
FREE = 17
IGNORE = 255
# Training only, never written to a file: a pseudo-label voxel the LiDAR hit but no 2-D mask labelled
# ("occupied, class unknown"): the occupancy loss counts it occupied, the grounding loss ignores it.
OCCUPIED_UNLABELLED = 254
NUM_SEMANTIC = 17  # classes 0..16
OCC3D_ID = {name: i for i, name in enumerate(OCC3D_CLASSES)}

# RGB colours, one per id 0..17 (free is drawn light grey where it is drawn at all).
OCC3D_COLORS = np.array(
    [
        [0, 0, 0],         # others
        [255, 120, 50],    # barrier
        [255, 192, 203],   # bicycle
        [255, 255, 0],     # bus
        [0, 150, 245],     # car
        [0, 255, 255],     # construction_vehicle
        [200, 180, 0],     # motorcycle
        [255, 0, 0],       # pedestrian
        [255, 240, 150],   # traffic_cone
        [135, 60, 0],      # trailer
        [160, 32, 240],    # truck
        [255, 0, 255],     # driveable_surface
        [139, 137, 137],   # other_flat
        [75, 0, 75],       # sidewalk
        [150, 240, 80],    # terrain
        [230, 230, 250],   # manmade
        [0, 175, 0],       # vegetation
        [240, 240, 240],   # free
    ],
    dtype=np.uint8,
)

# Classes the paper's mIoU* leaves out (no reliable prompt for them).
MIOU_STAR_EXCLUDED = ("others", "other_flat")


def class_color(name_or_id: str | int) -> np.ndarray:
    i = OCC3D_ID[name_or_id] if isinstance(name_or_id, str) else int(name_or_id)
    return OCC3D_COLORS[i]


# ---------------------------------------------------------------------------- the label table from data
MAX_TABLE_BYTES = 1 << 20   # a class-table JSON file larger than 1 MiB is refused unread
MAX_CLASSES = 254           # label values are uint8 and 255 is the ignore value
FREE_COLOR = (240, 240, 240)
UNKNOWN_ID_COLOR = (128, 128, 128)   # label values the table does not name (pictures only)


def name_key(name: str) -> str:
    """Comparison key of class names: case, spaces, hyphens and underscores don't matter."""
    return re.sub(r"[\s_\-]+", "_", str(name).strip().lower())


def _hue_series(n: int) -> list[tuple[int, int, int]]:
    """n distinct saturated colours, the same list for the same n (golden-ratio hue steps)."""
    out = []
    for step in range(n):
        h = (0.07 + 0.61803398875 * step) % 1.0
        s = 0.75 if step % 2 == 0 else 0.55
        v = 0.95 if (step // 2) % 2 == 0 else 0.75
        out.append(tuple(int(round(c * 255)) for c in colorsys.hsv_to_rgb(h, s, v)))
    return out


@dataclass(frozen=True)
class ClassTable:
    name: str
    names: tuple[str, ...]                       # semantic classes, dense order
    ids: tuple[int, ...]                         # label value of each class in the files
    free_id: int                                 # label value of free voxels
    colors: tuple[tuple[int, int, int], ...]     # RGB per class, then free
    ignore_ids: tuple[int, ...] = (IGNORE,)

    def __post_init__(self):
        object.__setattr__(self, "names", tuple(str(n) for n in self.names))
        object.__setattr__(self, "ids", tuple(int(i) for i in self.ids))
        object.__setattr__(self, "free_id", int(self.free_id))
        object.__setattr__(self, "ignore_ids", tuple(int(i) for i in self.ignore_ids))
        object.__setattr__(self, "colors", tuple(tuple(int(c) for c in col) for col in self.colors))
        problem = self._problem()
        if problem:
            raise ValueError(f"class table {self.name!r}: {problem}")

    def _problem(self) -> str | None:
        n = len(self.names)
        if not 1 <= n <= MAX_CLASSES:
            return f"needs 1..{MAX_CLASSES} classes, got {n}"
        if len(self.ids) != n:
            return f"{n} names but {len(self.ids)} ids"
        keys = [name_key(x) for x in self.names]
        if any(not k.strip("_") for k in keys):
            return "a class name is empty"
        if len(set(keys)) != n or "free" in keys:
            return "class names must be unique and none may be 'free'"
        values = list(self.ids) + [self.free_id]
        if any(not 0 <= v <= 254 for v in values):
            return "ids and the free id must lie in 0..254"
        if len(set(values)) != len(values):
            return "ids (free included) must be unique"
        if any(not 0 <= v <= 255 for v in self.ignore_ids) or set(self.ignore_ids) & set(values):
            return "ignore ids must lie in 0..255 and differ from every class id and the free id"
        if len(self.colors) != n + 1 or any(len(c) != 3 or min(c) < 0 or max(c) > 255 for c in self.colors):
            return f"needs {n + 1} RGB colours (0..255), one per class and one for free"
        return None

    # ---- the dense order --------------------------------------------------------------------------
    @property
    def num_classes(self) -> int:
        return len(self.names)

    @property
    def free_index(self) -> int:
        """Dense index of free (= num_classes)."""
        return len(self.names)

    @property
    def label_names(self) -> list[str]:
        """Dense order: the class names, then "free"."""
        return list(self.names) + ["free"]

    def dense_colors(self) -> np.ndarray:
        """(num_classes + 1, 3) uint8 RGB in dense order."""
        return np.array(self.colors, dtype=np.uint8)

    def dense_lut(self) -> np.ndarray:
        """int16 (256,): file label value -> dense index; ignore ids -> 255; values the table does not name -> -1."""
        lut = np.full(256, -1, dtype=np.int16)
        lut[list(self.ids)] = np.arange(self.num_classes)
        lut[self.free_id] = self.free_index
        lut[list(self.ignore_ids)] = IGNORE
        return lut

    def to_dense(self, labels: np.ndarray, what: str = "labels") -> np.ndarray:
        """uint8 labels in dense order (free = num_classes, ignore = 255); ValueError naming the values the table lacks."""
        a = np.asarray(labels)
        if a.size and (a.min() < 0 or a.max() > 255):
            raise ValueError(f"{what} must lie in 0..255, found {int(a.min())}..{int(a.max())}")
        out = self.dense_lut()[a.astype(np.uint8)]
        if a.size and out.min() < 0:
            bad = sorted(set(np.unique(a[out < 0]).tolist()))[:8]
            raise ValueError(f"{what} hold values {bad} that class table {self.name!r} does not name "
                             f"(ids {list(self.ids)}, free {self.free_id}, ignore {list(self.ignore_ids)})")
        return out.astype(np.uint8)

    @property
    def is_dense(self) -> bool:
        """True when file ids already are the dense order (Occ3D-nuScenes)."""
        return self.ids == tuple(range(self.num_classes)) and self.free_id == self.num_classes

    def dense(self) -> "ClassTable":
        """This table in its dense order (ids 0..K-1, free K): the table of a prediction file's `semantics`."""
        return ClassTable(self.name, self.names, tuple(range(self.num_classes)), self.free_index, self.colors,
                          self.ignore_ids)

    # ---- by file id -------------------------------------------------------------------------------
    def palette_by_id(self) -> np.ndarray:
        """(max id + 1, 3) uint8 RGB indexed by the file label value (free included); unnamed values grey."""
        top = max(max(self.ids), self.free_id)
        pal = np.tile(np.array(UNKNOWN_ID_COLOR, np.uint8), (top + 1, 1))
        pal[list(self.ids)] = np.array(self.colors[:-1], np.uint8)
        pal[self.free_id] = self.colors[-1]
        return pal

    def id_of(self, name: str) -> int:
        """File label value of a class name ("Traffic light" == "traffic_light"); KeyError if absent."""
        keys = [name_key(n) for n in self.names]
        try:
            return self.ids[keys.index(name_key(name))]
        except ValueError:
            raise KeyError(f"no class {name!r} in class table {self.name!r} ({', '.join(self.names)})") from None

    def name_of(self, label_id: int) -> str:
        if int(label_id) == self.free_id:
            return "free"
        return self.names[self.ids.index(int(label_id))]

    # ---- files ------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {"name": self.name, "free_id": self.free_id, "ignore_ids": list(self.ignore_ids),
                "classes": [{"name": n, "id": i, "color": list(c)} for n, i, c in zip(self.names, self.ids, self.colors)],
                "free_color": list(self.colors[-1])}

    @classmethod
    def from_dict(cls, d, source: str | Path | None = None) -> "ClassTable":
        """Build and check a table from its JSON form; AgoInputError naming `source` for any problem."""
        where = str(source) if source is not None else "<class table>"
        if not isinstance(d, dict):
            raise AgoInputError(where, f"a class table is a JSON object, got {type(d).__name__}")
        unknown = sorted(set(d) - {"name", "free_id", "ignore_ids", "classes", "free_color"})
        if unknown:
            raise AgoInputError(where, f"unknown keys {unknown} (known: name, free_id, ignore_ids, classes, free_color)")
        rows = d.get("classes")
        if not isinstance(rows, list) or not rows:
            raise AgoInputError(where, "'classes' must be a non-empty list of {\"name\", \"id\"[, \"color\"]}")
        if len(rows) > MAX_CLASSES:
            raise AgoInputError(where, f"{len(rows)} classes (at most {MAX_CLASSES})")
        names, ids, colors = [], [], []
        auto = iter(_hue_series(len(rows)))
        for k, row in enumerate(rows):
            if not isinstance(row, dict) or not isinstance(row.get("name"), str) or not _is_int(row.get("id")):
                raise AgoInputError(where, f"classes[{k}] must be {{\"name\": text, \"id\": integer[, \"color\": [r, g, b]]}}")
            if len(row["name"]) > 100 or not row["name"].strip():
                raise AgoInputError(where, f"classes[{k}]: a name of 1..100 characters")
            names.append(row["name"].strip())
            ids.append(row["id"])
            colors.append(_color(row["color"], where, f"classes[{k}].color") if "color" in row else next(auto))
        if not _is_int(d.get("free_id")):
            raise AgoInputError(where, "'free_id' (the label value of free voxels) must be an integer")
        ignore = d.get("ignore_ids", [IGNORE])
        if not isinstance(ignore, list) or not all(_is_int(v) for v in ignore) or len(ignore) > 256:
            raise AgoInputError(where, "'ignore_ids' must be a list of integers")
        colors.append(_color(d["free_color"], where, "free_color") if "free_color" in d else FREE_COLOR)
        name = d.get("name", Path(where).stem if source is not None else "custom")
        if not isinstance(name, str) or not name.strip() or len(name) > 100:
            raise AgoInputError(where, "'name' must be a text of 1..100 characters")
        try:
            table = cls(name.strip(), tuple(names), tuple(ids), d["free_id"], tuple(colors), tuple(ignore))
        except ValueError as e:
            raise AgoInputError(where, str(e).split(": ", 1)[-1]) from None
        if table.name in SHIPPED_TABLES and SHIPPED_TABLES[table.name] != table:
            raise AgoInputError(where, f"'name' {table.name!r} is a shipped table's and this table differs from it: "
                                "give yours another name")
        return table


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _color(v, where: str, what: str) -> tuple[int, int, int]:
    if not isinstance(v, list) or len(v) != 3 or not all(_is_int(c) and 0 <= c <= 255 for c in v):
        raise AgoInputError(where, f"{what} must be [r, g, b] with integers 0..255")
    return tuple(v)


OCC3D_NUSCENES = ClassTable(
    "occ3d_nuscenes", OCC3D_CLASSES[:NUM_SEMANTIC], tuple(range(NUM_SEMANTIC)), FREE,
    tuple(tuple(int(c) for c in col) for col in OCC3D_COLORS), (IGNORE,))

# Occ3D-Waymo: ids 0..14 as the Occ3D README and tools/eval_waymo.py list them, free stored as 23
# (docs/dataset_format.md cites the sources). Colours: the nuScenes colour of the nearest nuScenes
# class where there is one, distinct ones for the classes nuScenes lacks.
OCC3D_WAYMO = ClassTable(
    "occ3d_waymo",
    ("general_object", "vehicle", "pedestrian", "sign", "bicyclist", "traffic_light", "pole",
     "construction_cone", "bicycle", "motorcycle", "building", "vegetation", "tree_trunk", "road", "walkable"),
    tuple(range(15)), 23,
    ((0, 0, 0),          # general_object (as nuScenes others)
     (0, 150, 245),      # vehicle (car)
     (255, 0, 0),        # pedestrian
     (255, 215, 0),      # sign
     (255, 100, 160),    # bicyclist
     (255, 140, 0),      # traffic_light
     (90, 90, 160),      # pole
     (255, 240, 150),    # construction_cone (traffic_cone)
     (255, 192, 203),    # bicycle
     (200, 180, 0),      # motorcycle
     (230, 230, 250),    # building (manmade)
     (0, 175, 0),        # vegetation
     (135, 60, 0),       # tree_trunk
     (255, 0, 255),      # road (driveable_surface)
     (75, 0, 75),        # walkable (sidewalk)
     FREE_COLOR),        # free
    (IGNORE,))

SHIPPED_TABLES = {t.name: t for t in (OCC3D_NUSCENES, OCC3D_WAYMO)}
TABLE_FILE = "class_table.json"   # a dataset root's own class table (dataset_class_table)


def shipped_name(table: ClassTable) -> str | None:
    """The shipped name of `table` when it is one of SHIPPED_TABLES (same content), else None."""
    return table.name if SHIPPED_TABLES.get(table.name) == table else None


def table_ref(table: ClassTable) -> str | dict:
    """How banks and bundles record a class table: a shipped table by its name, any other by its JSON form."""
    return shipped_name(table) or table.to_dict()


def table_record(table: ClassTable, key: str = "class_table") -> dict:
    """`{key: table_ref(table)}`, or {} for Occ3D-nuScenes: what a bank, checkpoint, pseudo-label folder or bundle
    writes of its table (nothing for the default every reader assumes, so nuScenes files stay as they were)."""
    return {} if table == OCC3D_NUSCENES else {key: table_ref(table)}


def table_from_ref(ref, source: str | Path | None = None) -> ClassTable:
    """The inverse of `table_ref` (a shipped name or a table's JSON form); AgoInputError naming `source`."""
    if isinstance(ref, str):
        if ref not in SHIPPED_TABLES:
            raise AgoInputError(source, f"class table {ref!r} is not a shipped one ({', '.join(SHIPPED_TABLES)}) "
                                "and its definition is not recorded")
        return SHIPPED_TABLES[ref]
    return ClassTable.from_dict(ref, source=source)


def load_class_table(name_or_path: str | Path, relative_to: str | Path | None = None) -> ClassTable:
    """A shipped table by name ("occ3d_nuscenes", "occ3d_waymo"; hyphens allowed) or a JSON file (see the module
    docstring); a relative path is taken from the folder `relative_to` when given (a prompt file's folder)."""
    key = name_key(str(name_or_path))
    path = Path(name_or_path)
    if relative_to is not None and not path.is_absolute():
        path = Path(relative_to) / path
    if key in SHIPPED_TABLES and not path.is_file():
        return SHIPPED_TABLES[key]
    if not path.is_file():
        raise AgoInputError(path, f"class table not found (shipped: {', '.join(SHIPPED_TABLES)})")
    size = path.stat().st_size
    if size > MAX_TABLE_BYTES:
        raise AgoInputError(path, f"class table of {size} bytes (at most {MAX_TABLE_BYTES})")
    return ClassTable.from_dict(read_json(path, expect=dict), source=path)


def dataset_class_table(root: str | Path, default):
    """The class table of the labels a dataset folder holds: its own `class_table.json` (TABLE_FILE, a class-table
    JSON file: `load_class_table`) when it has one, else the layout's `default`."""
    path = Path(root) / TABLE_FILE
    return load_class_table(path) if path.is_file() else default
