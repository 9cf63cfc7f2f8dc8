"""Training, checkpoints, resume, DDP, evaluation and the CLI on a tiny synthetic dataset.

The dataset (2 scenes x 3 frames, 20 x 20 x 4 grid = the tiny model's) and its pseudo-labels are
made once per session with `ago synth` and `ago pseudo-labels`.
"""

from __future__ import annotations

import json
import os
import random
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from ago_runtime.errors import AgoInputError
from ago_runtime.geometry.grid import Grid

REPO = Path(__file__).resolve().parents[1]
GRID = "20x20x4"


def _ago(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    env = dict(os.environ, AGO_NO_PROGRESS="1", OMP_NUM_THREADS="1")
    r = subprocess.run([sys.executable, "-m", "ago_runtime.cli", *args], cwd=REPO, env=env,
                       capture_output=True, text=True)
    if check and r.returncode != 0:
        raise AssertionError(f"ago {' '.join(args)} failed ({r.returncode}):\n{r.stdout}\n{r.stderr}")
    return r


@pytest.fixture(scope="session")
def tiny_data(tmp_path_factory) -> dict:
    """A tiny synthetic dataset with Occ3D GT and cw pseudo-labels on the tiny model's grid."""
    root = tmp_path_factory.mktemp("ago_train_data")
    data, pseudo = root / "synth", root / "pseudo"
    _ago("synth", "--out", str(data), "--scenes", "2", "--frames", "3", "--image-size", "192x128",
         "--grid", GRID, "--seed", "3")
    _ago("pseudo-labels", "--data", str(data), "--out", str(pseudo), "--prompts", "cw", "--grid", GRID,
         "--split", "all", "--embedder", "sim", "--keyframes", "2")
    return {"data": data, "pseudo": pseudo, "root": root}


def tiny_config(tiny_data, out: Path, **changes):
    from ago_train.train_config import TrainConfig

    cfg = TrainConfig.preset("tiny")
    d = cfg.to_dict()
    d.update(data=str(tiny_data["data"]), pseudo=str(tiny_data["pseudo"]), out=str(out), train_split="all",
             device="cpu")
    d.update(changes)
    return TrainConfig.from_dict(d)


# ---- config ---------------------------------------------------------------------------------
def test_config_presets_roundtrip_and_overrides(tmp_path):
    from ago_train.train_config import TrainConfig

    for name in ("tiny", "cpu", "full"):
        cfg = TrainConfig.preset(name)
        cfg.save(tmp_path / f"{name}.json")
        back = TrainConfig.load(tmp_path / f"{name}.json")
        assert back.to_dict() == cfg.to_dict()
    full = TrainConfig.preset("full")
    assert (full.lr, full.weight_decay, full.warmup_lr, full.warmup_steps, full.min_lr, full.epochs,
            full.noise_words) == (1e-3, 0.01, 1e-5, 500, 1e-6, 24, 100)
    cfg = TrainConfig.preset("tiny").with_overrides(["epochs=3", "model.hidden_dim=16", "out=runs/x",
                                                     "loss.use_noise=false"])
    assert cfg.epochs == 3 and cfg.model.hidden_dim == 16 and cfg.out == "runs/x" and cfg.loss.use_noise is False
    with pytest.raises(AgoInputError):
        TrainConfig.preset("tiny").with_overrides(["no_such_key=1"])
    with pytest.raises(AgoInputError):
        TrainConfig.preset("huge")


def test_lr_schedule_warmup_and_cosine():
    from ago_train.train_config import TrainConfig

    cfg = TrainConfig.preset("full")
    total = 84000
    assert cfg.effective_warmup(total) == 500
    assert cfg.lr_at(0, total) == pytest.approx(1e-5)
    assert cfg.lr_at(250, total) == pytest.approx(1e-5 + (1e-3 - 1e-5) / 2)
    assert cfg.lr_at(500, total) == pytest.approx(1e-3)
    assert cfg.lr_at(total - 1, total) == pytest.approx(1e-6)
    lrs = [cfg.lr_at(s, total) for s in range(500, total, 997)]
    assert all(a >= b for a, b in zip(lrs, lrs[1:]))  # monotone cosine decay
    assert cfg.effective_warmup(200) == 10  # short runs: capped at 5 % of the steps


def test_run_length_says_which_limit_wins():
    """epochs x steps-per-epoch vs max_steps: the shorter sets the run and its schedule, and a note says so."""
    import dataclasses

    from ago_train.train_config import TrainConfig
    from ago_train.trainer import parameter_groups

    full = TrainConfig.preset("full")
    assert full.run_length(3) == (72, None)                        # max_steps unset: the epochs
    steps, note = dataclasses.replace(full, max_steps=600).run_length(3)
    assert steps == 72 and "epochs=24" in note and "max_steps=600" in note and "--set epochs=200" in note
    steps, note = dataclasses.replace(full, max_steps=50).run_length(3)
    assert steps == 50 and note.startswith("note: max_steps=50 comes before")
    assert dataclasses.replace(full, max_steps=72).run_length(3) == (72, None)
    # the full preset's parameter groups: backbone and FPN at 0.1x, the rest at 1x
    from ago_train.model import ModelConfig

    cfg = ModelConfig.preset("tiny")
    model = cfg.build()
    groups = {g["name"]: g["lr"] for g in parameter_groups(model, full)}
    assert groups == {"backbone": pytest.approx(1e-4), "fpn": pytest.approx(1e-4), "rest": pytest.approx(1e-3)}
    assert [g["name"] for g in parameter_groups(model, TrainConfig.preset("cpu"))] == ["all"]


# ---- dataset pieces -------------------------------------------------------------------------
def test_target_mapping_and_collate():
    from ago_train.dataset import IGNORE_INDEX, collate, pseudo_to_target

    sem = np.array([0, 3, 17, 255, 4], dtype=np.uint8)
    assert pseudo_to_target(sem, 5).tolist() == [0, 3, 5, IGNORE_INDEX, 4]
    items = [{"images": torch.zeros(6, 3, 4, 4), "ego2img": torch.eye(4).repeat(6, 1, 1), "token": t, "scene": "s",
              "semantics": torch.zeros(8, dtype=torch.long), "e3d_index": torch.arange(n) + 1,
              "e3d_embeds": torch.full((n, 3), float(n))} for t, n in (("a", 2), ("b", 5))]
    b = collate(items)
    assert b["semantics"].shape == (2, 8) and b["images"].shape == (2, 6, 3, 4, 4)
    assert b["align_index"].tolist() == [1, 2] + [8 + i for i in range(1, 6)]  # b * N + voxel
    assert b["align_embed"].shape == (7, 3) and b["align_embed"][:2].eq(2).all() and b["align_embed"][2:].eq(5).all()


def test_checkpoint_refuses_objects_and_rng_roundtrip(tmp_path):
    import dataclasses

    from ago_export.testing import random_checkpoint
    from ago_train.checkpoint import CheckpointContract, TrainingState, rng_state, set_rng_state

    ckpt = CheckpointContract.load(random_checkpoint(tmp_path / "m.pt", "tiny"))
    with pytest.raises(TypeError):
        dataclasses.replace(ckpt, train_config={"bad": object()}).save(tmp_path / "x.pt")
    assert not (tmp_path / "x.pt").exists()
    state = rng_state()
    a = (torch.rand(3), np.random.rand(3), random.random())
    dataclasses.replace(ckpt, training=TrainingState({"state": {}, "param_groups": []}, {}, state)).save(tmp_path / "r.pt")
    set_rng_state(CheckpointContract.load(tmp_path / "r.pt").training.rng_of_rank(0))
    b = (torch.rand(3), np.random.rand(3), random.random())
    assert torch.equal(a[0], b[0]) and np.array_equal(a[1], b[1]) and a[2] == b[2]


# ---- training --------------------------------------------------------------------------------
def _params(model) -> dict:
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def test_resume_is_exact(tiny_data, tmp_path):
    """4 steps straight == 2 steps, stop, resume from the checkpoint, 2 more (over an epoch boundary)."""
    from ago_train.trainer import Trainer

    # 2 steps per epoch; heads on a seeded 800-voxel sample per frame (as the cpu preset does)
    kw = dict(max_steps=4, epochs=2, max_frames=3, batch_size=2, noise_words=8, train_voxels=800)
    straight = Trainer(tiny_config(tiny_data, tmp_path / "a", **kw), quiet=True)
    straight.run()
    first = Trainer(tiny_config(tiny_data, tmp_path / "b", **kw), quiet=True)
    first.run(until=3)  # stops mid-epoch 1 and writes last.pt at step 3
    assert torch.load(tmp_path / "b" / "last.pt", weights_only=True)["step"] == 3
    resumed = Trainer(tiny_config(tiny_data, tmp_path / "b", **kw), resume=True, quiet=True)
    resumed.run()
    assert resumed.step == 4
    a, b = _params(straight.model), _params(resumed.model)
    assert a.keys() == b.keys()
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=1e-5, atol=1e-6, msg=f"{k} differs after resume")
    # training changed the weights (else the comparison proves nothing)
    init = Trainer(tiny_config(tiny_data, tmp_path / "c", **kw), quiet=True)
    init.setup()
    start = _params(init.model)
    assert any(not torch.allclose(v, start[k]) for k, v in a.items() if v.is_floating_point())


