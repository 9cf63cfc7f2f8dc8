"""The checkpoint contract (ago_train/checkpoint.py, issue 50): one writer, one reader, what is written is read.

- a checkpoint of the trainer and one of `random_checkpoint` round-trip to an equal contract, and the file holds
  exactly `to_payload()`;
- the keys written are the keys declared (PAYLOAD_KEYS, the dataclass fields), and the trainer writes every one
  of the version-1 layout (the keys `ago train` wrote at b3080d8, frozen here: the shipped default model's);
- an older, newer or foreign checkpoint, or one with an undeclared key, gets one error line from `ago export`;
- no module outside ago_train/checkpoint.py indexes a checkpoint by its keys.
"""

from __future__ import annotations

import dataclasses
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from ago_export.testing import random_checkpoint  # noqa: E402
from ago_train.checkpoint import (DERIVED_KEYS, PAYLOAD_KEYS, BankRecord, CalibrationRecord,  # noqa: E402
                                  CheckpointContract, LabelSpaceRecord, TrainingState)

pytestmark = pytest.mark.xdist_group("test_checkpoint_contract")  # one worker builds the module fixtures (--dist loadgroup)

REPO = Path(__file__).resolve().parents[1]
# the top-level keys `ago train` wrote at b3080d8 (last.pt of the shipped default model): the layout stays readable
V1_TRAINER_KEYS = {"format", "version", "model", "optimizer", "scheduler", "step", "epoch", "total_steps",
                   "world_size", "rng", "model_config", "train_config", "loss_config", "label_space", "bank",
                   "preprocess", "rig", "align_center", "calibration"}
V1_LABEL_SPACE_KEYS = {"name", "prompt_file", "prompt_text", "class_names", "num_classes", "known"}
V1_BANK_KEYS = {"encoder_id", "encoder_hash", "encoder_variant", "embeddings", "phrase_class", "class_names"}
# where each contract field is written (a sub-record's fields are its record's keys)
FIELD_KEYS = {"training": {"optimizer", "scheduler", "rng"}}


def same(a, b, where="payload") -> None:
    """a == b, recursively, tensors by dtype and value."""
    if isinstance(a, torch.Tensor) or isinstance(b, torch.Tensor):
        assert isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor), where
        assert a.dtype == b.dtype and a.shape == b.shape and torch.equal(a, b), where
    elif isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), (where, set(a) ^ set(b))
        for k in a:
            same(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, (list, tuple)):
        assert isinstance(b, (list, tuple)) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            same(x, y, f"{where}[{i}]")
    else:
        assert type(a) is type(b) and a == b, (where, a, b)


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> dict:
    """A trainer's last.pt (with calibration and align_center) and model-only snapshot, 2 steps of the tiny preset."""
    from ago_train.train_config import TrainConfig
    from ago_train.trainer import Trainer

    root = tmp_path_factory.mktemp("ckpt_contract")
    env = dict(os.environ, AGO_NO_PROGRESS="1", OMP_NUM_THREADS="1", PYTHONPATH=str(REPO))
    data, pseudo = root / "synth", root / "pseudo"
    for args in (["synth", "--out", data, "--scenes", "1", "--frames", "2", "--image-size", "192x128", "--grid",
                  "20x20x4", "--seed", "3"],
                 ["pseudo-labels", "--data", data, "--out", pseudo, "--prompts", "cw", "--grid", "20x20x4",
                  "--split", "all", "--embedder", "sim", "--keyframes", "2"]):
        subprocess.run([sys.executable, "-m", "ago_runtime.cli", *map(str, args)], check=True, env=env,
                       capture_output=True, cwd=REPO)
    d = TrainConfig.preset("tiny").to_dict()
    d.update(data=str(data), pseudo=str(pseudo), out=str(root / "run"), train_split="all", device="cpu",
             max_steps=2, snapshot_steps=[1])
    d["loss"]["align_center"] = True   # every optional field set: the checkpoint holds every key of the layout
    trainer = Trainer(TrainConfig.from_dict(d), quiet=True)
    trainer.run()
    return {"root": root, "trainer": trainer, "last": root / "run" / "last.pt",
            "snapshot": root / "run" / "snapshots" / "step_000001.pt"}


def test_a_trainer_checkpoint_round_trips_and_the_file_is_the_payload(trained):
    ckpt = CheckpointContract.load(trained["last"])
    assert ckpt.training is not None and ckpt.calibration is not None and ckpt.rig is not None and ckpt.step == 2
    raw = torch.load(trained["last"], weights_only=True)
    assert set(raw) == V1_TRAINER_KEYS   # the trainer writes every key of the version-1 layout, no other
    same({k: v for k, v in raw.items() if v is not None}, ckpt.to_payload())   # what is written is what is read
    again = CheckpointContract.from_payload(ckpt.to_payload(), "again")
    same(again.to_payload(), ckpt.to_payload())
    # the contract the trainer builds is the one read back (its last step's, re-made: same weights and records)
    built = trained["trainer"].checkpoint_contract(epoch=ckpt.epoch)
    built = dataclasses.replace(built, training=dataclasses.replace(built.training, rng=ckpt.training.rng))
    same(built.to_payload(), ckpt.to_payload())
    snap = CheckpointContract.load(trained["snapshot"])
    assert snap.training is None and snap.step == 1
    assert not {"optimizer", "scheduler", "rng"} & set(torch.load(trained["snapshot"], weights_only=True))


