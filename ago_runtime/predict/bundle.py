"""`Bundle`: an exported model folder (what `ago export` writes and `ago infer` reads), read and checked.

A bundle is self-describing, like torchvision's Weights: it carries the grid, the label space the
model was trained with, the text encoder its banks must come from, the preprocessing and the
camera rig it was trained with. Layout (see docs/runtime.md):

    bundle_dir/
      bundle.json        metadata (below); format_version, sha256 of every file
      planes.onnx        images (1,6,3,H,W) f32 + ego2img (1,6,4,4) f32 -> plane_xy (X,Y,Dh),
                         plane_xz (X,Z,Dh), plane_yz (Y,Z,Dh): the TPV planes at the grid's resolution
                         times the decoder's first linear layer, channels last
      voxels_<i>.onnx    the per-voxel MLP, one graph per layer: x (n, d) -> y = x W^T + b and, for
                         the stages whose input is h or g, the folded bank's scores (bundle.json
                         "voxel_stages"; ago_runtime/predict/encoder.py)
      planes.int8.onnx, voxels_<i>.int8.onnx   optional: dynamically quantised (`ago export --int8`)
      heads.npz          W_dec (C,Dh), b_dec (C,), W_ad (C,Da), b_ad (C,), free_embedding (C,),
                         branch_scales (2,) the identifier's logit scales (main, adapted; absent = 1, 1),
                         free_bias (1,) added to the main branch's free score (absent = 0)
      banks/<name>.npz   prompt banks (ago_runtime.vocab.bank.PromptBank files); "train" = the
                         training label space's embeddings stored in the checkpoint

`card.json` (optional, ago_export/card.py): what the model was trained on; `Bundle.card`, `card_line`.

`Bundle.load(dir)` refuses (AgoInputError naming the file) a missing folder or file, a newer
format_version, a file whose sha256 differs from bundle.json (e.g. a truncated ONNX), heads of
the wrong shapes.

Format versions: 3 = the split encoder above (files "planes", "voxels_<i>"; channels-last planes
with the decoder's first linear inside planes.onnx). Format 2 (planes (D, X, Y) channels first) and
format 1 (one monolithic `encoder.onnx`) are refused with a message to re-export the checkpoint.
"""

from __future__ import annotations

import hashlib
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ago_runtime.geometry.camera import Rig
from ago_runtime.errors import AgoInputError
from ago_runtime.paths import inside_root
from ago_runtime.readers import check_npz, read_json
from ago_runtime.geometry.grid import Grid
from ago_runtime.predict.heads import HeadWeights
from ago_runtime.geometry.preprocess import Preprocess

BUNDLE_FORMAT = "ago-bundle"
BUNDLE_FORMAT_VERSION = 3
ENCODER_FILES = ("planes",)      # plus the voxel stages listed in bundle.json "voxel_stages"
BUNDLE_JSON = "bundle.json"
CARD_FILE = "card.json"          # written by ago_export/card.py
ENV_BUNDLE = "AGO_BUNDLE"
DEFAULT_BUNDLE_DIR = Path(__file__).resolve().parents[1] / "assets" / "default_bundle"
DEMO_FRAME_DIR = Path(__file__).resolve().parents[1] / "assets" / "demo_frame"
HOW_TO_MAKE_DEFAULT = ("build one with scripts/make_default_bundle.sh (synth data -> pseudo-labels -> "
                       "train -> ago export), or pass --bundle DIR / set $AGO_BUNDLE")


