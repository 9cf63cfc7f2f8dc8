"""The bundle contract: what `bundle.json` holds (format 4), as dataclasses, and the checks made against it.

`ago export` builds a `BundleContract` and writes it (`to_dict`); `Bundle.load` (the runtime) and
`ago eval` read it (`BundleContract.from_dict`). Nothing else reads bundle.json by string keys.

    BundleContract
      format_version   4 (older bundles are refused with the command that re-exports them)
      grid, model_grid, preprocess      the read-out grid, the training grid, the image preprocessing
      rig              RigSpec: the cameras the model takes, by name, and each camera's input image size
      training_rig     the calibration of the training rig (native image size; the fallback calibration)
      label_space      LabelSpaceSpec: the classes the model was trained on
      text_encoder     TextEncoderSpec: the encoder every bank must come from (id, hash, width)
      identifier       Identifier: the open-world identifier for banks with unknown classes
      banks, default_bank              bank name -> file
      files            name -> FileEntry (path, sha256, size): every file of the bundle
      voxel_stages     VoxelStageSpec per ONNX graph of the per-voxel MLP after the planes
      hidden_dim, adapted_dim          widths of h (main branch) and g (adapted branch)

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
from dataclasses import asdict, dataclass, field

from ago_runtime.classes import OCC3D_NUSCENES, ClassTable, table_from_ref, table_record
from ago_runtime.errors import AgoInputError
from ago_runtime.geometry.camera import Rig, check_camera_names
from ago_runtime.geometry.grid import check_grid_dict
from ago_runtime.predict.decision import Branch, Identifier

__all__ = ["BUNDLE_FORMAT", "BUNDLE_FORMAT_VERSION", "BUNDLE_JSON", "FileEntry",
           "VoxelStageSpec", "CameraSlot", "RigSpec", "TextEncoderSpec", "LabelClass", "LabelSpaceSpec",
           "BundleContract", "TensorSpec", "planes_signature", "planes_width", "stage_signature", "check_graph",
           "check_bank_fits", "file_sha256", "reexport_hint"]


def file_sha256(path) -> str:
    """sha256 hex of a file's bytes (ago_runtime.vocab.text_encoder.file_sha256, memoised), imported when first
    used so that the CLI's option types (Identifier) cost no onnxruntime import."""
    from ago_runtime.vocab.text_encoder import file_sha256 as sha256_of_file

    return sha256_of_file(path)

BUNDLE_FORMAT = "ago-bundle"
BUNDLE_FORMAT_VERSION = 4
BUNDLE_JSON = "bundle.json"
MAX_VOXEL_STAGES = 16           # an exported decoder has 1-4
MAX_EMBED_DIM = 8192            # a text embedding's or a hidden layer's width
MAX_IMAGE_SIDE = 16384          # a model input image's side (pixels)
FLOAT_TENSOR = "tensor(float)"  # onnxruntime's name of a float32 graph input / output
REBUILD_BANK = "rebuild it with `ago prompts build <prompt file> -o BANK`"


def reexport_hint(version) -> str:
    return (f"bundle format version {version} is no longer read (this ago reads {BUNDLE_FORMAT_VERSION}); "
            "re-export the checkpoint: `ago export CKPT -o BUNDLE_DIR`")


def _need(d: dict, key: str, kind, what: str):
    if not isinstance(d, dict) or key not in d:
        raise ValueError(f"{what} lacks {key!r}")
    value = d[key]
    if kind is not None and not isinstance(value, kind) or isinstance(value, bool) and kind is int:
        raise ValueError(f"{what}.{key} must be {getattr(kind, '__name__', kind)}, got {value!r}")
    return value


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _finite_numbers(v, n: int) -> bool:
    return (isinstance(v, list) and len(v) == n and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                         and math.isfinite(x) for x in v))


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
    return ([TensorSpec("images", (1, cameras, 3, height, width)), TensorSpec("ego2img", (1, cameras, 4, 4))],
            [TensorSpec("plane_xy", (X, Y, planes_width)), TensorSpec("plane_xz", (X, Z, planes_width)),
             TensorSpec("plane_yz", (Y, Z, planes_width))])


