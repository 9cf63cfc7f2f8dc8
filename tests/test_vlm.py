"""The paper's first stage from the user's weights (issue 48): `ago vlm-files` and `ago pseudo-labels --segmenter
grounded-sam / --embedder maskclip`, with tiny GroundingDINO / SAM / CLIP folders made here from configs (random
weights, a tokenizer written by the test; no network). The real scene (../shared) is skipped when absent."""

from __future__ import annotations

import json
import shutil
import sys
import types
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("transformers")
sys.path.insert(0, str(Path(__file__).resolve().parent))
from conftest import shared_path  # noqa: E402
from test_bad_inputs import assert_one_error_line, ok, run_ago  # noqa: E402
import vlm_tiny  # noqa: E402

FAST = ["--max-boxes", "4", "--box-threshold", "0", "--text-threshold", "0", "--clip-width", "64"]


@pytest.fixture(scope="session")
def models(tmp_path_factory):
    from ago_train.vlm.loading import quiet_transformers

    quiet_transformers()
    root = tmp_path_factory.mktemp("vlm_models")
    m = types.SimpleNamespace(**vlm_tiny.write_all(root))
    m.detector_resnet = vlm_tiny.write_grounding_dino(root / "gdino_resnet", backbone="resnet")
    m.root = root
    return m


@pytest.fixture(scope="module")
def town(tmp_path_factory):
    root = tmp_path_factory.mktemp("vlm_town")
    ok(run_ago(["synth", "--out", root / "synth", "--scenes", "1", "--frames", "2", "--image-size", "96x54",
                "--grid", "20x20x4"], root))
    return root / "synth"


def weights(m, clip=True):
    return ["--detector", m.detector, "--sam", m.sam] + (["--clip", m.clip] if clip else [])


def files_of(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and p.suffix in (".png", ".npy")}


# ------------------------------------------------------------------------------------ the models' code
def test_maskclip_is_the_last_blocks_value_path(models):
    """At CLIP's own input size (no interpolation) the features equal the value path computed from transformers'
    hidden states; at another size the map has the documented shape."""
    import torch
    from transformers import CLIPModel

    from ago_train.vlm.maskclip import MaskClip

    mc = MaskClip(models.clip, torch.device("cpu"), width=32)
    img = np.random.default_rng(0).integers(0, 256, (32, 32, 3), dtype=np.uint8)
    feats = mc.features(img)
    ref_model = CLIPModel.from_pretrained(str(models.clip)).eval()
    from ago_train.vlm.loading import to_tensor

    px = to_tensor(img, 32, 32, mc.mean, mc.std, torch.device("cpu"))
    with torch.no_grad():
        hs = ref_model.vision_model(px, output_hidden_states=True).hidden_states[-2]
        last = ref_model.vision_model.encoder.layers[-1]
        ref = ref_model.visual_projection(ref_model.vision_model.post_layernorm(
            last.self_attn.out_proj(last.self_attn.v_proj(last.layer_norm1(hs)))))[0, 1:]
    np.testing.assert_allclose(feats.astype(np.float32), ref.numpy().T.reshape(24, 4, 4), atol=2e-2, rtol=1e-2)
    wide = MaskClip(models.clip, torch.device("cpu"), width=96).features(np.zeros((900, 1600, 3), np.uint8))
    assert wide.shape == (24, 7, 12) and wide.dtype == np.float16 and np.isfinite(wide).all()   # 96*900/1600/8 = 6.75


