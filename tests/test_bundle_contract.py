"""What `ago export` writes is what the bundle contract declares and what `Bundle.load` reads (issue 50):
bundle.json's keys at every level, heads.npz's arrays, the graphs' input / output names, the int8 variant
through its typed field, the card; a format-4 bundle is refused with the re-export command."""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest
from conftest import tiny_town

from ago_runtime.errors import AgoInputError
from ago_runtime.predict.card import BundleCard, read_card
from ago_runtime.predict.contract import (BUNDLE_JSON, HEADS_NPZ, PLANES_INPUTS, PLANES_OUTPUTS, STAGE_INPUT,
                                          STAGE_OUTPUT, BundleContract, FileEntry, file_sha256)

REPO = Path(__file__).resolve().parents[1]
torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")

from ago_export.export import export_bundle  # noqa: E402
from ago_export.testing import random_checkpoint  # noqa: E402
from ago_runtime.predict.bundle import Bundle, load_heads  # noqa: E402
from ago_runtime.predict.heads import HeadWeights  # noqa: E402


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    root = tmp_path_factory.mktemp("contract")
    os.environ["AGO_CACHE_DIR"] = str(root / "cache")
    ckpt = random_checkpoint(root / "tiny.pt", "tiny", prompts="cw", seed=3)
    bundle = root / "bundle"
    town = tiny_town(root / "town")   # the int8 graph's calibration frames (a random checkpoint records none)
    export_bundle(ckpt, bundle, int8=True, bank_prompts=[], real_frame=False, log=lambda s: None,
                  calibration_data=town)
    return {"root": root, "ckpt": ckpt, "bundle": bundle, "meta": json.loads((bundle / BUNDLE_JSON).read_text())}


def _copy(exported, tmp_path: Path, change) -> Path:
    """A copy of the exported bundle with bundle.json changed by `change(meta, folder)`, its files' entries
    recomputed (so only the change is wrong)."""
    d = tmp_path / "b"
    shutil.copytree(exported["bundle"], d)
    meta = json.loads((d / BUNDLE_JSON).read_text())
    change(meta, d)
    for key, entry in meta["files"].items():
        if (d / entry["path"]).is_file():
            meta["files"][key] = {"path": entry["path"], "sha256": file_sha256(d / entry["path"]),
                                  "size": (d / entry["path"]).stat().st_size}
    (d / BUNDLE_JSON).write_text(json.dumps(meta))
    return d


# every JSON object bundle.json holds whose keys the contract declares (not the maps from names the export
# chooses: files, banks, bank_notes, variants, graphs; nor the ModelConfig record), by where it is
OBJECTS = {
    "bundle": lambda m: m, "checkpoint": lambda m: m["checkpoint"], "model": lambda m: m["model"],
    "grid": lambda m: m["grid"], "model_grid": lambda m: m["model_grid"], "preprocess": lambda m: m["preprocess"],
    "rig": lambda m: m["rig"], "rig.cameras[0]": lambda m: m["rig"]["cameras"][0],
    "training_rig": lambda m: m["training_rig"], "training_rig.cameras[0]": lambda m: m["training_rig"]["cameras"][0],
    "label_space": lambda m: m["label_space"], "label_space.classes[0]": lambda m: m["label_space"]["classes"][0],
    "text_encoder": lambda m: m["text_encoder"], "files[heads]": lambda m: m["files"]["heads"],
    "voxel_stages[0]": lambda m: m["voxel_stages"][0], "parity": lambda m: m["parity"],
    "parity.fp32": lambda m: m["parity"]["fp32"], "parity.fp32.tolerance": lambda m: m["parity"]["fp32"]["tolerance"],
    "variants[int8]": lambda m: m["variants"]["int8"], "variants[int8].parity": lambda m: m["variants"]["int8"]["parity"],
}


def test_bundle_json_is_exactly_the_contract(exported):
    """Every key written is a declared field, every declared field is written, and reading gives back the file."""
    meta = exported["meta"]
    assert sorted(meta) == sorted(BundleContract.keys())
    assert BundleContract.keys() == ["format"] + [f.name for f in fields(BundleContract)]
    c = BundleContract.from_dict(meta, "bundle.json")
    assert c.to_dict() == meta and json.loads(json.dumps(c.to_dict())) == meta
    assert c.format_version == 5 and c.checkpoint.sha256 == file_sha256(exported["ckpt"])
    assert c.grid.shape == (20, 20, 4) and c.preprocess.width == 96 and c.training_rig.names == c.rig.names
    assert c.label_space.classes[4].name == "car" and c.label_space.classes[4].table_ids == [4]
    assert c.parity.fp32.ok and not c.parity.skipped and c.parity.text_encoder is None
    assert "adapter_dim" not in json.dumps(meta) and "hidden_dim" not in meta["model"]   # widths stated once
    assert set(c.banks.values()) <= set(c.files) and c.banks["train"] in c.files