def planes_width(stages: "list[VoxelStageSpec]", hidden_dim: int) -> int:
    """Dh of the planes: the first decoder stage's input width, or h's width when the decoder has no stage."""
    main = [s for s in stages if s.branch == Branch.MAIN]
    return main[0].input_dim if main else int(hidden_dim)


def stage_signature(spec: "VoxelStageSpec"):
    """voxels_<i>.onnx: x (n, input_dim) -> y (n, output_dim)."""
    return [TensorSpec("x", ("n", spec.input_dim))], [TensorSpec("y", ("n", spec.output_dim))]


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
        return cls(_need(d, "path", str, what), _need(d, "sha256", str, what), _need(d, "size", int, what))


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
        return {"cameras": [asdict(c) for c in self.cameras]}

    @classmethod
    def from_dict(cls, d: dict, what: str = "rig") -> "RigSpec":
        cams = _need(d, "cameras", list, what)
        slots = [CameraSlot(_need(c, "name", str, f"{what}.cameras"), _need(c, "width", int, f"{what}.cameras"),
                            _need(c, "height", int, f"{what}.cameras")) for c in cams]
        if not slots or len({s.name for s in slots}) != len(slots):
            raise ValueError(f"{what}.cameras must name at least one camera, each once")
        if any(not 1 <= s.width <= 16384 or not 1 <= s.height <= 16384 for s in slots):
            raise ValueError(f"{what}.cameras: image sizes must be 1..16384 pixels")
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

    @classmethod
    def from_dict(cls, d: dict) -> "TextEncoderSpec":
        dim = _need(d, "dim", int, "text_encoder")
        if not 1 <= dim <= MAX_EMBED_DIM:
            raise ValueError(f"text_encoder.dim must be an integer 1..{MAX_EMBED_DIM}, got {dim!r}")
        return cls(_need(d, "id", str, "text_encoder"), _need(d, "hash", str, "text_encoder"), dim,
                   str(d.get("variant", "")))


@dataclass
class LabelClass:
    name: str
    occ3d_ids: list[int]
    known: bool
    phrases: list[str]


@dataclass
class LabelSpaceSpec:
    name: str | None
    sha256: str
    classes: list[LabelClass]
    table: ClassTable = OCC3D_NUSCENES   # the class table the classes' occ3d_ids index (ago_runtime.classes)

    @property
    def class_names(self) -> list[str]:
        return [c.name for c in self.classes]

    def to_dict(self) -> dict:
        d = asdict(self)
        del d["table"]
        return {**d, **table_record(self.table, "table")}   # a shipped table's name, or the table itself

    @classmethod
    def from_dict(cls, d: dict) -> "LabelSpaceSpec":
        from ago_runtime.vocab.bank import MAX_INFER_CLASSES

        classes = _need(d, "classes", list, "label_space")
        if not 1 <= len(classes) <= MAX_INFER_CLASSES:
            raise ValueError(f"label_space.classes must list 1 to {MAX_INFER_CLASSES} classes")
        out = [LabelClass(_need(c, "name", str, "label_space.classes"), [int(i) for i in c.get("occ3d_ids", [])],
                          bool(c.get("known", True)), [str(p) for p in c.get("phrases", [])]) for c in classes]
        try:
            table = table_from_ref(d.get("table", "occ3d_nuscenes"), "label_space.table")
        except AgoInputError as e:
            raise ValueError(str(e)) from None
        known_ids = set(table.ids)
        for c in out:
            if not set(c.occ3d_ids) <= known_ids:
                raise ValueError(f"label_space.classes: {c.name!r} has ids {c.occ3d_ids} outside class table {table.name}")
        return cls(d.get("name"), str(d.get("sha256", "")), out, table)