def test_checkpoint_loads_weights_only_and_holds_the_bank(tiny_data, tmp_path):
    from ago_train.trainer import Trainer

    t = Trainer(tiny_config(tiny_data, tmp_path / "run", max_steps=2), quiet=True)
    r = t.run()
    ckpt = torch.load(r["last"], weights_only=True)
    assert ckpt["format"] == "ago-checkpoint" and ckpt["step"] == 2
    assert ckpt["label_space"]["class_names"][:2] == ["others", "barrier"]
    assert ckpt["bank"]["embeddings"].shape == (len(ckpt["bank"]["phrase_class"]), 384)
    assert isinstance(ckpt["bank"]["encoder_hash"], str) and ckpt["bank"]["encoder_hash"]
    assert set(ckpt["rng"]) >= {"torch", "numpy", "python"}
    assert ckpt["model_config"]["grid"]["shape"] == [20, 20, 4]
    assert json.loads((tmp_path / "run" / "log.jsonl").read_text().splitlines()[-1])["step"] == 2


def test_bad_inputs_raise_ago_input_error(tiny_data, tmp_path):
    from ago_train.trainer import Trainer

    with pytest.raises(AgoInputError, match="pseudo-label"):
        Trainer(tiny_config(tiny_data, tmp_path / "x", pseudo=str(tmp_path / "missing")), quiet=True).setup()
    cfg = tiny_config(tiny_data, tmp_path / "y")
    cfg.model.grid = Grid.with_shape((10, 10, 2)).to_dict()
    with pytest.raises(AgoInputError, match="grid"):
        Trainer(cfg, quiet=True).setup()
    with pytest.raises(AgoInputError, match="classes"):  # cw pseudo-labels, another label space
        Trainer(tiny_config(tiny_data, tmp_path / "w", prompts="ow"), quiet=True).setup()
    with pytest.raises(AgoInputError, match="variant"):
        tiny_config(tiny_data, tmp_path / "v").with_overrides(['loss.variant="nope"'])
    r = _ago("train", "--config", "tiny", "--data", str(tiny_data["data"]), "--pseudo", str(tmp_path / "nope"),
             "--out", str(tmp_path / "z"), check=False)
    assert r.returncode == 2 and r.stderr.startswith("error: ") and "nope" in r.stderr


