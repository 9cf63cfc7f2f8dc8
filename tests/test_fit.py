"""Does the `full` preset's structure keep its voxel features apart? (issue: "The paper's configuration learns")

A small copy of the `full` preset's structure - ImageNet EfficientNet with stages 2-3 trained, a trained FPN,
a two-layer decoder, the loss on the whole grid - on three synthetic frames of a 100x100x8 grid, where
free space outnumbers occupied voxels about 5 to 1, trained 48 steps through the trainer's own loop.
With the `full` preset's optimiser settings (backbone and FPN at 0.1x the learning rate, the free score's
bias started at the data's prior) the features keep their spread; with the old ones (everything at 1e-3,
no free bias) the spread falls to ~0.015 by step 12 and every voxel is free (docs/training.md, "Does it
learn?"), and this test fails. A second test fails for a model that calls every voxel free whatever its
features (`check_not_all_free`: the free share of the last logged batch must stay under 0.99). Started at the
data's prior, the free score wins every voxel at first (free share 1.0 through step ~24); this run leaves that by
step ~28 (about 0.95 at step 48), which is why it trains 48 steps and not 12 (issue 46).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

pytestmark = pytest.mark.xdist_group("test_fit")  # one worker builds the module fixtures (--dist loadgroup)

REPO = Path(__file__).resolve().parents[1]
GRID = '{"range_min": [-40.0, -40.0, -1.0], "range_max": [40.0, 40.0, 5.4], "voxel_size": [0.8, 0.8, 0.8], ' \
       '"shape": [100, 100, 8]}'


def _ago(*args: str) -> None:
    env = dict(os.environ, AGO_NO_PROGRESS="1")
    r = subprocess.run([sys.executable, "-m", "ago_runtime.cli", *args], cwd=REPO, env=env, capture_output=True,
                       text=True)
    assert r.returncode == 0, r.stderr


@pytest.fixture(scope="module")
def fit_log(tmp_path_factory) -> list[dict]:
    """The log.jsonl rows of the small `full`-structure run (see the module doc), trained once for both tests."""
    from ago_train.train_config import TrainConfig
    from ago_train.trainer import Trainer

    tmp_path = tmp_path_factory.mktemp("fit")
    data, pseudo = tmp_path / "synth", tmp_path / "pseudo"
    _ago("synth", "--out", str(data), "--scenes", "1", "--frames", "3", "--image-size", "192x128",
         "--grid", "100x100x8", "--seed", "3", "--val-fraction", "0")
    _ago("pseudo-labels", "--data", str(data), "--out", str(pseudo), "--prompts", "cw", "--grid", "100x100x8",
         "--split", "all", "--embedder", "sim", "--keyframes", "3", "--interval", "1")
    full = TrainConfig.preset("full")
    cfg = TrainConfig.preset("tiny").with_overrides([
        f"data={data}", f"pseudo={pseudo}", f"out={tmp_path / 'run'}", "train_split=all", "device=cpu",
        "max_steps=48", "epochs=16", "log_every=4", "warmup_steps=2", "noise_words=100", "train_voxels=0",
        f"model.grid={GRID}", "model.tpv_h=25", "model.tpv_w=25", "model.backbone=efficientnet_lite0",
        "model.pretrained=true", "model.frozen_stages=1", "model.decoder_layers=2", "model.hidden_dim=64",
        f"lr={full.lr}", f"backbone_lr_mult={full.backbone_lr_mult}", f"fpn_lr_mult={full.fpn_lr_mult}",
        f"model.free_bias={json.dumps(full.model.free_bias)}"])
    Trainer(cfg, quiet=True).run()
    return [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]


def test_full_structure_keeps_its_feature_spread(fit_log):
    check_spread(fit_log)


def test_full_structure_is_not_all_free(fit_log):
    check_not_all_free(fit_log)


def check_spread(rows: list[dict]) -> None:
    """AssertionError when the logged batches' voxel features collapse (spread <= 0.05)."""
    spreads = [r["feat_spread"] for r in rows if "feat_spread" in r]
    assert len(spreads) >= 2
    assert min(spreads) > 0.05, f"voxel features collapse: spread per 4 steps {spreads}"


def check_not_all_free(rows: list[dict]) -> None:
    """AssertionError when the last logged batch calls (almost) every voxel free (free share >= 0.99)."""
    free = [r["free_share"] for r in rows if "free_share" in r]
    assert len(free) >= 2
    assert free[-1] < 0.99, f"the model calls (almost) every voxel free: free share per 4 steps {free}"


def test_the_checks_fail_for_an_all_free_or_collapsed_model():
    with pytest.raises(AssertionError, match="every voxel free"):
        check_not_all_free([{"step": s, "feat_spread": 0.3, "free_share": 1.0} for s in (4, 8, 12)])
    with pytest.raises(AssertionError, match="collapse"):
        check_spread([{"step": s, "feat_spread": 0.01, "free_share": 0.8} for s in (4, 8, 12)])
    good = [{"step": s, "feat_spread": 0.3, "free_share": 0.85} for s in (4, 8, 12)]
    check_spread(good)
    check_not_all_free(good)
