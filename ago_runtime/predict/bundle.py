"""`Bundle`: an exported model folder (what `ago export` writes and `ago infer` reads), read and checked.

A bundle is self-describing: bundle.json (its schema is ago_runtime/predict/contract.py, `BundleContract`)
carries the grid, the label space the model was trained with, the text encoder its banks must come from,
the preprocessing, the camera rig, and the sha256 of every file. Layout (format 5):

    bundle_dir/
      bundle.json        the contract (format_version 5)
      planes.onnx        images (1,V,3,H,W) f32 + ego2img (1,V,4,4) f32 -> plane_xy (X,Y,Dh),
                         plane_xz (X,Z,Dh), plane_yz (Y,Z,Dh): the TPV planes at the grid's resolution
                         times the decoder's first linear layer, channels last
      voxels_<i>.onnx    the per-voxel MLP after the planes, one graph per linear layer: x (n, d) -> y = x W^T + b
                         (contract "voxel_stages"; ago_runtime/predict/encoder.py)
      planes.int8.onnx, voxels_<i>.int8.onnx   optional: the "int8" variant (contract "variants"; `ago export --int8`)
      heads.npz          the arrays contract.HEADS_NPZ declares: W_dec (C,Dh), b_dec (C,), W_ad (C,Da), b_ad (C,),
                         free_embedding (C,), branch_scales (2,) the identifier's logit scales (main, adapted),
                         free_bias (1,) added to the main branch's free score, and optionally together
                         adapted_mean (C,), adapted_cov (C,C): the adapted branch's standardisation
      banks/<name>.npz   prompt banks (ago_runtime.vocab.bank.PromptBank files); "train" = the
                         training label space's embeddings stored in the checkpoint
      card.json          optional (ago_runtime/predict/card.py, written by ago_export/card.py): what the model
                         was trained on
      text_encoder.onnx, text_encoder.json, text_encoder.tokenizer.json
                         optional: the CLIP text tower the model was trained with (ago_export/text_tower.py),
                         its sidecar and tokenizer; `bundle_text_encoder` encodes new prompts with it

`Bundle.load(dir)` refuses (AgoInputError naming the file) a missing folder or file, another format
version (older ones with the `ago export` command that re-exports them), a file whose sha256 or size
differs from bundle.json, heads.npz arrays the contract does not declare, of other shapes than the bundle's
widths, or holding NaN / inf, and any field of bundle.json out of its range (`BundleContract.check_values`);
each graph's inputs and outputs are checked against the contract when it is opened (`contract.check_graph`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ago_runtime.errors import AgoInputError
from ago_runtime.geometry.camera import Rig
from ago_runtime.geometry.grid import Grid
from ago_runtime.geometry.preprocess import Preprocess
from ago_runtime.paths import inside_root
from ago_runtime.predict.card import CARD_FILE, BundleCard, read_card
from ago_runtime.predict.contract import (BUNDLE_FORMAT, BUNDLE_FORMAT_VERSION, BUNDLE_JSON,  # noqa: F401
                                          HEADS_NPZ, BundleContract, file_sha256)
from ago_runtime.predict.decision import Identifier
from ago_runtime.predict.heads import HeadWeights
from ago_runtime.readers import open_npz, read_json

ENV_BUNDLE = "AGO_BUNDLE"
DEFAULT_BUNDLE_DIR = Path(__file__).resolve().parents[1] / "assets" / "default_bundle"
DEMO_FRAME_DIR = Path(__file__).resolve().parents[1] / "assets" / "demo_frame"
HOW_TO_MAKE_DEFAULT = ("build one with scripts/make_default_bundle.sh (synth data -> pseudo-labels -> "
                       "train -> ago export), or pass --bundle DIR / set $AGO_BUNDLE")


@dataclass
class FileRef:
    """A bundle file: where it is and its sha256 (for the optimised-graph cache)."""

    path: Path
    sha256: str


@dataclass
class Bundle:
    root: Path
    contract: BundleContract
    rig: Rig                       # the training rig's calibration, in the model's camera order (fallback calibration)
    heads: HeadWeights
    banks: dict[str, Path] = field(default_factory=dict)
    card: BundleCard | None = None   # card.json (what the model was trained on), None when the bundle has none

    @property
    def meta(self) -> dict:
        """bundle.json's content (the contract as a dict)."""
        return self.contract.to_dict()

    @property
    def grid(self) -> Grid:
        return self.contract.grid

    @property
    def preprocess(self) -> Preprocess:
        return self.contract.preprocess

    @property
    def label_space(self):
        return self.contract.label_space

    @property
    def text_encoder(self):
        return self.contract.text_encoder

    # ---- paths -----------------------------------------------------------------------------
    def file(self, key: str) -> FileRef:
        entry = self.contract.files[key]
        return FileRef(self.root / entry.path, entry.sha256)   # paths checked under the root by Bundle.load

    def encoder_graphs(self, variant: str | None = None):
        """-> (planes FileRef, [StageGraph, ...]) of the float32 graphs, or of a variant's (contract "variants",
        e.g. "int8")."""
        from ago_runtime.predict.encoder import StageGraph

        planes, stage_keys = self.contract.graph_keys(variant, self.root)
        stages = []
        for st, key in zip(self.contract.voxel_stages, stage_keys):
            ref = self.file(key)
            stages.append(StageGraph(st, ref.path, ref.sha256))
        return self.file(planes), stages

    @property
    def default_bank(self) -> str:
        return self.contract.default_bank

    @property
    def identifier(self) -> Identifier:
        """The open-world identifier (bundle.json "identifier"), used for banks with unknown classes."""
        return self.contract.identifier

    @property
    def trained_classes(self) -> list[str]:
        return self.contract.label_space.class_names

    def identifier_for(self, bank) -> Identifier:
        """The default identifier for `bank` (ago_runtime.predict.heads.default_identifier): the
        open-world one when the bank holds classes this bundle was not trained on, else NONE."""
        from .heads import default_identifier

        return default_identifier(bank.class_names, bank.known, self.trained_classes, self.identifier)

    @property
    def embed_dim(self) -> int:
        return int(self.contract.text_encoder.dim)

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
        contract = BundleContract.from_dict(meta, meta_path)   # every field checked by value (check_values)
        rig = contract.training_rig.ordered_as(contract.rig.names, meta_path)
        for key, entry in contract.files.items():
            p = inside_root(root, entry.path, meta_path, f"bundle file {key!r}")
            if not p.is_file():
                raise AgoInputError(p, f"bundle file {key!r} is missing")
            if p.stat().st_size != entry.size:
                raise AgoInputError(p, f"file has {p.stat().st_size} bytes, bundle.json says {entry.size} "
                                    "(truncated or replaced; re-export the bundle)")
            if verify_hashes and file_sha256(p) != entry.sha256:
                raise AgoInputError(p, "sha256 differs from bundle.json (corrupt or replaced; re-export the bundle)")
        heads = load_heads(root / contract.files[BundleContract.HEADS].path, contract.head_widths)
        banks = {name: root / contract.files[key].path for name, key in contract.banks.items()}
        card = read_card(root / CARD_FILE) if (root / CARD_FILE).is_file() else None
        bundle = cls(root, contract, rig, heads, banks, card)
        if "train" in banks:   # the label space bundle.json states is the training bank's
            names = bundle.load_bank("train").class_names
            if names != bundle.trained_classes:
                raise AgoInputError(meta_path, f"label_space lists {len(bundle.trained_classes)} classes "
                                    f"{bundle.trained_classes[:5]}..., its train bank {len(names)} {names[:5]}...")
        return bundle