@pytest.mark.slow
def test_overfit_one_frame_then_eval(tiny_data, tmp_path):
    """A short run lowers the loss; 100 steps on one frame fit its pseudo-labels (mIoU > 0.7); eval writes files."""
    from ago_runtime.scoring.metric import OccupancyMetric
    from ago_train.checkpoint import CheckpointContract
    from ago_train.dataset import IGNORE_INDEX, pseudo_to_target
    from ago_train.evaluate import evaluate, load_model, predict_labels
    from ago_train.trainer import Trainer

    steps = 100
    cfg = tiny_config(tiny_data, tmp_path / "fit", max_frames=1, epochs=steps, max_steps=steps, lr=1e-2,
                      warmup_steps=5, log_every=10)
    t = Trainer(cfg, quiet=True)
    r = t.run()
    losses = r["losses"]
    assert np.mean(losses[-10:]) < 0.5 * np.mean(losses[:5]), losses[::10]

    # fit: predictions vs the frame's own pseudo-labels on the model grid
    ckpt = CheckpointContract.load(r["last"])
    mcfg, model = load_model(ckpt, torch.device("cpu"))
    item = t.dataset[0]
    K = t.label_space.num_classes
    pred = predict_labels(model, item["images"][None], item["ego2img"][None], ckpt.bank.embeddings,
                          ckpt.bank.phrase_class, K, "none")[0].numpy()
    target = pseudo_to_target(item["semantics"].numpy(), K)
    keep = target != IGNORE_INDEX
    m = OccupancyMetric(list(t.label_space.class_names) + ["free"], free_index=K)
    m.update(pred[keep], target[keep])
    assert m.miou() > 0.7, m.to_markdown()

    res = evaluate(r["last"], tiny_data["data"], split="all", out=tmp_path / "eval", quiet=True, device="cpu")
    assert res["mIoU"] is not None
    cli = _ago("eval", "--ckpt", r["last"], "--data", str(tiny_data["data"]), "--split", "all",
               "--out", str(tmp_path / "eval"), "--device", "cpu")
    assert "mIoU" in cli.stdout
    js = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    md = (tmp_path / "eval" / "metrics.md").read_text()
    assert js["identifier"] == "none" and js["frames"] == 6 and js["metric"]["frames"] == 6
    assert "| car |" in md and "mIoU" in md
    assert js["mIoU"] == res["mIoU"]
    assert js["readout"] == "model"

    # the GT-grid read-out: same weights, the planes read at the GT voxel centres (finer than the model grid)
    fine = evaluate(r["last"], tiny_data["data"], split="all", quiet=True, device="cpu", readout="gt")
    assert fine["readout"] == "gt" and fine["model_grid"] == list(mcfg.grid_obj().shape)
    assert fine["frames"] == res["frames"] and fine["metric"]["voxels"] == res["metric"]["voxels"]
    assert fine["mIoU"] is not None


