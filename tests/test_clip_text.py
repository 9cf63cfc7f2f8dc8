"""Issue 49: the paper's text encoder, a CLIP text tower from the user's folder, from the bank to the torch-free runtime.

A tiny CLIP (random weights from a CLIPConfig, a byte-level BPE tokenizer written from a small vocabulary:
tests/clip_tiny.py) is saved once per session. The parts first (the tokenizer against transformers', the torch
tower against `get_text_features`, the ONNX tower, banks, noise words), then the chain on a synthetic town:
a MaskCLIP-like feature folder made in the CLIP's width -> `ago pseudo-labels --text-encoder` -> `ago train
--text-encoder` (the adapter aligned) -> `ago export` (the tower ships, parity-checked) -> a new prompt file made
into a bank and predicted with, in a process where torch cannot be imported; then every mismatch row."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("transformers")

from clip_tiny import WORDS, write_clip, write_noise  # noqa: E402
from test_bad_inputs import assert_one_error_line, ok, run_ago  # noqa: E402

pytestmark = pytest.mark.xdist_group("test_clip_text")  # one worker builds the module fixtures (--dist loadgroup)

REPO = Path(__file__).resolve().parents[1]
PROMPTS = """car [car]: car, van
road [driveable_surface]: road, street
building [manmade]: building, house
tree [vegetation]: tree, bush
"""
NEW_PROMPTS = """fire hydrant: fire hydrant, hydrant
road [driveable_surface]: road, street
sky: sky
"""
TEXTS = ["car", "a photo of a car", "", "Fire  HYDRANT!", "the sidewalk's edge", "café déjà vu", "road, street",
         "x" * 60, "12 cars", "a\ttree"]


def _quiet():
    from transformers.utils import logging

    logging.set_verbosity_error()
    logging.disable_progress_bar()


@pytest.fixture(scope="session")
def clip_dir(tmp_path_factory) -> Path:
    _quiet()
    return write_clip(tmp_path_factory.mktemp("clip") / "tiny-clip")


@pytest.fixture(scope="session")
def encoder(clip_dir):
    from ago_train.text.clip import TorchClipTextEncoder

    return TorchClipTextEncoder(clip_dir)


# ---------------------------------------------------------------------------- the parts
def test_the_tokenizer_matches_transformers_token_for_token(clip_dir):
    import warnings

    from transformers import CLIPTokenizer

    from ago_runtime.vocab.clip_tokenizer import ClipTokenizer

    ours = ClipTokenizer(clip_dir / "tokenizer.json", max_length=32)
    ref = CLIPTokenizer.from_pretrained(clip_dir)(TEXTS, padding=True, truncation=True, max_length=32)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ids, mask = ours.encode(TEXTS)
    assert np.array_equal(ids, np.array(ref["input_ids"])) and np.array_equal(mask, np.array(ref["attention_mask"]))
    assert any("truncated to 30" in str(w.message) for w in caught)      # "x" * 60: 60 byte tokens, cut, end kept
    assert ids[7, -1] == ours.eos_id and ids[0, 0] == ours.bos_id and ids[0, mask[0].sum():].tolist() == \
        [ours.eos_id] * (ids.shape[1] - mask[0].sum())                    # padded with the end token


@pytest.mark.parametrize("legacy", [False, True], ids=["eos_token_id", "argmax-legacy"])
def test_the_torch_tower_is_get_text_features_normalised(tmp_path, legacy, clip_dir, encoder):
    import torch
    from transformers import CLIPModel, CLIPTokenizer

    from ago_train.text.clip import TorchClipTextEncoder

    _quiet()
    folder = write_clip(tmp_path / "legacy", legacy_eos=True) if legacy else clip_dir
    enc = TorchClipTextEncoder(folder) if legacy else encoder
    model = CLIPModel.from_pretrained(folder).eval()
    batch = CLIPTokenizer.from_pretrained(folder)(TEXTS[:7], padding=True, return_tensors="pt")
    with torch.no_grad():
        ref = model.get_text_features(**batch).pooler_output.numpy()
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    got = enc.encode(TEXTS[:7])
    assert got.shape == (7, 24) and np.abs(got - ref).max() < 1e-5
    assert abs(float((got[0] * got[1]).sum())) < 0.99999                # different texts, different embeddings


def test_the_onnx_tower_agrees_and_carries_its_tokenizer(tmp_path, encoder):
    from ago_runtime.vocab.model_folder import clip_encoder_id
    from ago_runtime.vocab.text_encoder import OnnxTextEncoder
    from ago_train.text.clip import export_clip_onnx

    (tmp_path / "tower").mkdir()
    path = export_clip_onnx(encoder, tmp_path / "tower" / "text_encoder.onnx")
    side = json.loads(path.with_suffix(".json").read_text())
    assert side["pooling"] == "eos" and side["tokenizer"] == "text_encoder.tokenizer.json" and side["max_length"] == 32
    onnx = OnnxTextEncoder(path)
    assert (onnx.encoder_id, onnx.dim) == (clip_encoder_id(encoder.folder), 24)
    texts = TEXTS[:7] + [f"{w} {w}" for w in WORDS]                    # several batches of several lengths
    onnx.batch_size = 8
    cos = (onnx.encode(texts) * encoder.encode(texts)).sum(1)
    assert cos.min() > 1 - 1e-5


def test_a_bank_records_the_clip_folder(tmp_path, clip_dir, encoder):
    from ago_runtime.vocab.bank import PromptBank
    from ago_runtime.vocab.model_folder import clip_encoder_id, folder_hash

    (tmp_path / "p.txt").write_text(PROMPTS)
    r = ok(run_ago(["prompts", "build", "p.txt", "--text-encoder", clip_dir, "-o", "bank.npz"], tmp_path))
    assert clip_encoder_id(clip_dir) in r.stdout
    bank = PromptBank.load(tmp_path / "bank.npz")
    assert (bank.encoder_id, bank.dim, bank.encoder_variant) == (clip_encoder_id(clip_dir), 24, "torch-fp32")
    assert bank.encoder_hash == folder_hash(clip_dir)
    assert np.allclose(bank.embeddings, encoder.encode(bank.phrases), atol=1e-6)


def test_bad_text_encoder_folders_are_one_line(tmp_path, clip_dir):
    (tmp_path / "p.txt").write_text(PROMPTS)
    bert = tmp_path / "bert"
    bert.mkdir()
    (bert / "config.json").write_text(json.dumps({"model_type": "bert"}))
    (bert / "model.safetensors").write_bytes(b"x")
    no_tok = tmp_path / "no-tokenizer"
    no_tok.mkdir()
    for f in ("config.json", "model.safetensors"):
        (no_tok / f).write_bytes((clip_dir / f).read_bytes())
    for folder, needles in ((tmp_path / "missing", ("--text-encoder", "no such folder", "CLIP")),
                            (bert, ("--text-encoder", "holds a 'bert' model", "clip-vit-base-patch16")),
                            (no_tok, ("--text-encoder", "no tokenizer.json"))):
        r = run_ago(["prompts", "build", "p.txt", "--text-encoder", folder, "-o", "b.npz"], tmp_path)
        assert_one_error_line(r, *needles)
    r = run_ago(["prompts", "build", "p.txt", "--text-encoder", clip_dir, "--encoder", "int8", "-o", "b.npz"], tmp_path)
    assert_one_error_line(r, "--encoder", "--text-encoder", "give one")
    r = run_ago(["pseudo-labels", "--data", tmp_path, "--out", "pl", "--text-encoder", bert], tmp_path)
    assert_one_error_line(r, "--text-encoder", "holds a 'bert' model")
    assert not (tmp_path / "b.npz").exists() and not (tmp_path / "pl").exists()


def test_noise_words_record_their_encoder_and_a_mismatch_is_refused(tmp_path, encoder):
    from ago_runtime.errors import AgoInputError
    from ago_runtime.vocab.text_encoder import MINILM_ID
    from ago_train.text import noise

    nb = noise.build_noise_bank(encoder, candidates=WORDS[23:], labels=["car"], threshold=1.0)
    assert nb.meta["encoder_id"] == encoder.encoder_id and nb.dim == 24 and len(nb) == len(WORDS) - 23
    nb.save(tmp_path / "clip_noise.npz")
    assert len(noise.training_noise_bank(str(tmp_path / "clip_noise.npz"), None, encoder.encoder_id, 24)) == len(nb)
    noise.NoiseBank(["apple"], np.ones((1, 384), np.float16), {"encoder_id": MINILM_ID}).save(tmp_path / "mini.npz")
    with pytest.raises(AgoInputError, match=f"noise words were made with encoder '{MINILM_ID}' but the prompt bank "
                                            f"with '{encoder.encoder_id}'"):
        noise.training_noise_bank(str(tmp_path / "mini.npz"), None, encoder.encoder_id, 24)
    with pytest.raises(AgoInputError, match="no noise word is left"):   # random weights: every word is "near"
        noise.build_noise_bank(encoder, candidates=WORDS[23:], labels=["car"], threshold=0.5 - 2)
    assert noise.default_noise_bank_path(encoder.encoder_id).name == f"noise_bank-clip_{encoder.encoder_id[5:]}.npz"


@pytest.mark.parametrize("int8_allowed", [0.995, 1.0 + 1e-9], ids=["int8-holds", "int8-refused"])
def test_the_int8_tower_ships_only_within_its_tolerance(tmp_path, monkeypatch, clip_dir, encoder, int8_allowed):
    from ago_export import text_tower
    from ago_runtime.vocab.bank import build_bank
    from ago_runtime.vocab.prompts import parse_prompt_text
    from ago_runtime.vocab.text_encoder import OnnxTextEncoder

    monkeypatch.setattr(text_tower, "TEXT_INT8_MIN_COS", int8_allowed)
    bank = build_bank(parse_prompt_text(PROMPTS, name="p"), encoder)
    r = text_tower.export_text_tower(clip_dir, tmp_path, bank, True, "ckpt", log=lambda s: None)
    onnx = OnnxTextEncoder(tmp_path / r["files"]["text_encoder"])
    assert r["parity"]["fp32"]["ok"] and not (tmp_path / "text_encoder.int8.onnx").exists()
    if int8_allowed < 1:   # random tiny weights: int8 keeps min cosine ~0.9996 here
        assert r["parity"]["shipped"] == onnx.variant == "onnx-int8" and r["parity"]["int8"]["ok"]
    else:
        assert r["parity"]["shipped"] == onnx.variant == "onnx-fp32" and "fp32 tower ships" in r["parity"]["int8"]["note"]
    assert r["card"]["variant"] == onnx.variant and r["card"]["kind"] == "clip"
    assert (onnx.encode(bank.phrases) * bank.embeddings).sum(1).min() >= min(int8_allowed, 1 - 1e-5)


# ---------------------------------------------------------------------------- the chain
def write_features(root: Path, out: Path, clip_dir: Path, dim: int = 24) -> None:
    """A MaskCLIP-like feature folder (docs/vlm_files.md): per camera image a (D, 9, 16) float16 map, a fixed random
    projection of the image's colours, and meta.json naming the CLIP folder's encoder id and width."""
    import cv2

    from ago_runtime.vocab.model_folder import clip_encoder_id

    w = np.random.default_rng(0).standard_normal((dim, 3)).astype(np.float32)
    for img in sorted((root / "samples").glob("CAM_*/*.jpg")):
        small = cv2.imread(str(img), cv2.IMREAD_REDUCED_COLOR_8)     # decoded at 1/8 size: fast on 1600x900
        rgb = cv2.resize(small[:, :, ::-1], (16, 9), interpolation=cv2.INTER_AREA) / 255.0
        (out / img.parent.name).mkdir(parents=True, exist_ok=True)
        np.save(out / img.parent.name / f"{img.stem}.npy", np.einsum("dc,hwc->dhw", w, rgb - 0.5).astype(np.float16))
    (out / "meta.json").write_text(json.dumps({"channels": dim, "encoder_id": clip_encoder_id(clip_dir),
                                               "model": "test"}))


BLOCK_TORCH = """import sys
class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("torch", "transformers"):
            raise ImportError(f"{name} is blocked: a runtime-only process")
        return None