def test_boxes_take_the_class_of_their_phrase_span(models):
    """Each query's class comes from the phrase whose tokens hold its highest probability; NMS drops the weaker of
    two overlapping boxes; --max-boxes caps; the thresholds gate box and phrase."""
    import torch

    from ago_train.vlm.grounded_sam import GroundedSamConfig, PhraseDetector

    phrases = ["car", "driveable surface", "traffic cone"]
    det = PhraseDetector(models.detector, phrases, torch.device("cpu"))
    spans = det.passes[0]["spans"]
    assert [s[0] for s in spans] == [0, 1, 2] and spans[1][2] - spans[1][1] == 2   # "driveable surface": 2 tokens
    T = det.passes[0]["input_ids"].shape[1]
    logits = torch.full((1, 4, 256), -10.0)
    logits[0, 0, spans[1][1] + 1] = 3.0       # query 0: second token of "driveable surface" -> phrase 1
    logits[0, 1, spans[2][1]] = 2.0           # query 1: "traffic" -> phrase 2, box overlapping query 0's
    logits[0, 2, spans[0][1]] = 1.0           # query 2: "car", its own box
    logits[0, 3, spans[0][1]] = -3.0          # query 3: below the box threshold (sigmoid 0.05)
    boxes = torch.tensor([[[0.3, 0.3, 0.2, 0.2], [0.31, 0.3, 0.2, 0.2], [0.8, 0.8, 0.1, 0.1], [0.5, 0.5, 0.1, 0.1]]])
    det.model = lambda **kw: types.SimpleNamespace(logits=logits, pred_boxes=boxes)
    found = det.detect(np.zeros((100, 200, 3), np.uint8), GroundedSamConfig())
    assert found.phrases.tolist() == [1, 0] and T <= det.max_text_len
    np.testing.assert_allclose(found.boxes[0], [40, 20, 80, 40], atol=1e-4)
    assert len(det.detect(np.zeros((100, 200, 3), np.uint8), GroundedSamConfig(max_boxes=1)).scores) == 1


def test_a_long_prompt_is_split_not_truncated(tmp_path):
    import torch

    from ago_runtime.vocab.prompts import parse_prompt_file, resolve_prompt_file
    from ago_train.vlm.grounded_sam import PhraseDetector

    folder = vlm_tiny.write_grounding_dino(tmp_path / "short", max_text_len=24)
    phrases = parse_prompt_file(resolve_prompt_file("cw")).phrases
    det = PhraseDetector(folder, phrases, torch.device("cpu"))
    assert len(det.passes) > 3
    assert all(p["input_ids"].shape[1] <= 24 for p in det.passes)
    assert sorted(k for p in det.passes for k, _, _ in p["spans"]) == list(range(len(phrases)))


def test_resnet_backbone_and_label_map(models):
    import torch

    from ago_train.vlm.grounded_sam import GroundedSam, GroundedSamConfig

    img = np.random.default_rng(1).integers(0, 256, (90, 160, 3), dtype=np.uint8)
    for det in (models.detector, models.detector_resnet):
        gs = GroundedSam(det, models.sam, ["car", "road"], GroundedSamConfig(box_threshold=0, text_threshold=0,
                                                                            max_boxes=3), torch.device("cpu"))
        label = gs.label_map(img)
        assert label.shape == (90, 160) and label.dtype == np.uint8 and set(np.unique(label)) <= {0, 1, 2}


# ------------------------------------------------------------------------------------ the verbs
def test_vlm_files_on_the_real_scene(tmp_path, models):
    """The layout the file backends read, on a real nuScenes keyframe; resumable; the same input gives the same
    files; pseudo-labels from the label maps; the features refused against today's MiniLM bank, naming both."""
    from ago_runtime.vocab.model_folder import clip_encoder_id

    scene = shared_path("nuscenes-scene")
    common = ["--data", scene, "--prompts", "cw", "--shard", "20/41", *weights(models), *FAST]
    r = ok(run_ago(["vlm-files", "--out", "v1", *common], tmp_path))
    assert "6 written" in r.stdout
    v1 = tmp_path / "v1"
    classes = json.loads((v1 / "masks" / "classes.json").read_text())
    assert classes["1"] == "car" or len(classes) >= 17
    meta = json.loads((v1 / "feats" / "meta.json").read_text())
    assert meta["channels"] == 24 and meta["stride"] == 8 and meta["encoder_id"] == clip_encoder_id(models.clip)
    import cv2

    pngs = sorted((v1 / "masks").rglob("*.png"))
    assert len(pngs) == 6
    for png in pngs:
        assert cv2.imread(str(png), cv2.IMREAD_UNCHANGED).shape == (900, 1600)
        feat = np.load(v1 / "feats" / png.parent.name / f"{png.stem}.npy")
        assert feat.shape == (24, 4, 8) and feat.dtype == np.float16        # 64 wide -> 36 -> 4 patch rows
        assert (scene / "samples" / png.parent.name / f"{png.stem}.jpg").is_file()
    before = {p: p.stat().st_mtime_ns for p in v1.rglob("*") if p.is_file()}
    r = ok(run_ago(["vlm-files", "--out", "v1", *common], tmp_path))
    assert "0 written, 6 already there" in r.stdout
    assert before == {p: p.stat().st_mtime_ns for p in v1.rglob("*") if p.is_file()}
    pngs[0].write_bytes(pngs[0].read_bytes()[:100])            # a kill mid-write of a non-atomic writer
    r = ok(run_ago(["vlm-files", "--out", "v1", *common], tmp_path))
    assert "1 written" in r.stdout and "1 damaged ones remade" in r.stdout
    ok(run_ago(["vlm-files", "--out", "v2", *common], tmp_path))
    assert files_of(v1) == files_of(tmp_path / "v2")                       # same input, same files
    pl = ["pseudo-labels", "--data", scene, "--shard", "20/41", "--keyframes", "1", "--sweeps", "0",
          "--segmenter", "files", "--masks", "v1/masks"]
    ok(run_ago([*pl, "--out", "pl", "--embedder", "none"], tmp_path))
    assert len(list((tmp_path / "pl").rglob("labels.npz"))) == 1
    r = run_ago([*pl, "--out", "pl2", "--embedder", "files", "--feats", "v1/feats"], tmp_path)
    assert_one_error_line(r, "--feats", clip_encoder_id(models.clip)[:5], "24-d", "all-MiniLM-L6-v2", "384-d")
    assert not (tmp_path / "pl2").exists()


