"""The bundle contract: what `bundle.json` holds (format 5), as dataclasses, and the checks made against it.

`ago export` (ago_export/export.py) builds a `BundleContract` and writes it (`to_dict`); `Bundle.load`
(ago_runtime/predict/bundle.py) reads it (`BundleContract.from_dict`). Nothing else reads bundle.json, and
nothing reads it by string keys: every JSON object of it is one of the dataclasses below, whose `from_dict`
refuses a key the dataclass does not declare and one it declares that is missing.

    BundleContract
      format_version   5 (older bundles are refused with the command that re-exports them)
      ago_version, created_utc          who wrote it, when
      checkpoint       CheckpointRecord: the checkpoint it was exported from (path, sha256, step, epoch)
      model            ModelRecord: the training side's ModelConfig (a record; ago_train reads it back) and the opset
      grid, model_grid Grid (ago_runtime.geometry): the read-out grid and the grid the model was trained on
      preprocess       Preprocess (ago_runtime.geometry): the image preprocessing
      rig              RigSpec: the cameras the model takes, by name, and each camera's input image size
      training_rig     Rig (ago_runtime.geometry): the training rig's calibration (the fallback calibration)
      rig_source       where the training rig came from
      label_space      LabelSpaceSpec: the classes the model was trained on
      text_encoder     TextEncoderSpec: the encoder every bank must come from (id, hash, width)
      identifier       Identifier: the open-world identifier for banks with unknown classes
      banks, default_bank, bank_notes   bank name -> its key in `files`; a note per bank not built
      files            key -> FileEntry (path, sha256, size): every file of the bundle
      voxel_stages     VoxelStageSpec per ONNX graph of the per-voxel MLP after the planes
      hidden_dim, adapted_dim          widths of h (main branch) and g (adapted branch), stated once
      variants         name -> VariantSpec: other-precision copies of the graphs ("int8"), each graph by its key
      parity           ParityReport: the export's parity checks (fp32 graphs; text tower)

The other files are declared here too: heads.npz's arrays (`HEADS_NPZ`: names and shapes in the widths
above), the graphs' input and output names (`PLANES_INPUTS`, `PLANES_OUTPUTS`, `STAGE_INPUT`, `STAGE_OUTPUT`:
ago_export traces with them, the runtime runs and checks with them) and the card (ago_runtime/predict/card.py).

`BundleContract.from_dict` checks every field by value (`check_values`: sizes, mean / std, grids, widths,
the training rig, sha256 entries), so a bundle whose hashes were recomputed after tampering is still refused
before any work; the graphs' inputs and outputs are the contract's (`planes_signature`, `stage_signature`),
checked when a graph is opened (`check_graph`, from ago_runtime/predict/encoder.py).

Also here: the one check of a prompt bank against a bundle (`check_bank_fits`: text encoder id and width,
class count; every user of a bank calls it) and of a frame's cameras with the rig (`RigSpec.check_cameras`).
The identifier names (`Identifier`) and the two branches (`Branch`) are the decision's
(ago_runtime.predict.decision).
"""

from __future__ import annotations

import math
import re
import typing
from dataclasses import MISSING, dataclass, field, fields

from ago_runtime.classes import OCC3D_NUSCENES, ClassTable, table_from_ref, table_ref
from ago_runtime.errors import AgoInputError
from ago_runtime.geometry.camera import Rig, check_camera_names
from ago_runtime.geometry.grid import Grid, check_grid_dict
from ago_runtime.geometry.preprocess import Preprocess
from ago_runtime.predict.decision import Branch, Identifier

__all__ = ["BUNDLE_FORMAT", "BUNDLE_FORMAT_VERSION", "BUNDLE_JSON", "FileEntry",
           "VoxelStageSpec", "CameraSlot", "RigSpec", "TextEncoderSpec", "LabelClass", "LabelSpaceSpec",
           "CheckpointRecord", "ModelRecord", "ParityCheck", "TowerParity", "ParityReport", "VariantSpec",
           "HeadsSpec", "HEADS_NPZ", "PLANES_INPUTS", "PLANES_OUTPUTS", "STAGE_INPUT", "STAGE_OUTPUT",
           "BundleContract", "TensorSpec", "planes_signature", "planes_width", "stage_signature", "check_graph",
           "check_bank_fits", "file_sha256", "reexport_hint", "record_from_dict", "record_to_dict", "declared_keys",
           "typed_value"]


def file_sha256(path) -> str:
    """sha256 hex of a file's bytes (ago_runtime.vocab.text_encoder.file_sha256, memoised), imported when first
    used so that the CLI's option types (Identifier) cost no onnxruntime import."""
    from ago_runtime.vocab.text_encoder import file_sha256 as sha256_of_file

    return sha256_of_file(path)

