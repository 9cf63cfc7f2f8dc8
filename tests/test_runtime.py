"""The torch-free runtime: folded heads, Predictor, bank swapping, `ago infer/retrieve/demo`, bad input.

A tiny-preset bundle is exported once per module (that step needs torch; the runtime itself is
checked torch-free in a subprocess).
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
import shutil
import subprocess
import sys
import threading
import types
from pathlib import Path

import cv2
import numpy as np
import pytest

from ago_runtime.formats.calibration import load_calibration, save_calibration
from ago_runtime.formats.random_frame import write_random_frame
from ago_runtime.geometry.camera import CAMERA_NAMES, Rig
from ago_runtime.classes import FREE, OCC3D_CLASSES, OCC3D_ID
from ago_runtime.errors import AgoInputError
from ago_runtime.predict import decision
from ago_runtime.predict.decision import Branch, Identifier
from ago_runtime.predict.classifier import VoxelClassifier, decide_block
from ago_runtime.predict.heads import FoldedHeads, HeadWeights


def decide_scores(folded, s_main, s_ad, identifier, volumes=False):
    """The voxel decision of hand-made bias-free phrase scores (P+1, n) of both branches (every voxel), as the
    slab loop takes it (classifier.decide_block)."""
    return decide_block(folded, s_main.copy(), lambda need: s_ad[:, need].copy(), Identifier(identifier), volumes)

REPO = Path(__file__).resolve().parents[1]
SHARED_SAMPLE = REPO.parent / "shared" / "data" / "nuscenes-sample"


# ---------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def bundle_dir(tmp_path_factory):
    pytest.importorskip("torch")
    from ago_export.export import export_bundle
    from ago_export.testing import random_checkpoint

    root = tmp_path_factory.mktemp("runtime")
    os.environ["AGO_CACHE_DIR"] = str(root / "cache")
    ckpt = random_checkpoint(root / "tiny.pt", "tiny", prompts="cw", seed=1)
    out = root / "bundle"
    export_bundle(ckpt, out, bank_prompts=["ow"], real_frame=False, log=lambda s: None)
    return out


@pytest.fixture
def frame_dir(tmp_path):
    return write_random_frame(tmp_path / "frame")


def run_subprocess(args, cwd=None):
    """`python -m ago_runtime ARGS` -> CompletedProcess (text)."""
    env = dict(os.environ, AGO_NO_PROGRESS="1")
    return subprocess.run([sys.executable, "-m", "ago_runtime", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, env=env)


def run_cli(args, cwd=None):
    """`ago ARGS` in this process through ago_runtime.cli.main (its error handling and exit codes)."""
    from ago_runtime.cli import main

    out, err = io.StringIO(), io.StringIO()
    old_cwd, old_argv, code = os.getcwd(), sys.argv, 0
    try:
        if cwd:
            os.chdir(cwd)
        sys.argv = ["ago", *map(str, args)]
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                main()
            except SystemExit as e:
                code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    finally:
        os.chdir(old_cwd)
        sys.argv = old_argv
    return types.SimpleNamespace(returncode=code, stdout=out.getvalue(), stderr=err.getvalue())


def assert_refused(r, path_part: str, out: Path | None = None):
    assert r.returncode == 2, (r.stdout, r.stderr)
    lines = [ln for ln in r.stderr.strip().splitlines() if ln.startswith("error:")]
    assert len(lines) == 1 and path_part in lines[0], r.stderr
    assert "Traceback" not in r.stderr
    if out is not None:
        assert not out.exists() or not any(out.iterdir())


# ---------------------------------------------------------------------------- torch-free
def test_runtime_never_imports_torch():
    code = ("import ago_runtime.predict.predictor, ago_runtime.cli, ago_runtime.predict.cli, ago_runtime.predict.bundle, "
            "ago_runtime.formats.calibration, ago_runtime.predict.heads; import sys; assert 'torch' not in sys.modules, 'torch'")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


# ---------------------------------------------------------------------------- heads
def _random_heads(rng, C=24, Dh=10, Da=12):
    f = lambda *s: rng.standard_normal(s).astype(np.float32)  # noqa: E731
    return HeadWeights(f(C, Dh), f(C), f(C, Da), f(C), f(C))


def test_softplus_matches_the_exact_function():
    from ago_runtime.predict.encoder import Softplus, softplus_

    x = np.concatenate([np.linspace(-120, 120, 200000), np.random.default_rng(0).normal(0, 4, 50000)]).astype(np.float32)
    want = np.logaddexp(0.0, x.astype(np.float64))
    got = softplus_(x.copy(), np.empty_like(x))
    # float32 result: within 1e-6 absolute or 2 ulps relative (at x = 120 one ulp is 7.6e-6; a CPU with
    # another vector exp differs there in the last bits)
    tol = 1e-6 + 2 * np.finfo(np.float32).eps * np.abs(want)
    assert np.all(np.abs(got - want) <= tol) and np.all(np.isfinite(got))
    two = Softplus(threads=2)(x.reshape(-1, 10).copy())            # split over threads: the same values
    assert np.array_equal(two.reshape(-1), got)
    cube = x[:249993].reshape(-1, 3, 3).copy()                     # 3-D, last axis 3: no channel trap
    assert np.array_equal(softplus_(cube, np.empty_like(cube)).reshape(-1), got[:249993])
    wide = np.zeros((len(x), 2), np.float32)
    wide[:, 0] = x
    strided = softplus_(wide[:, 0], np.empty(len(x), np.float32))    # not contiguous: numpy's form, same values
    assert np.all(np.abs(strided - want) <= tol) and np.array_equal(wide[:, 0], strided)
    odd = softplus_(np.array([[np.nan, np.inf, -np.inf, 0.0, 1.0]], np.float32), np.empty((1, 5), np.float32))
    assert np.isnan(odd[0, 0]) and odd[0, 1] == np.inf and odd[0, 2] == 0.0 and abs(odd[0, 3] - np.log(2)) < 1e-6
    for shape in [(), (1,), (1, 1), (4, 1), (1, 4), (2, 2), (5, 0), (0, 7), (2, 2, 2)]:   # OpenCV reads some as scalars
        small = np.linspace(-3, 3, int(np.prod(shape))).astype(np.float32).reshape(shape)
        got_small = softplus_(small.copy(), np.empty_like(small))
        assert got_small.shape == shape and np.allclose(got_small, np.logaddexp(0.0, small.astype(np.float64)),
                                                        rtol=0, atol=1e-6), shape


def test_softplus_of_the_plane_sum_from_the_planes_exponentials():
    """The product form log(1 + E_xy E_xz E_yz) gives softplus(xy + xz + yz) to float32 rounding, over the whole
    range it is used in; a frame outside that range (or with a NaN) takes the direct form."""
    from ago_runtime.predict.encoder import EXP_RANGE, PlaneMaps, softplus_of_sum_

    rng = np.random.default_rng(1)
    X, Y, Z, D = 3, 5, 4, 6
    for spread in (1.0, 8.0, EXP_RANGE / 3):                 # the last reaches a = +-EXP_RANGE
        planes = [rng.uniform(-spread, spread, s).astype(np.float32) for s in ((X, Y, D), (X, Z, D), (Y, Z, D))]
        pm = PlaneMaps(planes)
        assert pm.exps is not None and isinstance(pm, tuple) and all(a is b for a, b in zip(pm, planes))
        a = (planes[0][:, :, None].astype(np.float64) + planes[1][:, None] + planes[2][None])
        want = np.logaddexp(0.0, a)
        got = np.empty((X, Y, Z, D), np.float32)
        softplus_of_sum_(pm.exps, 0, X, slice(None), got)
        tol = 1e-6 + 4 * np.finfo(np.float32).eps * np.abs(want)
        assert np.all(np.abs(got - want) <= tol), float(np.abs(got - want).max())
        part = np.empty((1, 2, Z, D), np.float32)                # one x row, some y: the same values
        softplus_of_sum_(pm.exps, 1, 2, slice(2, 4), part)
        assert np.array_equal(part, got[1:2, 2:4])
    tiny = [rng.uniform(-2, 2, s).astype(np.float32) for s in ((2, 4, 1), (2, 1, 1), (4, 1, 1))]   # rows of 4 x 1
    got = np.empty((2, 4, 1, 1), np.float32)
    softplus_of_sum_(PlaneMaps(tiny).exps, 0, 2, slice(None), got)
    want = np.logaddexp(0.0, tiny[0][:, :, None].astype(np.float64) + tiny[1][:, None] + tiny[2][None])
    assert np.allclose(got, want, rtol=0, atol=2e-6)
    big = [p.copy() for p in planes]
    big[0][0, 0, 0] = EXP_RANGE                                  # the sum could pass EXP_RANGE: no exps
    assert PlaneMaps(big).exps is None
    nan = [p.copy() for p in planes]
    nan[2][0, 0, 0] = np.nan
    assert PlaneMaps(nan).exps is None


def test_hidden_slab_product_form_matches_the_direct_form(tmp_path):
    """The encoder's first activation from PlaneMaps (product form, split over threads by x rows or by y) equals
    the direct form (softplus of the plane sum) within float32 rounding, for any slab."""
    from ago_runtime.predict.encoder import PlaneMaps, SplitEncoder, Softplus

    rng = np.random.default_rng(2)
    X, Y, Z, D = 7, 9, 3, 8
    planes = [rng.normal(0, 3, s).astype(np.float32) for s in ((X, Y, D), (X, Z, D), (Y, Z, D))]
    pm = PlaneMaps(planes)
    enc = SplitEncoder.__new__(SplitEncoder)                     # only the numpy part: no graphs
    enc._local = threading.local()
    for threads in (1, 2, 3):
        enc.softplus = Softplus(threads)
        for x0, x1 in ((0, 1), (2, 5), (0, X)):
            direct = enc.first_activation(list(planes), x0, x1)
            product = enc.first_activation(pm, x0, x1)
            assert product.shape == direct.shape == ((x1 - x0) * Y * Z, D)
            assert np.allclose(product, direct, rtol=4e-7, atol=2e-6)


def test_folded_heads_match_unfolded_reference():
    rng = np.random.default_rng(0)
    w = _random_heads(rng)
    K, P = 5, 13
    pc = np.array([3, 0, 1, 2, 4, 0, 0, 3, 1, 4, 4, 2, 0])     # unsorted, several phrases per class
    emb = rng.standard_normal((P, 24)).astype(np.float32)
    h = rng.standard_normal((1000, 10)).astype(np.float32)
    g = rng.standard_normal((1000, 12)).astype(np.float32)
    fh = FoldedHeads.fold(w, emb, pc, K)
    run = VoxelClassifier().classify_hidden
    ref = {}
    for name, x, W, b in (("main", h, w.W_dec, w.b_dec), ("adapted", g, w.W_ad, w.b_ad)):
        s = (x.astype(np.float64) @ W.T.astype(np.float64) + b) @ np.concatenate([emb, w.free_embedding[None]]).T
        z = np.stack([s[:, :P][:, pc == k].max(1) for k in range(K)] + [s[:, P]], axis=1)
        # entropy and confidence: of the softmax over the K classes (free only decides occupancy), for every
        # identifier, "none" included (ago_runtime.predict.decision)
        p = np.exp(z[:, :K] - z[:, :K].max(1, keepdims=True))
        p /= p.sum(1, keepdims=True)
        ref[name] = (z.argmax(1), -(p * np.log(p)).sum(1), p.max(1))
    out = run(h, g, fh, "none", chunk=37)
    assert np.array_equal(out["label"], ref["main"][0])
    np.testing.assert_allclose(out["entropy"], ref["main"][1], rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(out["confidence"], ref["main"][2], rtol=1e-4, atol=1e-5)
    assert not out["branch"].any()
    # the identifier: free from the main branch; else the class of the branch whose scaled class
    # distribution (K classes only) has the lower entropy
    for scales in ((1.0, 1.0), (1.0, 5.0)):
        w.branch_scales = np.array(scales, np.float32)
        fs = FoldedHeads.fold(w, emb, pc, K)
        both = run(h, g, fs, "min-entropy", chunk=1000)
        cls = {}
        for (name, x, W, b), sc in zip((("main", h, w.W_dec, w.b_dec), ("adapted", g, w.W_ad, w.b_ad)), scales):
            s = (x.astype(np.float64) @ W.T.astype(np.float64) + b) @ emb.T.astype(np.float64)
            z = sc * np.stack([s[:, pc == k].max(1) for k in range(K)], axis=1)
            p = np.exp(z - z.max(1, keepdims=True))
            p /= p.sum(1, keepdims=True)
            cls[name] = (z.argmax(1), -(p * np.log(p)).sum(1))
        free = ref["main"][0] == K
        use_ad = (cls["adapted"][1] < cls["main"][1]) & ~free
        decided = np.abs(cls["adapted"][1] - cls["main"][1]) > 1e-4
        want = np.where(free, K, np.where(use_ad, cls["adapted"][0], cls["main"][0]))
        assert np.array_equal(both["branch"][decided].astype(bool), use_ad[decided])
        assert np.array_equal(both["label"][decided], want[decided])
        assert free.any() and (~free).any() and use_ad.any() and (~use_ad & ~free).any()
    w.branch_scales = None
    conf = run(h, g, fh, "max-conf")
    assert np.all(conf["label"][ref["main"][0] == K] == K)
    # chunking changes nothing but float rounding (BLAS blocks differ with the chunk width)
    a, b = run(h, g, fh, chunk=7), run(h, g, fh, chunk=100000)
    assert np.array_equal(a["label"], b["label"]) and np.array_equal(a["branch"], b["branch"])
    np.testing.assert_allclose(a["entropy"], b["entropy"], rtol=1e-5, atol=1e-6)


# ---------------------------------------------------------------------------- calibration
def test_calibration_roundtrip_and_list_layout(tmp_path):
    rig = Rig.nuscenes_like(800, 450)
    save_calibration(tmp_path / "c.json", rig)
    back = load_calibration(tmp_path / "c.json")
    assert np.allclose(back.ego2img(), rig.ego2img())
    (tmp_path / "l.json").write_text(json.dumps(rig.to_dict()))          # Rig.to_dict layout
    assert np.allclose(load_calibration(tmp_path / "l.json").ego2img(), rig.ego2img())


# ---------------------------------------------------------------------------- predictor
def test_predictor_outputs_and_identifier(bundle_dir, frame_dir):
    from ago_runtime.formats.calibration import load_images_folder
    from ago_runtime.predict.predictor import Predictor

    p = Predictor(bundle_dir)
    images, rig, _ = load_images_folder(frame_dir)
    bank = p.bundle.load_bank()
    K = bank.num_classes
    main = p.predict(images, rig, bank, "none")
    best = p.predict(images, rig, bank, "min-entropy")
    assert main.semantics.shape == (20, 20, 4) and main.semantics.dtype == np.uint8
    assert main.semantics.max() <= K and main.free_index == K
    assert np.all((best.entropy >= 0) & (best.entropy <= np.log(K + 1) + 1e-5))
    assert np.all((best.confidence >= 1 / (K + 1) - 1e-6) & (best.confidence <= 1 + 1e-6))
    assert not main.branch.any()
    assert np.all(best.entropy <= main.entropy + 1e-6)                  # picks the lower-entropy branch
    sel = best.branch == 0
    assert np.array_equal(best.semantics[sel], main.semantics[sel])
    # cw classes are each one Occ3D class -> an Occ3D-id volume, free = 17
    assert best.table_ids is not None and set(np.unique(best.table_ids)) <= set(range(18))
    assert np.array_equal(best.table_ids == FREE, best.semantics == K)


def test_streamed_slabs_match_whole_grid_heads(bundle_dir, frame_dir, monkeypatch):
    """`predict` (voxels.onnx slab by slab, the bank's scores from the graph's GEMM) gives what the
    numpy heads give on the whole grid's h, g; a large bank is cut into thinner slabs."""
    import ago_runtime.predict.encoder as enc
    from ago_runtime.formats.calibration import load_images_folder
    from ago_runtime.predict.heads import SCORE_BUDGET_BYTES
    from ago_runtime.predict.predictor import Predictor

    p = Predictor(bundle_dir)
    assert isinstance(p.encoder, enc.SplitEncoder)
    images, rig, _ = load_images_folder(frame_dir)
    x, m = p.prepare(images, rig)
    bank = p.bundle.load_bank()
    h, g = p.encode_arrays(x, m)
    whole = p.predict_hidden(h, g, bank, "min-entropy")
    for slab_voxels in (20 * 4, 7 * 20 * 4):            # one x-row per slab; 7 rows (uneven last slab)
        p.encoder = enc.open_encoder(p.bundle, slab_voxels=slab_voxels)
        got = p.predict_arrays(x, m, bank, "min-entropy")
        assert np.mean(got.semantics == whole.semantics) > 0.999
        np.testing.assert_allclose(got.entropy, whole.entropy, atol=1e-4)
    # the score block of a slab stays within the budget: with a tiny budget every slab is one row
    monkeypatch.setattr(enc, "SCORE_BUDGET_BYTES", 1)
    seen = [(x1 - x0) * 20 * 4 for x0, x1 in p.encoder.slabs(p.encoder.slab_rows(p.fold(bank).num_rows))]
    assert seen == [20 * 4] * 20 and SCORE_BUDGET_BYTES > 1