def file_sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@dataclass
class Bundle:
    root: Path
    meta: dict
    grid: Grid
    preprocess: Preprocess
    rig: Rig                       # the training rig at native image size
    heads: HeadWeights
    label_space: dict              # {"name", "classes": [{"name", "occ3d_ids", "known"}], ...}
    text_encoder: dict             # {"id", "hash", "dim"}
    banks: dict[str, Path] = field(default_factory=dict)
    card: dict | None = None       # card.json (what the model was trained on), None when the bundle has none

    # ---- paths -----------------------------------------------------------------------------
    def encoder_paths(self, int8: bool = False) -> dict:
        """{"planes": path, "voxels": [stage spec + "path", ...]} (bundle.json "voxel_stages"); int8: the
        quantised graphs."""
        files = self.meta["files"]
        suffix = "_int8" if int8 else ""

        def path(key):
            entry = files.get(key + suffix)
            if entry is None:
                raise AgoInputError(self.root, "bundle has no int8 encoder (export with `ago export --int8`)")
            return self.root / entry["path"]

        return {"planes": path("planes"),   # paths checked under the root by Bundle.load
                "voxels": [{**st, "path": path(st["file"]), "sha256": files[st["file"] + suffix].get("sha256")}
                           for st in self.meta["voxel_stages"]]}

    @property
    def default_bank(self) -> str:
        return self.meta.get("default_bank", "train")

    @property
    def identifier(self) -> str:
        """The open-world identifier (bundle.json "identifier"), used for banks with unknown classes."""
        return self.meta.get("identifier", "min-entropy")

    @property
    def trained_classes(self) -> list[str]:
        return [str(c["name"]) for c in self.label_space.get("classes", [])]

    def check_bank(self, bank, source=None) -> None:
        """A bank made by another text encoder or of another width than this bundle's: AgoInputError."""
        te = self.text_encoder
        bank.check_compatible(te["id"], int(te["dim"]), source or self.root)

    def identifier_for(self, bank) -> str:
        """The default identifier for `bank` (ago_runtime.predict.heads.default_identifier): the
        open-world one when the bank holds classes this bundle was not trained on, else "none"."""
        from .heads import default_identifier

        return default_identifier(bank.class_names, bank.known, self.trained_classes, self.identifier)

    @property
    def embed_dim(self) -> int:
        return int(self.text_encoder["dim"])

    def bank_path(self, name: str | None = None) -> Path:
        name = name or self.default_bank
        if name not in self.banks:
            raise AgoInputError(self.root / BUNDLE_JSON, f"bundle has no bank {name!r} (has {sorted(self.banks)})")
        return self.banks[name]

    def load_bank(self, name: str | None = None):
        from ago_runtime.vocab.bank import PromptBank

        return PromptBank.load(self.bank_path(name))

    # ---- reading ---------------------------------------------------------------------------
    @classmethod
    def load(cls, root: str | Path, verify_hashes: bool = True) -> "Bundle":
        root = Path(root)
        if not root.is_dir():
            raise AgoInputError(root, "bundle folder not found")
        meta_path = root / BUNDLE_JSON
        meta = read_json(meta_path, missing="not an ago bundle (no bundle.json)")
        if not isinstance(meta, dict) or meta.get("format") != BUNDLE_FORMAT:
            raise AgoInputError(meta_path, f"not an ago bundle (format tag is not {BUNDLE_FORMAT!r})")
        version = meta.get("format_version")
        if not isinstance(version, int) or version < 1:
            raise AgoInputError(meta_path, f"bad format_version {version!r}")
        if version < BUNDLE_FORMAT_VERSION:
            raise AgoInputError(meta_path, f"bundle format version {version} is no longer read (this ago reads "
                                f"{BUNDLE_FORMAT_VERSION}); re-export the checkpoint with `ago export`")
        if version > BUNDLE_FORMAT_VERSION:
            raise AgoInputError(meta_path, f"bundle format version {version} is newer than this ago reads "
                                f"({BUNDLE_FORMAT_VERSION}); upgrade ago or re-export the model")
        try:
            grid = Grid.from_dict(meta["grid"])
            pre = Preprocess.from_dict(meta["preprocess"])
            rig = Rig.from_dict(meta["rig"])
            label_space = meta["label_space"]
            text_encoder = meta["text_encoder"]
            files = meta["files"]
            stages = meta["voxel_stages"]
            if not isinstance(stages, list) or not 1 <= len(stages) <= MAX_VOXEL_STAGES:
                raise ValueError(f"voxel_stages must list 1 to {MAX_VOXEL_STAGES} stages")
            for key in ENCODER_FILES + ("heads",) + tuple(st["file"] for st in stages):
                files[key]["path"]
            if not isinstance(files, dict) or not all(isinstance(e, dict) for e in files.values()):
                raise TypeError("files must map names to {path, sha256, size}")
        except (KeyError, TypeError, ValueError, AttributeError, AgoInputError) as e:
            raise AgoInputError(meta_path, f"bundle metadata incomplete or malformed ({e.__class__.__name__}: {e})") from None
        _check_meta_sizes(meta, grid, meta_path)
        rig.validate(str(meta_path))
        for key, entry in files.items():
            p = inside_root(root, entry["path"], meta_path, f"bundle file {key!r}")
            if not p.is_file():
                raise AgoInputError(p, f"bundle file {key!r} is missing")
            if "size" in entry and p.stat().st_size != int(entry["size"]):
                raise AgoInputError(p, f"file has {p.stat().st_size} bytes, bundle.json says {entry['size']} "
                                    "(truncated or replaced; re-export the bundle)")
            if verify_hashes and "sha256" in entry and file_sha256(p) != entry["sha256"]:
                raise AgoInputError(p, "sha256 differs from bundle.json (corrupt or replaced; re-export the bundle)")
        heads = _load_heads(root / files["heads"]["path"], int(text_encoder["dim"]))
        if not isinstance(meta.get("banks", {}), dict):
            raise AgoInputError(meta_path, "banks must map bank names to files")
        banks = {name: inside_root(root, rel, meta_path, f"bank {name!r}") for name, rel in meta.get("banks", {}).items()}
        for name, p in banks.items():
            if not p.is_file():
                raise AgoInputError(p, f"bundle bank {name!r} is missing")
        card = read_json(root / CARD_FILE, expect=dict) if (root / CARD_FILE).is_file() else None
        bundle = cls(root, meta, grid, pre, rig, heads, label_space, text_encoder, banks, card)
        if "train" in banks:   # the label space bundle.json states is the training bank's
            names = bundle.load_bank("train").class_names
            if names != bundle.trained_classes:
                raise AgoInputError(meta_path, f"label_space lists {len(bundle.trained_classes)} classes "
                                    f"{bundle.trained_classes[:5]}..., its train bank {len(names)} {names[:5]}...")
        return bundle