sys.meta_path.insert(0, Block())
from ago_runtime.cli import run
rc = run(sys.argv[1:])
assert "torch" not in sys.modules and "transformers" not in sys.modules
sys.exit(rc)
"""


def run_without_torch(args, cwd: Path) -> subprocess.CompletedProcess:
    """`ago ARGS` in a child python in which importing torch or transformers fails (a runtime-only install)."""
    env = dict(os.environ, PYTHONPATH=str(REPO), AGO_NO_PROGRESS="1")
    env.pop("AGO_TEXT_ENCODER", None)
    return subprocess.run([sys.executable, "-c", BLOCK_TORCH, *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, env=env)


@pytest.fixture(scope="module")
def chain(tmp_path_factory, clip_dir) -> Path:
    d = tmp_path_factory.mktemp("clip_chain")
    ok(run_ago(["synth", "--out", "s", "--scenes", "2", "--frames", "3", "--image-size", "192x108", "--grid",
                "40x40x4", "--seed", "7"], d))
    write_features(d / "s", d / "feats", clip_dir)
    (d / "p.txt").write_text(PROMPTS)
    (d / "new.txt").write_text(NEW_PROMPTS)
    write_noise(d / "noise.npz", clip_dir)
    ok(run_ago(["pseudo-labels", "--data", "s", "--out", "pl", "--prompts", "p.txt", "--segmenter", "sim",
                "--embedder", "files", "--feats", "feats", "--text-encoder", clip_dir, "--grid", "20x20x4"], d))
    ok(run_ago(["train", "--config", "tiny", "--data", "s", "--pseudo", "pl", "--prompts", "p.txt", "--out", "run",
                "--text-encoder", clip_dir, "--set", 'noise_bank="noise.npz"', "--set", 'device="cpu"'], d))
    ok(run_ago(["export", "run/last.pt", "-o", "bundle", "--parity-frame", "s", "--train-bank-only"], d))
    d.joinpath("swap.txt").write_text(json.dumps([
        run_without_torch(["prompts", "build", "new.txt", "--bundle", "bundle", "-o", "new.npz"], d).__dict__,
        run_without_torch(["infer", "--images", "s", "--bundle", "bundle", "--prompts", "new.txt", "--out", "pred"],
                          d).__dict__], default=str))
    return d


def test_training_aligns_the_adapter_in_the_clip_space(chain, clip_dir):
    import torch

    from ago_runtime.vocab.model_folder import clip_encoder_id

    ckpt = torch.load(chain / "run" / "last.pt", weights_only=True, map_location="cpu")
    assert ckpt["bank"]["encoder_id"] == clip_encoder_id(clip_dir) and ckpt["bank"]["embeddings"].shape[1] == 24
    assert ckpt["model_config"]["embed_dim"] == 24 and ckpt["train_config"]["text_encoder"] == str(clip_dir)
    last = json.loads((chain / "run" / "log.jsonl").read_text().splitlines()[-1])
    assert last["align"] > 0                          # the modality adapter was aligned to the CLIP-width features
    meta = json.loads((chain / "pl" / "meta.json").read_text())
    assert meta["embedder"]["channels"] == 24


def test_the_bundle_ships_the_tower_and_its_card_names_it(chain, clip_dir):
    from ago_runtime.predict.bundle import Bundle
    from ago_runtime.vocab.model_folder import clip_encoder_id

    b = Bundle.load(chain / "bundle")
    cid = clip_encoder_id(clip_dir)
    assert (b.contract.text_encoder.id, b.contract.text_encoder.dim) == (cid, 24)
    assert {"text_encoder", "text_encoder_sidecar", "text_encoder_tokenizer"} <= set(b.contract.files)
    parity = b.contract.parity.text_encoder
    assert parity.fp32.ok and parity.shipped == "onnx-fp32"
    assert parity.fp32.transformers.min_cosine >= 1 - 1e-5 and parity.fp32.bank.min_cosine >= 1 - 1e-5
    card = json.loads((chain / "bundle" / "card.json").read_text())
    assert card["text_encoder"]["kind"] == "clip" and card["text_encoder"]["id"] == cid
    assert f"text encoder CLIP text tower {cid} (24-d)" in card["summary"]


def test_a_new_prompt_file_is_encoded_by_the_bundles_tower_without_torch(chain, encoder):
    from ago_runtime.vocab.bank import PromptBank

    build, infer = json.loads((chain / "swap.txt").read_text())
    assert build["returncode"] == 0, build["stderr"]
    assert infer["returncode"] == 0, infer["stderr"]
    bank = PromptBank.load(chain / "new.npz")
    assert bank.encoder_id == encoder.encoder_id and bank.encoder_variant == "onnx-fp32"
    assert bank.class_names == ["fire hydrant", "road", "sky"]
    assert (bank.embeddings * encoder.encode(bank.phrases)).sum(1).min() > 1 - 1e-5
    preds = sorted((chain / "pred").glob("*.npz"))
    assert len(preds) == 6
    with np.load(preds[0]) as z:
        assert [str(c) for c in z["class_names"]] == ["fire hydrant", "road", "sky", "free"]


def test_ago_eval_encodes_another_prompt_file_with_the_checkpoints_folder(chain, encoder):
    from ago_runtime.vocab.prompts import parse_prompt_file
    from ago_train.checkpoint import CheckpointContract
    from ago_train.evaluate import bank_for

    ckpt = CheckpointContract.load(chain / "run" / "last.pt")
    space = parse_prompt_file(chain / "new.txt")
    emb, pc = bank_for(ckpt, space)
    assert np.allclose(emb.numpy(), encoder.encode(space.phrases), atol=1e-6) and pc.tolist() == [0, 0, 1, 1, 2]


@pytest.mark.slow
def test_a_real_scene_goes_from_clip_features_to_a_torch_free_prompt_swap(tmp_path, clip_dir):
    """The real nuScenes scene (../shared, skipped without it): MaskCLIP features of the same CLIP folder for its camera
    images (`--embedder maskclip`, issue 48's code), labels from its 3D boxes (no detector here), a few training steps, export (parity on the real keyframe), then a new prompt
    file's bank and a prediction of one keyframe without torch (about 2 minutes on 2 shared cores)."""
    from conftest import shared_path

    root = shared_path("nuscenes-scene")
    (tmp_path / "p.txt").write_text(PROMPTS.replace("tree [vegetation]: tree, bush", "pedestrian [pedestrian]: person"))
    (tmp_path / "new.txt").write_text(NEW_PROMPTS)
    ok(run_ago(["pseudo-labels", "--data", root, "--out", "pl", "--prompts", "p.txt", "--segmenter", "boxes",
                "--embedder", "maskclip", "--clip", clip_dir, "--clip-width", "128",   # issue 48's MaskCLIP read-out
                "--text-encoder", clip_dir, "--grid", "20x20x4",
                "--keyframes", "1", "--limit", "2"], tmp_path))
    write_noise(tmp_path / "noise.npz", clip_dir)
    ok(run_ago(["train", "--config", "tiny", "--data", root, "--pseudo", "pl", "--prompts", "p.txt", "--out", "run",
                "--text-encoder", clip_dir, "--set", 'noise_bank="noise.npz"', "--set", 'train_split="all"', "--set",
                "max_frames=2", "--set", 'device="cpu"'], tmp_path))
    assert json.loads((tmp_path / "run" / "log.jsonl").read_text().splitlines()[-1])["align"] > 0
    ok(run_ago(["export", "run/last.pt", "-o", "bundle", "--train-bank-only"], tmp_path))
    token = json.loads((root / "v1.0-mini" / "sample.json").read_text())[5]["token"]
    build = run_without_torch(["prompts", "build", "new.txt", "--bundle", "bundle", "-o", "new.npz"], tmp_path)
    infer = run_without_torch(["infer", "--images", root, "--sample", token, "--bundle", "bundle", "--prompts",
                               "new.txt", "--out", "pred"], tmp_path)
    assert build.returncode == 0 and infer.returncode == 0, build.stderr + infer.stderr
    assert "text encoder CLIP text tower clip:" in infer.stdout + infer.stderr      # the card line names it
    with np.load(tmp_path / "pred" / f"{token}.npz") as z:
        assert [str(c) for c in z["class_names"]] == ["fire hydrant", "road", "sky", "free"]


# ---------------------------------------------------------------------------- every mismatch row
@pytest.fixture(scope="module")
def other_clip(tmp_path_factory) -> Path:
    """Another tiny CLIP of the same shapes (other weights): its own encoder id."""
    _quiet()
    return write_clip(tmp_path_factory.mktemp("clip2") / "other-clip", seed=1)


def test_a_bank_of_another_encoder_is_refused_by_the_bundle(chain, other_clip):
    from ago_runtime.vocab.model_folder import clip_encoder_id

    ok(run_ago(["prompts", "build", "new.txt", "--text-encoder", other_clip, "-o", "other.npz"], chain))
    r = run_ago(["infer", "--images", "s", "--bundle", "bundle", "--bank", "other.npz", "--out", "pred2"], chain)
    bundle_id = json.loads((chain / "bundle" / "bundle.json").read_text())["text_encoder"]["id"]
    assert_one_error_line(r, "other.npz", clip_encoder_id(other_clip), f"the bundle needs {bundle_id!r}")
    # and the CLIP bank against a MiniLM bundle (the shipped default one)
    r = run_ago(["infer", "--images", "s", "--bank", "new.npz", "--out", "pred3"], chain)
    assert_one_error_line(r, "new.npz", "all-MiniLM-L6-v2", "clip:")
    assert not (chain / "pred2").exists() and not (chain / "pred3").exists()


def test_noise_words_of_another_encoder_are_refused_by_training(chain, other_clip, clip_dir):
    from ago_runtime.vocab.model_folder import clip_encoder_id

    # the bank (and the pseudo-labels' features) from clip_dir, the noise words from another CLIP
    write_noise(chain / "noise_other.npz", other_clip)
    r = run_ago(["train", "--config", "tiny", "--data", "s", "--pseudo", "pl", "--prompts", "p.txt", "--out", "run2",
                 "--text-encoder", clip_dir, "--set", 'noise_bank="noise_other.npz"', "--set", 'device="cpu"'], chain)
    assert_one_error_line(r, "noise_other.npz", "noise words", clip_encoder_id(clip_dir), clip_encoder_id(other_clip))
    assert not (chain / "run2" / "last.pt").exists()


def test_resuming_with_another_text_encoder_is_refused(chain, other_clip, clip_dir):
    from ago_runtime.vocab.model_folder import clip_encoder_id
    write_noise(chain / "noise2.npz", other_clip)
    before = (chain / "run" / "last.pt").stat().st_mtime_ns
    r = run_ago(["train", "--config", "tiny", "--data", "s", "--pseudo", "pl", "--prompts", "p.txt", "--out", "run",
                 "--resume", "--text-encoder", other_clip, "--set", 'noise_bank="noise2.npz"', "--set",
                 'device="cpu"'], chain)
    assert_one_error_line(r, "last.pt", "the checkpoint's prompt bank", clip_encoder_id(clip_dir),
                          clip_encoder_id(other_clip))
    assert (chain / "run" / "last.pt").stat().st_mtime_ns == before


def test_export_refuses_a_folder_that_did_not_make_the_bank(chain, other_clip, clip_dir):
    from ago_runtime.vocab.model_folder import clip_encoder_id

    r = run_ago(["export", "run/last.pt", "-o", "bundle2", "--parity-frame", "s", "--text-encoder", other_clip], chain)
    assert_one_error_line(r, "--text-encoder", clip_encoder_id(clip_dir), clip_encoder_id(other_clip))
    assert not (chain / "bundle2").exists()


def test_export_asks_for_the_folder_when_the_recorded_one_is_gone(clip_dir):
    from ago_export.text_tower import clip_folder_for
    from ago_runtime.errors import AgoInputError
    from ago_runtime.vocab.bank import PromptBank
    from ago_runtime.vocab.model_folder import clip_encoder_id

    bank = PromptBank(np.ones((1, 24), np.float32), ["car"], ["car"], [0], clip_encoder_id(clip_dir), "torch-fp32", "h", 24)
    for recorded in (None, "/nowhere/clip"):   # CheckpointContract.text_encoder: none, or a folder that is gone
        with pytest.raises(AgoInputError, match=f"trained with the CLIP text encoder {bank.encoder_id}.*give its folder"):
            clip_folder_for(recorded, "last.pt", bank, None)
    assert clip_folder_for(str(clip_dir), "last.pt", bank, None) == clip_dir
