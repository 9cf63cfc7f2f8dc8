"""`ago experiments`: the driver end to end on the tiny profile (data -> runs -> views -> tables -> figures),
its cache (a second call trains and scores nothing), resuming a half-finished run, and refusing a folder
made with another profile."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")

from ago_runtime.errors import AgoInputError  # noqa: E402
from ago_train.experiments.driver import EXPERIMENTS, ExperimentRunner, runs_for, views_for  # noqa: E402
from ago_train.experiments.plan import ExperimentProfile, cw_run, fewshot_run, ow_run  # noqa: E402

pytestmark = pytest.mark.xdist_group("test_experiments")  # one worker builds the module fixtures (--dist loadgroup)

ENV = {**os.environ, "AGO_NO_PROGRESS": "1"}


@pytest.fixture(scope="module")
def tiny_experiments(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("experiments") / "exp"
    # the nuScenes-layout experiments (tabG / tabH on the Waymo city: tests/test_experiments_waymo.py)
    nuscenes = [e for e in EXPERIMENTS if e not in ("tabG", "tabH")]
    r = subprocess.run([sys.executable, "-m", "ago_runtime.cli", "experiments", "run", *nuscenes, "--profile", "tiny",
                        "--out", str(out)], capture_output=True, text=True, env=ENV, timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    return out


def test_plan_names_every_run_once_and_views_match_the_method():
    p = ExperimentProfile.preset("cpu")
    names = [s.name for e in EXPERIMENTS for s in runs_for(e, p)]
    assert "cw/ago" in names and "ow/ago-adapter3" in names and "fewshot/grounding/seed1" in names
    assert cw_run("ago", use_noise=False, use_occ=False).name == "cw/ago-no-noise-no-occ"
    assert ow_run("ago", adapter_depth=2).name == "ow/ago" and ow_run("ago", align_loss="l1").name == "ow/ago-l1"
    # seeds: every cw / ow run once per seed (seed 0 keeps the plain name), few-shot s starts from pretraining s
    assert fewshot_run("align", 0).init_from == "ow/align" and fewshot_run("align", 1).init_from == "ow/align-seed1"
    assert {"cw/ago", "cw/ago-seed1", "ow/ago-adapter3-seed1", "cw/ago-no-noise-no-occ-seed1"} <= set(names)
    assert cw_run("ago", seed=1).seed == 1 and ow_run("ago", seed=1).name == "ow/ago-seed1"
    assert len(set(names)) == 38 + 6 and p.seeds == (0, 1)   # + tabG / tabH: waymo/{cw,ow,fewshot} x 2 seeds
    # the closed-world classifier is the grounding run scored without the unknown classes' phrases
    assert any(v.closed_set for v in views_for(ow_run("grounding"), "ow.txt"))
    assert {v.identifier for v in views_for(ow_run("ago"), "ow.txt")} == {"none", "max-conf", "min-entropy", "adapted"}
    with pytest.raises(AgoInputError):
        runs_for("tab9", p)


def test_seed_means_keep_each_value_and_the_spread_note_says_what_is_apart(tmp_path):
    from ago_train.experiments.collect import SeedMean, fmt, views
    from ago_train.experiments.tables import spread_note
    from ago_runtime.atomic import write_json

    for name, known in (("ow/ago", 10.0), ("ow/ago-seed1", 12.0)):
        write_json(tmp_path / "runs" / name / "views.json",
                   {"views": {"ow-none": {"mIoU": known, "subsets": {"known": known, "unknown": None}}},
                    "stats": {"classes": ["a"]}})
    missing = []
    v = views(tmp_path, "ow/ago", (0, 1, 2), missing)
    m = v["views"]["ow-none"]["mIoU"]
    assert isinstance(m, SeedMean) and m == 11.0 and m.values == [10.0, 12.0]
    assert missing == ["ow/ago-seed2"] and v["views"]["ow-none"]["subsets"]["unknown"] is None
    assert fmt(m) == "11.00 (10.00, 12.00)" and fmt(None) == "–" and fmt(3.0) == "3.00"
    rows = [{"n": "ref", "x": SeedMean([10.0, 11.0])}, {"n": "far", "x": SeedMean([13.0, 14.0])},
            {"n": "near", "x": SeedMean([10.5, 12.0])}]
    note = " ".join(spread_note(rows, "x", lambda r: r["n"], rows[0], "mIoU"))
    assert "above the spread (the seeds' ranges do not overlap): far +3.00" in note
    assert "Within the spread: near +0.75" in note
    assert spread_note([{"n": "a", "x": 1.0}], "x", lambda r: r["n"], {"n": "a", "x": 1.0}, "m") == []


def test_open_world_runs_get_the_open_world_recipe_and_closed_world_runs_do_not(tmp_path):
    from ago_train.experiments.plan import OW_RECIPE

    runner = ExperimentRunner(ExperimentProfile.preset("cpu"), tmp_path, quiet=True)
    ow = runner.train_config(ow_run("ago", seed=1))
    assert ow.loss.w_unlabelled_uniform == 0.5 and ow.loss.occ_unlabelled_weight == 4.0 and ow.loss.align_center
    assert ow.seed == 1 and ow.max_steps == 1000
    cw = runner.train_config(cw_run("ago"))
    assert cw.loss.w_unlabelled_uniform == 0.0 and cw.loss.occ_unlabelled_weight == 1.0
    full = ExperimentProfile.preset("full")
    assert full.ow_loss == {} and OW_RECIPE["w_unlabelled_uniform"] == 0.5   # the paper's losses on GPU


def test_tiny_profile_end_to_end(tiny_experiments):
    out = tiny_experiments
    res = json.loads((out / "results.json").read_text())
    t = res["tables"]
    # every table is complete (nothing missing) and holds numbers
    for key in ("tab2", "tab3", "tab4", "tab5", "supp"):
        assert not t[key].get("missing"), (key, t[key].get("missing"))
    assert t["tab1"]["rows"][0]["mIoU"] is not None
    pseudo_row = [r for r in t["tab1"]["rows"] if r["method"].startswith("pseudo-labels")][0]
    assert 0 < pseudo_row["mIoU"] <= 100          # the pseudo-labels' own score on the val frames
    assert len(t["tab3"]["rows"]) == 4 and len(t["tab5"]["rows"]) == 4
    assert [r["adapter_layers"] for r in t["supp"]["depth"]] == [1, 2, 3, 4]
    closed = [r for r in t["tab2"]["rows"] if r["method"].startswith("closed-world")][0]
    assert closed["unknown"] in (0.0, None)       # it cannot predict unknown classes
    # views.json of the ago open-world run: 4 identifiers + figure statistics
    v = json.loads((out / "runs" / "ow" / "ago" / "views.json").read_text())
    assert {"ow-none", "ow-max-conf", "ow-min-entropy", "ow-adapted", "ow-min-entropy-x10"} <= set(v["views"])
    s = v["stats"]
    assert len(s["entropy_main"]) == len(s["classes"]) == 15 and np.array(s["cos_main"]).shape == (15, 15)
    # the few-shot subset was recorded and used
    kshot = json.loads((out / "kshot" / "seed0.json").read_text())
    cfg = json.loads((out / "runs" / "fewshot" / "ago" / "seed0" / "config.json").read_text())
    assert cfg["frame_tokens"] == kshot["tokens"] and cfg["init_from"].endswith("ow/ago/last.pt")
    for png in ("entropy_per_class.png", "modality_gap.png", "voxel_renders.png"):
        assert (out / "figures" / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    md = (out / "results.md").read_text()
    assert "Tab. 4" in md and "min entropy" in md
    # Tab. I: per-class rows for 4 paradigms zero-shot (+2 more identifiers for ago) and 3 variants few-shot
    ti = t["tabI"]
    assert not ti["missing"] and len(ti["rows"]) == 6 + 5
    assert {r["stage"] for r in ti["rows"]} == {"zero-shot", "1-shot"}
    ago_zs = [r for r in ti["rows"] if r["stage"] == "zero-shot" and r["paper_method"] == "AGO (Tab. 2)"][0]
    tab2_ago = [r for r in t["tab2"]["rows"] if r["stage"] == "zero-shot" and r["method"].startswith("AGO")][0]
    assert ago_zs["unknown"] == tab2_ago["unknown"] and len(ago_zs["iou"]) == 16   # 15 classes + free
    assert "## Tab. I" in md and "tab:detailed_open_world_exp" in md
    # two seeds: each run twice, cells "mean (a, b)", results.json keeps both values, a seed-spread line
    assert (out / "runs" / "cw" / "ago-seed1" / "done.json").is_file()
    row = t["tab3"]["rows"][0]
    assert len(row["per_seed"]["cw_mIoU"]) == 2 and abs(np.mean(row["per_seed"]["cw_mIoU"]) - row["cw_mIoU"]) < 1e-6
    assert "Seed spread (closed-world mIoU" in md
    # each few-shot run trains right after its pretraining run (whose checkpoint it starts from)
    trained = [ln.split(" train ", 1)[1] for ln in (out / "driver.log").read_text().splitlines() if " train " in ln]
    assert trained.index("fewshot/align/seed0") == trained.index("ow/align") + 1
    assert trained.index("fewshot/ago/seed1") == trained.index("ow/ago-seed1") + 1


def test_second_run_reuses_everything_and_a_half_run_resumes(tiny_experiments):
    out = tiny_experiments
    runner = ExperimentRunner(ExperimentProfile.preset("tiny"), out, quiet=True)
    before = (out / "driver.log").read_text().count("\n")
    runner.run(["tab1", "tab5"])
    new = (out / "driver.log").read_text().splitlines()[before:]
    assert not any(" train " in ln or " score " in ln or "$ ago" in ln for ln in new), new
    # a run whose folder has a checkpoint but no done.json resumes (and is then marked done)
    spec = cw_run("ago", use_occ=False)
    (out / "runs" / spec.name / "done.json").unlink()
    (out / "runs" / spec.name / "views.json").unlink()
    runner.run(["tab5"])
    log = (out / "driver.log").read_text()
    assert f"train {spec.name} (resume)" in log
    assert (out / "runs" / spec.name / "done.json").is_file()


def test_another_profile_in_the_same_folder_is_refused(tiny_experiments):
    p = ExperimentProfile.preset("tiny")
    p.steps = 3
    with pytest.raises(AgoInputError, match="another profile"):
        ExperimentRunner(p, tiny_experiments, quiet=True).run(["tab1"])


def test_run_records_carry_finished_runs_to_another_folder_and_a_changed_recipe_retrains(tiny_experiments, tmp_path):
    import shutil

    out, rec = tiny_experiments, tmp_path / "records"
    tiny = ExperimentProfile.preset("tiny")
    ExperimentRunner(tiny, out, quiet=True, records=rec).run(["tab5"])     # all reused; records written
    names = [s.name for s in runs_for("tab5", tiny)]
    assert all((rec / "runs" / n / "views.json").is_file() and (rec / "runs" / n / "recipe.json").is_file()
               for n in names)
    assert not any(p.name.startswith(".") for p in (rec / "runs" / "cw").iterdir())   # no half-written record

    def fresh_folder(name: str) -> Path:   # another machine: same profile and data, no runs, no checkpoints
        new = tmp_path / name
        new.mkdir()
        for d in ("synth", "pseudo_cw"):
            shutil.copytree(out / d, new / d)
        shutil.copyfile(out / "profile.json", new / "profile.json")
        return new

    other = fresh_folder("other")
    ExperimentRunner(tiny, other, quiet=True, records=rec).run(["tab5"])
    log = (other / "driver.log").read_text()
    assert f"reused {len(names)} run record(s)" in log and " train " not in log, log
    for n in names:
        assert json.loads((other / "runs" / n / "views.json").read_text()) == \
            json.loads((out / "runs" / n / "views.json").read_text())
    assert not (other / "runs" / "cw" / "ago" / "last.pt").exists()
    assert "Tab. 5" in (other / "results.md").read_text()

    # a record whose recipe is not today's is not reused: that run trains again (and its record is replaced)
    r = json.loads((rec / "runs" / "cw" / "ago" / "recipe.json").read_text())
    r["lr"] = r["lr"] * 2
    (rec / "runs" / "cw" / "ago" / "recipe.json").write_text(json.dumps(r))
    third = fresh_folder("third")
    ExperimentRunner(tiny, third, quiet=True, records=rec).run(["tab5"])
    log = (third / "driver.log").read_text()
    assert "record cw/ago not reused: its recipe differs in ['lr']" in log and "train cw/ago\n" in log + "\n"
    assert f"reused {len(names) - 1} run record(s)" in log
    assert json.loads((rec / "runs" / "cw" / "ago" / "recipe.json").read_text())["lr"] == r["lr"] / 2

    # records of another profile are refused before any work; records of other data once the data is there
    steps3 = ExperimentProfile.preset("tiny")
    steps3.steps = 3
    with pytest.raises(AgoInputError, match="another profile"):
        ExperimentRunner(steps3, tmp_path / "never", quiet=True, records=rec).run(["tab5"])
    assert not (tmp_path / "never" / "synth").exists()
    head = json.loads((rec / "records.json").read_text())
    (rec / "records.json").write_text(json.dumps({**head, "data": "0" * 64}))
    with pytest.raises(AgoInputError, match="other data"):
        ExperimentRunner(tiny, fresh_folder("fourth"), quiet=True, records=rec).run(["tab5"])
