"""The voxel decision has one specification (ago_runtime/predict/decision.py): the torch path of training and
evaluation, the runtime's slab loop and the export parity reference agree with it; the bundle contract
(ago_runtime/predict/contract.py) reads back what it writes, refuses old formats with the re-export command
and frames whose cameras are not the rig's."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from ago_runtime.errors import AgoInputError
from ago_runtime.predict import decision
from ago_runtime.predict.contract import BundleContract
from ago_runtime.predict.decision import Branch, Identifier
from ago_runtime.predict.heads import HeadWeights
from ago_runtime.vocab.phrase_layout import PhraseLayout

REPO = Path(__file__).resolve().parents[1]
DEFAULT_BUNDLE = REPO / "ago_runtime" / "assets" / "default_bundle"


def _heads(rng, C=16, Dh=10, Da=12, stats=True, free_bias=0.7):
    w = HeadWeights(rng.standard_normal((C, Dh)).astype(np.float32), rng.standard_normal(C).astype(np.float32),
                    rng.standard_normal((C, Da)).astype(np.float32), rng.standard_normal(C).astype(np.float32),
                    rng.standard_normal(C).astype(np.float32), np.array([1.3, 0.6], np.float32), free_bias=free_bias)
    if stats:
        A = rng.standard_normal((C, C))
        w.adapted_mean, w.adapted_cov = rng.standard_normal(C).astype(np.float32), (A @ A.T / C + 0.1 * np.eye(C))
    return w


def _spec_decision(z_main, z_ad, identifier, K, scales):
    """decision.decide on voxel-major class scores (n, K + 1) of both branches, the adapted one on every voxel."""
    zm, za = np.ascontiguousarray(z_main.T), np.ascontiguousarray(z_ad.T)
    free = decision.main_free(zm, K)
    need = decision.adapted_voxels(free, identifier)
    return decision.decide(zm, free, za[:, need] if len(need) else None, need, identifier, K, scales)


@pytest.mark.parametrize("identifier", list(Identifier))
def test_torch_identifier_equals_the_numpy_specification(identifier):
    """ago_train.model.text_logits (class logits with free bias, the adapted standardisation, decide)
    gives the labels, branches and entropies of decision.decide, for every identifier ("none" included:
    entropy over the K classes, scaled, in both)."""
    torch = pytest.importorskip("torch")
    from ago_train.model.text_logits import adapted_logits, class_logits, decide

    rng = np.random.default_rng(3)
    w = _heads(rng)
    K, pc = 5, np.array([3, 0, 1, 2, 4, 0, 0, 3, 1, 4, 4, 2, 0])
    emb = rng.standard_normal((len(pc), 16)).astype(np.float32)
    feat = (rng.standard_normal((3000, 16)) * 0.6).astype(np.float32)
    feat_ad = rng.standard_normal((3000, 16)).astype(np.float32)
    t = lambda a: torch.from_numpy(np.asarray(a, np.float32))  # noqa: E731
    main = class_logits(t(feat)[None], t(emb), torch.from_numpy(pc), K, t(w.free_embedding),
                        free_bias=torch.tensor(w.free_bias))[0].double()
    stats = {"adapted_mean": w.adapted_mean, "adapted_cov": w.adapted_cov}
    adapted = adapted_logits(t(feat_ad)[None], t(emb), torch.from_numpy(pc), K, t(w.free_embedding), stats)[0].double()
    # the spec's score rows give the same class logits (float64 reference vs torch float32)
    layout = PhraseLayout(pc, K)
    z = {}
    for branch, f in ((Branch.MAIN, feat), (Branch.ADAPTED, feat_ad)):
        R, o = decision.score_rows(w, emb[layout.order], branch)
        z[branch] = decision.class_scores(R @ f.astype(np.float64).T, o[:, None], layout).T   # (n, K + 1)
    np.testing.assert_allclose(z[Branch.MAIN], main.numpy(), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(z[Branch.ADAPTED][:, :K], adapted.numpy()[:, :K], rtol=1e-4, atol=1e-4)
    d = decide(main, adapted, identifier, K, w.scales)
    pred, branch, entropy = d.label, d.branch, d.entropy
    spec = _spec_decision(main.numpy(), adapted.numpy(), identifier, K, w.scales)
    free = spec.label == K
    assert free.any() and (~free).any()
    np.testing.assert_array_equal(spec.label, pred.numpy())
    np.testing.assert_array_equal(spec.branch, branch.numpy())
    np.testing.assert_allclose(spec.entropy, entropy.numpy(), rtol=1e-6, atol=1e-6)
    if identifier == Identifier.MIN_ENTROPY:
        assert spec.branch.any() and not spec.branch[free].any()


@pytest.mark.parametrize("rows", [1, 2, 17, 256, 257])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_softmax_stats_labels_are_the_first_argmax(rows, dtype):
    """softmax_stats' label is np.argmax's (the first maximum on ties), on blocks of up to 256 rows (the byte
    weights) and more (the row loop), in float32 and float64."""
    rng = np.random.default_rng(rows)
    z = rng.integers(-4, 2, size=(rows, 3000)).astype(dtype)    # small integers: many ties
    z[:, :7] = 0.5                                               # every row tied
    want = np.argmax(z, axis=0)
    got = decision.softmax_stats(z.copy()).label
    assert got.dtype == np.intp and np.array_equal(got, want)


def test_runtime_float32_equals_the_float64_specification():
    """The runtime's slab loop on whole-grid features (VoxelClassifier.classify_hidden: FoldedHeads float32,
    folded, class-major, numpy products) decides as the float64 spec does on the unfolded embeddings, with
    standardisation, free bias and branch scales."""
    from ago_export.parity import reference_labels  # noqa: F401  (numpy only; torch imported lazily)

    from ago_runtime.predict.classifier import VoxelClassifier
    from ago_runtime.predict.heads import FoldedHeads, embeddings

    rng = np.random.default_rng(5)
    w = _heads(rng)
    K, pc = 4, np.array([2, 0, 1, 3, 0, 2, 1, 3, 3])
    emb = rng.standard_normal((len(pc), 16)).astype(np.float32)
    h = rng.standard_normal((4000, 10)).astype(np.float32)
    g = rng.standard_normal((4000, 12)).astype(np.float32)
    F, Fa = embeddings(h, w.W_dec, w.b_dec), embeddings(g, w.W_ad, w.b_ad)
    bank = type("Bank", (), {"embeddings": emb, "phrase_class": pc, "num_classes": K})()
    fh = FoldedHeads.fold(w, emb, pc, K)
    for identifier in Identifier:
        want = reference_labels(F, Fa, bank, w, identifier)["identifier"]
        got = VoxelClassifier().classify_hidden(h, g, fh, identifier, chunk=999)
        assert np.mean(got["label"] == want) > 0.999
        assert got["label"].dtype == np.uint8


def test_predict_arrays_uses_the_folded_it_is_given():
    """With volumes, `predict_arrays` uses the `folded` passed in (here: without reference classes, so every
    voxel the user's classes do not explain looks free) instead of folding its own."""
    pytest.importorskip("onnxruntime")
    from ago_runtime.formats.calibration import load_images_folder
    from ago_runtime.predict.bundle import DEMO_FRAME_DIR
    from ago_runtime.predict.predictor import Predictor

    p = Predictor(DEFAULT_BUNDLE)
    images, rig, _ = load_images_folder(DEMO_FRAME_DIR)
    x, m = p.prepare(images, rig)
    bank = p.bundle.load_bank("ow_pretrain")          # 5 classes: the reference classes matter
    with_ref = p.predict_arrays(x, m, bank, Identifier.NONE, volumes=True)
    plain = p.predict_arrays(x, m, bank, Identifier.NONE, p.fold(bank), volumes=True)
    np.testing.assert_array_equal(with_ref.semantics, plain.semantics)     # labels never use the reference rows
    assert np.mean(with_ref.occupancy > 0.5) > np.mean(plain.occupancy > 0.5)


def test_bank_product_graph_is_valid_onnx_and_the_product():
    onnx = pytest.importorskip("onnx")
    from ago_runtime.predict.bank_product import BankProduct, bank_product_model_bytes

    model = onnx.load_from_string(bank_product_model_bytes())
    onnx.checker.check_model(model, full_check=True)
    assert [n.op_type for n in model.graph.node] == ["Gemm"] and not model.graph.initializer
    bp = BankProduct()
    rng = np.random.default_rng(0)
    for n, d, P in ((1, 3, 1), (777, 128, 46), (50, 384, 5), (0, 8, 4)):
        x = rng.normal(size=(n, d)).astype(np.float32)
        bank = rng.normal(size=(P, d)).astype(np.float32)
        np.testing.assert_allclose(bp(bank, x), bank.astype(np.float64) @ x.T.astype(np.float64), rtol=1e-5, atol=1e-4)


# ---- the contract ---------------------------------------------------------------------------------
def _meta():
    return json.loads((DEFAULT_BUNDLE / "bundle.json").read_text())


def test_contract_round_trip_and_types():
    meta = _meta()
    c = BundleContract.from_dict(meta, "bundle.json")
    assert c.to_dict() == meta                                   # what is read is what is written, field for field
    assert json.loads(json.dumps(c.to_dict())) == meta
    assert c.identifier is Identifier.MIN_ENTROPY and isinstance(c.identifier, Identifier)
    assert [s.branch for s in c.voxel_stages] == [Branch.ADAPTED] and c.format_version == 5
    assert c.rig.names == ["CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT",
                           "CAM_BACK_RIGHT"]
    assert f"{Identifier.MAX_CONF}" == str(Identifier.MAX_CONF) == "max-conf"


@pytest.mark.parametrize("change,words", [
    (lambda m: m.update(format_version=4), "re-export the checkpoint: `ago export CKPT -o BUNDLE_DIR`"),
    (lambda m: m.update(format_version=2), "bundle format version 2 is no longer read"),
    (lambda m: m.update(format_version=6), "newer than this ago reads"),
    (lambda m: m.pop("rig"), "lacks 'rig'"),
    (lambda m: m["voxel_stages"][0].update(branch="sideways"), "sideways"),
    (lambda m: m["voxel_stages"][0].update(input_dim=7), "takes width 7"),
    (lambda m: m.update(adapted_dim=3), "adapted_dim"),
    (lambda m: m["files"]["planes"].pop("sha256"), "sha256"),
    (lambda m: m["text_encoder"].update(dim=10 ** 6), "text_encoder.dim"),
    (lambda m: m["label_space"].update(classes=[{"name": f"c{i}"} for i in range(300)]), "label_space.classes"),
    (lambda m: m.update(identifier="loudest"), "loudest"),
])
def test_contract_refuses_bad_metadata_naming_the_file(change, words):
    meta = _meta()
    change(meta)
    with pytest.raises(AgoInputError) as e:
        BundleContract.from_dict(meta, "some/bundle.json")
    assert str(e.value).startswith("some/bundle.json:") and words in str(e.value)


def test_identifier_names_come_from_one_type():
    """ago eval takes the identifiers ago infer takes; no module spells an identifier name as a string
    literal outside the decision module (the CLI option defaults of ago_train/cli.py and open_world.py excepted)."""
    from ago_runtime.predict.decision import Identifier as I

    assert I.parse("adapted", "--identifier") is I.ADAPTED
    with pytest.raises(AgoInputError, match="--identifier: must be one of min-entropy, max-conf, none, adapted"):
        I.parse("bogus", "--identifier")
    pytest.importorskip("torch")
    from ago_train.evaluate import IDENTIFIERS, evaluate

    assert list(IDENTIFIERS) == I.names()
    with pytest.raises(AgoInputError, match="--identifier"):
        evaluate("no/such.pt", "no/data", identifier="bogus")
    with pytest.raises(AgoInputError) as e:          # "adapted" passes; what fails is the missing checkpoint
        evaluate("no/such.pt", "no/data", identifier="adapted")
    assert "identifier" not in str(e.value)
    pattern = re.compile(r"""["'](min-entropy|max-conf)["']""")
    allowed = {"ago_runtime/predict/decision.py", "ago_train/cli.py", "ago_train/open_world.py"}
    found = [str(p.relative_to(REPO)) for pkg in ("ago_runtime", "ago_train", "ago_export")
             for p in (REPO / pkg).rglob("*.py")
             if str(p.relative_to(REPO)) not in allowed and pattern.search(p.read_text())]
    assert found == []


def test_frame_with_other_cameras_is_refused_naming_the_camera():
    from ago_runtime.formats.calibration import load_images_folder
    from ago_runtime.predict.bundle import DEMO_FRAME_DIR, Bundle
    from ago_runtime.predict.predictor import prepare_inputs

    b = Bundle.load(DEFAULT_BUNDLE, verify_hashes=False)
    images, rig, _ = load_images_folder(DEMO_FRAME_DIR)
    extra = {**images, "CAM_ROOF": images["CAM_FRONT"]}
    with pytest.raises(AgoInputError, match="camera CAM_ROOF: not a camera of the bundle's rig"):
        prepare_inputs(b, extra, rig, "frame7")
    missing = {k: v for k, v in images.items() if k != "CAM_BACK"}
    with pytest.raises(AgoInputError, match="frame7: camera CAM_BACK: the bundle's rig takes it"):
        prepare_inputs(b, missing, rig, "frame7")
    x, m = prepare_inputs(b, images, rig, "frame7")
    assert x.shape[1] == len(b.contract.rig.cameras) == m.shape[1]