BUNDLE_FORMAT = "ago-bundle"
BUNDLE_FORMAT_VERSION = 5
BUNDLE_JSON = "bundle.json"
MAX_VOXEL_STAGES = 16           # an exported decoder has 1-4
MAX_EMBED_DIM = 8192            # a text embedding's or a hidden layer's width
MAX_IMAGE_SIDE = 16384          # a model input image's side (pixels)
FLOAT_TENSOR = "tensor(float)"  # onnxruntime's name of a float32 graph input / output
REBUILD_BANK = "rebuild it with `ago prompts build <prompt file> -o BANK`"

# the graphs' input and output names (ago_export traces the graphs with them; the runtime feeds and checks them)
PLANES_INPUTS = ("images", "ego2img")
PLANES_OUTPUTS = ("plane_xy", "plane_xz", "plane_yz")
STAGE_INPUT = "x"
STAGE_OUTPUT = "y"


def reexport_hint(version) -> str:
    return (f"bundle format version {version} is no longer read (this ago reads {BUNDLE_FORMAT_VERSION}); "
            "re-export the checkpoint: `ago export CKPT -o BUNDLE_DIR`")


def _need(d: dict, key: str, kind, what: str):
    if not isinstance(d, dict) or key not in d:
        raise ValueError(f"{what} lacks {key!r}")
    value = d[key]
    if kind is not None and not isinstance(value, kind) or isinstance(value, bool) and kind is int:
        raise ValueError(f"{what}.{key} must be {getattr(kind, '__name__', kind)}, got {str(value)[:60]}")
    return value


def declared_keys(d, keys, what: str) -> dict:
    """`d` must be a JSON object with no key outside `keys` (what is read is what the contract declares)."""
    if not isinstance(d, dict):
        raise ValueError(f"{what} must be an object, got {str(d)[:60]}")
    extra = sorted(str(k) for k in d if k not in keys)
    if extra:
        raise ValueError(f"{what} has {extra[:4]}, which the bundle contract does not declare")
    return d


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _finite_numbers(v, n: int) -> bool:
    return (isinstance(v, list) and len(v) == n and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                         and math.isfinite(x) for x in v))


def typed_value(value, kind, where: str):
    """One JSON value against a record field's annotation: str, int, float (an int is taken), bool, list, dict,
    `X | None`, or another record (a dataclass: record_from_dict)."""
    args = typing.get_args(kind)
    if type(None) in args:
        if value is None:
            return None
        (kind,) = [a for a in args if a is not type(None)]
    origin = typing.get_origin(kind) or kind
    if isinstance(origin, type) and hasattr(origin, "__dataclass_fields__"):
        return record_from_dict(origin, value, where)
    ok = {str: isinstance(value, str), bool: isinstance(value, bool), int: _is_int(value),
          float: isinstance(value, (int, float)) and not isinstance(value, bool),
          list: isinstance(value, list), dict: isinstance(value, dict)}.get(origin)
    if not ok:
        raise ValueError(f"{where} must be {getattr(origin, '__name__', origin)}, got {str(value)[:60]}")
    return float(value) if origin is float else value


def record_from_dict(cls, d, what: str):
    """A flat record dataclass from its JSON object: exactly its fields (a field with a default may be absent),
    each of its annotated type (`typed_value`). ValueError naming `what`.<field> otherwise."""
    hints = typing.get_type_hints(cls)
    declared_keys(d, [f.name for f in fields(cls)], what)
    values = {}
    for f in fields(cls):
        if f.name not in d:
            if f.default is not MISSING or f.default_factory is not MISSING:
                continue
            raise ValueError(f"{what} lacks {f.name!r}")
        values[f.name] = typed_value(d[f.name], hints[f.name], f"{what}.{f.name}")
    return cls(**values)


