"""The real chain's honest recipe selection (issue 35): the train/val cut of a one-scene dataroot
(ago_runtime/formats/nuscenes_cut.py, run by `python -m benchmarks.dataroot_cut`) and the declared selection
rule of benchmarks/real_chain_select.py (imported as the `benchmarks` package: the suite runs from the
repository root, `python -m pytest`). Tests on ../shared skip when it is absent."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import shared_path

from ago_runtime.errors import AgoInputError
from ago_runtime.formats.nuscenes_cut import cut_dataroot
from benchmarks.real_chain_select import pick

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def cut(tmp_path_factory):
    src = shared_path("nuscenes-scene")
    dst = tmp_path_factory.mktemp("cut") / "data"
    return src, dst, cut_dataroot(src, dst, 22, 8)


def test_cut_splits_the_first_keyframes_into_two_scenes(cut):
    from ago_runtime.formats.nuscenes import NuScenesDataset

    src, dst, record = cut
    full = NuScenesDataset(src, load_images=False, load_extras=False)
    part = NuScenesDataset(dst, load_images=False, load_extras=False)
    assert part.sample_tokens == full.sample_tokens[:30]          # the first 30, in time order
    train, val = part.split("train"), part.split("val")
    assert [part.sample_tokens[i] for i in train] == full.sample_tokens[:22] == record["train_tokens"]
    assert [part.sample_tokens[i] for i in val] == full.sample_tokens[22:30] == record["val_tokens"]
    # superimposing neighbours never crosses the cut: the last train frame's are all train frames
    assert set(part.neighbours(train[-1], 9, 1)) <= set(train)
    assert set(part.neighbours(val[0], 7, 1)) <= set(val)
    # the frame data is the source's (same LiDAR file, same pose)
    a, b = full[21], part[train[-1]]
    assert a.token == b.token and (a.ego2global == b.ego2global).all()


def test_cut_keeps_only_the_chosen_keyframes_boxes(cut):
    src, dst, _ = cut
    kept = {r["token"] for r in json.loads((dst / "v1.0-mini" / "sample.json").read_text())}
    boxes = json.loads((dst / "v1.0-mini" / "sample_annotation.json").read_text())
    assert boxes and {b["sample_token"] for b in boxes} <= kept
    all_tokens = {b["token"] for b in boxes}
    assert all(b["next"] in all_tokens or b["next"] == "" for b in boxes)


def test_cut_is_reused_or_refused(cut, tmp_path):
    src, dst, record = cut
    assert cut_dataroot(src, dst, 22, 8) == record                  # same cut: reused
    with pytest.raises(AgoInputError, match="not a cut"):
        cut_dataroot(src, dst, 30, 11)
    with pytest.raises(AgoInputError, match="41"):
        cut_dataroot(src, tmp_path / "x", 40, 5)
    assert not (tmp_path / "x").exists()
    r = subprocess.run([sys.executable, "-m", "benchmarks.dataroot_cut", str(src), str(tmp_path / "y"),
                        "--train", "0", "--val", "3"], capture_output=True, text=True, cwd=REPO,
                       env={**os.environ, "PYTHONPATH": str(REPO)})
    assert r.returncode == 2 and r.stderr.strip().startswith("error: --train/--val") and len(r.stderr.splitlines()) == 1


def _run(median, hits, seen_free, synth=(2.0, 70.0, 10.0)):
    wins = {"depth_error_median_m": median < synth[0], "lidar_hits_in_occupied_pct": hits > synth[1],
            "occupied_seen_free_pct": seen_free < synth[2]}
    return {"results": {"real": {"depth_error_median_m": median}}, "wins": wins, "target_met": all(wins.values())}


def test_rule_picks_the_passing_recipe_with_the_lowest_depth_error():
    runs = {1: _run(1.5, 65.0, 6.0), 3: _run(1.9, 72.0, 9.0), 10: _run(1.8, 75.0, 9.5)}
    assert pick(runs) == 10                 # 3 and 10 pass; 10 has the lower median; 1 (lowest) fails hits


def test_rule_without_a_passing_recipe_counts_wins_then_depth_error():
    runs = {1: _run(1.5, 65.0, 11.0), 3: _run(1.9, 72.0, 12.0), 10: _run(1.8, 75.0, 12.0)}
    assert pick(runs) == 10                 # 3 and 10 win 2 of 3; 1 wins 1; tie -> lower median
    runs = {1: _run(1.8, 75.0, 12.0), 10: _run(1.8, 75.0, 12.0)}
    assert pick(runs) == 1                  # full tie -> fewer keyframes


def test_report_says_incomplete_and_picks_nothing_until_every_candidate_ran():
    import argparse

    from benchmarks.real_chain import MEASURES
    from benchmarks.real_chain_select import report

    def run(median):
        r = _run(median, 65.0, 6.0)
        values = {key: 1.0 for key, _, _ in MEASURES}
        r["results"] = {"real": {**values, "depth_error_median_m": median}, "synthetic": values}
        r["stages"] = [{"stage": "train", "seconds": 1.0, "peak_rss_mb": 2, "note": "resumed"}]
        return r

    args = argparse.Namespace(data="D", steps=2000)
    text = report(args, "cmd", [1, 3], {1: run(1.5)}, None, None)
    assert "Status: incomplete" in text and "not finished: keyframes 3" in text
    assert "Picked by the rule" not in text and "## Test" not in text and "| resumed |" in text


def test_benchmarks_refuse_a_run_trained_otherwise(tmp_path, capsys):
    """benchmarks/run_settings.check_reuse (fit_check.py, real_chain.py): a run folder whose config.json differs
    from the asked settings is one error line and exit 2, not reused; the same settings pass."""
    pytest.importorskip("torch")
    from benchmarks.run_settings import asked_config, check_reuse, trained_settings

    run = tmp_path / "run"
    run.mkdir()
    check_reuse(run, asked_config("tiny", ["max_steps=20"]))             # nothing there yet: nothing to refuse
    asked_config("tiny", ["max_steps=20", f"out={run}"]).save(run / "config.json")
    check_reuse(run, asked_config("tiny", ["max_steps=20", f"out={run}"]))
    with pytest.raises(SystemExit) as e:
        check_reuse(run, asked_config("tiny", ["max_steps=40", f"out={run}"]))
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {run / 'config.json'}: ") and "max_steps was 20, asked 40" in err[0]
    assert "max_steps=20" in trained_settings(run, "tiny") and f"out={json.dumps(str(run))}" in trained_settings(run, "tiny")
