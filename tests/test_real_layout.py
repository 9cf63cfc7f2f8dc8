"""Real nuScenes as a user has it, on a small stand-in: a dataset written by `ago synth` with non-key
LiDAR sweeps, then edited into the shape of a real extract — tables the reader does not need removed,
no splits.json, no synthetic/ ground-truth pictures, label maps in <data>/masks as Grounded SAM would
write them. Checks: the reader needs only its six tables (and names every missing one at once),
`ago pseudo-labels` runs with its defaults and uses the real non-key sweeps, and a failed run writes
nothing, so the corrected command is not refused.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from ago_runtime.geometry.camera import CAMERA_NAMES
from ago_runtime.classes import FREE, NUM_SEMANTIC, OCC3D_CLASSES
from ago_runtime.errors import AgoInputError
from ago_runtime.formats.nuscenes import READ_TABLES, NuScenesDataset

VERSION = "v1.0-trainval"
SWEEPS = 3


def _run(args, cwd):
    from test_bad_inputs import run_ago

    return run_ago(args, cwd)


@pytest.fixture(scope="module")
def synth_with_sweeps(tmp_path_factory):
    root = tmp_path_factory.mktemp("real_layout") / "synth"
    r = _run(["synth", "--out", root, "--scenes", "1", "--frames", "3", "--image-size", "160x90", "--grid", "20x20x4",
              "--sweeps-between", str(SWEEPS)], root.parent)
    assert r.code == 0, r.stderr
    return root


@pytest.fixture
def real_like(synth_with_sweeps, tmp_path):
    """A copy edited into a trimmed real extract, with label maps (the rendered truth) in <data>/masks."""
    data = shutil.copytree(synth_with_sweeps, tmp_path / "nuscenes")
    ds = NuScenesDataset(data, load_images=False)
    masks = data / "masks"
    masks.mkdir()
    (masks / "classes.json").write_text(json.dumps({str(i + 1): OCC3D_CLASSES[i] for i in range(NUM_SEMANTIC)}))
    for i in range(len(ds)):
        f = ds[i]
        for cam in CAMERA_NAMES:
            sem = f.extras["semantic"][cam]
            (masks / cam).mkdir(exist_ok=True)
            cv2.imwrite(str(masks / cam / f"{Path(f.image_paths[cam]).stem}.png"),
                        np.where(sem < NUM_SEMANTIC, sem + 1, 0).astype(np.uint8))
    shutil.rmtree(data / "synthetic")
    (data / "splits.json").unlink()
    for table in ("attribute", "log", "map", "visibility", "category", "instance", "sample_annotation"):
        (data / VERSION / f"{table}.json").unlink()
    return data


def test_synth_writes_nonkey_sweeps_only_when_asked(synth_with_sweeps, tmp_path):
    ds = NuScenesDataset(synth_with_sweeps, load_images=False)
    assert ds.num_nonkey_lidar == SWEEPS * (len(ds) - 1) and ds.max_nonkey_sweeps() == SWEEPS
    sweeps = ds.nonkey_sweeps(2)
    key = ds[2].lidar
    stamps = [s.timestamp for s in sweeps]
    assert stamps == sorted(stamps, reverse=True) and key.timestamp > stamps[0] > stamps[-1] > ds[1].lidar.timestamp
    assert all(Path(s.path).parent.name == "LIDAR_TOP" and "sweeps" in Path(s.path).parts for s in sweeps)
    # the ego moves: each sweep has its own pose, between the two keyframes'
    xs = [s.ego2global[0, 3] for s in sweeps]
    assert len(set(np.round(xs, 6))) == SWEEPS
    assert ds.nonkey_sweeps(0) == [] and len(ds.nonkey_sweeps(2, 1)) == 1
    plain = tmp_path / "plain"
    assert _run(["synth", "--out", plain, "--scenes", "1", "--frames", "2", "--image-size", "96x54",
                 "--grid", "20x20x4"], tmp_path).code == 0
    assert not (plain / "sweeps").exists() and NuScenesDataset(plain, load_images=False).num_nonkey_lidar == 0


def test_reader_needs_only_its_tables_and_names_all_missing_ones(real_like):
    ds = NuScenesDataset(real_like, load_images=False, load_extras=False)      # seven tables gone: fine
    assert len(ds) == 3 and sorted(p.stem for p in (real_like / VERSION).glob("*.json")) == sorted(READ_TABLES)
    for name in ("ego_pose", "sample"):
        (real_like / VERSION / f"{name}.json").unlink()
    with pytest.raises(AgoInputError) as e:
        NuScenesDataset(real_like)
    assert "ego_pose.json" in e.value.problem and "sample.json" in e.value.problem


def test_pseudo_labels_defaults_fit_a_real_extract_and_use_its_sweeps(real_like, tmp_path):
    out = tmp_path / "pl"
    r = _run(["pseudo-labels", "--data", real_like, "--out", out, "--prompts", "cw", "--grid", "20x20x4",
              "--keyframes", "2"], tmp_path)
    assert r.code == 0, r.stderr
    for note in ("--masks", "--segmenter files", "--split all", f"--sweeps {SWEEPS}"):
        assert note in r.stdout, r.stdout
    from ago_train.pseudo.generate import PseudoLabelDir

    d = PseudoLabelDir(out)
    assert d.meta["segmenter"]["name"] == "files" and d.meta["nonkey_sweeps"] == SWEEPS and len(d.samples()) == 3
    no_sweeps = tmp_path / "pl0"
    assert _run(["pseudo-labels", "--data", real_like, "--out", no_sweeps, "--prompts", "cw", "--grid", "20x20x4",
                 "--keyframes", "2", "--sweeps", "0"], tmp_path).code == 0
    d0 = PseudoLabelDir(no_sweeps)
    ds = NuScenesDataset(real_like, load_images=False, load_extras=False)
    gts = {t: ds[i].gt for i, t in enumerate(ds.sample_tokens)}
    more, right = [], []
    for scene, token in d.samples():
        sem, sem0 = d.labels(scene, token)[0], d0.labels(scene, token)[0]
        more.append(((sem < FREE).sum(), (sem0 < FREE).sum()))
        gt = gts[token].semantics
        agree = []
        for labels in (sem, sem0):
            both = (labels < FREE) & (gt < FREE)
            agree.append((labels[both] == gt[both]).mean())
        right.append(agree)
    print("labelled voxels (sweeps, keyframes only):", more, "agreement with GT:", right)
    # the sweeps add labelled voxels (more LiDAR returns), and the labels agree with the GT as well as before
    assert sum(a for a, _ in more) > 1.02 * sum(b for _, b in more)
    assert np.mean([a for a, _ in right]) > np.mean([b for _, b in right]) - 0.05, right


def test_a_failed_run_writes_nothing_and_the_fixed_command_runs(real_like, tmp_path):
    out = tmp_path / "pl"
    args = ["pseudo-labels", "--data", real_like, "--out", out, "--prompts", "cw", "--grid", "20x20x4",
            "--keyframes", "1", "--sweeps", "0"]
    # no label maps and not `ago synth` data: no segmenter can be chosen
    masks = real_like / "masks"
    hidden = real_like.parent / "masks_aside"
    masks.rename(hidden)
    r = _run(args, tmp_path)
    assert r.code == 2 and "--segmenter" in r.stderr and not out.exists()
    # the simulated segmenter on real data: refused at the first sample, before meta.json
    r = _run(args + ["--segmenter", "sim"], tmp_path)
    assert r.code == 2 and "simulated" in r.stderr and not out.exists(), r.stderr
    # a label map missing: named, nothing written
    hidden.rename(masks)
    victim = next((masks / "CAM_FRONT").glob("*.png"))
    moved = victim.with_suffix(".aside")
    victim.rename(moved)
    r = _run(args, tmp_path)
    assert r.code == 2 and victim.stem in r.stderr and not out.exists(), r.stderr
    moved.rename(victim)
    r = _run(args, tmp_path)                  # the corrected command: not refused as "other settings"
    assert r.code == 0, r.stderr
    assert (out / "meta.json").is_file()


def test_split_given_without_splits_json_is_refused(real_like, tmp_path):
    # train / val have a documented default without splits.json (issue 35); any other name is refused
    r = _run(["pseudo-labels", "--data", real_like, "--out", tmp_path / "pl", "--split", "test",
              "--grid", "20x20x4"], tmp_path)
    assert r.code == 2 and "splits.json" in r.stderr and not (tmp_path / "pl").exists()


def test_old_pseudo_label_folders_resume_as_before(tmp_path, synth_with_sweeps):
    """A folder written before non-key sweeps existed (meta says num_sweeps, no nonkey_sweeps) is the
    same settings as --keyframes N --sweeps 0 and resumes."""
    out = tmp_path / "pl"
    args = ["pseudo-labels", "--data", synth_with_sweeps, "--out", out, "--grid", "20x20x4", "--keyframes", "2",
            "--sweeps", "0", "--split", "all", "--limit", "1"]
    assert _run(args, tmp_path).code == 0
    meta = json.loads((out / "meta.json").read_text())
    meta["num_sweeps"] = meta.pop("num_keyframes")
    meta.pop("nonkey_sweeps")
    meta["config"]["num_sweeps"] = meta["config"].pop("num_keyframes")
    meta["config"].pop("nonkey_sweeps")
    (out / "meta.json").write_text(json.dumps(meta))
    r = _run(args[:-2], tmp_path)
    assert r.code == 0 and "2 written, 1 already there" in r.stdout, r.stdout + r.stderr
