"""`ago experiments` Tab. G and H (issue 38): the Occ3D-Waymo runs end to end on the tiny profile (a synthetic
Waymo city, its pseudo-labels, waymo/cw/ago, waymo/ow/ago, waymo/fewshot/ago/seed<s>, both seeds), the tables
beside the paper's AGO rows, the plan (names, canvas, folders) and folders made before the Waymo settings."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")

from ago_runtime.atomic import write_json  # noqa: E402
from ago_runtime.classes import OCC3D_WAYMO  # noqa: E402
from ago_runtime.errors import AgoInputError  # noqa: E402
from ago_train.experiments.driver import EXPERIMENTS, ExperimentRunner, runs_for  # noqa: E402
from ago_train.experiments.plan import ExperimentProfile, profile_differences, waymo_run  # noqa: E402
from ago_train.experiments.paper import read_paper_tables  # noqa: E402

pytestmark = pytest.mark.xdist_group("test_experiments_waymo")  # one worker builds the module fixtures (--dist loadgroup)

ENV = {**os.environ, "AGO_NO_PROGRESS": "1"}
OW_WAYMO = ["pedestrian", "road", "sidewalk", "vehicle", "bicycle", "motorcycle", "bicyclist", "sign", "traffic light",
            "pole", "construction cone", "building", "vegetation", "tree trunk"]


def ago_cli(*args: str, timeout: int = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ago_runtime.cli", *args], capture_output=True, text=True, env=ENV,
                          timeout=timeout)


@pytest.fixture(scope="module")
def waymo_experiments(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("experiments_waymo") / "exp"
    r = ago_cli("experiments", "run", "tabG", "tabH", "--profile", "tiny", "--out", str(out))
    assert r.returncode == 0, r.stderr[-2000:]
    return out


def test_list_and_plan_name_the_waymo_runs_with_a_3_to_2_canvas(tmp_path):
    r = ago_cli("experiments", "list", "--profile", "tiny", timeout=120)
    assert r.returncode == 0, r.stderr
    lines = dict(line.split(": ", 1) for line in r.stdout.splitlines() if ": " in line)
    assert lines["tabG"] == "waymo/cw/ago, waymo/cw/ago-seed1"
    assert lines["tabH"] == "waymo/ow/ago, waymo/ow/ago-seed1, waymo/fewshot/ago/seed0, waymo/fewshot/ago/seed1"
    assert {"tabG", "tabH"} <= set(EXPERIMENTS)
    few = waymo_run("fewshot", 1)
    assert few.init_from == "waymo/ow/ago-seed1" and few.dataset == "waymo" and few.prompts == "waymo/ow_waymo"
    for name, canvas in (("tiny", (96, 64)), ("cpu", (288, 192))):
        runner = ExperimentRunner(ExperimentProfile.preset(name), tmp_path / name, quiet=True)
        cfg = runner.train_config(waymo_run("ow", 1))
        assert (cfg.model.image_width, cfg.model.image_height) == canvas and canvas[0] * 2 == canvas[1] * 3
        assert cfg.prompts == "waymo/ow_waymo_pretrain" and cfg.seed == 1
        assert cfg.data == str(tmp_path / name / "synth_waymo")
        assert cfg.pseudo == str(tmp_path / name / "pseudo_waymo_ow_pretrain")
        assert cfg.loss.w_unlabelled_uniform == 0.5          # the open-world recipe, as the nuScenes ow runs
    nus = runner.train_config(runs_for("tab1", runner.profile)[0])
    assert (nus.model.image_width, nus.model.image_height) == (352, 192)   # cpu's nuScenes runs keep their canvas


def test_a_folder_made_before_the_waymo_settings_is_still_accepted(tmp_path):
    tiny = ExperimentProfile.preset("tiny")
    old = tiny.to_dict()
    del old["waymo"]
    assert profile_differences(old, tiny.to_dict()) == []
    assert profile_differences({**old, "steps": 3}, tiny.to_dict()) == ["steps"]
    changed = tiny.to_dict()
    changed["waymo"]["model"] = {"image_width": 64, "image_height": 64}
    assert profile_differences(changed, tiny.to_dict()) == ["waymo"]
    write_json(tmp_path / "profile.json", old)
    runner = ExperimentRunner(tiny, tmp_path, quiet=True)
    runner.check_profile()                                   # accepted, and the file gains the new key
    assert json.loads((tmp_path / "profile.json").read_text()) == tiny.to_dict()
    write_json(tmp_path / "profile.json", changed)
    with pytest.raises(AgoInputError, match="waymo"):
        runner.check_profile()


def _ours(rows: list[dict]) -> list[dict]:
    return [r for r in rows if not r.get("paper")]


def _in_range(v) -> bool:
    return isinstance(v, (int, float)) and 0.0 <= v <= 100.0


def test_tiny_tab_g_and_h_beside_the_papers_ago_rows(waymo_experiments):
    out = waymo_experiments
    res = json.loads((out / "results.json").read_text())
    paper = read_paper_tables()
    # only the Waymo city was made (five cameras, the Occ3D-Waymo layout), with its own pseudo-labels
    assert not (out / "synth").exists()
    assert sorted(p.name for p in (out / "synth_waymo" / "kitti_format" / "training").iterdir()) == \
        [f"image_{k}" for k in range(5)] + ["velodyne"]
    for space, classes in (("cw", list(OCC3D_WAYMO.names)), ("ow", OW_WAYMO)):
        meta = json.loads((out / f"pseudo_waymo_{space}" / "meta.json").read_text())
        assert meta["label_space"]["classes"] == classes and meta["embedder"]["name"] == "simulated"

    g = res["tables"]["tabG"]
    assert not g["missing"] and g["classes"] == list(OCC3D_WAYMO.names)
    (ours, pseudo) = _ours(g["rows"])
    assert ours["method"].startswith("ago") and pseudo["method"].startswith("pseudo-labels themselves")
    assert _in_range(ours["mIoU"]) and _in_range(ours["geometry_IoU"])
    assert _in_range(pseudo["mIoU"]) and pseudo["mIoU"] > 0     # the supervision's own score on the val frames
    assert list(ours["iou"]) == list(OCC3D_WAYMO.names)
    assert all(v is None or _in_range(v) for v in ours["iou"].values())
    assert sum(v is not None for v in ours["iou"].values()) >= 8          # classes of the val GT were scored
    assert len(ours["per_seed"]["mIoU"]) == 2 and np.isclose(np.mean(ours["per_seed"]["mIoU"]), ours["mIoU"])
    (p_row,) = [r for r in g["rows"] if r.get("paper")]
    (p_ago,) = [r for r in paper["tabG_waymo_closed_world"]["rows"] if r["method"] == "AGO (ours)"]
    assert p_row["mIoU"] == p_ago["mIoU"] == 16.02 and p_row["iou"] == {c: p_ago["iou"][c] for c in g["classes"]}

    h = res["tables"]["tabH"]
    assert not h["missing"]
    assert h["known"] == ["pedestrian", "road", "sidewalk", "vehicle", "cycle"]
    assert h["unknown"] == OW_WAYMO[4:]
    ours_h = {r["stage"]: r for r in _ours(h["rows"])}
    assert list(ours_h) == ["pretraining", "zero-shot", "few-shot"]
    for stage, r in ours_h.items():
        assert all(_in_range(r[k]) for k in ("known", "unknown", "all")), (stage, r)
        assert len(r["per_seed"]["all"]) == 2
        scored = {c for c, v in r["iou"].items() if v is not None}
        assert all(_in_range(r["iou"][c]) for c in scored)
        # pretraining scores cycle whole; the other stages bicycle and motorcycle (as the paper's columns)
        if stage == "pretraining":
            assert r["iou"]["cycle"] is not None or "cycle" not in scored
            assert r["iou"]["bicycle"] is None and r["iou"]["motorcycle"] is None
        else:
            assert r["iou"]["cycle"] is None
    papers_h = {r["stage"]: r for r in h["rows"] if r.get("paper")}
    assert [papers_h[s]["all"] for s in ours_h] == [10.01, 9.21, 12.81]
    assert papers_h["few-shot"]["unknown"] == 5.49 and papers_h["zero-shot"]["known"] == 28.87
    # the few-shot runs start from the pretraining run of their seed, on the Waymo k-shot subset
    cfg = json.loads((out / "runs" / "waymo" / "fewshot" / "ago" / "seed1" / "config.json").read_text())
    kshot = json.loads((out / "kshot" / "waymo" / "seed1.json").read_text())
    assert cfg["init_from"].endswith("waymo/ow/ago-seed1/last.pt") and cfg["frame_tokens"] == kshot["tokens"]
    assert (cfg["model"]["image_width"], cfg["model"]["image_height"]) == (96, 64)

    md = (out / "results.md").read_text()
    for text in ("## Tab. G", "## Tab. H", "paper: AGO (ours), Tab. G", "paper: AGO (ours), Tab. H",
                 "Paper, tab:selfsupervised_waymo_benchmark [Table G]",
                 "Paper, tab:open_world_waymo_benchmark [Table H]",
                 "| traffic_light |", "| construction cone |"):
        assert text in md, text
    notes = [line for line in md.splitlines() if line.startswith("What agrees and what does not")]
    assert len(notes) == 2
    assert f"our mIoU is {ours['mIoU']:.2f} against the paper's 16.02" in notes[0]     # made from the numbers
    assert "the paper's 0.97 -> 1.35 -> 5.49" in notes[1]
    assert f"ours {ours_h['pretraining']['unknown']:.2f} -> {ours_h['zero-shot']['unknown']:.2f}" in notes[1]


def test_simulated_embeddings_of_the_waymo_city_sit_nearest_their_own_class_text(waymo_experiments):
    """The simulated embedder on Occ3D-Waymo pixels: a voxel's embedding is closer to its own class text than to
    the others' on average (it embeds Waymo ids with the Waymo class texts, not the nuScenes ones)."""
    from ago_runtime.formats.datasets import open_dataset
    from ago_train.pseudo.cli import simulated_text_embeddings
    from ago_train.pseudo.generate import load_pseudo_labels, load_voxel_embeds

    text, _sky = simulated_text_embeddings("occ3d_waymo")
    pdir = waymo_experiments / "pseudo_waymo_cw"
    ds = open_dataset(waymo_experiments / "synth_waymo", load_images=False, load_extras=False)
    right, wrong, nearest = [], [], []
    for i in ds.split("train"):
        scene, token = ds.scene_of(i), ds.sample_tokens[i]
        sem, _ml, _mc = load_pseudo_labels(pdir, scene, token)
        index, e = load_voxel_embeds(pdir, scene, token)
        lab = sem.reshape(-1)[index]
        keep = lab < 15
        e = e[keep].astype(np.float64)
        s = (e / np.linalg.norm(e, axis=1, keepdims=True)) @ text.T
        own = s[np.arange(len(s)), lab[keep]]
        right.append(own)
        wrong.append((s.sum(1) - own) / 14)
        nearest.append(s.argmax(1) == lab[keep])
    right, wrong, nearest = np.concatenate(right), np.concatenate(wrong), np.concatenate(nearest)
    assert right.size > 100 and right.mean() > wrong.mean() + 0.05
    assert nearest.mean() > 0.5                       # nearest class text = its own class (chance: 1 / 15)