def test_a_random_checkpoint_round_trips(tmp_path):
    path = random_checkpoint(tmp_path / "r.pt", "tiny", prompts="cw", seed=1)
    ckpt = CheckpointContract.load(path)
    assert ckpt.training is None and ckpt.rig is None and ckpt.bank.encoder_variant   # the encoder's variant
    same(torch.load(path, weights_only=True), ckpt.to_payload())
    same(CheckpointContract.from_payload(ckpt.to_payload(), "x").to_payload(), ckpt.to_payload())


def test_written_keys_are_the_declared_keys(trained):
    """Every key to_payload writes is declared (PAYLOAD_KEYS) and every declared field is written: each contract
    field under its own key (or FIELD_KEYS'), the sub-records' fields under theirs, the derived keys besides."""
    full = CheckpointContract.load(trained["last"])
    payload = full.to_payload()
    assert set(payload) == set(PAYLOAD_KEYS)
    fields = {f.name for f in dataclasses.fields(CheckpointContract)}
    written = set()
    for name in fields:
        written |= FIELD_KEYS.get(name, {name})
    assert written | set(DERIVED_KEYS) == set(PAYLOAD_KEYS), set(PAYLOAD_KEYS) ^ (written | set(DERIVED_KEYS))
    assert not written & set(DERIVED_KEYS)   # a derived key is never also a stored field
    for record, cls in (("label_space", LabelSpaceRecord), ("bank", BankRecord), ("calibration", CalibrationRecord)):
        declared = {f.name for f in dataclasses.fields(cls) if f.init}
        assert set(payload[record]) <= declared, (record, set(payload[record]) - declared)
    assert set(payload["bank"]) == V1_BANK_KEYS == {f.name for f in dataclasses.fields(BankRecord)}
    assert set(payload["label_space"]) == V1_LABEL_SPACE_KEYS   # + class_table for a table other than nuScenes'
    assert set(payload["calibration"]) == {f.name for f in dataclasses.fields(CalibrationRecord)}   # a full fit
    assert {f.name for f in dataclasses.fields(TrainingState)} == FIELD_KEYS["training"]


@pytest.mark.parametrize("change, words", [
    (lambda p: p.update(extra=1), ["'extra'", "not in the version-1 layout"]),
    (lambda p: p["bank"].update(extra=1), ["bank: unknown fields", "'extra'"]),
    (lambda p: p.update(version=2), ["version 2 is newer", "upgrade ago"]),
    (lambda p: p.update(version=0), ["version 0 is not one this ago reads", "train it again"]),
    (lambda p: p.pop("version"), ["version None is not one this ago reads"]),
    (lambda p: p.update(format="other"), ["not an ago checkpoint"]),
    (lambda p: p.pop("bank"), ["lacks 'bank'"]),
    (lambda p: p["bank"].update(embeddings=p["bank"]["embeddings"][:, :10]), ["bank.embeddings", "float32"]),
    (lambda p: p["label_space"].update(num_classes=3), ["num_classes 3"]),
    (lambda p: p.update(preprocess={**p["preprocess"], "width": 7}), ["preprocess differs"]),
])
def test_older_newer_foreign_or_undeclared_checkpoints_get_one_error_line(tmp_path, change, words):
    good = random_checkpoint(tmp_path / "good.pt", "tiny", prompts="cw", seed=1)
    payload = torch.load(good, weights_only=True)
    change(payload)
    torch.save(payload, tmp_path / "bad.pt")
    env = dict(os.environ, AGO_NO_PROGRESS="1", PYTHONPATH=str(REPO))
    r = subprocess.run([sys.executable, "-m", "ago_runtime.cli", "export", "bad.pt", "-o", "b", "--no-real-frame"],
                       cwd=tmp_path, env=env, capture_output=True, text=True)
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: bad.pt: "), r.stderr
    for w in words:
        assert w in lines[0], lines[0]
    assert not (tmp_path / "b").exists()


def test_derived_keys_are_checked_against_what_they_derive_from(trained):
    payload = torch.load(trained["last"], weights_only=True)
    payload["loss_config"] = {**payload["loss_config"], "w_align": 123.0}
    with pytest.raises(Exception, match="loss_config differs"):
        CheckpointContract.from_payload(payload, "x.pt")
    payload = torch.load(trained["last"], weights_only=True)
    payload["train_config"]["model"]["hidden_dim"] = 24
    with pytest.raises(Exception, match="train_config.model differs"):
        CheckpointContract.from_payload(payload, "x.pt")


def test_no_module_outside_the_checkpoint_module_reads_a_checkpoint_by_key():
    """Consumers read CheckpointContract attributes; a checkpoint's keys appear only in ago_train/checkpoint.py."""
    pattern = re.compile(r"""\b(ckpt|ck|checkpoint|init|payload)\s*(\[["']|\.get\(["'])"""
                         r"""|["'](model_config|train_config|loss_config)["']\s*\]|torch\.load\(""")
    for bad in ('b = ckpt["bank"]', 'ckpt.get("calibration") or {}', 'ModelConfig.from_dict(dict(x["model_config"]))',
                'torch.load(path, weights_only=True)'):   # what b3080d8's readers did: the pattern catches it
        assert pattern.search(bad), bad
    # the reader itself; the backbone's weight files (not checkpoints); the hostile sweep forges bad checkpoints
    allowed = {REPO / "ago_train" / "checkpoint.py", REPO / "ago_train" / "model" / "backbone.py",
               REPO / "benchmarks" / "hostile_sweep.py"}
    offenders = []
    for top in ("ago_train", "ago_export", "benchmarks", "scripts"):
        for path in sorted((REPO / top).rglob("*.py")):
            if path in allowed:
                continue
            for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
                if pattern.search(line):
                    offenders.append(f"{path.relative_to(REPO)}:{n}: {line.strip()}")
    assert not offenders, "\n".join(offenders)