MAX_VOXEL_STAGES = 16           # an exported decoder has 2-4
MAX_BUNDLE_VOXELS = 1 << 25     # 33 M voxels (Occ3D's 200x200x16 is 640 k)


def _check_meta_sizes(meta: dict, grid: Grid, meta_path: Path) -> None:
    """Refuse, before any array is made, sizes in bundle.json that do not agree or could not be allocated:
    the grid (its shape against range / voxel size, its voxel count), the class list, the embedding width."""
    stated = meta["grid"].get("shape")
    shape = grid.shape
    if min(grid.voxel_size) <= 0 or min(shape) <= 0:
        raise AgoInputError(meta_path, f"grid has {shape} voxels of {grid.voxel_size} m")
    if stated is not None and list(stated) != list(shape):
        raise AgoInputError(meta_path, f"grid shape {stated} does not match its range / voxel size ({list(shape)})")
    if grid.num_voxels > MAX_BUNDLE_VOXELS:
        raise AgoInputError(meta_path, f"grid of {grid.num_voxels} voxels, more than ago predicts ({MAX_BUNDLE_VOXELS})")
    from ago_runtime.vocab.bank import MAX_INFER_CLASSES

    classes = meta["label_space"].get("classes") if isinstance(meta["label_space"], dict) else None
    if (not isinstance(classes, list) or not 1 <= len(classes) <= MAX_INFER_CLASSES
            or not all(isinstance(c, dict) and isinstance(c.get("name"), str) for c in classes)):
        raise AgoInputError(meta_path, f"label_space.classes must list 1 to {MAX_INFER_CLASSES} classes with names")
    dim = meta["text_encoder"].get("dim") if isinstance(meta["text_encoder"], dict) else None
    if not isinstance(dim, int) or not 1 <= dim <= 8192:
        raise AgoInputError(meta_path, f"text_encoder.dim must be an integer 1..8192, got {dim!r}")