@pytest.mark.slow
def test_town_vlm_files_pseudo_labels_and_training(tmp_path, models, town):
    """A synthetic town (another rig size): vlm-files -> pseudo-labels from the files -> a few training steps; and
    the on-the-fly segmenter gives the same label maps, each image computed once."""
    ok(run_ago(["vlm-files", "--data", town, "--out", "v", "--prompts", "cw", *weights(models), *FAST], tmp_path))
    assert len(list((tmp_path / "v" / "masks").rglob("*.png"))) == 12
    ok(run_ago(["pseudo-labels", "--data", town, "--out", "pl", "--grid", "20x20x4", "--split", "all",
                "--keyframes", "2", "--segmenter", "files", "--masks", "v/masks", "--embedder", "none"], tmp_path))
    ok(run_ago(["pseudo-labels", "--data", town, "--out", "pl_fly", "--grid", "20x20x4", "--split", "all",
                "--keyframes", "2", "--segmenter", "grounded-sam", "--detector", models.detector, "--sam",
                models.sam, "--embedder", "none", *FAST[:6]], tmp_path))
    a, b = sorted((tmp_path / "pl").rglob("labels.npz")), sorted((tmp_path / "pl_fly").rglob("labels.npz"))
    assert len(a) == len(b) == 2
    for x, y in zip(a, b):
        np.testing.assert_array_equal(np.load(x)["semantics"], np.load(y)["semantics"])
    ok(run_ago(["train", "--config", "tiny", "--data", town, "--pseudo", "pl", "--prompts", "cw", "--out", "run",
                "--set", "max_steps=2"], tmp_path))
    assert (tmp_path / "run" / "last.pt").is_file()
    # the paper's pairing (issues 48 + 49): MaskCLIP features of a CLIP folder, the text bank from the same CLIP's
    # text tower (--text-encoder), so the modality adapter trains against features in the bank's own space
    ok(run_ago(["pseudo-labels", "--data", town, "--out", "pl_clip", "--grid", "20x20x4", "--split", "all",
                "--keyframes", "2", "--segmenter", "files", "--masks", "v/masks", "--embedder", "files", "--feats",
                "v/feats", "--text-encoder", models.clip], tmp_path))
    from ago_runtime.vocab.model_folder import clip_encoder_id
    from clip_tiny import write_noise

    meta = json.loads((tmp_path / "pl_clip" / "meta.json").read_text())
    assert meta["embedder"]["encoder_id"] == clip_encoder_id(models.clip)
    write_noise(tmp_path / "noise.npz", models.clip)
    ok(run_ago(["train", "--config", "tiny", "--data", town, "--pseudo", "pl_clip", "--prompts", "cw", "--out",
                "run_clip", "--text-encoder", models.clip, "--set", 'noise_bank="noise.npz"', "--set", "max_steps=2"],
               tmp_path))
    assert json.loads((tmp_path / "run_clip" / "log.jsonl").read_text().splitlines()[-1])["align"] > 0