def _tiny_model_and_frame():
    """The tiny preset's model (seed 0, eval mode) and one random frame: (cfg, model, images, ego2img)."""
    from ago_train.model.config import ModelConfig

    cfg = ModelConfig.preset("tiny")
    torch.manual_seed(0)
    model = cfg.build().eval()
    imgs = torch.randn(1, 6, 3, cfg.image_height, cfg.image_width)
    return cfg, model, imgs, torch.eye(4).repeat(1, 6, 1, 1)


def test_readout_grid_reads_the_same_planes_on_another_grid():
    """forward(grid_shape=...) reads the TPV planes on another grid over the same range: on the model's own
    grid it is the default forward; on a 2x grid it gives 8x the voxels, read bilinearly between the coarse
    voxels (not copies of them, which is what repeating a coarse prediction does)."""
    from ago_train.model.aggregate import planes_to_voxels

    cfg, model, imgs, e2i = _tiny_model_and_frame()
    X, Y, Z = model.grid_shape
    with torch.no_grad():
        base = model(imgs, e2i, adapted=False)["feat"]
        same = model(imgs, e2i, adapted=False, grid_shape=(X, Y, Z))["feat"]
        fine = model(imgs, e2i, adapted=False, grid_shape=(2 * X, 2 * Y, 2 * Z))["feat"]
        planes = model.planes(imgs, e2i)
        vf = planes_to_voxels(planes, (2 * X, 2 * Y, 2 * Z))
    assert torch.equal(base, same)
    assert fine.shape == (1, 8 * X * Y * Z, base.shape[-1])
    assert not torch.allclose(vf.reshape(1, 2 * X, 2 * Y, 2 * Z, -1)[:, ::2, ::2, ::2].reshape(1, X * Y * Z, -1),
                              planes_to_voxels(planes, (X, Y, Z)))