@pytest.mark.parametrize("where", sorted(OBJECTS))
def test_an_undeclared_key_is_refused_at_every_level(exported, where):
    meta = json.loads(json.dumps(exported["meta"]))
    OBJECTS[where](meta)["bogus"] = 1
    with pytest.raises(AgoInputError) as e:
        BundleContract.from_dict(meta, "some/bundle.json")
    assert str(e.value).startswith("some/bundle.json:") and "'bogus'" in str(e.value) and "does not declare" in str(e.value)


@pytest.mark.parametrize("key", [k for k in BundleContract.keys() if k not in ("format", "format_version")])
def test_a_declared_key_missing_is_refused(exported, key):
    meta = dict(exported["meta"])
    meta.pop(key)
    with pytest.raises(AgoInputError, match=f"lacks '{key}'"):
        BundleContract.from_dict(meta, "some/bundle.json")


def test_format_4_is_refused_with_the_reexport_command(exported):
    meta = dict(exported["meta"], format_version=4)
    with pytest.raises(AgoInputError, match=r"bundle format version 4 is no longer read \(this ago reads 5\); "
                                            r"re-export the checkpoint: `ago export CKPT -o BUNDLE_DIR`"):
        BundleContract.from_dict(meta, "b/bundle.json")


def test_model_record_reads_back_as_the_training_config(exported):
    from ago_train.checkpoint import CheckpointContract
    from ago_train.model import ModelConfig

    c = BundleContract.from_dict(exported["meta"], "bundle.json")
    assert ModelConfig.from_dict(dict(c.model.config)) == CheckpointContract.load(exported["ckpt"]).model_config
    assert c.model.opset == 17


def test_heads_npz_holds_exactly_the_declared_arrays(exported, tmp_path):
    b = Bundle.load(exported["bundle"])
    with np.load(exported["bundle"] / "heads.npz") as z:
        written = sorted(z.files)
    assert written == sorted(HEADS_NPZ.required)          # a checkpoint without calibration: no standardisation
    assert sorted(f.name for f in fields(HeadWeights)) == sorted(HEADS_NPZ.names)   # one name per array and field
    rng = np.random.default_rng(0)
    w = b.heads
    w.adapted_mean = rng.standard_normal(w.embed_dim).astype(np.float32)
    w.adapted_cov = np.eye(w.embed_dim, dtype=np.float32)
    arrays = w.to_arrays()
    assert sorted(arrays) == sorted(HEADS_NPZ.names)
    widths = b.contract.head_widths
    for name, a in arrays.items():
        assert a.shape == HEADS_NPZ.shape(name, widths) and a.dtype == np.float32, name
    np.savez(tmp_path / "h.npz", **arrays)
    back = load_heads(tmp_path / "h.npz", widths)
    for name in HEADS_NPZ.names:
        np.testing.assert_array_equal(HeadWeights.to_arrays(back)[name], arrays[name])
    cases = {"extra": ({**arrays, "W_extra": arrays["b_dec"]}, "does not declare"),
             "missing": ({k: v for k, v in arrays.items() if k != "free_bias"}, "lack 'free_bias'"),
             "half the pair": ({k: v for k, v in arrays.items() if k != "adapted_cov"}, "go together"),
             "widths": ({**arrays, "W_ad": arrays["W_ad"][:, :3]}, "W_ad has shape"),
             "nan": ({**arrays, "b_ad": arrays["b_ad"] * np.nan}, "NaN")}
    for what, (bad, words) in cases.items():
        np.savez(tmp_path / "bad.npz", **bad)
        with pytest.raises(AgoInputError) as e:
            load_heads(tmp_path / "bad.npz", widths)
        assert str(e.value).startswith(str(tmp_path / "bad.npz")) and words in str(e.value), what


def test_graph_names_are_the_contracts(exported):
    """The exporter traces every graph (float32 and the int8 variant's) with the contract's input / output names,
    and writes no ago metadata_props (bundle.json is the one record of what a graph is; onnxruntime's quantiser
    adds its own)."""
    c = BundleContract.from_dict(exported["meta"], "bundle.json")
    graphs = {c.PLANES: (PLANES_INPUTS, PLANES_OUTPUTS), **{s.file: ((STAGE_INPUT,), (STAGE_OUTPUT,)) for s in c.voxel_stages}}
    for key, (inputs, outputs) in graphs.items():
        for file_key in (key, c.variants["int8"].graphs[key]):
            model = onnx.load(str(exported["bundle"] / c.files[file_key].path))
            assert tuple(i.name for i in model.graph.input) == inputs, file_key
            assert tuple(o.name for o in model.graph.output) == outputs, file_key
            assert not [p.key for p in model.metadata_props if p.key.startswith("ago")], file_key