def test_on_the_fly_backends_compute_each_image_once(town, models):
    """generate() with the grounded-sam segmenter and the maskclip embedder: every camera image runs once however
    many samples superimpose it; the folder records the features' encoder and width."""
    from ago_runtime.formats.datasets import open_dataset
    from ago_runtime.vocab.model_folder import clip_encoder_id
    from ago_runtime.vocab.prompts import parse_prompt_file, resolve_prompt_file
    from ago_train.pseudo.generate import PseudoLabelConfig, PseudoLabelDir, generate
    from ago_runtime.geometry.grid import Grid
    from ago_train.vlm.backends import vlm_backends
    from ago_train.vlm.grounded_sam import GroundedSamConfig

    space = parse_prompt_file(resolve_prompt_file("cw"))
    ds = open_dataset(town, load_images=False, load_extras=False)
    seg, emb = vlm_backends(space, models.detector, models.sam, models.clip, "cpu",
                            GroundedSamConfig(box_threshold=0, text_threshold=0, max_boxes=2), 64)
    out = Path(town).parent / "gen"
    generate(ds, list(range(len(ds))), out, space, seg, emb,
             PseudoLabelConfig(grid=Grid.parse("20x20x4", "--grid"), num_keyframes=2), progress=False)
    cams = len(ds[0].rig.cameras)
    assert seg.computed == len(ds) * cams
    assert emb.computed <= len(ds) * cams
    meta = PseudoLabelDir(out).meta["embedder"]
    assert meta["encoder_id"] == clip_encoder_id(models.clip) and meta["channels"] == 24


# ------------------------------------------------------------------------------------ one error line each
def _other_tokenizer(models, tmp_path) -> Path:
    """The detector with a tokenizer of more tokens than its text model embeds (ids would index past the table)."""
    folder = tmp_path / "bad_tok"
    shutil.copytree(models.detector, folder)
    from transformers import BertTokenizerFast

    for f in folder.glob("tokenizer*"):
        f.unlink()
    vocab = vlm_tiny.bert_vocab(min_size=3000)
    BertTokenizerFast(vocab={w: i for i, w in enumerate(vocab)}).save_pretrained(folder)
    return folder


def _clip_tokenizer(models, tmp_path) -> Path:
    """The detector with no [CLS] / [SEP] / "." tokens (e.g. another model's tokenizer copied in)."""
    folder = tmp_path / "no_cls"
    shutil.copytree(models.detector, folder)
    from transformers import BertTokenizerFast

    for f in folder.glob("tokenizer*"):
        f.unlink()
    vocab = ["<pad>", "<unk>"] + vlm_tiny.WORDS
    BertTokenizerFast(vocab={w: i for i, w in enumerate(vocab)}, cls_token="<s>", sep_token="</s>",
                      unk_token="<unk>", pad_token="<pad>").save_pretrained(folder)
    return folder


def _no_tokenizer(models, tmp_path) -> Path:
    folder = tmp_path / "no_tok"
    shutil.copytree(models.detector, folder)
    for f in folder.glob("tokenizer*"):
        f.unlink()
    return folder


def test_a_tokenizer_with_other_special_ids_is_adapted(tmp_path, models):
    """A BERT-style tokenizer whose [CLS], [SEP], "." sit at other ids than bert-base-uncased's: the model splits the
    caption at the tokenizer's ids (a tiny model made elsewhere need not copy BERT's id layout)."""
    import torch

    from ago_train.vlm.grounded_sam import GroundedSamConfig, PhraseDetector

    folder = tmp_path / "own_ids"
    shutil.copytree(models.detector, folder)
    from transformers import BertTokenizerFast

    for f in folder.glob("tokenizer*"):
        f.unlink()
    vocab = ["[PAD]", "[UNK]", "[CLS]", "[SEP]", "[MASK]", "."] + vlm_tiny.WORDS
    BertTokenizerFast(vocab={w: i for i, w in enumerate(vocab)}).save_pretrained(folder)
    det = PhraseDetector(folder, ["car", "road"], torch.device("cpu"))
    assert det.model.model.special_tokens.tolist() == [2, 3, 5, 5]
    assert det.passes[0]["input_ids"].tolist() == [[2, vocab.index("car"), 5, vocab.index("road"), 5, 3]]
    det.detect(np.zeros((60, 100, 3), np.uint8), GroundedSamConfig())   # runs