def test_eval_decodes_only_the_scored_voxels_with_the_same_labels():
    """`ago eval` runs the decoder on the camera-mask voxels only: predict_labels(voxel_index=...) gives the
    full grid's labels at those voxels, and a GT-resolution mask maps to a coarser prediction grid by "any"."""
    from ago_train.evaluate import predict_labels, scored_voxels

    cfg, model, imgs, e2i = _tiny_model_and_frame()
    X, Y, Z = model.grid_shape
    text = torch.nn.functional.normalize(torch.randn(7, cfg.embed_dim), dim=-1)
    phrase_class = torch.tensor([0, 0, 1, 2, 3, 3, 4])
    idx = torch.randperm(X * Y * Z)[: X * Y * Z // 3].sort().values
    for identifier in ("none", "min-entropy"):
        with torch.no_grad():
            full = predict_labels(model, imgs, e2i, text, phrase_class, 5, identifier)
            part = predict_labels(model, imgs, e2i, text, phrase_class, 5, identifier, voxel_index=idx[None])
        assert part.shape == (1, len(idx)) and torch.equal(part[0], full[0, idx])
        assert len(torch.unique(full)) > 1

    mask = np.zeros((4, 4, 2), bool)
    mask[3, 0, 1] = True                      # one fine voxel -> its coarse voxel (1, 0, 0)
    coarse = scored_voxels(mask, (2, 2, 1), "t")
    assert coarse.sum() == 1 and coarse[1, 0, 0]
    assert scored_voxels(mask, (4, 4, 2), "t") is mask
    with pytest.raises(AgoInputError):
        scored_voxels(mask, (3, 4, 2), "t")


def test_overfit_three_frames_with_the_stratified_sample(tiny_data, tmp_path):
    """The cpu preset's sampling rule on a few frames: the loss falls, the frames' pseudo-labels are fitted
    (mIoU > 0.5) and the amount of predicted matter matches theirs (0.5-2x the occupied labelled voxels):
    a model that fills the grid, as the old priority sample taught, fails the last bound."""
    from ago_runtime.classes import OCCUPIED_UNLABELLED
    from ago_runtime.scoring.metric import OccupancyMetric
    from ago_train.checkpoint import CheckpointContract
    from ago_train.dataset import IGNORE_INDEX, pseudo_to_target
    from ago_train.evaluate import load_model, predict_labels
    from ago_train.trainer import Trainer

    steps = 150
    cfg = tiny_config(tiny_data, tmp_path / "fit3", max_frames=3, epochs=steps, max_steps=steps, lr=1e-2,
                      warmup_steps=5, log_every=10, train_voxels=600, voxel_sampling="stratified",
                      occupied_share=0.5)
    t = Trainer(cfg, quiet=True)
    r = t.run()
    assert np.mean(r["losses"][-10:]) < 0.5 * np.mean(r["losses"][:5])
    ckpt = CheckpointContract.load(r["last"])
    _, model = load_model(ckpt, torch.device("cpu"))
    K = t.label_space.num_classes
    m = OccupancyMetric(list(t.label_space.class_names) + ["free"], free_index=K)
    pred_occ = true_occ = 0
    for i in range(3):
        item = t.dataset[i]
        sem = item["semantics"].numpy()
        pred = predict_labels(model, item["images"][None], item["ego2img"][None], ckpt.bank.embeddings,
                              ckpt.bank.phrase_class, K, "none")[0].numpy()
        target = pseudo_to_target(np.where(sem == OCCUPIED_UNLABELLED, 255, sem), K)
        keep = target != IGNORE_INDEX
        m.update(pred[keep], target[keep])
        pred_occ += int((pred[keep] != K).sum())
        true_occ += int((target[keep] != K).sum())
    assert m.miou() > 0.5, m.to_markdown()
    assert 0.5 < pred_occ / true_occ < 2.0, (pred_occ, true_occ)


def test_amp_bf16_runs_the_forward_in_bfloat16_and_the_loss_falls(tiny_data, tmp_path):
    """`--set amp=bf16`: the model's layers run in bfloat16 under autocast, the losses in float32, and a few steps
    on three frames still reduce the loss; any other value is refused before any work."""
    from ago_train.trainer import Trainer

    with pytest.raises(AgoInputError, match=r"amp must be one of \['none', 'bf16'\], got 'fp16'"):
        tiny_config(tiny_data, tmp_path / "x").with_overrides(["amp=fp16"])
    steps = 40
    cfg = tiny_config(tiny_data, tmp_path / "amp", amp="bf16", max_frames=3, epochs=steps, max_steps=steps, lr=1e-2,
                      warmup_steps=3, log_every=10, train_voxels=600)
    t = Trainer(cfg, quiet=True)
    t.setup()
    seen = {"forward": set(), "adapter": set()}
    in_step = []                                  # dtypes seen inside training steps only (not at set-up or save)

    def hook(part):
        def record(module, inputs, output) -> None:
            if in_step:
                seen[part].add(output.dtype)
        return record

    for name, m in t.model.named_modules():       # the adapter runs inside the alignment loss: float32
        if isinstance(m, (torch.nn.Linear, torch.nn.Conv2d)):
            m.register_forward_hook(hook("adapter" if name.startswith("adapter") else "forward"))
    step = t.train_step

    def counted_step(batch):
        in_step.append(1)
        try:
            return step(batch)
        finally:
            in_step.pop()

    t.train_step = counted_step
    r = t.run()
    assert seen["forward"] == {torch.bfloat16}                        # every linear / conv of the forward in bf16
    assert seen["adapter"] <= {torch.float32}
    assert all(p.dtype == torch.float32 for p in t.model.parameters())  # weights and optimiser stay float32
    assert np.isfinite(r["losses"]).all()
    assert np.mean(r["losses"][-5:]) < 0.7 * np.mean(r["losses"][:5])


def test_class_balance_counts_only_the_training_frames(tiny_data, tmp_path):
    """loss.class_balance: the counts behind the CE weights are those of the run's own training frames
    (max_frames=2 of 6), written to class_weights.json, and the weights change the step's CE."""
    import json

    from ago_train.losses.class_balance import class_balance_weights, count_classes
    from ago_train.trainer import Trainer

    kw = dict(max_steps=1, max_frames=2, noise_words=8, train_voxels=600)
    cfg = tiny_config(tiny_data, tmp_path / "cb", loss={"class_balance": 0.5}, **kw)
    t = Trainer(cfg, quiet=True)
    t.setup()
    frames = t.dataset.frames
    assert len(frames) == 2
    K = t.label_space.num_classes
    expect = count_classes([t.pseudo.labels(frames[i].scene, frames[i].token) for i in range(2)], K)
    record = json.loads((tmp_path / "cb" / "class_weights.json").read_text())
    assert [v["voxels"] for v in record["classes"].values()] == expect.tolist()
    assert np.allclose(t.class_weight.numpy(), class_balance_weights(expect, 0.5))
    assert len(set(np.round(t.class_weight.numpy(), 4))) > 2   # not uniform on these frames
    plain = Trainer(tiny_config(tiny_data, tmp_path / "plain", **kw), quiet=True)
    plain.setup()
    assert plain.class_weight is None
    torch.manual_seed(0)
    a = float(t.run()["losses"][0])
    b = float(plain.run()["losses"][0])
    assert a != pytest.approx(b, rel=1e-4)


def _ddp_worker(rank: int, world: int, port: int, cfg_dict: dict, out: str) -> None:
    os.environ.update(RANK=str(rank), WORLD_SIZE=str(world), LOCAL_RANK=str(rank), MASTER_ADDR="127.0.0.1",
                      MASTER_PORT=str(port), AGO_NO_PROGRESS="1")
    torch.set_num_threads(1)
    from ago_train import distributed as D
    from ago_train.train_config import TrainConfig
    from ago_train.trainer import Trainer

    info = D.setup("cpu")
    try:
        t = Trainer(TrainConfig.from_dict(cfg_dict), dist_info=info, quiet=True)
        r = t.run()
        params = {k: v.detach() for k, v in t.model.named_parameters()}
        torch.save({"step": r["step"], "model": params}, Path(out) / f"rank{rank}.pt")
    finally:
        D.cleanup(info)


def test_ddp_two_processes_agree(tiny_data, tmp_path):
    """A 2-process gloo run: both ranks end with the same parameters, and they moved from the start.

    (BatchNorm running statistics are buffers: DDP broadcasts rank 0's at each forward, so after the
    last step each rank holds its own; checkpoints store rank 0's.)"""
    import socket

    import torch.multiprocessing as mp

    from ago_train.trainer import Trainer

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    cfg = tiny_config(tiny_data, tmp_path / "ddp", max_steps=2, max_frames=4, ckpt_every=1)
    mp.spawn(_ddp_worker, args=(2, port, cfg.to_dict(), str(tmp_path)), nprocs=2, join=True)
    ckpt = torch.load(tmp_path / "ddp" / "last.pt", weights_only=True)
    assert ckpt["world_size"] == 2 and ckpt["step"] == 2 and isinstance(ckpt["rng"], list)
    r0 = torch.load(tmp_path / "rank0.pt", weights_only=True)
    r1 = torch.load(tmp_path / "rank1.pt", weights_only=True)
    assert r0["step"] == r1["step"] == 2
    for k in r0["model"]:
        torch.testing.assert_close(r0["model"][k], r1["model"][k], msg=f"ranks disagree on {k}")
    init = Trainer(cfg, quiet=True)
    init.setup()
    start = init.model.state_dict()
    assert any(not torch.allclose(v, start[k]) for k, v in r0["model"].items() if v.is_floating_point())


# ---- open-world protocol ---------------------------------------------------------------------
def test_select_kshot_covers_every_class_k_times(tmp_path):
    from ago_runtime.atomic import save_npz, write_json
    from ago_train.dataset import PseudoLabelSet
    from ago_train.open_world import select_kshot

    grid = Grid.with_shape((4, 4, 2))
    write_json(tmp_path / "meta.json", {"grid": grid.to_dict(), "label_space": {"classes": ["a", "b", "c"]}})
    rng = np.random.default_rng(0)
    frames = []
    for i in range(30):
        sem = np.full(grid.shape, 17, np.uint8)
        present = [c for c in range(3) if rng.random() < (0.8, 0.4, 0.1)[c]]
        for j, c in enumerate(present):
            sem[j, 0, 0] = c
        d = tmp_path / "s" / f"t{i}"
        save_npz(d / "labels.npz", semantics=sem, mask_lidar=sem * 0, mask_camera=sem * 0)
        frames.append(("s", f"t{i}"))
    pseudo = PseudoLabelSet.open(tmp_path)
    tokens, counts = select_kshot(pseudo, frames, 3, k=2, seed=1)
    occurring = {c for s, t in frames for c in np.unique(pseudo.labels(s, t)) if c < 3}
    assert all(counts[c] >= 2 for c in occurring)
    assert len(tokens) < len(frames) and len(set(tokens)) == len(tokens)
    # the counts are the true counts over the chosen frames
    for c in range(3):
        assert counts[c] == sum(c in np.unique(pseudo.labels("s", t)) for t in tokens)
    assert select_kshot(pseudo, frames, 3, k=2, seed=1)[0] == tokens          # seeded
    assert select_kshot(pseudo, frames, 3, k=2, seed=2)[0] != tokens          # another seed, another subset


def test_paper_split_counts_refined_classes_unknown(tmp_path):
    """The paper's zero-shot split: known only where one pretraining class is exactly the class; classes
    refining a super-category count unknown (this driver's own split counts them known)."""
    from ago_train.open_world import open_world_label_space, paper_split

    known, unknown = paper_split("ow", "ow_pretrain")
    assert known == ["pedestrian", "driveable_surface", "sidewalk"]
    assert len(unknown) == 12 and {"car", "bicycle", "barrier", "vegetation"} <= set(unknown)
    assert {"car", "bicycle"} <= open_world_label_space("ow", "ow_pretrain").known
    pre = tmp_path / "pre.txt"
    pre.write_text("@name: pre\ncar: car\nflat [driveable_surface, sidewalk]: road, pavement\n")
    ev = tmp_path / "ev.txt"
    ev.write_text("@name: ev\ncar: car\ntruck: truck\ndriveable_surface: road\nsidewalk: sidewalk\n")
    assert paper_split(str(ev), str(pre)) == (["car"], ["truck", "driveable_surface", "sidewalk"])


@pytest.mark.slow
def test_open_world_protocol_end_to_end(tiny_data, tmp_path):
    """Stages pretrain -> zeroshot -> fewshot on the tiny set through the CLI; results JSON + markdown."""
    pre, full = tmp_path / "pseudo_pre", tmp_path / "pseudo_ow"
    for prompts, out in (("ow_pretrain", pre), ("ow", full)):
        _ago("pseudo-labels", "--data", str(tiny_data["data"]), "--out", str(out), "--prompts", prompts,
             "--grid", GRID, "--split", "all", "--embedder", "sim", "--keyframes", "1")
    out = tmp_path / "ow"
    _ago("open-world", "--stage", "all", "--config", "tiny", "--data", str(tiny_data["data"]),
         "--set", "train_split=\"all\"", "--set", "max_steps=2", "--set", "device=\"cpu\"",
         "--pseudo-pretrain", str(pre), "--pseudo-full", str(full), "--k", "1", "--seeds", "0",
         "--eval-split", "all", "--out", str(out))
    res = json.loads((out / "results.json").read_text())
    assert res["pretrain"]["steps"] == 2
    z = res["zeroshot"]
    assert set(z) >= {"mIoU", "mIoU_known", "mIoU_unknown", "iou"} and "car" in z["iou"]
    f = res["fewshot"]
    assert f["k"] == 1 and len(f["runs"]) == 1 and f["runs"][0]["frames"] >= 1
    assert all(n >= 1 for n in f["runs"][0]["class_frames"].values() if n)
    ck = torch.load(out / "fewshot" / "seed0" / "last.pt", weights_only=True)
    assert ck["label_space"]["num_classes"] == 15
    md = (out / "results.md").read_text()
    assert "zero-shot" in md and "1-shot" in md
    zs = json.loads((out / "zeroshot" / "metrics.json").read_text())
    assert zs["identifier"] == "min-entropy" and set(zs["subsets"]) == {"known", "unknown"}


# ---- the frozen-backbone feature cache ---------------------------------------------------------
def _cached_config(tiny_data, out: Path, cache: Path, **changes):
    from ago_train.model.config import ModelConfig

    mc = ModelConfig.preset("tiny")
    mc.backbone, mc.pretrained, mc.frozen_stages = "efficientnet_lite0", True, 1
    kw = dict(model=mc.to_dict(), feature_cache=str(cache), max_steps=2, train_voxels=400)
    kw.update(changes)
    return tiny_config(tiny_data, out, **kw)


def test_feature_cache_matches_images(tiny_data, tmp_path):
    """Training from cached frozen-stage maps equals training from the images (to float16 precision);
    the cache is reused from disk, keyed by image content and weights, and corrupt entries are remade."""
    from ago_train.dataset import collate
    from ago_train.feature_cache import FeatureCache
    from ago_train.trainer import Trainer

    cache = tmp_path / "cache"
    with_cache = Trainer(_cached_config(tiny_data, tmp_path / "a", cache), quiet=True)
    with_cache.setup()
    fc = with_cache.dataset.feature_cache
    assert fc is not None and fc.stats["computed"] == 6 * len(with_cache.dataset)   # filled once, per image
    item = with_cache.dataset[0]
    assert "prefix" in item and "images" not in item                                   # no JPEG decoded
    assert item["prefix"][0].dtype == torch.float16 and item["prefix"][0].shape[:2] == (6, 40)

    plain = Trainer(_cached_config(tiny_data, tmp_path / "b", cache, feature_cache="off"), quiet=True)
    plain.setup()
    assert plain.dataset.feature_cache is None
    # same frame through both paths: the frozen prefix from the cache equals the one from the images
    img_item = plain.dataset[0]
    with torch.no_grad():
        ref = plain.model.frozen_prefix(img_item["images"][None])[0]
    got = item["prefix"][0].float()
    assert float((got - ref).abs().max()) <= 2e-3 * float(ref.abs().max()) + 1e-3
    # the mirror augmentation's prefix is the backbone's output on the flipped images
    flipped = fc.frame_prefix(with_cache.dataset.frames[0].image_paths, with_cache.dataset.frames[0].rig, flip=True)[0]
    with torch.no_grad():
        ref_flip = plain.model.frozen_prefix(img_item["images"].flip(-1)[None])[0]
    assert float((torch.from_numpy(flipped).float() - ref_flip).abs().max()) <= 2e-3 * float(ref_flip.abs().max()) + 1e-3
    # one optimiser step from each gives the same losses
    a = with_cache.train_step(collate([item]))
    b = plain.train_step(collate([img_item]))
    for k in ("grounding_ce", "occ", "align"):
        assert float(a[k].detach()) == pytest.approx(float(b[k].detach()), rel=2e-3, abs=1e-4), k

    # a new process finds everything on disk; a corrupt entry is rejected and recomputed
    frame = with_cache.dataset.frames[0]
    again = FeatureCache(with_cache.model, with_cache.preprocess, cache)
    again.frame_prefix(frame.image_paths, frame.rig)
    assert again.stats["computed"] == 0 and again.stats["read"] == 6
    from ago_train.feature_cache import image_key

    victim = again._path(image_key(frame.image_paths["CAM_FRONT"]))
    victim.write_bytes(victim.read_bytes()[:100])
    fresh = FeatureCache(with_cache.model, with_cache.preprocess, cache)
    fresh.frame_prefix(frame.image_paths, frame.rig)
    assert fresh.stats["rejected"] == 1 and fresh.stats["computed"] == 1
    # other frozen weights -> another folder (nothing stale is read)
    with torch.no_grad():
        with_cache.model.backbone.stem[0].weight.add_(0.01)
    other = FeatureCache(with_cache.model, with_cache.preprocess, cache)
    assert other.dir != fresh.dir
