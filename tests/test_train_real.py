"""Issue 47: training from several (data, pseudo-labels) sources (ago_train/sources.py), the flip augmentation
as the dataset applies it, the time split (time_split.py) and `ago train-real`'s reuse of finished stages."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from ago_runtime.errors import AgoInputError

from conftest import shared_path  # noqa: E402

pytestmark = pytest.mark.xdist_group("test_train_real")  # one worker builds the module fixtures (--dist loadgroup)

REPO = Path(__file__).resolve().parents[1]
GRID = "20x20x4"


def _ago(*args: str) -> None:
    env = dict(os.environ, AGO_NO_PROGRESS="1", OMP_NUM_THREADS="1", PYTHONPATH=str(REPO))
    r = subprocess.run([sys.executable, "-m", "ago_runtime.cli", *args], cwd=REPO, env=env, capture_output=True, text=True)
    assert r.returncode == 0, f"ago {' '.join(args)}:\n{r.stdout}\n{r.stderr}"


def _town(root: Path, seed: int, rig: str = "nuscenes") -> tuple[Path, Path]:
    data, pseudo = root / f"town{seed}{rig}", root / f"pseudo{seed}{rig}"
    _ago("synth", "--out", str(data), "--scenes", "2", "--frames", "2", "--image-size", "96x64", "--grid", GRID,
         "--seed", str(seed), "--rig", rig, "--layout", "nuscenes")
    _ago("pseudo-labels", "--data", str(data), "--out", str(pseudo), "--prompts", "cw", "--grid", GRID,
         "--split", "all", "--embedder", "none", "--keyframes", "1")
    return data, pseudo


@pytest.fixture(scope="module")
def towns(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("ago_sources")
    return {"a": _town(root, 1), "b": _town(root, 2), "front": _town(root, 3, "front")}


def _config(out: Path, sources: list[dict], **changes):
    from ago_train.train_config import TrainConfig

    d = TrainConfig.preset("tiny").to_dict()
    d.update(out=str(out), train_split="all", device="cpu", sources=sources, augment="flip", **changes)
    return TrainConfig.from_dict(d)


def _src(pair, weight=1.0) -> dict:
    return {"data": str(pair[0]), "pseudo": str(pair[1]), "weight": weight}


def test_two_sources_train_together_each_frame_reads_its_own_labels(towns, tmp_path):
    from ago_train.dataset import PseudoLabelSet
    from ago_train.trainer import Trainer

    cfg = _config(tmp_path / "run", [_src(towns["a"]), _src(towns["b"], 1.5)])
    assert cfg.to_dict()["sources"][1]["weight"] == 1.5                          # saved with the config
    t = Trainer(cfg, quiet=True)
    t.setup()
    frames = t.dataset.frames
    assert len(frames) == 4 + 6                        # 4 frames each; town b seen 1.5 times per epoch
    assert len(frames.unique()) == 8
    own = {0: PseudoLabelSet.open(towns["a"][1]), 1: PseudoLabelSet.open(towns["b"][1])}
    for n in range(len(frames)):
        part, _ = frames.key(n)
        f = frames[n]
        assert np.array_equal(t.pseudo.labels(f.scene, f.token), own[part].labels(f.scene, f.token))
    r = t.run(until=2)
    assert r["step"] == 2 and all(np.isfinite(r["losses"]))


def test_a_source_of_another_rig_or_a_repeated_source_is_refused(towns, tmp_path):
    from ago_train.trainer import Trainer

    with pytest.raises(AgoInputError) as e:
        Trainer(_config(tmp_path / "r1", [_src(towns["a"]), _src(towns["front"])]), quiet=True).setup()
    assert str(towns["front"][0]) in str(e.value) and "cameras" in str(e.value)
    with pytest.raises(AgoInputError) as e:
        Trainer(_config(tmp_path / "r2", [_src(towns["a"]), _src(towns["a"])]), quiet=True).setup()
    assert "also in source" in str(e.value)


@pytest.mark.parametrize("bad, words", [
    ([], "non-empty list"), ([{"data": "d"}], "pseudo must be"), ([{"data": "d", "pseudo": "p", "weight": 0}], "weight"),
    ([{"data": "d", "pseudo": "p", "colour": 1}], "unknown keys"), ("d", "non-empty list")])
def test_bad_sources_are_one_config_error(bad, words, tmp_path):
    with pytest.raises(AgoInputError) as e:
        _config(tmp_path, bad)
    assert words in str(e.value)


def test_repeat_by_weight():
    from ago_train.sources import repeat_by_weight

    assert repeat_by_weight([5, 6, 7, 8], 1) == [5, 6, 7, 8]
    assert repeat_by_weight([5, 6, 7, 8], 2.5) == [5, 6, 7, 8] * 2 + [5, 7]
    assert repeat_by_weight([5, 6, 7, 8], 0.5) == [5, 7]
    assert repeat_by_weight([5, 6, 7, 8], 0.01) == [5]


def test_a_flipped_item_mirrors_images_projections_and_labels_together(towns):
    """The dataset's mirrored item: the image is flipped left-right, and a labelled voxel projects onto the pixel
    that shows, in the flipped image, what the original image showed where the voxel projected before."""
    from ago_runtime.formats.datasets import open_dataset
    from ago_runtime.geometry.preprocess import Preprocess
    from ago_train.augment import draw
    from ago_train.dataset import FrameList, OccSampleDataset, PseudoLabelSet

    ds = open_dataset(towns["a"][0], load_extras=False)
    pseudo = PseudoLabelSet.open(towns["a"][1])
    grid = pseudo.grid
    pre = Preprocess(96, 64)
    plain = OccSampleDataset(FrameList(ds, range(len(ds))), pseudo, 17, grid, pre, augment="none")
    mirrored = OccSampleDataset(FrameList(ds, range(len(ds))), pseudo, 17, grid, pre, augment="flip")
    epoch, i = next((e, i) for e in range(20) for i in range(len(ds)) if draw("flip", 0, e, i).flip_y)
    mirrored.set_epoch(epoch)
    a, b = plain[i], mirrored[i]
    assert torch.equal(b["images"], a["images"].flip(-1))
    X, Y, Z = grid.shape
    sa, sb = a["semantics"].reshape(X, Y, Z), b["semantics"].reshape(X, Y, Z)
    assert torch.equal(sb, sa.flip(1))                                   # y -> -y
    centres = grid.centres().reshape(-1, 3)
    occupied = np.flatnonzero((sa.reshape(-1) < 17).numpy())
    assert occupied.size
    checked = 0
    for v in occupied[:: max(1, occupied.size // 50)]:
        x, y, z = np.unravel_index(v, (X, Y, Z))
        w = np.ravel_multi_index((x, Y - 1 - y, z), (X, Y, Z))           # the same voxel in the mirrored frame
        assert sb.reshape(-1)[w] == sa.reshape(-1)[v]
        pa = a["ego2img"].numpy().astype(np.float64) @ np.r_[centres[v], 1.0]
        pb = b["ego2img"].numpy().astype(np.float64) @ np.r_[centres[w], 1.0]
        for cam in range(pa.shape[0]):
            if pa[cam, 2] < 0.5:
                continue
            ua, va_ = pa[cam, 0] / pa[cam, 2], pa[cam, 1] / pa[cam, 2]
            ub, vb = pb[cam, 0] / pb[cam, 2], pb[cam, 1] / pb[cam, 2]
            if not (0 <= ua < pre.width and 0 <= va_ < pre.height):
                continue
            assert abs(vb - va_) < 1e-3 and abs(ub - (pre.width - ua)) < 1e-3
            # the pixel under the voxel shows the same colour in both items
            assert torch.equal(b["images"][cam, :, int(va_), int(ub)], a["images"][cam, :, int(va_), int(ua)])
            checked += 1
    assert checked > 0


def test_time_split_parts_and_its_reuse(tmp_path):
    from ago_runtime.formats.nuscenes import NuScenesDataset
    from ago_train.time_split import part_sizes, time_split

    assert part_sizes(41, 0.15, 0.2) == (27, 6, 8)
    src = shared_path("nuscenes-scene")
    rec = time_split(src, tmp_path / "s")
    ds = NuScenesDataset(tmp_path / "s", load_images=False, load_extras=False)
    parts = {p: [ds.sample_tokens[i] for i in ds.split(p)] for p in ("train", "val", "test")}
    assert [len(parts[p]) for p in parts] == [27, 6, 8]
    stamps = {t: ds.sample_tokens.index(t) for t in ds.sample_tokens}
    assert max(map(stamps.get, parts["train"])) < min(map(stamps.get, parts["val"]))
    assert parts["test"] == rec["scenes"]["scene-0916"]["test"]
    assert time_split(src, tmp_path / "s") == rec                                  # reused
    with pytest.raises(AgoInputError) as e:
        time_split(src, tmp_path / "s", test_share=0.3)                           # another split: refused
    assert "not the time split" in str(e.value)


def test_train_real_reuses_finished_stages_after_checking(tmp_path):
    """A second run calls no verb for a stage whose output is there and checked (town, select, export);
    the verbs that resume themselves (pseudo-labels, train --resume) are called again; a changed setting redoes."""
    from ago_train.time_split import time_split
    from ago_train.train_real import RealRecipe, train_real

    src = shared_path("nuscenes-scene")
    calls = []

    def fake(name, args, work, say):
        calls.append((name, args[0], "--resume" in args))
        a = [str(x) for x in args]
        if args[0] == "synth":
            time_split(src, a[a.index("--out") + 1])          # any nuScenes-layout folder with a splits.json
        elif args[0] == "train":
            steps = json.loads(next(x for x in a if x.startswith("snapshot_steps=")).split("=", 1)[1])
            out = Path(a[a.index("--out") + 1])
            (out / "snapshots").mkdir(parents=True, exist_ok=True)
            (out / "last.pt").write_bytes(b"x")
            for s in steps:
                p = out / "snapshots" / f"step_{s:06d}.pt"
                if not p.exists():
                    p.write_bytes(b"x")
        elif args[0] == "eval":
            step = int(Path(a[a.index("--ckpt") + 1]).stem.split("_")[1])
            out = Path(a[a.index("--out") + 1])
            out.mkdir(parents=True, exist_ok=True)
            (out / "metrics.json").write_text(json.dumps({"mIoU": 10 - abs(step - 4), "geometry_IoU": 20.0}))
        elif args[0] == "export":
            Path(a[a.index("-o") + 1]).mkdir(parents=True)

    recipe = RealRecipe(steps=8, snapshots=4, town_scenes=2, town_frames=2)
    r1 = train_real(src, tmp_path / "out", recipe, say=lambda s: None, run_verb=fake)
    assert r1["select"]["chosen_step"] == 4 and (tmp_path / "out/bundle/train_real.json").is_file()
    first = [c[1] for c in calls]
    assert first.count("synth") == 1 and first.count("eval") == 4 and first.count("export") == 1
    calls.clear()
    r2 = train_real(src, tmp_path / "out", recipe, say=lambda s: None, run_verb=fake)
    again = [c[1] for c in calls]
    assert "synth" not in again and "eval" not in again and "export" not in again
    assert ("train", "train", True) in calls                        # training is resumed, not restarted
    assert "reused" in r2["stages"]["town"]["note"] and "reused" in r2["stages"]["export"]["note"]
    assert "note" not in r2["earlier_invocations"][0]["stages"]["town"]   # the first run's own times are kept
    calls.clear()
    train_real(src, tmp_path / "out", RealRecipe(steps=8, snapshots=4, town_scenes=3, town_frames=2),
               say=lambda s: None, run_verb=fake)
    assert [c[1] for c in calls].count("synth") == 1                # another town: made again


def test_train_real_pseudo_labels_on_the_preset_grid_with_the_carve_rule(tmp_path):
    """The pseudo-labels stage runs on the preset model's grid with the recipe's --carve (default grazing)."""
    from ago_train.model import ModelConfig
    from ago_train.time_split import time_split
    from ago_train.train_real import RealRecipe, train_real

    src = shared_path("nuscenes-scene")
    pseudo_calls = []

    def fake(name, args, work, say):
        a = [str(x) for x in args]
        if args[0] == "synth":
            time_split(src, a[a.index("--out") + 1])
        elif args[0] == "pseudo-labels":
            pseudo_calls.append(a)
            raise SystemExit("stop after the pseudo-labels stage")

    for carve in (None, "all", "grazing"):
        pseudo_calls.clear()
        recipe = RealRecipe(town_scenes=2, town_frames=2, **({} if carve is None else {"carve": carve}))
        with pytest.raises(SystemExit):
            train_real(src, tmp_path / str(carve), recipe, say=lambda s: None, run_verb=fake)
        a = pseudo_calls[0]
        assert a[a.index("--carve") + 1] == (carve or "grazing")
        assert a[a.index("--grid") + 1] == "x".join(map(str, ModelConfig.preset("cpu").grid_obj().shape))


def test_train_real_bad_dataroot_is_one_line_and_writes_nothing(tmp_path):
    env = dict(os.environ, AGO_NO_PROGRESS="1", PYTHONPATH=str(REPO))
    for root, words in ((tmp_path / "missing", "dataroot not found"), (tmp_path, "no v1.0-* table folder")):
        r = subprocess.run([sys.executable, "-m", "ago_runtime", "train-real", str(root), str(tmp_path / "out")],
                           cwd=REPO, env=env, capture_output=True, text=True)
        assert r.returncode == 2 and words in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert not (tmp_path / "out" / "work").exists()