ERROR_ROWS = [
    ("missing detector folder", lambda m, t: ["--detector", t / "nope", "--sam", m.sam], ["--detector", "nope",
                                                                                          "grounding-dino-tiny"]),
    ("detector of another architecture", lambda m, t: ["--detector", m.sam, "--sam", m.sam],
     ["--detector", "'sam'", "grounding-dino-tiny"]),
    ("sam of another architecture", lambda m, t: ["--detector", m.detector, "--sam", m.clip],
     ["--sam", "'clip'", "sam-vit-base"]),
    ("clip of another architecture", lambda m, t: ["--detector", m.detector, "--sam", m.sam, "--clip", m.detector],
     ["--clip", "'grounding-dino'", "clip-vit-base-patch16"]),
    ("missing clip folder", lambda m, t: ["--detector", m.detector, "--sam", m.sam, "--clip", t / "nope"],
     ["--clip", "no such folder", "clip-vit-base-patch16"]),
    ("tokenizer larger than the embeddings", lambda m, t: ["--detector", _other_tokenizer(m, t), "--sam", m.sam],
     ["--detector", "tokenizer does not fit", "3000 tokens", "grounding-dino-tiny"]),
    ("tokenizer without [CLS]", lambda m, t: ["--detector", _clip_tokenizer(m, t), "--sam", m.sam],
     ["--detector", "tokenizer does not fit", "[CLS]", "grounding-dino-tiny"]),
    ("detector without tokenizer", lambda m, t: ["--detector", _no_tokenizer(m, t), "--sam", m.sam],
     ["--detector", "no tokenizer", "grounding-dino-tiny"]),
]


@pytest.mark.parametrize("name,args,needles", ERROR_ROWS, ids=[r[0] for r in ERROR_ROWS])
def test_vlm_files_errors(tmp_path, models, town, name, args, needles):
    r = run_ago(["vlm-files", "--data", town, "--out", "o", "--prompts", "cw", *args(models, tmp_path)], tmp_path)
    assert_one_error_line(r, *needles)
    assert not (tmp_path / "o").exists()


def test_cuda_without_a_gpu(tmp_path, models, town):
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU")
    r = run_ago(["vlm-files", "--data", town, "--out", "o", "--prompts", "cw", *weights(models), "--device", "cuda"],
                tmp_path)
    assert_one_error_line(r, "--device", "no GPU")
    r = run_ago(["pseudo-labels", "--data", town, "--out", "p", "--segmenter", "grounded-sam", *weights(models, False),
                 "--device", "cuda"], tmp_path)
    assert_one_error_line(r, "--device", "no GPU")
    assert not (tmp_path / "o").exists() and not (tmp_path / "p").exists()


def test_pseudo_labels_option_errors(tmp_path, models, town):
    base = ["pseudo-labels", "--data", town, "--out", "p", "--grid", "20x20x4"]
    assert_one_error_line(run_ago([*base, "--segmenter", "grounded-sam", "--detector", models.detector], tmp_path),
                          "--sam")
    assert_one_error_line(run_ago([*base, "--embedder", "maskclip"], tmp_path), "--clip")
    r = run_ago([*base, "--segmenter", "sim", "--embedder", "maskclip", "--clip", models.clip], tmp_path)
    assert_one_error_line(r, "--clip", "all-MiniLM-L6-v2", "384-d", "24-d")
    assert not (tmp_path / "p").exists()