def test_the_int8_variant_is_found_through_its_typed_field(exported, tmp_path):
    """The int8 graphs are whatever files the variant names (no file-name convention): renamed files and keys
    still load and run; a variant that leaves out a graph, or names a file not listed, is refused."""
    from ago_runtime.predict.encoder import open_encoder

    def rename(m, d):
        (d / "q").mkdir()
        graphs = m["variants"]["int8"]["graphs"]
        for graph, key in list(graphs.items()):
            entry = m["files"].pop(key)
            (d / entry["path"]).rename(d / "q" / f"{graph}.onnx")
            graphs[graph] = f"quantised {graph}"
            m["files"][graphs[graph]] = dict(entry, path=f"q/{graph}.onnx")

    b = Bundle.load(_copy(exported, tmp_path, rename))
    planes, stages = b.encoder_graphs("int8")
    assert planes.path == b.root / "q" / "planes.onnx" and [s.path.name for s in stages] == ["voxels_0.onnx"]
    assert b.contract.variants["int8"].precision == "int8" and b.contract.variants["int8"].parity.ok
    enc = open_encoder(b, int8=True, warm_up=False)
    assert enc.planes_path == planes.path

    meta = dict(exported["meta"], variants={})
    with pytest.raises(AgoInputError, match="bundle has no int8 graphs .*ago export --int8"):
        BundleContract.from_dict(meta, "b.json").graph_keys("int8", "b")
    meta = json.loads(json.dumps(exported["meta"]))
    meta["variants"]["int8"]["graphs"].pop("voxels_0")
    with pytest.raises(AgoInputError, match=r"variants\['int8'\].graphs: must give one graph for each of"):
        BundleContract.from_dict(meta, "b.json")
    meta = json.loads(json.dumps(exported["meta"]))
    meta["variants"]["int8"]["graphs"]["planes"] = "planes"     # listed, but check it is a file key at all
    BundleContract.from_dict(meta, "b.json")
    meta["variants"]["int8"]["graphs"]["planes"] = "nowhere"
    with pytest.raises(AgoInputError, match="names file 'nowhere', which files does not list"):
        BundleContract.from_dict(meta, "b.json")


def test_a_bank_is_named_by_its_file_key(exported, tmp_path):
    meta = json.loads(json.dumps(exported["meta"]))
    meta["banks"]["train"] = "banks/train.npz"          # a path, not a key of files
    with pytest.raises(AgoInputError, match=r"banks\['train'\]: names file 'banks/train.npz'"):
        BundleContract.from_dict(meta, "b.json")


def test_the_card_is_exactly_its_contract(exported, tmp_path):
    from ago_export.card import read_card_options

    raw = json.loads((exported["bundle"] / "card.json").read_text())
    assert sorted(raw) == sorted(f.name for f in fields(BundleCard))
    card = read_card(exported["bundle"] / "card.json")
    assert card.to_dict() == raw and card.summary.startswith("trained on")
    assert Bundle.load(exported["bundle"]).card == card
    (tmp_path / "bad.json").write_text(json.dumps(dict(raw, bogus=1)))
    with pytest.raises(AgoInputError, match="not a bundle card.*'bogus'"):
        read_card(tmp_path / "bad.json")
    (tmp_path / "extra.json").write_text(json.dumps({"val_scores": {"mIoU": 7.5, "split": "val"}}))
    assert read_card_options(None, tmp_path / "extra.json")["extra"]["val_scores"]["mIoU"] == 7.5
    for extra, words in (({"scores": {"mIoU": 7.5}}, "'scores'"), ({"val_scores": {"miou": 7.5}}, "'miou'"),
                         ({"val_scores": {"mIoU": "high"}}, "card.val_scores.mIoU must be float")):
        (tmp_path / "extra.json").write_text(json.dumps(extra))
        with pytest.raises(AgoInputError) as e:
            read_card_options(None, tmp_path / "extra.json")
        assert str(e.value).startswith(str(tmp_path / "extra.json")) and words in str(e.value)


def test_records_round_trip_every_field():
    """A record written by record_to_dict is read back field for field (FileEntry as the smallest example)."""
    from ago_runtime.predict.contract import record_from_dict, record_to_dict

    e = FileEntry("a.onnx", "0" * 64, 3)
    assert record_from_dict(FileEntry, record_to_dict(e), "f") == e
    with pytest.raises(ValueError, match="f.size must be int"):
        record_from_dict(FileEntry, {"path": "a", "sha256": "b", "size": "3"}, "f")