def _load_heads(path: Path, dim: int) -> HeadWeights:
    try:
        with np.load(path, allow_pickle=False) as z:
            check_npz(path, z)
            arrays = {k: np.asarray(z[k], dtype=np.float32) for k in HeadWeights.KEYS}
            scales = np.asarray(z["branch_scales"], dtype=np.float32) if "branch_scales" in z.files else None
            stats = {k: np.asarray(z[k], dtype=np.float32) for k in ("adapted_mean", "adapted_cov") if k in z.files}
            free_bias = np.asarray(z["free_bias"], dtype=np.float32) if "free_bias" in z.files else None
    except KeyError as e:
        raise AgoInputError(path, f"heads file lacks array {e}") from None
    except (ValueError, OSError, zipfile.BadZipFile, EOFError) as e:
        raise AgoInputError(path, f"not a readable heads .npz ({e.__class__.__name__}: {e})") from None
    w = HeadWeights(**arrays)
    C = dim
    ok = (w.W_dec.ndim == 2 and w.W_dec.shape[0] == C and w.b_dec.shape == (C,) and w.W_ad.ndim == 2
          and w.W_ad.shape[0] == C and w.b_ad.shape == (C,) and w.free_embedding.shape == (C,))
    if not ok:
        raise AgoInputError(path, f"head shapes {[a.shape for a in arrays.values()]} do not fit embedding width {C}")
    if not all(np.isfinite(a).all() for a in arrays.values()):
        raise AgoInputError(path, "head weights contain NaN or inf")
    if scales is not None:
        if scales.shape != (2,) or not np.all(np.isfinite(scales)) or not np.all(scales > 0):
            raise AgoInputError(path, f"branch_scales must be two positive numbers, got {scales.tolist()}")
        w.branch_scales = scales
    if free_bias is not None:
        if free_bias.size != 1 or not np.isfinite(free_bias).all():
            raise AgoInputError(path, f"free_bias must be one finite number, got shape {free_bias.shape}")
        w.free_bias = float(free_bias.reshape(-1)[0])
    if stats:
        m, S = stats.get("adapted_mean"), stats.get("adapted_cov")
        if m is None or S is None or m.shape != (C,) or S.shape != (C, C):
            raise AgoInputError(path, f"adapted_mean and adapted_cov must be ({C},) and ({C}, {C}), got "
                                f"{None if m is None else m.shape} and {None if S is None else S.shape}")
        if not (np.isfinite(m).all() and np.isfinite(S).all() and np.all(np.diag(S) >= 0)):
            raise AgoInputError(path, "adapted_mean / adapted_cov contain NaN, inf or a negative variance")
        w.adapted_mean, w.adapted_cov = m, S
    return w


def resolve_bundle(path: str | Path | None = None) -> Path:
    """--bundle PATH, else $AGO_BUNDLE, else the shipped default bundle; a clear error when none exists."""
    if path is not None:
        return Path(path)
    env = os.environ.get(ENV_BUNDLE)
    if env:
        return Path(env)
    if (DEFAULT_BUNDLE_DIR / BUNDLE_JSON).is_file():
        return DEFAULT_BUNDLE_DIR
    raise AgoInputError(DEFAULT_BUNDLE_DIR, f"no default bundle installed; {HOW_TO_MAKE_DEFAULT}")


def card_line(bundle: Bundle) -> str:
    """One line saying what the bundle's model was trained on (its card's summary), for `ago infer` / `ago demo`."""
    if bundle.card and bundle.card.get("summary"):
        return f"bundle: {' '.join(str(bundle.card['summary']).split())}"
    step = (bundle.meta.get("checkpoint") or {}).get("step")
    known = f" (checkpoint step {step}, label space {bundle.label_space.get('name')})" if step is not None else ""
    if bundle.root.resolve() == DEFAULT_BUNDLE_DIR:
        return ("bundle: the shipped default bundle has no bundle card" + known + "; it is the small demo model "
                "scripts/make_default_bundle.sh trains on the SYNTHETIC world - not a nuScenes model")
    return f"bundle: {bundle.root} has no bundle card (card.json){known}: what it was trained on is not recorded"


def check_heads_fit_encoder(bundle: Bundle, encoder) -> None:
    """Refuse, naming heads.npz, heads whose hidden widths differ from the voxel graph's (h: Dh, g: Da)."""
    widths = getattr(encoder, "widths", None)   # the hidden widths the voxel stages give: {"main": Dh, "adapted": Da}
    if not widths:
        return   # an encoder without such stages: nothing to compare
    dh, da = int(widths["main"]), int(widths["adapted"])
    h = bundle.heads
    if (h.W_dec.shape[1], h.W_ad.shape[1]) != (dh, da):
        path = bundle.root / bundle.meta["files"]["heads"]["path"]
        raise AgoInputError(path, f"heads take hidden widths Dh {h.W_dec.shape[1]}, Da {h.W_ad.shape[1]} but the "
                            f"voxel stages give Dh {dh}, Da {da} (mixed files from two exports? re-export the bundle)")