def test_training_refuses_embeddings_of_another_encoder(tmp_path, town):
    """A pseudo-label folder whose voxel embeddings came from another encoder (or width) than the trainer's bank:
    one error line naming both; an older folder without encoder_id and of the bank's width still trains."""
    ok(run_ago(["pseudo-labels", "--data", town, "--out", "pl", "--grid", "20x20x4", "--split", "all",
                "--keyframes", "1", "--embedder", "sim"], tmp_path))       # simulated features: MiniLM space
    meta_path = tmp_path / "pl" / "meta.json"
    meta = json.loads(meta_path.read_text())
    assert meta["embedder"]["encoder_id"] == "all-MiniLM-L6-v2" and meta["embedder"]["channels"] == 384
    train = ["train", "--config", "tiny", "--data", town, "--pseudo", "pl", "--prompts", "cw", "--set", "max_steps=1"]
    meta["embedder"]["encoder_id"] = "clip:0123456789abcdef"
    meta_path.write_text(json.dumps(meta))
    assert_one_error_line(run_ago([*train, "--out", "r1"], tmp_path), "meta.json", "clip:0123456789abcdef",
                          "all-MiniLM-L6-v2")
    meta["embedder"]["encoder_id"], meta["embedder"]["channels"] = None, 512
    meta_path.write_text(json.dumps(meta))
    assert_one_error_line(run_ago([*train, "--out", "r2"], tmp_path), "512-d", "384-d")
    assert not (tmp_path / "r1").exists() and not (tmp_path / "r2").exists()
    del meta["embedder"]["encoder_id"]
    meta["embedder"]["channels"] = 384
    meta_path.write_text(json.dumps(meta))
    ok(run_ago([*train, "--out", "r3"], tmp_path))


def test_feature_folders_without_an_encoder_id_pass_when_their_width_fits(tmp_path):
    """Folders from before encoder ids (no meta.json): the width read from the first map decides, at
    `ago pseudo-labels` time; a recorded encoder other than the bank's is refused even at the bank's width."""
    from ago_runtime.errors import AgoInputError
    from ago_train.pseudo.backends import FileImageEmbedder
    from ago_train.pseudo.cli import check_embedder_fits_bank

    for c in (384, 512):
        (tmp_path / f"f{c}" / "CAM_FRONT").mkdir(parents=True)
        np.save(tmp_path / f"f{c}" / "CAM_FRONT" / "x.npy", np.zeros((c, 2, 3), np.float16))
    check_embedder_fits_bank(FileImageEmbedder(tmp_path / "f384"), "--feats")
    with pytest.raises(AgoInputError, match="512-d.*384-d"):
        check_embedder_fits_bank(FileImageEmbedder(tmp_path / "f512"), "--feats")
    (tmp_path / "f384" / "meta.json").write_text(json.dumps({"channels": 384, "encoder_id": "clip:0000000000000000"}))
    with pytest.raises(AgoInputError, match="clip:0000000000000000.*all-MiniLM-L6-v2"):
        check_embedder_fits_bank(FileImageEmbedder(tmp_path / "f384"), "--feats")


def test_backends_travel_to_workers_without_their_models(models):
    """`--jobs N`: a worker gets the settings (pickled) and loads the models itself, once, on first use."""
    import pickle

    from ago_runtime.vocab.prompts import parse_prompt_file, resolve_prompt_file
    from ago_train.vlm.backends import vlm_backends
    from ago_train.vlm.grounded_sam import GroundedSamConfig

    space = parse_prompt_file(resolve_prompt_file("cw"))
    seg, emb = vlm_backends(space, models.detector, models.sam, models.clip, "cpu", GroundedSamConfig(), 64)
    assert seg._model is not None and emb._model is not None
    for backend in (seg, emb):
        blob = pickle.dumps(backend)
        assert len(blob) < 100_000                     # no weights inside
        copy = pickle.loads(blob)
        assert copy._model is None and copy.computed == 0
        first = copy.load()
        assert copy.load() is first                     # loaded once


def test_features_of_the_banks_own_clip_pass(models):
    """With a bank from the same CLIP folder (issue 49's --text-encoder: encoder_id = clip_encoder_id(folder), the
    projection width), MaskCLIP features pass the check; a bank of another width does not."""
    from ago_runtime.errors import AgoInputError
    from ago_runtime.vocab.model_folder import clip_encoder_id
    from ago_train.pseudo.cli import check_embedder_fits_bank
    from ago_train.vlm.backends import MaskClipEmbedder

    emb = MaskClipEmbedder(models.clip)
    check_embedder_fits_bank(emb, "--clip", clip_encoder_id(models.clip), 24)
    with pytest.raises(AgoInputError, match="24-d.*512-d"):
        check_embedder_fits_bank(emb, "--clip", clip_encoder_id(models.clip), 512)