def load_heads(path: Path, widths: dict[str, int]) -> HeadWeights:
    """heads.npz -> HeadWeights: exactly the arrays HEADS_NPZ declares, each of its shape in the bundle's `widths`
    (BundleContract.head_widths), finite, branch scales > 0 and variances >= 0; else AgoInputError(path, ...)."""
    with open_npz(path, "heads .npz") as z:
        HEADS_NPZ.check_names(z.files, path)
        arrays = {k: np.asarray(z[k], dtype=np.float32) for k in z.files}
    for k, a in arrays.items():
        want = HEADS_NPZ.shape(k, widths)
        if a.shape != want:
            raise AgoInputError(path, f"{k} has shape {a.shape}, the bundle's widths (embedding C {widths['C']}, "
                                f"hidden Dh {widths['Dh']}, adapted Da {widths['Da']}) make it {want} (mixed files "
                                "from two exports? re-export the bundle)")
        if not np.isfinite(a).all():
            raise AgoInputError(path, f"head weights contain NaN or inf ({k})")
    if not np.all(arrays["branch_scales"] > 0):
        raise AgoInputError(path, f"branch_scales must be two positive numbers, got {arrays['branch_scales'].tolist()}")
    if "adapted_cov" in arrays and not np.all(np.diag(arrays["adapted_cov"]) >= 0):
        raise AgoInputError(path, "adapted_cov has a negative variance")
    return HeadWeights.from_arrays(arrays)


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
    if bundle.card and bundle.card.summary:
        return f"bundle: {' '.join(bundle.card.summary.split())}"
    known = f" (checkpoint step {bundle.contract.checkpoint.step}, label space {bundle.label_space.name})"
    if bundle.root.resolve() == DEFAULT_BUNDLE_DIR:
        return ("bundle: the shipped default bundle has no bundle card" + known + "; it is the small demo model "
                "scripts/make_default_bundle.sh trains on the SYNTHETIC world - not a nuScenes model")
    return f"bundle: {bundle.root} has no bundle card (card.json){known}: what it was trained on is not recorded"