def record_to_dict(rec) -> dict:
    """A record dataclass -> its JSON object, every field (nested records too)."""
    def plain(v):
        if hasattr(v, "__dataclass_fields__"):
            return record_to_dict(v)
        if isinstance(v, dict):
            return {k: plain(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [plain(x) for x in v]
        return v

    return {f.name: plain(getattr(rec, f.name)) for f in fields(rec)}


@dataclass(frozen=True)
class TensorSpec:
    """One input or output of a bundle graph as the contract states it: its name and shape, each axis an int
    (that size), "n" (a dynamic axis, any size at run time) or None (not stated). Every one is float32."""

    name: str
    shape: tuple

    def show(self) -> str:
        return f"{self.name} [{', '.join('?' if d is None else str(d) for d in self.shape)}]"


def planes_signature(cameras: int | None, height: int | None, width: int | None, grid_shape, planes_width: int):
    """planes.onnx: images (1,V,3,H,W) + ego2img (1,V,4,4) -> plane_xy (X,Y,Dh), plane_xz (X,Z,Dh), plane_yz (Y,Z,Dh)."""
    X, Y, Z = grid_shape
    images, ego2img = PLANES_INPUTS
    xy, xz, yz = PLANES_OUTPUTS
    return ([TensorSpec(images, (1, cameras, 3, height, width)), TensorSpec(ego2img, (1, cameras, 4, 4))],
            [TensorSpec(xy, (X, Y, planes_width)), TensorSpec(xz, (X, Z, planes_width)),
             TensorSpec(yz, (Y, Z, planes_width))])


def planes_width(stages: "list[VoxelStageSpec]", hidden_dim: int) -> int:
    """Dh of the planes: the first decoder stage's input width, or h's width when the decoder has no stage."""
    main = [s for s in stages if s.branch == Branch.MAIN]
    return main[0].input_dim if main else int(hidden_dim)


def stage_signature(spec: "VoxelStageSpec"):
    """voxels_<i>.onnx: x (n, input_dim) -> y (n, output_dim)."""
    return [TensorSpec(STAGE_INPUT, ("n", spec.input_dim))], [TensorSpec(STAGE_OUTPUT, ("n", spec.output_dim))]


def check_graph(session, signature, path, what: str) -> None:
    """The inputs and outputs of an opened graph (onnxruntime session; nothing run) against `signature`
    (planes_signature / stage_signature): names in order, float32, the stated sizes and dynamic axes; else
    AgoInputError(path, "<what>: ..."), so that a graph swapped for another is refused by name."""
    for kind, have, want in (("inputs", session.get_inputs(), signature[0]), ("outputs", session.get_outputs(), signature[1])):
        names = [t.name for t in have]
        if names != [t.name for t in want]:
            raise AgoInputError(path, f"{what}: graph {kind} {names[:6]}, the contract says {[t.name for t in want]} "
                                "(a graph of another part or bundle?)")
        for t, w in zip(have, want):
            shape = list(t.shape or [])
            fits = len(shape) == len(w.shape) and all(
                e is None or (not _is_int(d) if e == "n" else d == e) for d, e in zip(shape, w.shape))
            if t.type != FLOAT_TENSOR or not fits:
                got = f"{t.name} [{', '.join(str(d) for d in shape)}] {t.type}"
                raise AgoInputError(path, f"{what}: graph {kind[:-1]} {got}, the contract says {w.show()} float32 "
                                    "(a graph of another part or bundle?)")


@dataclass
class FileEntry:
    path: str          # relative to the bundle folder (checked to stay inside it by Bundle.load)
    sha256: str
    size: int

    @classmethod
    def of(cls, root, rel: str) -> "FileEntry":
        p = root / rel
        return cls(rel, file_sha256(p), p.stat().st_size)

    @classmethod
    def from_dict(cls, d: dict, what: str) -> "FileEntry":
        return record_from_dict(cls, d, what)


@dataclass
class VoxelStageSpec:
    """One ONNX graph of the per-voxel MLP after the planes: x (n, input_dim) -> y = x W^T + b (n, output_dim),
    then softplus in the runtime when activation == "softplus". branch MAIN: a decoder stage (runs on every
    voxel, toward h); ADAPTED: an adapter stage (from h toward g; runs on the voxels that need the adapted
    branch)."""

    file: str          # key into BundleContract.files
    input_dim: int
    output_dim: int
    activation: str    # "softplus" | "none"
    branch: Branch

    ACTIVATIONS = ("softplus", "none")

    def to_dict(self) -> dict:
        return {"file": self.file, "input_dim": self.input_dim, "output_dim": self.output_dim,
                "activation": self.activation, "branch": self.branch.value}

    @classmethod
    def from_dict(cls, d: dict, what: str) -> "VoxelStageSpec":
        declared_keys(d, [f.name for f in fields(cls)], what)
        act = _need(d, "activation", str, what)
        if act not in cls.ACTIVATIONS:
            raise ValueError(f"{what}.activation must be one of {cls.ACTIVATIONS}, got {act!r}")
        return cls(_need(d, "file", str, what), _need(d, "input_dim", int, what), _need(d, "output_dim", int, what),
                   act, Branch(_need(d, "branch", str, what)))


@dataclass
class CameraSlot:
    name: str
    width: int         # the model's input image size for this camera (images are resized to it)
    height: int


@dataclass
class RigSpec:
    """The cameras the model takes, in its input order."""

    cameras: list[CameraSlot]

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def check_cameras(self, names, source=None) -> None:
        """Refuse a frame whose cameras are not exactly this rig's, naming the first camera that differs."""
        check_camera_names(names, self.names, source, whose="bundle's")

    def to_dict(self) -> dict:
        return record_to_dict(self)

    @classmethod
    def from_dict(cls, d: dict, what: str = "rig") -> "RigSpec":
        declared_keys(d, ["cameras"], what)
        cams = _need(d, "cameras", list, what)
        slots = [record_from_dict(CameraSlot, c, f"{what}.cameras") for c in cams]
        if not slots or len({s.name for s in slots}) != len(slots):
            raise ValueError(f"{what}.cameras must name at least one camera, each once")
        if any(not 1 <= s.width <= MAX_IMAGE_SIDE or not 1 <= s.height <= MAX_IMAGE_SIDE for s in slots):
            raise ValueError(f"{what}.cameras: image sizes must be 1..{MAX_IMAGE_SIDE} pixels")
        return cls(slots)


@dataclass
class TextEncoderSpec:
    id: str
    hash: str
    dim: int
    variant: str = ""

    def check_made_by(self, encoder_id: str, dim: int, source, what: str, fix: str) -> None:
        """The one check of a text encoder's output against this bundle's: `what` ("prompt bank", "text
        encoder"), made by `encoder_id` of width `dim`, is refused naming `source` unless both match."""
        if encoder_id != self.id or int(dim) != int(self.dim):
            raise AgoInputError(source, f"{what}: text encoder {encoder_id!r} (dim {dim}), the bundle needs "
                                f"{self.id!r} (dim {self.dim}); {fix}")

    def to_dict(self) -> dict:
        return record_to_dict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "TextEncoderSpec":
        _need(d, "variant", str, "text_encoder")
        spec = record_from_dict(cls, d, "text_encoder")
        if not 1 <= spec.dim <= MAX_EMBED_DIM:
            raise ValueError(f"text_encoder.dim must be an integer 1..{MAX_EMBED_DIM}, got {spec.dim!r}")
        return spec


@dataclass
class LabelClass:
    name: str
    table_ids: list[int]   # the class's ids in the label space's class table (LabelSpaceSpec.table); [] = none
    known: bool
    phrases: list[str]


@dataclass
class LabelSpaceSpec:
    name: str | None
    sha256: str
    classes: list[LabelClass]
    table: ClassTable = OCC3D_NUSCENES   # the class table the classes' table_ids index (ago_runtime.classes)

    @property
    def class_names(self) -> list[str]:
        return [c.name for c in self.classes]

    def to_dict(self) -> dict:
        return {"name": self.name, "sha256": self.sha256, "classes": [record_to_dict(c) for c in self.classes],
                "table": table_ref(self.table)}   # a shipped table's name, or the table itself

    @classmethod
    def from_dict(cls, d: dict) -> "LabelSpaceSpec":
        from ago_runtime.vocab.bank import MAX_INFER_CLASSES

        declared_keys(d, ["name", "sha256", "classes", "table"], "label_space")
        classes = _need(d, "classes", list, "label_space")
        if not 1 <= len(classes) <= MAX_INFER_CLASSES:
            raise ValueError(f"label_space.classes must list 1 to {MAX_INFER_CLASSES} classes")
        out = []
        for c in classes:
            rec = record_from_dict(LabelClass, c, "label_space.classes")
            if not all(_is_int(i) for i in rec.table_ids) or not all(isinstance(p, str) for p in rec.phrases):
                raise ValueError(f"label_space.classes: {rec.name!r} needs integer table_ids and text phrases")
            out.append(rec)
        try:
            table = table_from_ref(_need(d, "table", None, "label_space"), "label_space.table")
        except AgoInputError as e:
            raise ValueError(str(e)) from None
        known_ids = set(table.ids)
        for c in out:
            if not set(c.table_ids) <= known_ids:
                raise ValueError(f"label_space.classes: {c.name!r} has ids {c.table_ids} outside class table {table.name}")
        name = _need(d, "name", None, "label_space")
        if name is not None and not isinstance(name, str):
            raise ValueError(f"label_space.name must be a string or null, got {str(name)[:60]}")
        return cls(name, _need(d, "sha256", str, "label_space"), out, table)


@dataclass
class CheckpointRecord:
    """The checkpoint a bundle was exported from."""

    path: str
    sha256: str
    step: int
    epoch: int


@dataclass
class ModelRecord:
    """The model's training-side configuration (ago_train.model.ModelConfig.to_dict(): a record the runtime never
    reads; ago_train reads it back with ModelConfig.from_dict) and the ONNX opset of the graphs."""

    config: dict
    opset: int


@dataclass
class ParityTolerance:
    max_rel_err: float
    min_agreement: float


@dataclass
class ParityCheck:
    """One parity check of a set of graphs against the torch model on one frame (ago_export/parity.py)."""

    frame: str
    num_voxels: int
    rel_err_feat: float
    rel_err_feat_adapted: float
    agreement_main: float
    agreement_adapted: float
    agreement_identifier: float
    tolerance: ParityTolerance
    ok: bool


@dataclass
class TowerAgreement:
    min_cosine: float
    mean_cosine: float
    max_abs: float
    phrases: int


@dataclass
class TowerCheck:
    """The ONNX text tower against transformers and against the checkpoint's bank (ago_export/text_tower.py)."""

    transformers: TowerAgreement
    bank: TowerAgreement
    min_cosine_allowed: float
    ok: bool
    note: str | None = None


@dataclass
class TowerParity:
    fp32: TowerCheck
    shipped: str                     # the variant that ships: "onnx-fp32" or "onnx-int8"
    int8: TowerCheck | None = None


@dataclass
class ParityReport:
    """The export's parity checks: the fp32 graphs' (None when skipped: benchmarks only) and the text tower's
    (a bundle that ships one). Each variant's check is in its VariantSpec."""

    skipped: bool
    fp32: ParityCheck | None
    text_encoder: TowerParity | None

    def to_dict(self) -> dict:
        return record_to_dict(self)

    @classmethod
    def from_dict(cls, d) -> "ParityReport":
        return record_from_dict(cls, d, "parity")


@dataclass
class VariantSpec:
    """The graphs at another precision ("int8": `ago export --int8`): `graphs` maps each float32 graph's key in
    `files` (planes, then every voxel stage's) to this variant's graph's key; `method` says how it was made
    ("static-qdq": the planes graph static QDQ, per-channel weights, activations calibrated on training frames;
    the voxel stages dynamic; then "; sampled-feature convolutions float32" where the convolutions that make the
    sampled features stayed float, "; float32: MODULES" for `--int8-float`; ago_export/quantize.py); `parity` its
    check against torch."""

    precision: str
    method: str
    graphs: dict[str, str]
    parity: ParityCheck | None

    def to_dict(self) -> dict:
        return record_to_dict(self)

    @classmethod
    def from_dict(cls, d, what: str) -> "VariantSpec":
        v = record_from_dict(cls, d, what)
        if not all(isinstance(k, str) and isinstance(x, str) for k, x in v.graphs.items()):
            raise ValueError(f"{what}.graphs must map graph keys to file keys")
        return v


@dataclass(frozen=True)
class HeadsSpec:
    """heads.npz: each array's name and shape in the bundle's widths ("C" the embedding width, text_encoder.dim;
    "Dh" hidden_dim; "Da" adapted_dim; or a number), all float32. `optional` arrays are written together or
    not at all; every other one always. The exporter writes exactly these names (HeadWeights.to_arrays), the
    runtime reads exactly these (Bundle.load)."""

    shapes: tuple[tuple[str, tuple], ...]
    optional: tuple[str, ...]

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(n for n, _ in self.shapes)

    @property
    def required(self) -> tuple[str, ...]:
        return tuple(n for n in self.names if n not in self.optional)

    def check_names(self, names, source) -> None:
        """AgoInputError naming `source` for an array this spec does not declare, a required one missing, or
        only part of the optional group."""
        names = set(names)
        extra = sorted(names - set(self.names))
        if extra:
            raise AgoInputError(source, f"heads hold {extra[:4]}, which the bundle contract does not declare")
        missing = [n for n in self.required if n not in names]
        if missing:
            raise AgoInputError(source, f"heads lack {missing[0]!r}")
        if names & set(self.optional) and not set(self.optional) <= names:
            raise AgoInputError(source, f"heads hold {sorted(names & set(self.optional))} without "
                                f"{sorted(set(self.optional) - names)} ({' and '.join(self.optional)} go together)")

    def shape(self, name: str, widths: dict[str, int]) -> tuple[int, ...]:
        """The shape `name` must have, given {"C": .., "Dh": .., "Da": ..}."""
        return tuple(widths[d] if isinstance(d, str) else int(d) for d in dict(self.shapes)[name])


HEADS_NPZ = HeadsSpec(
    shapes=(("W_dec", ("C", "Dh")), ("b_dec", ("C",)), ("W_ad", ("C", "Da")), ("b_ad", ("C",)),
            ("free_embedding", ("C",)),
            ("branch_scales", (2,)),          # the identifier's logit scales (main, adapted); 1, 1 = none
            ("free_bias", (1,)),              # added to the main branch's free score; 0 = none
            ("adapted_mean", ("C",)), ("adapted_cov", ("C", "C"))),   # the adapted branch's standardisation
    optional=("adapted_mean", "adapted_cov"))


@dataclass
class BundleContract:
    grid: Grid
    model_grid: Grid
    preprocess: Preprocess
    rig: RigSpec
    training_rig: Rig
    label_space: LabelSpaceSpec
    text_encoder: TextEncoderSpec
    files: dict[str, FileEntry]
    voxel_stages: list[VoxelStageSpec]
    hidden_dim: int
    adapted_dim: int
    checkpoint: CheckpointRecord
    model: ModelRecord
    parity: ParityReport
    identifier: Identifier = Identifier.MIN_ENTROPY
    banks: dict[str, str] = field(default_factory=dict)        # bank name -> its key in files
    default_bank: str = "train"
    bank_notes: dict[str, str] = field(default_factory=dict)   # bank name -> why it was not built
    variants: dict[str, VariantSpec] = field(default_factory=dict)
    ago_version: str = ""
    created_utc: str = ""
    rig_source: str = ""
    format_version: int = BUNDLE_FORMAT_VERSION

    PLANES = "planes"      # files key of planes.onnx
    HEADS = "heads"        # files key of heads.npz
    BANK_PREFIX = "bank/"  # files key of a bank: BANK_PREFIX + its name (bank_key)

    @classmethod
    def bank_key(cls, name: str) -> str:
        return cls.BANK_PREFIX + name

    @classmethod
    def keys(cls) -> list[str]:
        """bundle.json's keys: "format" and every field."""
        return ["format"] + [f.name for f in fields(cls)]

    def to_dict(self) -> dict:
        return {
            "format": BUNDLE_FORMAT, "format_version": self.format_version, "ago_version": self.ago_version,
            "created_utc": self.created_utc, "checkpoint": record_to_dict(self.checkpoint),
            "model": record_to_dict(self.model), "grid": self.grid.to_dict(), "model_grid": self.model_grid.to_dict(),
            "preprocess": self.preprocess.to_dict(), "rig": self.rig.to_dict(),
            "training_rig": self.training_rig.to_dict(), "rig_source": self.rig_source,
            "label_space": self.label_space.to_dict(), "text_encoder": self.text_encoder.to_dict(),
            "identifier": self.identifier.value, "default_bank": self.default_bank, "banks": dict(self.banks),
            "bank_notes": dict(self.bank_notes), "files": {k: record_to_dict(v) for k, v in self.files.items()},
            "voxel_stages": [s.to_dict() for s in self.voxel_stages],
            "hidden_dim": self.hidden_dim, "adapted_dim": self.adapted_dim,
            "variants": {k: v.to_dict() for k, v in self.variants.items()}, "parity": self.parity.to_dict(),
        }

    @classmethod
    def from_dict(cls, meta, source) -> "BundleContract":
        """bundle.json's content -> the contract; AgoInputError naming `source` for another format or version,
        a key the contract does not declare, or a missing / malformed field."""
        if not isinstance(meta, dict) or meta.get("format") != BUNDLE_FORMAT:
            raise AgoInputError(source, f"not an ago bundle (format tag is not {BUNDLE_FORMAT!r})")
        version = meta.get("format_version")
        if not isinstance(version, int) or isinstance(version, bool) or version < 1:
            raise AgoInputError(source, f"bad format_version {version!r}")
        if version < BUNDLE_FORMAT_VERSION:
            raise AgoInputError(source, reexport_hint(version))
        if version > BUNDLE_FORMAT_VERSION:
            raise AgoInputError(source, f"bundle format version {version} is newer than this ago reads "
                                f"({BUNDLE_FORMAT_VERSION}); upgrade ago or re-export the model")
        try:
            declared_keys(meta, cls.keys(), "bundle")
            for key in ("grid", "model_grid"):           # by value first: Grid.from_dict trusts its input
                check_grid_dict(declared_keys(_need(meta, key, dict, "bundle"), list(Grid().to_dict()), key), source, key)
            _check_preprocess(_need(meta, "preprocess", dict, "bundle"), source)
            files = {str(k): FileEntry.from_dict(v, f"files[{k!r}]") for k, v in _need(meta, "files", dict, "bundle").items()}
            stages = _need(meta, "voxel_stages", list, "bundle")
            if not 1 <= len(stages) <= MAX_VOXEL_STAGES:
                raise ValueError(f"voxel_stages must list 1 to {MAX_VOXEL_STAGES} stages")
            stages = [VoxelStageSpec.from_dict(s, f"voxel_stages[{i}]") for i, s in enumerate(stages)]
            banks = _need(meta, "banks", dict, "bundle")
            notes = _need(meta, "bank_notes", dict, "bundle")
            if not all(isinstance(k, str) and isinstance(v, str) for d in (banks, notes) for k, v in d.items()):
                raise ValueError("banks must map bank names to file keys, bank_notes bank names to notes")
            variants = {str(k): VariantSpec.from_dict(v, f"variants[{k!r}]")
                        for k, v in _need(meta, "variants", dict, "bundle").items()}
            contract = cls(
                grid=Grid.from_dict(meta["grid"]), model_grid=Grid.from_dict(meta["model_grid"]),
                preprocess=Preprocess.from_dict(meta["preprocess"]),
                rig=RigSpec.from_dict(_need(meta, "rig", dict, "bundle")),
                training_rig=_training_rig(_need(meta, "training_rig", dict, "bundle"), source),
                label_space=LabelSpaceSpec.from_dict(_need(meta, "label_space", dict, "bundle")),
                text_encoder=TextEncoderSpec.from_dict(_need(meta, "text_encoder", dict, "bundle")),
                files=files, voxel_stages=stages,
                hidden_dim=_need(meta, "hidden_dim", int, "bundle"), adapted_dim=_need(meta, "adapted_dim", int, "bundle"),
                checkpoint=record_from_dict(CheckpointRecord, _need(meta, "checkpoint", dict, "bundle"), "checkpoint"),
                model=record_from_dict(ModelRecord, _need(meta, "model", dict, "bundle"), "model"),
                parity=ParityReport.from_dict(_need(meta, "parity", dict, "bundle")),
                identifier=Identifier(_need(meta, "identifier", str, "bundle")),
                banks=dict(banks), default_bank=_need(meta, "default_bank", str, "bundle"), bank_notes=dict(notes),
                variants=variants, ago_version=_need(meta, "ago_version", str, "bundle"),
                created_utc=_need(meta, "created_utc", str, "bundle"),
                rig_source=_need(meta, "rig_source", str, "bundle"), format_version=version)
        except AgoInputError:   # a by-value check that names its field already
            raise
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            raise AgoInputError(source, f"bundle metadata incomplete or malformed ({e.__class__.__name__}: {e})") from None
        contract.check_values(source)
        try:
            contract.check_stages()
        except ValueError as e:
            raise AgoInputError(source, f"voxel_stages: {e}") from None
        return contract

    def check_values(self, source) -> None:
        """Every field by value, before any work (a manifest whose hashes were recomputed proves nothing about its
        values): widths 1..MAX_EMBED_DIM, an input canvas within the array bound, the training rig's calibration
        (Camera.validate) with the rig's cameras, the default bank listed, every bank and variant graph a listed
        file, sha256 entries of 64 hex digits (grids and preprocess sizes are checked as read: from_dict).
        AgoInputError(source, "<field>: <problem>")."""
        from ago_runtime.readers import max_array_bytes

        def bad(where: str, problem: str):
            raise AgoInputError(source, f"{where}: {problem}")

        pre = self.preprocess
        canvas = len(self.rig.cameras) * 3 * pre.width * pre.height * 4
        if canvas > max_array_bytes():
            bad("preprocess", f"{pre.width}x{pre.height} images of {len(self.rig.cameras)} cameras make a "
                f"{canvas}-byte input, more than ago allocates ({max_array_bytes()}; $AGO_MAX_ARRAY_BYTES)")
        for key in ("hidden_dim", "adapted_dim"):
            if not 1 <= getattr(self, key) <= MAX_EMBED_DIM:
                bad(key, f"must be an integer 1..{MAX_EMBED_DIM}, got {getattr(self, key)}")
        for i, st in enumerate(self.voxel_stages):
            for key in ("input_dim", "output_dim"):
                if not 1 <= getattr(st, key) <= MAX_EMBED_DIM:
                    bad(f"voxel_stages[{i}].{key}", f"must be an integer 1..{MAX_EMBED_DIM}, got {getattr(st, key)}")
        try:
            self.training_rig.validate()
            self.training_rig.ordered_as(self.rig.names)
        except AgoInputError as e:
            bad("training_rig", e.problem)
        if self.banks and self.default_bank not in self.banks:
            bad("default_bank", f"{self.default_bank!r} is not one of banks {sorted(self.banks)[:8]}")
        for name, key in self.banks.items():
            if key not in self.files:
                bad(f"banks[{name!r}]", f"names file {key!r}, which files does not list")
        graphs = [self.PLANES] + [s.file for s in self.voxel_stages]
        for name, v in self.variants.items():
            if sorted(v.graphs) != sorted(graphs):
                bad(f"variants[{name!r}].graphs", f"must give one graph for each of {graphs}, got {sorted(v.graphs)}")
            for key in v.graphs.values():
                if key not in self.files:
                    bad(f"variants[{name!r}].graphs", f"names file {key!r}, which files does not list")
        for key, entry in self.files.items():
            if not re.fullmatch(r"[0-9a-f]{64}", entry.sha256):
                bad(f"files[{key!r}].sha256", f"must be 64 hex digits, got {entry.sha256[:80]!r}")
            if entry.size < 0:
                bad(f"files[{key!r}].size", f"must be >= 0, got {entry.size}")

    def check_stages(self) -> None:
        """The stages chain: decoder stages (MAIN) from the planes' width to h, then adapter stages (ADAPTED) from
        h to g; every stage's file is listed."""
        for key in (self.PLANES, self.HEADS):
            if key not in self.files:
                raise ValueError(f"files lacks {key!r}")
        branches = [s.branch for s in self.voxel_stages]
        if Branch.ADAPTED not in branches or branches != sorted(branches, key=lambda b: b == Branch.ADAPTED):
            raise ValueError(f"voxel_stages {[b.value for b in branches]}: decoder (main) stages, then at least one "
                             "adapter (adapted) stage")
        width = None           # the first decoder stage takes the planes' width, which bundle.json does not state
        for i, s in enumerate(self.voxel_stages):
            if s.file not in self.files:
                raise ValueError(f"voxel_stages[{i}] names file {s.file!r}, which files does not list")
            if s.branch == Branch.ADAPTED and (i == 0 or self.voxel_stages[i - 1].branch == Branch.MAIN):
                if width is not None and width != self.hidden_dim:
                    raise ValueError(f"the decoder stages give width {width}, hidden_dim says {self.hidden_dim}")
                width = self.hidden_dim   # the first adapter stage takes h
            if width is not None and s.input_dim != width:
                raise ValueError(f"voxel_stages[{i}] takes width {s.input_dim}, the stage before gives {width}")
            width = s.output_dim
        if width != self.adapted_dim:
            raise ValueError(f"the adapter stages give width {width}, adapted_dim says {self.adapted_dim}")

    def stages(self, branch: Branch) -> list[VoxelStageSpec]:
        return [s for s in self.voxel_stages if s.branch == branch]

    def graph_keys(self, variant: str | None = None, source=None) -> tuple[str, list[str]]:
        """(planes' files key, each voxel stage's files key) of the float32 graphs, or of `variant`'s;
        AgoInputError naming `source` when the bundle has no such variant."""
        planes, stages = self.PLANES, [s.file for s in self.voxel_stages]
        if variant is None:
            return planes, stages
        if variant not in self.variants:
            raise AgoInputError(source, f"bundle has no {variant} graphs (variants: {sorted(self.variants) or 'none'}; "
                                f"export with `ago export --{variant}`)")
        graphs = self.variants[variant].graphs
        return graphs[planes], [graphs[k] for k in stages]

    @property
    def head_widths(self) -> dict[str, int]:
        """The widths HEADS_NPZ's shapes are stated in."""
        return {"C": int(self.text_encoder.dim), "Dh": int(self.hidden_dim), "Da": int(self.adapted_dim)}


def _check_preprocess(pre: dict, source) -> None:
    """bundle.json "preprocess" (Preprocess.to_dict) by value: exactly its keys, sizes 1..MAX_IMAGE_SIDE, mean / std
    3 finite numbers and std > 0, the fixed resize / channel order / layout Preprocess states."""
    def bad(where: str, problem: str):
        raise AgoInputError(source, f"{where}: {problem}")

    fixed = Preprocess().to_dict()
    declared_keys(pre, list(fixed), "preprocess")
    for key in ("width", "height"):
        v = pre.get(key)
        if not _is_int(v) or not 1 <= v <= MAX_IMAGE_SIDE:
            bad(f"preprocess.{key}", f"must be an integer 1..{MAX_IMAGE_SIDE} (pixels), got {str(v)[:40]}")
    for key in ("mean", "std"):
        if not _finite_numbers(pre.get(key), 3):
            bad(f"preprocess.{key}", f"must be 3 finite numbers, got {str(pre.get(key))[:60]}")
    if min(pre["std"]) <= 0:
        bad("preprocess.std", f"must be > 0 (every pixel is divided by it), got {pre['std']}")
    for key in ("resize", "channel_order", "layout"):
        if pre.get(key) != fixed[key]:
            bad(f"preprocess.{key}", f"must be {fixed[key]!r} (the one preprocessing ago runs), got {str(pre.get(key))[:40]}")


def _training_rig(d: dict, source) -> Rig:
    """bundle.json "training_rig" (Rig.to_dict): exactly its keys, then the Rig (validated by check_values)."""
    keys = list(Rig.nuscenes_like().cameras[0].to_dict())
    for i, cam in enumerate(_need(declared_keys(d, ["cameras"], "training_rig"), "cameras", list, "training_rig")):
        declared_keys(cam, keys, f"training_rig.cameras[{i}]")
    try:
        return Rig.from_dict(d)
    except AgoInputError as e:
        raise AgoInputError(source, f"training_rig: {e.problem}") from None
    except (KeyError, TypeError, ValueError, AttributeError, IndexError) as e:
        raise AgoInputError(source, f"training_rig: malformed ({e.__class__.__name__}: {str(e)[:160]})") from None


def check_bank_fits(bank, text_encoder: TextEncoderSpec, source=None) -> None:
    """The one check of a prompt bank against a bundle (its `contract.text_encoder`; `ago export` passes the
    training bank's before the contract exists): a bank made by another text encoder or of another width, or
    with more classes than `ago infer` writes, is refused with AgoInputError naming `source` (the bank file,
    the prompt file, the bundle or the checkpoint)."""
    from ago_runtime.vocab.bank import check_class_count

    text_encoder.check_made_by(bank.encoder_id, bank.dim, source, "prompt bank", REBUILD_BANK)
    check_class_count(bank.num_classes, source)
