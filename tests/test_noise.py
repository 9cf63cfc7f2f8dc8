"""Noise-word dictionary and noise bank (WordNet via scripts/setup_nltk_data.sh)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ago_runtime.vocab import text_encoder as te
from ago_runtime.errors import AgoInputError

noise = pytest.importorskip("ago_train.text.noise")
REPO = Path(__file__).resolve().parents[1]


def _wordnet_ready() -> bool:
    try:
        noise._nltk()
        from nltk.corpus import wordnet

        wordnet.synsets("car")
        return True
    except LookupError:
        return False


@pytest.fixture(scope="module")
def encoder():
    if te.int8_model_path() is None or te.minilm_vocab_path() is None:
        pytest.skip("bundled MiniLM packages not installed")
    return te.OnnxTextEncoder(te.int8_model_path(), variant="onnx-int8")


@pytest.fixture(scope="module")
def small_bank(encoder):
    if not _wordnet_ready():
        pytest.fail("WordNet data missing: run scripts/setup_nltk_data.sh")
    return noise.build_noise_bank(encoder, max_candidates=800, max_words=500)


def test_label_phrases_cover_shipped_files():
    labels = noise.label_phrases()
    for p in ("car", "traffic cone", "driveable surface", "wheel barrow", "vegetation", "vehicle"):
        assert p in labels


def test_noise_words_exclude_labels_and_near_synonyms(small_bank, encoder):
    labels = noise.label_phrases()
    label_words = {w for p in labels for w in [p, *p.split()]}
    assert len(small_bank) == 500
    assert not set(small_bank.words) & label_words
    emb = small_bank.embeddings.astype(np.float32)
    assert ((emb @ encoder.encode(labels).T).max(1) <= noise.NEAR_SYNONYM_COS + 0.01).all()
    assert all(w.isalpha() and w.islower() and " " not in w for w in small_bank.words)
    counts = small_bank.meta["filter_counts"]
    values = list(counts.values())
    assert values == sorted(values, reverse=True) and values[-1] == 500


def test_candidates_drop_label_words(encoder):
    if not _wordnet_ready():
        pytest.fail("WordNet data missing: run scripts/setup_nltk_data.sh")
    words = noise.candidate_words(encoder.tokenizer, noise.label_phrases())
    assert "tree" not in words and "car" not in words and "road" not in words
    assert "violin" in words and "philosophy" in words     # ordinary nouns survive
    assert "aaron" not in words                            # proper noun (capitalised in WordNet)


def test_near_synonyms_dropped(encoder):
    bank = noise.build_noise_bank(encoder, candidates=["forest", "pond", "automobile", "lorry", "banana",
                                                       "philosophy", "violin", "car", "tree"])
    assert set(bank.words) == {"banana", "philosophy", "violin"}


def test_sampling_deterministic_and_file_small(small_bank, tmp_path):
    path = small_bank.save(tmp_path / "noise.npz")
    nb = noise.NoiseBank.load(path)
    assert nb.words == small_bank.words and nb.embeddings.dtype == np.float16 and nb.dim == 384
    a = nb.sample(100, np.random.default_rng(7))
    b = nb.sample(100, np.random.default_rng(7))
    c = nb.sample(100, np.random.default_rng(8))
    assert a.shape == (100, 384) and a.dtype == np.float32
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert len(set(nb.sample_indices(100, np.random.default_rng(7)).tolist())) == 100   # distinct words
    assert np.allclose(np.linalg.norm(a, axis=1), 1.0, atol=2e-3)
    assert path.stat().st_size < 500 * 384 * 2 * 1.1 + 20_000


def test_ensure_noise_bank_reuses_file(tmp_path, small_bank):
    p = small_bank.save(tmp_path / "n.npz")
    mtime = p.stat().st_mtime_ns
    assert noise.ensure_noise_bank(p) == p and p.stat().st_mtime_ns == mtime
    assert small_bank.meta["recipe_version"] == noise.RECIPE_VERSION


def test_bad_noise_bank_file(tmp_path):
    p = tmp_path / "x.npz"
    np.savez(p, words=np.array(["a"]))
    with pytest.raises(AgoInputError):
        noise.NoiseBank.load(p)
    with pytest.raises(AgoInputError, match="ago prompts noise"):
        noise.NoiseBank.load(tmp_path / "missing.npz")


def test_missing_wordnet_gives_setup_hint(tmp_path):
    code = (
        "import nltk, ago_train.text.noise as n; from pathlib import Path; "
        f"n.REPO_ROOT = Path({str(tmp_path)!r}); nltk.data.path[:] = [{str(tmp_path)!r}]; "
        "from ago_runtime.vocab.tokenizer import WordPieceTokenizer; from ago_runtime.vocab.text_encoder import minilm_vocab_path; "
        "n.candidate_words(WordPieceTokenizer(minilm_vocab_path()), ['car'])"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO,
                       env={"PATH": "/usr/bin:/bin", "HOME": str(tmp_path), "NLTK_DATA": str(tmp_path)})
    assert r.returncode != 0 and "AgoInputError" in r.stderr and "setup_nltk_data.sh" in r.stderr


def test_setup_script_is_idempotent(tmp_path):
    if not Path("/usr/share/wordnet/data.noun").is_file() or not Path("/usr/share/dict/web2").is_file():
        pytest.skip("Debian wordnet-base / miscfiles not installed (the script would apt-get them)")
    env = {"PATH": "/usr/bin:/bin", "NLTK_DATA": str(tmp_path / "nd")}
    for _ in range(2):
        r = subprocess.run(["bash", str(REPO / "scripts/setup_nltk_data.sh")], capture_output=True, text=True, env=env)
        assert r.returncode == 0, r.stderr
    wn = tmp_path / "nd/corpora/wordnet"
    assert (wn / "data.noun").is_file() and not (wn / "data.noun").is_symlink()
    lex = (wn / "lexnames").read_text().splitlines()
    assert len(lex) == 45 and lex[3].split("\t") == ["03", "noun.Tops", "1"] and lex[44].startswith("44\tadj.ppl")
    assert (tmp_path / "nd/corpora/words/en").stat().st_size > 1_000_000


@pytest.mark.slow
def test_full_default_bank(tmp_path, encoder):
    """The real dictionary (~7.7k candidates encoded): size and filter counts (~20-40 s)."""
    if not _wordnet_ready():
        pytest.fail("WordNet data missing: run scripts/setup_nltk_data.sh")
    path = noise.ensure_noise_bank(tmp_path / "full.npz", encoder=encoder)
    nb = noise.NoiseBank.load(path)
    assert len(nb) == noise.MAX_WORDS
    assert path.stat().st_size < 6_000_000
    assert nb.meta["filter_counts"]["wordnet noun lemmas"] > 100_000