def test_slab_size_follows_the_widest_array_a_slab_holds(bundle_dir, frame_dir, monkeypatch):
    """Without slab_voxels a slab holds as many x rows as keep its widest per-voxel array near SLAB_BYTES: h (and
    the main branch's stages) on the usual path, the adapted branch's widths too where it runs on every voxel
    (volumes); classify sizes its slabs that way."""
    import ago_runtime.predict.encoder as enc
    from ago_runtime.formats.calibration import load_images_folder
    from ago_runtime.predict.predictor import Predictor

    p = Predictor(bundle_dir)
    X, Y, Z = p.bundle.grid.shape
    wide_main, wide_all = p.encoder.widest
    assert wide_all > wide_main                       # the fixture bundle: the adapted branch is wider
    assert wide_main == max([p.bundle.contract.hidden_dim] + [s.output_dim for s in p.bundle.contract.voxel_stages
                                                              if s.branch == "main"])
    assert wide_all >= max([wide_main, p.bundle.contract.adapted_dim] + [s.output_dim for s in
                                                                        p.bundle.contract.voxel_stages])
    monkeypatch.setattr(enc, "SLAB_BYTES", 4 * Y * Z * wide_main * 3)        # three rows of h
    assert p.encoder.slab_rows() == 3
    assert p.encoder.slab_rows(every_voxel_adapted=True) == max(1, 3 * wide_main // wide_all)
    assert enc.open_encoder(p.bundle, slab_voxels=2 * Y * Z).slab_rows(every_voxel_adapted=True) == 2
    images, rig, _ = load_images_folder(frame_dir)
    x, m = p.prepare(images, rig)
    bank = p.bundle.load_bank()
    seen = []
    slabs = p.encoder.slabs
    p.encoder.slabs = lambda rows: seen.append(rows) or slabs(rows)
    p.predict_arrays(x, m, bank, "min-entropy")
    p.predict_arrays(x, m, bank, "min-entropy", p.fold_with_reference(bank), volumes=True)
    assert seen == [3, max(1, 3 * wide_main // wide_all)]


def test_slabs_in_parallel_give_what_one_thread_gives(bundle_dir, frame_dir):
    """With several threads the slabs run in parallel (SplitEncoder.map_slabs), each on one thread: every output
    equals the one-thread run's, for every identifier, with volumes, and through FrameFeatures re-queries."""
    import ago_runtime.predict.encoder as enc
    from ago_runtime.formats.calibration import load_images_folder
    from ago_runtime.predict.classifier import FrameFeatures
    from ago_runtime.predict.predictor import Predictor

    p = Predictor(bundle_dir)
    images, rig, _ = load_images_folder(frame_dir)
    x, m = p.prepare(images, rig)
    bank = p.bundle.load_bank()
    one = enc.open_encoder(p.bundle, threads=1, slab_voxels=20 * 4)
    two = enc.open_encoder(p.bundle, threads=2, slab_voxels=20 * 4)
    assert one.slab_pool is None and two.slab_pool is not None
    seen = []
    run_slab = two.hidden_slab
    two.hidden_slab = lambda *a: seen.append(two._single()) or run_slab(*a)
    for identifier in ("none", "min-entropy", "max-conf", "adapted"):
        for volumes in (False, True):
            got = {}
            for name, e in (("one", one), ("two", two)):
                p.encoder = p.classifier.encoder = e
                got[name] = p.predict_arrays(x, m, bank, identifier, volumes=volumes)
            for field in ("semantics", "entropy", "confidence", "branch", "unexplained", "occupancy"):
                a, b = getattr(got["one"], field), getattr(got["two"], field)
                assert (a is None and b is None) or np.array_equal(a, b), (identifier, volumes, field)
            t = got["two"].timings
            assert t["encoder"] > 0 and t["heads"] > 0
    assert seen and all(seen)                   # every slab ran in a worker, on its one thread
    features = FrameFeatures()
    p.encoder = p.classifier.encoder = two
    first = p.predict_arrays(x, m, bank, "min-entropy", features=features)
    again = p.predict_arrays(x, m, bank, "min-entropy", features=features)
    assert len(features.hidden) == 20 and np.array_equal(first.semantics, again.semantics)


def test_adapted_branch_runs_only_where_the_main_branch_sees_matter(bundle_dir, frame_dir, monkeypatch):
    """The adapter's stages and the adapted bank's product run only on the voxels the main branch calls
    occupied (with volumes: on every voxel, for the unexplained-obstacle score, also with identifier
    "none", whose labels never use it), and every output equals the full computation (adapted branch on
    every voxel) on every voxel."""
    import ago_runtime.predict.encoder as enc
    from ago_runtime.formats.calibration import load_images_folder
    from ago_runtime.predict.predictor import Predictor

    p = Predictor(bundle_dir)
    images, rig, _ = load_images_folder(frame_dir)
    x, m = p.prepare(images, rig)
    # weaker phrases, so that about a quarter of the voxels are occupied (random weights call ~all occupied)
    bank = dataclasses.replace(p.bundle.load_bank(), embeddings=p.bundle.load_bank().embeddings * 0.3)
    K, N = bank.num_classes, p.grid.num_voxels
    rows = []
    real = enc.SplitEncoder.adapted_hidden
    monkeypatch.setattr(enc.SplitEncoder, "adapted_hidden", lambda self, h: rows.append(len(h)) or real(self, h))
    for ident in ("min-entropy", "max-conf", "adapted", "none"):
        for volumes in (False, True):
            folded = p.fold_with_reference(bank) if volumes else p.fold(bank)
            rows.clear()
            got = p.predict_arrays(x, m, bank, ident, volumes=volumes)
            adapter_rows = sum(rows)
            # the full computation: both branches' scores on every voxel, the adapted one used everywhere
            full = {k: [] for k in ("label", "entropy", "confidence", "branch", "unexplained", "occupancy", "need")}
            for _a, _b, h, g in p.encoder.chunks(x, m):
                z_main = decision.class_scores(p.encoder.scores(folded.A[Branch.MAIN], h), folded.c[Branch.MAIN],
                                               folded.layout)
                free = decision.main_free(z_main, K)
                full["need"].append(np.isin(np.arange(len(h)), decision.adapted_voxels(free, ident, volumes)))
                z_ad = decision.class_scores(p.encoder.scores(folded.A[Branch.ADAPTED], g), folded.c[Branch.ADAPTED],
                                             folded.layout)
                d = decision.decide(z_main, free, z_ad, np.arange(len(h)), ident, K, folded.scales, volumes)
                for k in ("label", "entropy", "confidence", "branch", "unexplained", "occupancy"):
                    full[k].append(getattr(d, k))
            full = {k: np.concatenate(v) if v[0] is not None else None for k, v in full.items()}
            np.testing.assert_array_equal(got.semantics.reshape(-1), full["label"])
            np.testing.assert_array_equal(got.branch.reshape(-1), full["branch"])
            np.testing.assert_allclose(got.entropy.reshape(-1), full["entropy"], atol=1e-5)
            np.testing.assert_allclose(got.confidence.reshape(-1), full["confidence"], atol=1e-5)
            occupied = got.semantics.reshape(-1) != K
            if volumes:
                np.testing.assert_allclose(got.unexplained.reshape(-1), full["unexplained"], atol=1e-5)
                np.testing.assert_allclose(got.occupancy.reshape(-1), full["occupancy"], atol=1e-5)
            if ident == "none":
                # labels from the main branch alone: the adapter runs only for the unexplained score
                assert adapter_rows == (N if volumes else 0)
                assert not got.branch.any()
            else:
                need = full["need"]
                assert 0.05 * N < occupied.sum() < 0.95 * N and np.all(need[occupied])
                assert adapter_rows == need.sum()                        # the adapter ran on those voxels only
                assert need.sum() == (N if volumes else occupied.sum())
                assert not got.branch.reshape(-1)[~occupied].any()
            if volumes:
                np.testing.assert_allclose(got.occupancy.reshape(-1), full["occupancy"], atol=1e-6)
                np.testing.assert_allclose(got.unexplained.reshape(-1), full["unexplained"], atol=1e-5)


def test_requery_with_the_frames_planes_skips_the_planes_graph(bundle_dir, frame_dir, tmp_path):
    """Another bank on the same frame with its planes passed in gives what a whole new prediction gives."""
    from ago_runtime.formats.calibration import load_images_folder
    from ago_runtime.predict.predictor import Predictor
    from ago_runtime.vocab.bank import load_prompt_bank

    p = Predictor(bundle_dir)
    images, rig, _ = load_images_folder(frame_dir)
    x, m = p.prepare(images, rig)
    planes = p.encoder.plane_maps(x, m)
    prompt = tmp_path / "street.txt"
    prompt.write_text("fire hydrant: fire hydrant, hydrant\ncar: car\nroad [driveable_surface]: road\n")
    bank = load_prompt_bank(prompt, cache_dir=tmp_path / "banks")
    whole = p.predict_arrays(x, m, bank)
    calls = []
    run = p.encoder.planes.run
    p.encoder.planes = types.SimpleNamespace(run=lambda *a, **k: calls.append(1) or run(*a, **k))
    again = p.predict_arrays(x, m, bank, planes=planes)
    assert calls == []
    np.testing.assert_array_equal(again.semantics, whole.semantics)
    np.testing.assert_allclose(again.entropy, whole.entropy, atol=1e-6)


def test_requery_with_frame_features_skips_planes_and_decoder(bundle_dir, frame_dir, tmp_path):
    """FrameFeatures keeps the planes and every voxel's h: a re-query of the frame with another bank runs
    neither planes.onnx nor the decoder's stages, and gives what a whole new prediction gives."""
    from ago_runtime.formats.calibration import load_images_folder
    from ago_runtime.predict.predictor import FrameFeatures, Predictor
    from ago_runtime.vocab.bank import load_prompt_bank

    p = Predictor(bundle_dir)
    images, rig, _ = load_images_folder(frame_dir)
    x, m = p.prepare(images, rig)
    features = FrameFeatures()
    first = p.predict_arrays(x, m, p.bundle.load_bank(), features=features)
    n, dh = p.grid.num_voxels, p.encoder.widths["main"]
    assert sum(len(h) for h in features.hidden.values()) == n
    assert features.nbytes >= n * dh * 4
    prompt = tmp_path / "street.txt"
    prompt.write_text("fire hydrant: fire hydrant, hydrant\ncar: car\nroad [driveable_surface]: road\n")
    bank = load_prompt_bank(prompt, cache_dir=tmp_path / "banks")
    whole = p.predict_arrays(x, m, bank)
    calls = []
    run, hidden = p.encoder.planes.run, p.encoder.hidden_slab
    p.encoder.planes = types.SimpleNamespace(run=lambda *a, **k: calls.append("planes") or run(*a, **k))
    p.encoder.hidden_slab = lambda *a, **k: calls.append("decoder") or hidden(*a, **k)
    again = p.predict_arrays(x, m, bank, features=features)
    assert calls == []
    np.testing.assert_array_equal(again.semantics, whole.semantics)
    np.testing.assert_allclose(again.entropy, whole.entropy, atol=1e-6)
    assert first.semantics.shape == again.semantics.shape
    # kept slabs thinner than a re-query's (volumes first): h is joined from them, never computed again
    p.encoder.planes, p.encoder.hidden_slab = types.SimpleNamespace(run=run), hidden
    thin = FrameFeatures()
    p.encoder.slab_voxels = p.grid.shape[1] * p.grid.shape[2]            # one x row a slab
    p.predict_arrays(x, m, bank, folded=p.fold_with_reference(bank), volumes=True, features=thin)
    kept = dict(thin.hidden)
    p.encoder.slab_voxels = 3 * p.grid.shape[1] * p.grid.shape[2]        # three rows a slab
    p.encoder.hidden_slab = lambda *a, **k: calls.append("decoder") or hidden(*a, **k)
    joined = p.predict_arrays(x, m, bank, features=thin)
    assert calls == [] and thin.hidden.keys() == kept.keys()
    np.testing.assert_array_equal(joined.semantics, whole.semantics)


def test_bank_swap_to_unseen_classes(bundle_dir, frame_dir, tmp_path):
    """Classes the model never saw ("fire hydrant", "mailbox") with no retraining and no re-export."""
    from ago_runtime.vocab.bank import load_prompt_bank
    from ago_runtime.formats.calibration import load_images_folder
    from ago_runtime.predict.predictor import Predictor

    prompt = tmp_path / "street.txt"
    prompt.write_text("fire hydrant: fire hydrant, hydrant\nmailbox: mailbox, letter box\nroad [driveable_surface]: road\n")
    bank = load_prompt_bank(prompt, cache_dir=tmp_path / "banks")
    assert bank.class_names == ["fire hydrant", "mailbox", "road"]
    p = Predictor(bundle_dir)
    images, rig, _ = load_images_folder(frame_dir)
    pred = p.predict(images, rig, bank)
    assert pred.class_names == ["fire hydrant", "mailbox", "road"] and pred.free_index == 3
    assert set(np.unique(pred.semantics)) <= {0, 1, 2, 3}
    assert len(set(np.unique(pred.semantics)) - {3}) >= 1                # some voxel gets an unseen class
    assert pred.table_ids is None                                           # not all classes are Occ3D classes
    # the bank is cached by hash: building it again reads the cache file
    assert load_prompt_bank(prompt, cache_dir=tmp_path / "banks").embeddings.tobytes() == bank.embeddings.tobytes()
    arrays = pred.output_arrays()
    assert list(arrays["class_names"]) == ["fire hydrant", "mailbox", "road", "free"]


@pytest.mark.skipif(not SHARED_SAMPLE.exists(), reason="real reference data not present")
def test_infer_real_keyframe_from_info(bundle_dir, tmp_path):
    out = tmp_path / "out"
    r = run_subprocess(["infer", "--info", SHARED_SAMPLE / "mmdet3d_info.pkl", "--images", SHARED_SAMPLE,
                 "--bundle", bundle_dir, "--out", out, "--prompts", "prompts/ow.txt"], cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    with np.load(out / "ca9a282c9e77460f8360f564131a8af5.npz") as z:
        assert z["semantics"].shape == (20, 20, 4)
        assert list(z["class_names"]) == list(OCC3D_CLASSES)          # ow classes are Occ3D classes
        assert set(np.unique(z["semantics"])) <= set(range(1, 18)) - {12}   # no "others", "other_flat"
    assert (out / "ca9a282c9e77460f8360f564131a8af5.png").stat().st_size > 1000


# ---------------------------------------------------------------------------- CLI
def test_cli_infer_images_folder(bundle_dir, frame_dir, tmp_path):
    out = tmp_path / "out"
    r = run_cli(["infer", "--images", frame_dir, "--bundle", bundle_dir, "--out", out, "--save-volumes",
                 "--prompts", "prompts/ow.txt", "--identifier", "max-conf"], cwd=tmp_path)   # not the repo cwd
    assert r.returncode == 0, r.stderr
    with np.load(out / "frame.npz") as z:
        assert z["semantics"].dtype == np.uint8 and z["semantics"].shape == (20, 20, 4)
        assert z["entropy"].dtype == np.float32 and z["branch"].shape == (20, 20, 4)
        assert int(z["free_index"]) == FREE
    img = cv2.imread(str(out / "frame.png"))
    assert img is not None and img.shape[0] > 200
    # the unexplained-obstacle volume folds in reference classes, but the labels stay those of a plain run
    plain = tmp_path / "plain"
    r = run_cli(["infer", "--images", frame_dir, "--bundle", bundle_dir, "--out", plain,
                 "--prompts", "prompts/ow.txt", "--identifier", "max-conf"], cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    with np.load(out / "frame.npz") as z, np.load(plain / "frame.npz") as zp:
        np.testing.assert_array_equal(z["semantics"], zp["semantics"])
        assert "unexplained" in z.files and "unexplained" not in zp.files
        assert np.all((z["unexplained"] >= 0) & (z["unexplained"] <= 1))


def test_cli_infer_unexplained_threshold_sets_the_mask(bundle_dir, frame_dir, tmp_path):
    """--unexplained-threshold T: the saved mask is occupancy > 0.5 and score > T, the npz records T, and a run
    with another T is not taken as already done (resume)."""
    out = tmp_path / "out"
    args = ["infer", "--images", frame_dir, "--bundle", bundle_dir, "--out", out, "--save-volumes",
            "--prompts", "prompts/ow_pretrain.txt", "--picture", "none"]
    masks = {}
    for t in ("0.5", None, "0.3"):
        r = run_cli(args + (["--unexplained-threshold", t] if t else []), cwd=tmp_path)
        assert r.returncode == 0, r.stderr
        assert "resuming" not in r.stdout + r.stderr        # each threshold is another run: nothing reused
        with np.load(out / "frame.npz") as z:
            want = float(t) if t else 0.5
            assert float(z["unexplained_threshold"]) == pytest.approx(want)
            mask = (z["occupancy"] > 0.5) & (z["unexplained"] > np.float32(want))
            assert np.array_equal(z["unexplained_mask"].astype(bool), mask)
            masks[t] = mask
    assert masks["0.3"].sum() >= masks["0.5"].sum() and np.array_equal(masks["0.5"], masks[None])


def test_choose_unexplained_threshold():
    """ago_runtime.predict.threshold.choose_threshold: the lowest threshold whose strict mask flags at most the
    given share of explained voxels; voxels called free never count."""
    from ago_runtime.predict.threshold import choose_threshold

    s = np.array([0.9, 0.8, 0.7, 0.6, 0.2, 0.95, 0.1, 0.85], np.float32)
    occ = np.array([1, 1, 1, 1, 1, 0, 1, 1], np.float32)      # the 0.95 voxel is called free
    explained = np.array([1, 1, 1, 1, 1, 1, 1, 0], bool)      # 7 explained voxels
    t = choose_threshold(s, occ, explained, 2 / 7)             # at most 2 of 7 flagged
    assert t == pytest.approx(0.7)
    assert ((s > t) & (occ > 0.5) & explained).sum() == 2
    assert choose_threshold(s, occ, explained, 0.0) == pytest.approx(0.9)    # nothing explained flagged
    assert choose_threshold(s, occ, explained, 0.99) == 0.0                  # every explained voxel may be flagged
    with pytest.raises(ValueError):
        choose_threshold(s, occ, np.zeros(8, bool), 0.05)


def test_cli_infer_without_calib_warns_and_uses_bundle_rig(bundle_dir, tmp_path):
    frame = write_random_frame(tmp_path / "f", 800, 450, calib=False)
    r = run_subprocess(["infer", "--images", frame, "--bundle", bundle_dir, "--out", tmp_path / "o"])
    assert r.returncode == 0, r.stderr
    assert "no calib.json" in r.stderr and "scaling the intrinsics" in r.stderr   # 800x450 vs 1600x900
    assert (tmp_path / "o" / "f.npz").is_file()


def test_cli_retrieve(bundle_dir, frame_dir, tmp_path):
    r = run_cli(["retrieve", "--images", frame_dir, "--phrase", "traffic cone", "--bundle", bundle_dir,
                 "--out", tmp_path / "r"])
    assert r.returncode == 0, r.stderr
    with np.load(tmp_path / "r" / "frame_traffic_cone.npz") as z:
        sim = z["similarity"]
        assert sim.shape == (20, 20, 4) and np.all(np.abs(sim) <= 1 + 1e-5) and sim.std() > 0
    assert (tmp_path / "r" / "frame_traffic_cone.png").is_file()


def test_shipped_demo_runs_out_of_the_box(tmp_path):
    """The default bundle and demo frame ship in the package: `ago demo` works after install."""
    import json

    from ago_runtime.predict.bundle import DEFAULT_BUNDLE_DIR, DEMO_FRAME_DIR

    assert (DEFAULT_BUNDLE_DIR / "bundle.json").is_file() and (DEFAULT_BUNDLE_DIR / "planes.onnx").is_file()
    assert sorted(p.stem for p in DEMO_FRAME_DIR.glob("CAM_*.jpg")) == sorted(CAMERA_NAMES)
    meta = json.loads((DEFAULT_BUNDLE_DIR / "bundle.json").read_text())
    assert meta["text_encoder"]["id"] == "all-MiniLM-L6-v2"
    env = {k: v for k, v in os.environ.items() if k != "AGO_BUNDLE"}
    r = subprocess.run([sys.executable, "-m", "ago_runtime", "demo", "--out", str(tmp_path / "d")],
                       capture_output=True, text=True, env=env, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    with np.load(tmp_path / "d" / "demo_frame.npz", allow_pickle=False) as z:
        sem = z["semantics"]
    assert sem.shape == tuple(meta["grid"]["shape"])
    # a trained model, not noise: the road under the ego is predicted as driveable surface
    x0, y0 = sem.shape[0] // 2, sem.shape[1] // 2
    column = sem[x0 - 2:x0 + 3, y0 - 1:y0 + 2, :]
    assert (column == OCC3D_ID["driveable_surface"]).any()
    # a plausible amount of matter (issue 11: the old bundle called 84 % of the grid occupied)
    assert 0.01 < (sem != FREE).mean() < 0.5
    assert (tmp_path / "d" / "demo_frame.png").is_file()


def test_cli_demo_explains_missing_assets(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "AGO_BUNDLE"}
    r = subprocess.run([sys.executable, "-m", "ago_runtime", "demo", "--out", str(tmp_path / "d"),
                        "--bundle", str(tmp_path / "no_such_bundle")], capture_output=True, text=True, env=env)
    assert r.returncode == 2 and "no_such_bundle" in r.stderr
    assert not (tmp_path / "d").exists()


# ---------------------------------------------------------------------------- bad input
def _infer(bundle, frame, out, *extra):
    return run_cli(["infer", "--images", frame, "--bundle", bundle, "--out", out, *extra])


def test_refuses_missing_and_extra_camera(bundle_dir, frame_dir, tmp_path):
    out = tmp_path / "out"
    shutil.copy(frame_dir / "CAM_BACK.jpg", frame_dir / "CAM_ROOF.jpg")
    assert_refused(_infer(bundle_dir, frame_dir, out), "CAM_ROOF", out)
    (frame_dir / "CAM_ROOF.jpg").unlink()
    (frame_dir / "CAM_BACK.jpg").unlink()
    assert_refused(_infer(bundle_dir, frame_dir, out), "CAM_BACK", out)


def test_refuses_wrong_aspect_ratio(bundle_dir, frame_dir, tmp_path):
    out = tmp_path / "out"
    img = cv2.imread(str(frame_dir / "CAM_FRONT.jpg"))
    cv2.imwrite(str(frame_dir / "CAM_FRONT.jpg"), cv2.resize(img, (300, 300)))
    assert_refused(_infer(bundle_dir, frame_dir, out), "CAM_FRONT.jpg", out)


def test_refuses_corrupt_jpeg(bundle_dir, frame_dir, tmp_path):
    out = tmp_path / "out"
    data = (frame_dir / "CAM_BACK_LEFT.jpg").read_bytes()
    (frame_dir / "CAM_BACK_LEFT.jpg").write_bytes(data[: len(data) // 2])       # truncated
    assert_refused(_infer(bundle_dir, frame_dir, out), "CAM_BACK_LEFT.jpg", out)
    (frame_dir / "CAM_BACK_LEFT.jpg").write_bytes(b"\xff\xd8garbage\xff\xd9")   # markers, no image
    assert_refused(_infer(bundle_dir, frame_dir, out), "CAM_BACK_LEFT.jpg", out)


@pytest.mark.parametrize("damage", ["nan", "singular", "missing_camera"])
def test_refuses_bad_calibration(bundle_dir, frame_dir, tmp_path, damage):
    out = tmp_path / "out"
    calib = json.loads((frame_dir / "calib.json").read_text())
    if damage == "nan":
        calib["cameras"]["CAM_FRONT"]["intrinsics"][0][0] = float("nan")
    elif damage == "singular":
        calib["cameras"]["CAM_BACK"]["cam2ego"][0][:3] = [0.0, 0.0, 0.0]
    else:
        del calib["cameras"]["CAM_FRONT_LEFT"]
    (frame_dir / "calib.json").write_text(json.dumps(calib))
    assert_refused(_infer(bundle_dir, frame_dir, out), "calib.json", out)


def test_refuses_newer_bundle_and_truncated_onnx(bundle_dir, frame_dir, tmp_path):
    out = tmp_path / "out"
    newer = tmp_path / "newer"
    shutil.copytree(bundle_dir, newer)
    meta = json.loads((newer / "bundle.json").read_text())
    meta["format_version"] = 99
    (newer / "bundle.json").write_text(json.dumps(meta))
    assert_refused(_infer(newer, frame_dir, out), "bundle.json", out)
    for old in (1, 2, 3):       # one encoder.onnx; channels-first planes; voxel stages with bank products
        meta["format_version"] = old
        (newer / "bundle.json").write_text(json.dumps(meta))
        r = _infer(newer, frame_dir, out)
        assert_refused(r, "bundle.json", out)
        assert f"bundle format version {old} is no longer read" in r.stderr
        assert "re-export the checkpoint: `ago export CKPT -o BUNDLE_DIR`" in r.stderr

    cut = tmp_path / "cut"
    shutil.copytree(bundle_dir, cut)
    data = (cut / "voxels_0.onnx").read_bytes()
    (cut / "voxels_0.onnx").write_bytes(data[: len(data) // 3])
    assert_refused(_infer(cut, frame_dir, out), "voxels_0.onnx", out)
    # Even with the size and hash of the cut file recorded, onnxruntime's refusal becomes a one-line error.
    from ago_runtime.predict.contract import file_sha256

    meta = json.loads((cut / "bundle.json").read_text())
    meta["files"]["voxels_0"].update(size=(cut / "voxels_0.onnx").stat().st_size,
                                     sha256=file_sha256(cut / "voxels_0.onnx"))
    (cut / "bundle.json").write_text(json.dumps(meta))
    assert_refused(_infer(cut, frame_dir, out), "voxels_0.onnx", out)
    # without them bundle.json itself is incomplete
    for k in ("size", "sha256"):
        meta["files"]["voxels_0"].pop(k)
    (cut / "bundle.json").write_text(json.dumps(meta))
    assert_refused(_infer(cut, frame_dir, out), "bundle.json", out)


def test_refuses_bank_of_other_encoder_or_width(bundle_dir, frame_dir, tmp_path):
    from ago_runtime.vocab.bank import PromptBank

    out = tmp_path / "out"
    bank = PromptBank.load(bundle_dir / "banks" / "ow.npz")
    other = PromptBank(**{**{k: getattr(bank, k) for k in (
        "embeddings", "phrases", "class_names", "phrase_class", "encoder_variant", "encoder_hash", "dim",
        "known", "occ3d_ids")}, "encoder_id": "clip-vit-b32"})
    other.save(tmp_path / "other.npz")
    r = _infer(bundle_dir, frame_dir, out, "--bank", tmp_path / "other.npz")
    assert_refused(r, "the bundle needs", out)
    assert r.stderr.startswith(f"error: {tmp_path / 'other.npz'}:")     # the bank is what must be rebuilt
    narrow = PromptBank(**{**{k: getattr(bank, k) for k in (
        "phrases", "class_names", "phrase_class", "encoder_id", "encoder_variant", "encoder_hash", "known",
        "occ3d_ids")}, "embeddings": bank.embeddings[:, :128], "dim": 128})
    narrow.save(tmp_path / "narrow.npz")
    r = _infer(bundle_dir, frame_dir, out, "--bank", tmp_path / "narrow.npz")
    assert_refused(r, "narrow.npz", out)
    assert "dim 128" in r.stderr and "the bundle needs" in r.stderr


def test_bundle_load_errors_name_the_file(bundle_dir, tmp_path):
    from ago_runtime.predict.bundle import Bundle

    with pytest.raises(AgoInputError, match="bundle folder not found"):
        Bundle.load(tmp_path / "nope")
    b = tmp_path / "b"
    shutil.copytree(bundle_dir, b)
    (b / "heads.npz").unlink()
    with pytest.raises(AgoInputError) as e:
        Bundle.load(b)
    assert "heads.npz" in str(e.value)


def test_cli_infer_several_samples_and_a_scene_with_one_bundle_load(bundle_dir, tmp_path, monkeypatch):
    """--sample takes tokens and scene names, repeatable; the bundle is loaded once for all frames."""
    from ago_runtime.predict import bundle as bundle_mod
    from ago_runtime.formats.nuscenes import NuScenesDataset

    data = tmp_path / "data"
    assert run_cli(["synth", "--out", data, "--scenes", "2", "--frames", "2", "--image-size", "96x54",
                    "--grid", "20x20x4", "--val-fraction", "0.5"], cwd=tmp_path).returncode == 0
    ds = NuScenesDataset(data, load_images=False)
    scene0, token_last = ds.scenes()[0], ds.sample_tokens[-1]
    loads = []
    real_load = bundle_mod.Bundle.load.__func__
    monkeypatch.setattr(bundle_mod.Bundle, "load", classmethod(lambda cls, *a, **k: loads.append(a) or real_load(cls, *a, **k)))
    out = tmp_path / "out"
    r = run_cli(["infer", "--images", data, "--sample", scene0, "--sample", token_last, "--bundle", bundle_dir,
                 "--out", out], cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    want = [ds.sample_tokens[i] for i in ds.indices_of([scene0])] + [token_last]
    assert sorted(p.stem for p in out.glob("*.npz")) == sorted(want) and len(want) == 3
    assert len(loads) == 1
    assert r.stdout.startswith("bundle: trained on")          # the card line (random test checkpoint)


def test_prediction_picture_title_is_never_cut(bundle_dir, frame_dir):
    """The frame name is a full-width header, wrapped when long (it was cut off inside the first panel)."""
    from ago_runtime.pictures import render
    from ago_runtime.formats.calibration import load_images_folder
    from ago_runtime.predict.cli import prediction_picture
    from ago_runtime.predict.predictor import Predictor

    p = Predictor(bundle_dir)
    images, rig, _ = load_images_folder(frame_dir)
    pred = p.predict(images, rig)
    long = "n015-2018-07-24-11-22-45+0800 ca9a282c9e77460f8360f564131a8af5 " * 3
    pic = prediction_picture(pred, images, long)
    plain = prediction_picture(pred, images, "")
    bar = render._title_bar(long, plain.shape[1])
    assert pic.shape[0] == plain.shape[0] + bar.shape[0] and pic.shape[1] == plain.shape[1]
    assert bar.shape[0] > render._title_bar("short", plain.shape[1]).shape[0]      # wrapped onto more lines
    scale = float(np.clip(plain.shape[1] / 1000, 0.5, 0.9))
    thick = 2 if scale >= 0.7 else 1
    lines = render._wrap(long, plain.shape[1] - 12, scale, thick)
    assert len(lines) >= 2 and "".join(lines).replace(" ", "") == long.replace(" ", "")   # nothing dropped
    assert all(render._text_size(line, scale, thick)[0] <= plain.shape[1] - 12 for line in lines)


def test_optimised_graph_cache_is_used_checked_and_remade(bundle_dir, frame_dir, tmp_path, monkeypatch):
    """The first session of a graph writes onnxruntime's optimised graph to the cache; later sessions
    read it (same results); a damaged cache file is removed and remade; AGO_NO_ORT_CACHE=1 bypasses it."""
    from ago_runtime.formats.calibration import load_images_folder
    from ago_runtime.cache import optimized_cache_path
    from ago_runtime.predict.predictor import Predictor

    monkeypatch.setenv("AGO_CACHE_DIR", str(tmp_path / "cache"))
    first = Predictor(bundle_dir)
    files = first.bundle.meta["files"]
    cached = {k: optimized_cache_path(files[k]["sha256"]) for k in ("planes", "voxels_0")}
    assert all(p.is_file() and p.stat().st_size > 0 for p in cached.values())
    assert not [p for p in cached["planes"].parent.iterdir() if p.name.endswith(".tmp.onnx")]
    images, rig, _ = load_images_folder(frame_dir)
    want = first.predict(images, rig)
    again = Predictor(bundle_dir)                     # reads the cached graphs
    got = again.predict(images, rig)
    assert np.array_equal(got.semantics, want.semantics)
    np.testing.assert_allclose(got.entropy, want.entropy, atol=1e-5)
    cached["planes"].write_bytes(b"damaged")
    remade = Predictor(bundle_dir)
    assert cached["planes"].stat().st_size > 1000
    assert np.array_equal(remade.predict(images, rig).semantics, want.semantics)
    monkeypatch.setenv("AGO_NO_ORT_CACHE", "1")
    for p in cached.values():
        p.unlink()
    Predictor(bundle_dir)
    assert not any(p.exists() for p in cached.values())


def test_runtime_sessions_run_without_onnxruntime_memory_pattern(bundle_dir, tmp_path, monkeypatch):
    """Every graph session of a Predictor runs with the memory pattern off, cached optimised graph or not:
    with it on, the compact planes graph's first real frame after the warm-up ran 1.8x its steady time and
    the peak RSS was 1.5x (benchmarks/results/mem_pattern.md)."""
    from ago_runtime.predict.decision import Branch
    from ago_runtime.predict.predictor import Predictor

    monkeypatch.setenv("AGO_CACHE_DIR", str(tmp_path / "cache"))
    for _ in range(2):                                # the first writes the optimised graphs, the second reads them
        enc = Predictor(bundle_dir, warm_up=False).encoder
        sessions = [enc.planes, enc.bank_product.session] + [s for s, _ in enc.sessions[Branch.MAIN]]
        assert [s.get_session_options().enable_mem_pattern for s in sessions] == [False] * len(sessions)


def _small_dataset(root: Path, frames: int = 4) -> list[str]:
    """A nuScenes-layout dataset of one scene with `frames` keyframes (smooth random images); -> tokens."""
    from ago_runtime.formats.nuscenes_writer import NuScenesWriter

    rng = np.random.default_rng(3)
    rig = Rig.nuscenes_like(320, 180)
    writer = NuScenesWriter(root, "v1.0-mini")
    scene = writer.add_scene("scene-0001", "pipeline test")
    tokens = []
    for k in range(frames):
        pose = np.eye(4)
        pose[:3, 3] = [10.0 + 2 * k, 5.0, 0.0]
        images = {c.name: np.clip(cv2.resize(rng.uniform(0, 255, (12, 21, 3)).astype(np.float32), (320, 180)),
                                  0, 255).astype(np.uint8) for c in rig}
        tokens.append(writer.add_sample(scene, 1_600_000_000_000_000 + k * 500_000, pose, rig, images,
                                        np.zeros((4, 5), np.float32), np.eye(4)))
    writer.close({"val": ["scene-0001"]})
    return tokens


def test_infer_dataset_pipeline_outputs_pictures_and_errors(bundle_dir, tmp_path):
    """The threaded reader / predictor / writer pipeline gives, per frame, what Predictor.predict gives;
    --picture none|bev|full; a corrupt image in frame 3 ends the run with one line after frames 1-2 are
    written completely."""
    from ago_runtime.formats.nuscenes import NuScenesDataset
    from ago_runtime.predict.predictor import Predictor

    ds_root = tmp_path / "ds"
    tokens = _small_dataset(ds_root)
    out = tmp_path / "none"
    r = _infer(bundle_dir, ds_root, out, "--picture", "none")
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in out.iterdir()) == sorted(f"{t}.npz" for t in tokens)
    p = Predictor(bundle_dir)
    ds = NuScenesDataset(ds_root, load_extras=False)
    for i in (0, len(tokens) - 1):
        f = ds[i]
        with np.load(out / f"{f.token}.npz", allow_pickle=False) as z:
            assert np.array_equal(z["bank_semantics"], p.predict(f.images, f.rig).semantics)
    # a dataset runs two frames at once by default (auto_workers); one at a time gives the same files' arrays
    from ago_runtime.predict.pipeline import auto_workers

    assert auto_workers(1) == 1 and auto_workers(len(tokens)) == (2 if (os.cpu_count() or 1) >= 2 else 1)
    one = tmp_path / "one_worker"
    r = _infer(bundle_dir, ds_root, one, "--picture", "none", "--workers", "1")
    assert r.returncode == 0, r.stderr
    for t in tokens:
        with np.load(out / f"{t}.npz", allow_pickle=False) as a, np.load(one / f"{t}.npz", allow_pickle=False) as b:
            assert a.files == b.files and all(np.array_equal(a[k], b[k]) for k in a.files)
    for kind in ("bev", "full"):
        r = _infer(bundle_dir, ds_root, tmp_path / kind, "--picture", kind)
        assert r.returncode == 0, r.stderr
        assert len(list((tmp_path / kind).glob("*.png"))) == len(tokens)
    bev = cv2.imread(str(next((tmp_path / "bev").glob("*.png"))))
    full = cv2.imread(str(next((tmp_path / "full").glob("*.png"))))
    assert bev.shape[0] < full.shape[0] and bev.shape[1] < full.shape[1]   # the cheap picture is smaller
    assert_refused(_infer(bundle_dir, ds_root, tmp_path / "x", "--picture", "huge"), "--picture", tmp_path / "x")
    # a corrupt JPEG in the third frame: one error line, the first two frames written completely
    bad = sorted((ds_root / "samples" / "CAM_FRONT").iterdir())[2]     # names sort by timestamp
    bad.write_bytes(bad.read_bytes()[: 200])
    out = tmp_path / "broken"
    r = _infer(bundle_dir, ds_root, out, "--picture", "none")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert [ln for ln in r.stderr.splitlines() if ln.startswith("error:")] and bad.name in r.stderr
    written = sorted(out.iterdir())
    assert [p.name for p in written] == sorted(f"{t}.npz" for t in tokens[:2])
    for f in written:
        with np.load(f, allow_pickle=False) as z:
            assert z["semantics"].shape == tuple(p.grid.shape)


def test_unexplained_obstacle_score_on_hand_made_scores():
    """score = 1 - best prompted-class confidence over both branches (whatever the identifier);
    occupancy = 1 - p(free): a voxel is flagged when the main branch says occupied and no branch is sure
    of any prompted class; free voxels and voxels a branch explains are not."""
    from ago_runtime.predict.heads import FoldedHeads, HeadWeights
    from ago_runtime.predict.predictor import UNEXPLAINED_THRESHOLD

    C, K = 4, 3
    z = np.zeros
    w = HeadWeights(z((C, 2), np.float32), z(C, np.float32), z((C, 2), np.float32), z(C, np.float32),
                    z(C, np.float32))
    fh = FoldedHeads.fold(w, np.eye(K, C, dtype=np.float32), np.arange(K), K)
    # rows: 3 phrases (one per class) + free; columns: 4 voxels
    main = np.array([[9, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [0, 9, 0, 0]], np.float32)   # col 1: free
    main[:, 2] = [5, 5, 5, 0]        # occupied, classes tied: unexplained
    main[:, 3] = [5, 5, 5, 0]        # occupied, main unsure, but the adapted branch is sure (below)
    ad = np.zeros((4, 4), np.float32)
    ad[:, 3] = [0, 9, 0, 0]
    for ident in ("none", "min-entropy"):
        d = decide_scores(fh, main, ad, ident, volumes=True)
        label, u, occ = d.label, d.unexplained, d.occupancy
        assert u.shape == occ.shape == (4,) and np.all((u >= 0) & (u <= 1)) and np.all((occ >= 0) & (occ <= 1))
        flagged = (occ > 0.5) & (u > UNEXPLAINED_THRESHOLD)
        assert occ[1] < 0.01 and occ[0] > 0.99 and occ[2] > 0.99
        assert u[0] < 0.01 and u[2] > 0.6
        assert not flagged[0] and not flagged[1] and flagged[2]
        # the adapted branch explains voxel 3 whatever the identifier; only min-entropy takes its label
        assert u[3] < 0.01 and not flagged[3]
        assert label[3] == (1 if ident == "min-entropy" else 0)


def test_unexplained_score_sees_reference_classes_and_keeps_the_labels():
    """With reference classes (training classes no prompt covers) folded in, a voxel that matches only a
    reference class is occupied and unexplained, while the labels equal those without reference classes."""
    from ago_runtime.predict.heads import FoldedHeads, HeadWeights

    C = 4
    z = np.zeros
    w = HeadWeights(z((C, 2), np.float32), z(C, np.float32), z((C, 2), np.float32), z(C, np.float32),
                    z(C, np.float32))
    user = FoldedHeads.fold(w, np.eye(2, C, dtype=np.float32), np.arange(2), 2)
    with_ref = FoldedHeads.fold(w, np.eye(3, C, dtype=np.float32), np.arange(3), 3, reference_classes=1)
    # rows: user class 0, user class 1, [reference class 2,] free; columns: 3 voxels
    # col 0: user class 0; col 1: only the reference class matches (user-only heads call it free);
    # col 2: free
    s_user = np.array([[9, 0, 0], [0, 0, 0], [0, 2, 9]], np.float32)
    s_ref = np.array([[9, 0, 0], [0, 0, 0], [0, 9, 0], [0, 2, 9]], np.float32)
    for ident in ("none", "min-entropy"):
        d_user = decide_scores(user, s_user, s_user, ident, volumes=True)
        d_ref = decide_scores(with_ref, s_ref, s_ref, ident, volumes=True)
        np.testing.assert_array_equal(d_user.label, d_ref.label)
        assert d_ref.label[1] == 2                # labels: free for the user's classes (index K = 2)
        assert d_user.occupancy[1] < 0.3          # without reference classes it looks free
        assert d_ref.occupancy[1] > 0.9 and d_ref.unexplained[1] > 0.9   # with them: occupied, unexplained
        assert d_ref.unexplained[0] < 0.01 and d_ref.occupancy[2] < 0.01
    with pytest.raises(ValueError):
        FoldedHeads.fold(w, np.eye(2, C, dtype=np.float32), np.arange(2), 2, reference_classes=2)


# ---------------------------------------------------------------------------- ago choose-threshold
def _pseudo_like(gt_root: Path, out: Path, step: int, range_max=(40.0, 40.0, 5.4)) -> Path:
    """An `ago pseudo-labels`-shaped folder (meta.json naming the cw classes, free 17) made from a synthetic town's
    Occ3D GT, every `step`-th voxel along x and y (a coarser grid)."""
    from ago_runtime.classes import OCC3D_CLASSES

    shape = None
    for f in sorted(gt_root.glob("*/*/labels.npz")):
        with np.load(f) as z:
            sem, mask = z["semantics"][::step, ::step], z["mask_camera"][::step, ::step]
        d = out / f.parent.parent.name / f.parent.name
        d.mkdir(parents=True)
        np.savez(d / "labels.npz", semantics=sem, mask_camera=mask)
        shape = sem.shape
    meta = {"label_space": {"name": "cw", "classes": list(OCC3D_CLASSES[:17])}, "free_index": 17,
            "ignore_index": 255, "grid": {"range_min": [-40.0, -40.0, -1.0], "range_max": list(range_max),
                                          "shape": list(shape)}}
    (out / "meta.json").write_text(json.dumps(meta))
    return out


def test_choose_threshold_on_labelled_frames(bundle_dir, tmp_path):
    """`ago choose-threshold` on Occ3D GT (labels finer than the bundle's grid) and on a pseudo-label folder
    (coarser): the threshold it prints is the one `ago infer --unexplained-threshold` then applies, flagging at most
    --false-rate of the voxels labelled with a prompted class (recomputed here from infer's own npz files and the
    labels), and --frames picks that many frames. Labels of another grid range or of frames the dataset lacks are
    refused with one line."""
    from ago_runtime.predict.threshold import LabelFolder
    from ago_runtime.scoring.metric import upsample_nearest
    from ago_runtime.vocab.prompts import parse_prompt_file

    data = tmp_path / "town"
    r = run_cli(["synth", "--out", data, "--scenes", "1", "--frames", "3", "--image-size", "96x54", "--grid",
                 "40x40x4"], cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    prompts = str(REPO / "prompts" / "ow_pretrain.txt")
    base = ["choose-threshold", "--images", data, "--bundle", bundle_dir, "--prompts", prompts]
    r = run_cli(base + ["--labels", data / "gts", "--json", tmp_path / "gt.json", "--false-rate", "0.1"], cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    choice = json.loads((tmp_path / "gt.json").read_text())
    t = choice["threshold"]
    assert f"--unexplained-threshold {t:.3f}" in r.stdout and len(choice["frames"]) == 3

    out = tmp_path / "infer"
    r = run_cli(["infer", "--images", data, "--bundle", bundle_dir, "--prompts", prompts, "--out", out,
                 "--save-volumes", "--picture", "none", "--unexplained-threshold", repr(t) if t > 0 else "1e-9"],
                cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    labels = LabelFolder.open(data / "gts")
    classes = parse_prompt_file(prompts).classes   # vehicle [car, bus, ...] explains car, bus ...
    covered = {c.name for c in classes} | {OCC3D_CLASSES[i] for c in classes for i in c.occ3d_ids}
    ids = [i for i, n in enumerate(labels.class_names) if n in covered]
    flagged, explained = 0, 0
    for token in choice["frames"]:
        sem, counted = labels.load(token)
        with np.load(out / f"{token}.npz") as z:
            factor = [a // b for a, b in zip(sem.shape, z["unexplained_mask"].shape)]
            mask = upsample_nearest(z["unexplained_mask"].astype(bool), factor)
        sel = counted & np.isin(sem, ids)
        flagged += int(mask[sel].sum())
        explained += int(sel.sum())
    assert explained == choice["explained_voxels"] > 0
    if t > 0:
        assert flagged / explained == pytest.approx(choice["flagged_explained"]) and flagged / explained <= 0.1

    pseudo = _pseudo_like(data / "gts", tmp_path / "pseudo", step=4)        # 10 x 10 x 4: coarser than the bundle's
    r = run_cli(base + ["--labels", pseudo, "--frames", "2", "--json", tmp_path / "p.json"], cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    p = json.loads((tmp_path / "p.json").read_text())
    assert len(p["frames"]) == 2 and 0.0 <= p["threshold"] <= 1.0 and p["flagged_explained"] <= 0.05

    wrong = _pseudo_like(data / "gts", tmp_path / "wrong_range", step=4, range_max=(50.0, 50.0, 5.4))
    r = run_cli(base + ["--labels", wrong], cwd=tmp_path)
    assert r.returncode == 2 and "meta.json" in r.stderr and "not the same space" in r.stderr
    other = tmp_path / "other" / "scene-x" / ("0" * 32)
    other.mkdir(parents=True)
    shutil.copy(next((data / "gts").glob("*/*/labels.npz")), other / "labels.npz")
    r = run_cli(base + ["--labels", tmp_path / "other"], cwd=tmp_path)
    assert r.returncode == 2 and "none of the 1 labelled frames" in r.stderr


def test_label_folder_reads_waymo_scene_paths_and_refuses_bad_meta(tmp_path):
    """LabelFolder finds labels one level deeper too (an Occ3D-Waymo dataset's scenes are `<split>/<scene>`, so its
    pseudo-labels lie at training/000/<token>/labels.npz), keeps the label space meta.json gives, counts only
    labelled voxels inside the camera mask, and refuses a meta.json whose classes are not a list of names."""
    from ago_runtime.predict.threshold import LabelFolder

    sem = np.full((4, 4, 2), 17, np.uint8)
    sem[0, 0, 0], sem[1, 1, 0], sem[2, 2, 0] = 1, 255, 3
    mask = np.ones_like(sem)
    mask[2, 2, 0] = 0
    for token in ("0000000", "0000001"):
        d = tmp_path / "training" / "000" / token
        d.mkdir(parents=True)
        np.savez(d / "labels.npz", semantics=sem, mask_camera=mask)
    meta = {"label_space": {"classes": ["general_object", "vehicle", "pedestrian", "sign"]}, "free_index": 17,
            "grid": {"range_min": [-40, -40, -1], "range_max": [40, 40, 5.4]}}
    (tmp_path / "meta.json").write_text(json.dumps(meta))
    folder = LabelFolder.open(tmp_path)
    assert list(folder.files) == ["0000000", "0000001"] and folder.kind == "pseudo-labels"
    assert folder.class_names[1] == "vehicle" and folder.free_index == 17
    labels, counted = folder.load("0000000")
    assert counted.sum() == 1 and counted[0, 0, 0]          # free, ignored (255) and outside the mask do not count
    from ago_runtime.scoring.cli import load_prior           # `ago metric --lidar --prior` reads the same layout

    meta["grid"]["shape"] = [4, 4, 2]
    (tmp_path / "meta.json").write_text(json.dumps(meta))
    prior, notes = load_prior(tmp_path, {"0000001"})
    assert notes and "1 of the scored keyframes" in notes[0]
    meta["label_space"]["classes"] = "vehicle"
    (tmp_path / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(AgoInputError, match="list of names"):
        LabelFolder.open(tmp_path)