@dataclass
class BundleContract:
    grid: dict
    model_grid: dict
    preprocess: dict
    rig: RigSpec
    training_rig: dict
    label_space: LabelSpaceSpec
    text_encoder: TextEncoderSpec
    files: dict[str, FileEntry]
    voxel_stages: list[VoxelStageSpec]
    hidden_dim: int
    adapted_dim: int
    identifier: Identifier = Identifier.MIN_ENTROPY
    banks: dict[str, str] = field(default_factory=dict)
    default_bank: str = "train"
    bank_notes: dict = field(default_factory=dict)
    checkpoint: dict = field(default_factory=dict)
    model: dict = field(default_factory=dict)
    parity: dict = field(default_factory=dict)
    ago_version: str = ""
    created_utc: str = ""
    rig_source: str = ""
    format_version: int = BUNDLE_FORMAT_VERSION

    PLANES = "planes"      # files key of planes.onnx
    HEADS = "heads"        # files key of heads.npz

    def to_dict(self) -> dict:
        return {
            "format": BUNDLE_FORMAT, "format_version": self.format_version, "ago_version": self.ago_version,
            "created_utc": self.created_utc, "checkpoint": self.checkpoint, "model": self.model,
            "grid": self.grid, "model_grid": self.model_grid, "preprocess": self.preprocess,
            "rig": self.rig.to_dict(), "training_rig": self.training_rig, "rig_source": self.rig_source,
            "label_space": self.label_space.to_dict(), "text_encoder": asdict(self.text_encoder),
            "identifier": self.identifier.value, "default_bank": self.default_bank, "banks": self.banks,
            "bank_notes": self.bank_notes, "files": {k: asdict(v) for k, v in self.files.items()},
            "voxel_stages": [s.to_dict() for s in self.voxel_stages],
            "hidden_dim": self.hidden_dim, "adapted_dim": self.adapted_dim, "parity": self.parity,
        }

    @classmethod
    def from_dict(cls, meta, source) -> "BundleContract":
        """bundle.json's content -> the contract; AgoInputError naming `source` for another format or version,
        or a missing / malformed field."""
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
            files = {str(k): FileEntry.from_dict(v, f"files[{k!r}]") for k, v in _need(meta, "files", dict, "bundle").items()}
            stages = _need(meta, "voxel_stages", list, "bundle")
            if not 1 <= len(stages) <= MAX_VOXEL_STAGES:
                raise ValueError(f"voxel_stages must list 1 to {MAX_VOXEL_STAGES} stages")
            stages = [VoxelStageSpec.from_dict(s, f"voxel_stages[{i}]") for i, s in enumerate(stages)]
            banks = _need(meta, "banks", dict, "bundle")
            if not all(isinstance(k, str) and isinstance(v, str) for k, v in banks.items()):
                raise ValueError("banks must map bank names to file paths")
            contract = cls(
                grid=_need(meta, "grid", dict, "bundle"), model_grid=meta.get("model_grid") or meta["grid"],
                preprocess=_need(meta, "preprocess", dict, "bundle"),
                rig=RigSpec.from_dict(_need(meta, "rig", dict, "bundle")),
                training_rig=_need(meta, "training_rig", dict, "bundle"),
                label_space=LabelSpaceSpec.from_dict(_need(meta, "label_space", dict, "bundle")),
                text_encoder=TextEncoderSpec.from_dict(_need(meta, "text_encoder", dict, "bundle")),
                files=files, voxel_stages=stages,
                hidden_dim=_need(meta, "hidden_dim", int, "bundle"), adapted_dim=_need(meta, "adapted_dim", int, "bundle"),
                identifier=Identifier(meta.get("identifier", Identifier.MIN_ENTROPY.value)),
                banks=dict(banks), default_bank=str(meta.get("default_bank", "train")),
                bank_notes=meta.get("bank_notes") or {}, checkpoint=meta.get("checkpoint") or {},
                model=meta.get("model") or {}, parity=meta.get("parity") or {},
                ago_version=str(meta.get("ago_version", "")), created_utc=str(meta.get("created_utc", "")),
                rig_source=str(meta.get("rig_source", "")), format_version=version)
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
        values): grids (check_grid_dict), preprocess sizes 1..MAX_IMAGE_SIDE with a canvas within the array
        bound, mean / std 3 finite numbers and std > 0, widths 1..MAX_EMBED_DIM, the training rig's calibration
        (Camera.validate) with the rig's cameras, the default bank listed, sha256 entries of 64 hex digits.
        AgoInputError(source, "<field>: <problem>")."""
        from ago_runtime.readers import max_array_bytes

        def bad(where: str, problem: str):
            raise AgoInputError(source, f"{where}: {problem}")

        check_grid_dict(self.grid, source, "grid")
        check_grid_dict(self.model_grid, source, "model_grid")
        pre = self.preprocess
        for key in ("width", "height"):
            v = pre.get(key)
            if not _is_int(v) or not 1 <= v <= MAX_IMAGE_SIDE:
                bad(f"preprocess.{key}", f"must be an integer 1..{MAX_IMAGE_SIDE} (pixels), got {str(v)[:40]}")
        canvas = len(self.rig.cameras) * 3 * pre["width"] * pre["height"] * 4
        if canvas > max_array_bytes():
            bad("preprocess", f"{pre['width']}x{pre['height']} images of {len(self.rig.cameras)} cameras make a "
                f"{canvas}-byte input, more than ago allocates ({max_array_bytes()}; $AGO_MAX_ARRAY_BYTES)")
        for key in ("mean", "std"):
            if not _finite_numbers(pre.get(key), 3):
                bad(f"preprocess.{key}", f"must be 3 finite numbers, got {str(pre.get(key))[:60]}")
        if min(pre["std"]) <= 0:
            bad("preprocess.std", f"must be > 0 (every pixel is divided by it), got {pre['std']}")
        for key in ("hidden_dim", "adapted_dim"):
            if not 1 <= getattr(self, key) <= MAX_EMBED_DIM:
                bad(key, f"must be an integer 1..{MAX_EMBED_DIM}, got {getattr(self, key)}")
        for i, st in enumerate(self.voxel_stages):
            for key in ("input_dim", "output_dim"):
                if not 1 <= getattr(st, key) <= MAX_EMBED_DIM:
                    bad(f"voxel_stages[{i}].{key}", f"must be an integer 1..{MAX_EMBED_DIM}, got {getattr(st, key)}")
        try:
            rig = Rig.from_dict(self.training_rig)
        except (KeyError, TypeError, ValueError, AttributeError, IndexError) as e:
            bad("training_rig", f"malformed ({e.__class__.__name__}: {str(e)[:160]})")
        try:
            rig.validate()
            rig.ordered_as(self.rig.names)
        except AgoInputError as e:
            bad("training_rig", e.problem)
        if self.banks and self.default_bank not in self.banks:
            bad("default_bank", f"{self.default_bank!r} is not one of banks {sorted(self.banks)[:8]}")
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


def check_bank_fits(bank, text_encoder: TextEncoderSpec, source=None) -> None:
    """The one check of a prompt bank against a bundle (its `contract.text_encoder`; `ago export` passes the
    training bank's before the contract exists): a bank made by another text encoder or of another width, or
    with more classes than `ago infer` writes, is refused with AgoInputError naming `source` (the bank file,
    the prompt file, the bundle or the checkpoint)."""
    from ago_runtime.vocab.bank import check_class_count

    text_encoder.check_made_by(bank.encoder_id, bank.dim, source, "prompt bank", REBUILD_BANK)
    check_class_count(bank.num_classes, source)
