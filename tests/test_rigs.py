"""Any camera rig (issue 38): a model trained for a rig of N cameras of their own sizes, through training,
export and the runtime; a frame of another rig refused, naming the camera."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from ago_runtime.errors import AgoInputError
from ago_runtime.formats.calibration import load_images_folder, save_calibration
from ago_runtime.geometry.camera import CAMERA_NAMES, Rig

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")

from ago_export.export import export_bundle, synthetic_frame  # noqa: E402
from ago_export.testing import random_checkpoint  # noqa: E402
from ago_runtime.predict.bundle import Bundle  # noqa: E402
from ago_runtime.predict.predictor import Predictor  # noqa: E402
from ago_train.synth.rigs import make_rig  # noqa: E402

pytestmark = pytest.mark.xdist_group("test_rigs")  # one worker builds the module fixtures (--dist loadgroup)

REPO = Path(__file__).resolve().parents[1]


def _ago(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "ago_runtime", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, env={**os.environ, "AGO_NO_PROGRESS": "1"})


def _write_folder(folder: Path, images: dict, rig: Rig) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for name, img in images.items():
        cv2.imwrite(str(folder / f"{name}.jpg"), np.ascontiguousarray(img[..., ::-1]))
    save_calibration(folder / "calib.json", rig)
    return folder


@pytest.fixture(scope="module")
def waymo_bundle(tmp_path_factory):
    """A random-weight tiny model for Waymo's five cameras (front three 192x128, side two 192x89), exported
    (the export's parity check runs on a synthetic frame of that rig)."""
    root = tmp_path_factory.mktemp("rigs")
    os.environ["AGO_CACHE_DIR"] = str(root / "cache")
    rig = make_rig("waymo", 192, 128)
    ckpt = random_checkpoint(root / "waymo.pt", "tiny", prompts="cw", seed=0, rig=rig)
    bundle = root / "bundle"
    meta = export_bundle(ckpt, bundle, bank_prompts=[], log=lambda s: None)
    return {"root": root, "rig": rig, "bundle": bundle, "meta": meta}


def test_bundle_carries_the_rig_with_each_cameras_input_size(waymo_bundle):
    meta = json.loads((waymo_bundle["bundle"] / "bundle.json").read_text())
    cams = meta["rig"]["cameras"]
    assert [c["name"] for c in cams] == ["FRONT", "FRONT_LEFT", "FRONT_RIGHT", "SIDE_LEFT", "SIDE_RIGHT"]
    w, h = meta["preprocess"]["width"], meta["preprocess"]["height"]
    assert [(c["width"], c["height"]) for c in cams[:3]] == [(w, h)] * 3
    side_h = int(round(89 * h / 128))
    assert [(c["width"], c["height"]) for c in cams[3:]] == [(w, side_h)] * 2 and side_h < h
    assert waymo_bundle["meta"]["parity"]["fp32"]["ok"]
    assert Bundle.load(waymo_bundle["bundle"]).rig.names == [c["name"] for c in cams]


def test_runtime_takes_the_bundles_rig_and_refuses_another(waymo_bundle, tmp_path):
    images, small, _ = synthetic_frame(waymo_bundle["rig"], seed=3)
    folder = _write_folder(tmp_path / "frame", images, small)
    imgs, rig, _ = load_images_folder(folder, names=Bundle.load(waymo_bundle["bundle"]).rig.names)
    pred = Predictor(waymo_bundle["bundle"], warm_up=False).predict(imgs, rig)
    assert pred.semantics.shape == tuple(json.loads((waymo_bundle["bundle"] / "bundle.json").read_text())["grid"]["shape"])
    # the same frame with its cameras listed in another order in calib.json gives the same labels
    shuffled = Rig([small[n] for n in reversed(small.names)])
    pred2 = Predictor(waymo_bundle["bundle"], warm_up=False).predict(imgs, shuffled)
    assert np.array_equal(pred.semantics, pred2.semantics)
    # a nuScenes frame: refused, naming a camera of the bundle's rig it lacks
    nus_images, nus_rig, _ = synthetic_frame(Rig.nuscenes_like(160, 90))
    with pytest.raises(AgoInputError, match="camera FRONT:"):
        Predictor(waymo_bundle["bundle"], warm_up=False).predict(nus_images, nus_rig)
    # ago infer on a folder missing a side camera: one line naming it, exit 2, nothing written
    (folder / "SIDE_RIGHT.jpg").unlink()
    out = _ago("infer", "--bundle", waymo_bundle["bundle"], "--images", folder, "--out", tmp_path / "pred")
    assert out.returncode == 2 and "SIDE_RIGHT" in out.stderr and out.stderr.startswith("error: ")
    assert not (tmp_path / "pred").exists()
    # a calib.json with a camera the bundle's rig lacks
    save_calibration(folder / "calib.json", Rig(list(small) + [small["FRONT"].__class__(
        "REAR", small["FRONT"].intrinsics, small["FRONT"].cam2ego, small["FRONT"].width, small["FRONT"].height)]))
    with pytest.raises(AgoInputError, match="camera REAR: not a camera of the model's rig"):
        load_images_folder(folder, names=small.names)


@pytest.fixture(scope="module")
def front_run(tmp_path_factory):
    """`ago synth --rig front --layout nuscenes` -> pseudo-labels -> `ago train` (tiny preset): the model's camera
    count comes from the data."""
    root = tmp_path_factory.mktemp("front")
    os.environ["AGO_CACHE_DIR"] = str(root / "cache")
    data, pl, run = root / "synth", root / "pl", root / "run"
    for args in (("synth", "--out", data, "--scenes", 2, "--frames", 2, "--rig", "front", "--layout", "nuscenes",
                  "--image-size", "160x106", "--grid", "20x20x4"),
                 ("pseudo-labels", "--data", data, "--out", pl, "--prompts", "cw", "--grid", "20x20x4"),
                 ("train", "--config", "tiny", "--data", data, "--pseudo", pl, "--out", run, "--prompts", "cw",
                  "--set", "max_steps=2")):
        out = _ago(*args)
        assert out.returncode == 0, out.stderr[-2000:]
    return {"root": root, "data": data, "run": run, "train_log": out.stderr}


def test_a_front_camera_rig_trains_and_records_its_rig(front_run):
    from ago_train.checkpoint import CheckpointContract

    ckpt = CheckpointContract.load(front_run["run"] / "last.pt")
    assert ckpt.model_config.num_cameras == 1 and ckpt.camera_names == ["FRONT"]
    assert "model.num_cameras 6 -> 1" in front_run["train_log"]
    bundle = front_run["root"] / "bundle"
    out = _ago("export", front_run["run"] / "last.pt", "-o", bundle)
    assert out.returncode == 0, out.stderr[-2000:]
    out = _ago("infer", "--bundle", bundle, "--images", front_run["data"], "--out", front_run["root"] / "pred",
               "--picture", "none")
    assert out.returncode == 0, out.stderr[-2000:]
    assert len(list((front_run["root"] / "pred").glob("*.npz"))) == 4


def test_eval_refuses_data_of_another_rig(front_run, tmp_path):
    nus = tmp_path / "nus"
    out = _ago("synth", "--out", nus, "--scenes", 1, "--frames", 1, "--image-size", "160x90", "--grid", "20x20x4")
    assert out.returncode == 0, out.stderr
    out = _ago("eval", "--ckpt", front_run["run"] / "last.pt", "--data", nus, "--split", "all",
               "--out", tmp_path / "ev")
    assert out.returncode == 2 and "camera FRONT: the model's rig takes it" in out.stderr, out.stderr
    assert not (tmp_path / "ev").exists()
