"""Bad input, one row each: the command, what is wrong, and the contract README promises for it —
exit code 2, exactly ONE stderr line `error: <file or option>: <problem>` that names the file or
option, no traceback, and nothing written (the working directory stays empty, the inputs unchanged,
the named outputs absent).

Every verb has usage-error rows (unknown option, wrong type, missing option, value out of range),
because those come from click's exception classes, which typer >= 0.26 vendors as `typer._click`
(ago_runtime/cli.py catches them by the classes typer exports). The rows run in this process through
`ago_runtime.cli.run`, the function the `ago` console script calls.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
import pickle
import shutil
import struct
import types
from pathlib import Path

import cv2
import numpy as np
import pytest

from ago_runtime.formats.calibration import save_calibration
from ago_runtime.formats.random_frame import write_random_frame
from ago_runtime.geometry.camera import CAMERA_NAMES, Rig

# ------------------------------------------------------------------------------------ running
def run_ago(args, cwd: Path):
    """`ago ARGS` in-process with `cwd` as the working directory -> (code, stdout, stderr)."""
    from ago_runtime.cli import run

    out, err = io.StringIO(), io.StringIO()
    old = os.getcwd()
    try:
        os.chdir(cwd)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = run([str(a) for a in args])
            except SystemExit as e:
                code = e.code if isinstance(e.code, int) else 1
    finally:
        os.chdir(old)
    return types.SimpleNamespace(code=code, stdout=out.getvalue(), stderr=err.getvalue())


def ok(r):
    """`r` (a run_ago result) when the command succeeded; else a failure showing its output."""
    assert r.code == 0, f"exit {r.code}\nstdout: {r.stdout[-3000:]}\nstderr: {r.stderr[-3000:]}"
    return r


def run_chain(cwd: Path, data: str, prompts, gt: str) -> None:
    """The whole chain on a synthetic dataset `data` (a folder in `cwd`): pseudo-labels (20x20x4) -> train (tiny, 2
    epochs) -> eval (val) -> export -> infer -> metric against `gt`, in the folders pl, run, ev, bundle, pred, m.json."""
    ok(run_ago(["pseudo-labels", "--data", data, "--prompts", prompts, "--out", "pl", "--grid", "20x20x4"], cwd))
    ok(run_ago(["train", "--config", "tiny", "--data", data, "--pseudo", "pl", "--prompts", prompts, "--out", "run",
                "--set", "epochs=2"], cwd))
    ok(run_ago(["eval", "--ckpt", "run/last.pt", "--data", data, "--split", "val", "--out", "ev"], cwd))
    ok(run_ago(["export", "run/last.pt", "-o", "bundle", "--parity-frame", data], cwd))
    ok(run_ago(["infer", "--images", data, "--bundle", "bundle", "--out", "pred"], cwd))
    ok(run_ago(["metric", "--pred", "pred", "--gt", gt, "--prompts", prompts, "--json", "m.json"], cwd))


def snapshot(root: Path) -> dict:
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in root.rglob("*") if p.is_file()}


def assert_one_error_line(r, *needles: str) -> str:
    assert r.code == 2, f"exit {r.code}\nstdout: {r.stdout[-2000:]}\nstderr: {r.stderr[-2000:]}"
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, f"expected one stderr line, got {len(lines)}:\n{r.stderr[-3000:]}"
    assert lines[0].startswith("error: "), lines[0]
    for needle in needles:
        assert needle in lines[0], f"{needle!r} not in {lines[0]!r}"
    assert "Traceback" not in r.stderr + r.stdout
    return lines[0]


# ------------------------------------------------------------------------------------ fixtures
def jpeg_with_size(data: bytes, width: int, height: int) -> bytes:
    """The same JPEG with its SOF0 frame header claiming another size (the data stays small)."""
    i = data.index(b"\xff\xc0")
    b = bytearray(data)
    b[i + 5:i + 9] = struct.pack(">HH", height, width)
    return bytes(b)


def scrambled(data: bytes, n: int, seed: int, no_ff: bool = False) -> bytes:
    """Random bytes over n bytes in the middle of the entropy-coded data (markers before and after intact)."""
    rng = np.random.default_rng(seed)
    sos = data.index(b"\xff\xda")
    start = (sos + len(data)) // 2
    seg = rng.integers(0, 256, n, dtype=np.uint8)
    if no_ff:
        seg[seg == 0xFF] = 0
    b = bytearray(data)
    b[start:start + n] = seg.tobytes()
    return bytes(b)


@pytest.fixture(scope="module")
def w(tmp_path_factory):
    """Inputs for the rows: a synthetic dataset + pseudo-labels, an images folder and damaged copies,
    a tiny checkpoint and its bundle and damaged copies, hostile pickles."""
    root = tmp_path_factory.mktemp("bad_inputs")
    cwd = tmp_path_factory.mktemp("bad_inputs_setup")
    old_cache = os.environ.get("AGO_CACHE_DIR")
    os.environ["AGO_CACHE_DIR"] = str(tmp_path_factory.mktemp("bad_inputs_cache"))
    x = types.SimpleNamespace(root=root)
    x.data = root / "synth"
    r = run_ago(["synth", "--out", x.data, "--scenes", "1", "--frames", "2", "--image-size", "96x54",
                 "--grid", "20x20x4"], cwd)
    assert r.code == 0, r.stderr
    x.pseudo = root / "pseudo"
    r = run_ago(["pseudo-labels", "--data", x.data, "--out", x.pseudo, "--grid", "20x20x4", "--keyframes", "1",
                 "--split", "all"], cwd)
    assert r.code == 0, r.stderr
    x.no_boxes = shutil.copytree(x.data, root / "no_boxes")   # the dataset without its box table
    next(x.no_boxes.glob("*/sample_annotation.json")).unlink()
    x.labels = next(x.pseudo.glob("*/*/labels.npz"))
    x.gt = next((x.data / "gts").glob("*/*/labels.npz"))
    x.token = x.gt.parent.name
    x.a_file = root / "a_file.txt"
    x.a_file.write_text("not a folder\n")

    x.frame = write_random_frame(root / "frame")
    front = (x.frame / "CAM_FRONT.jpg").read_bytes()
    x.bomb = shutil.copytree(x.frame, root / "bomb")
    (x.bomb / "CAM_FRONT.jpg").write_bytes(jpeg_with_size(front, 30000, 16875))
    x.scrambled = shutil.copytree(x.frame, root / "scrambled")
    (x.scrambled / "CAM_FRONT.jpg").write_bytes(scrambled(front, 2000, seed=1))
    x.truncated = shutil.copytree(x.frame, root / "truncated")
    (x.truncated / "CAM_BACK.jpg").write_bytes(front[: len(front) // 2])
    for name, change in (("negfocal", lambda c: c["intrinsics"][0].__setitem__(0, -c["intrinsics"][0][0])),
                         ("scaled", lambda c: c.__setitem__("cam2ego", (2 * np.array(c["cam2ego"])).tolist()))):
        d = shutil.copytree(x.frame, root / name)
        calib = json.loads((d / "calib.json").read_text())
        change(calib["cameras"]["CAM_FRONT_LEFT"])
        (d / "calib.json").write_text(json.dumps(calib))
        setattr(x, name, d)

    x.pkl_bomb = root / "bomb.pkl"      # 34 bytes that would allocate 3 GB: bytearray(3_000_000_000)
    x.pkl_bomb.write_bytes(b"c__builtin__\nbytearray\n(\x8a\x05\x00\x5e\xd0\xb2\x00tR.")
    x.pkl_code = root / "code.pkl"      # would run os.system
    x.pkl_code.write_bytes(b"cos\nsystem\n(S'echo pwned'\ntR.")
    nested = [0] * 10
    for _ in range(7):
        nested = [nested] * 10          # 10^8 values from a few hundred bytes
    x.pkl_laughs = root / "laughs.pkl"
    x.pkl_laughs.write_bytes(pickle.dumps({"data_list": nested}, protocol=4))

    x.big_prompts = root / "big5000.txt"
    x.big_prompts.write_text("".join(f"class {i}: word{i}\n" for i in range(5000)))
    x.bad_npz = root / "bad.npz"
    x.bad_npz.write_bytes(b"PK\x03\x04 this is no zip")

    pytest.importorskip("torch")

    from ago_export.export import export_bundle
    from ago_export.testing import random_checkpoint
    from ago_runtime.vocab.bank import PromptBank
    from ago_train.checkpoint import CheckpointContract, TrainingState, rng_state
    from ago_train.model import ModelConfig
    from ago_train.text.noise import NoiseBank

    x.ckpt = random_checkpoint(root / "tiny.pt", "tiny", prompts="cw", seed=1)
    x.bundle = root / "bundle"
    export_bundle(x.ckpt, x.bundle, bank_prompts=[], real_frame=False, log=lambda s: None)

    other = ModelConfig.preset("tiny")
    other.pretrained, other.hidden_dim = False, 24
    x.other_size = random_checkpoint(root / "other_size.pt", other, prompts="cw", seed=2)
    x.mismatched = root / "mismatched.pt"       # weights of the tiny model, model_config of another size
    tiny = CheckpointContract.load(x.ckpt)
    dataclasses.replace(tiny, model_config=other).save(x.mismatched)
    x.raw_pickle = root / "raw.pt"
    x.raw_pickle.write_bytes(pickle.dumps({"model": [1, 2, 3]}))
    x.resume_run = root / "resume_run"          # a run folder whose last.pt has the tiny model's size
    dataclasses.replace(tiny, training=TrainingState({"state": {}, "param_groups": []}, {}, rng_state()), step=1,
                        train_config={"epochs": 1, "batch_size": 1, "seed": 0, "max_steps": 4}
                        ).save(x.resume_run / "last.pt")
    x.noise = NoiseBank(["alpha", "beta", "gamma"], np.eye(3, 384, dtype=np.float16)).save(root / "noise.npz")
    x.broken_pseudo = shutil.copytree(x.pseudo, root / "broken_pseudo")
    victim = next(x.broken_pseudo.glob("*/*/labels.npz"))
    victim.write_bytes(victim.read_bytes()[: victim.stat().st_size // 2])    # a kill mid-write, by hand
    x.broken_labels = victim

    bank = PromptBank.load(x.bundle / "banks" / "train.npz")
    bank.encoder_id = "some-other-encoder"
    x.foreign_bank = bank.save(root / "foreign.npz")
    x.bad_heads = shutil.copytree(x.bundle, root / "bad_heads")
    with np.load(x.bad_heads / "heads.npz") as z:
        heads = {k: z[k] for k in z.files}
    heads["W_dec"] = np.concatenate([heads["W_dec"], heads["W_dec"][:, :1]], axis=1)   # Dh + 1
    np.savez(x.bad_heads / "heads.npz", **heads)
    meta = json.loads((x.bad_heads / "bundle.json").read_text())
    from ago_runtime.predict.bundle import file_sha256

    meta["files"]["heads"].update(sha256=file_sha256(x.bad_heads / "heads.npz"),
                                  size=(x.bad_heads / "heads.npz").stat().st_size)
    (x.bad_heads / "bundle.json").write_text(json.dumps(meta))
    yield x
    if old_cache is None:
        os.environ.pop("AGO_CACHE_DIR", None)
    else:
        os.environ["AGO_CACHE_DIR"] = old_cache


# ------------------------------------------------------------------------------------ the table
# (id, args (a function of the fixture namespace), words the one error line must contain, outputs
# that must not exist afterwards (relative to the empty working directory)). `{token}` etc. are
# attributes of the fixture.
TRAIN = lambda w: ["--data", w.data, "--pseudo", w.pseudo, "--set", 'train_split="all"', "--set",   # noqa: E731
                   f'noise_bank="{w.noise}"', "--set", 'device="cpu"']

CHOOSE = lambda w: ["choose-threshold", "--images", w.data, "--bundle", w.bundle]   # noqa: E731

ROWS = [
    # ---- usage errors, every verb (click's classes, whichever copy typer carries)
    ("unknown verb", lambda w: ["bogus"], ["bogus"], []),
    ("synth --scenes ten", lambda w: ["synth", "--scenes", "ten", "--out", "o"], ["--scenes"], ["o"]),
    ("synth --scenes 0", lambda w: ["synth", "--scenes", "0", "--out", "o"], ["--scenes"], ["o"]),
    ("synth --frames -3", lambda w: ["synth", "--frames", "-3", "--out", "o"], ["--frames"], ["o"]),
    ("synth --val-fraction 1.5", lambda w: ["synth", "--val-fraction", "1.5", "--out", "o"], ["--val-fraction"], ["o"]),
    ("synth --image-size 80", lambda w: ["synth", "--image-size", "80", "--out", "o"], ["--image-size"], ["o"]),
    ("synth --grid 0x2x2", lambda w: ["synth", "--grid", "0x2x2", "--out", "o"], ["--grid"], ["o"]),
    ("synth --seed -1", lambda w: ["synth", "--seed", "-1", "--out", "o"], ["--seed"], ["o"]),
    ("synth --rig kitti", lambda w: ["synth", "--rig", "kitti", "--out", "o"], ["--rig", "kitti"], ["o"]),
    ("synth --rig waymo --sweeps-between", lambda w: ["synth", "--rig", "waymo", "--sweeps-between", "2", "--out", "o"],
     ["--sweeps-between"], ["o"]),
    ("infer --bogus", lambda w: ["infer", "--bogus"], ["--bogus", "no such option"], []),
    ("infer --save-volumes=maybe", lambda w: ["infer", "--images", w.frame, "--bundle", w.bundle, "--save-volumes=x"],
     ["--save-volumes"], []),
    ("infer --identifier", lambda w: ["infer", "--images", w.frame, "--bundle", w.bundle, "--identifier", "vote",
                                      "--out", "o"], ["identifier", "vote"], ["o"]),
    ("infer --workers 0", lambda w: ["infer", "--images", w.frame, "--bundle", w.bundle, "--workers", "0",
                                     "--out", "o"], ["--workers", "between 1 and 64"], ["o"]),
    ("infer --unexplained-threshold 1.5", lambda w: ["infer", "--images", w.frame, "--bundle", w.bundle,
                                                     "--save-volumes", "--unexplained-threshold", "1.5", "--out", "o"],
     ["--unexplained-threshold", "between 0 and 1"], ["o"]),
    ("infer --unexplained-threshold nan", lambda w: ["infer", "--images", w.frame, "--bundle", w.bundle,
                                                     "--save-volumes", "--unexplained-threshold", "nan", "--out", "o"],
     ["--unexplained-threshold"], ["o"]),
    ("infer --unexplained-threshold without --save-volumes",
     lambda w: ["infer", "--images", w.frame, "--bundle", w.bundle, "--unexplained-threshold", "0.8", "--out", "o"],
     ["--unexplained-threshold", "--save-volumes"], ["o"]),
    ("choose-threshold --false-rate 1", lambda w: CHOOSE(w) + ["--labels", w.pseudo, "--false-rate", "1",
                                                              "--json", "o.json"], ["--false-rate", "below 1"],
     ["o.json"]),
    ("choose-threshold --false-rate nan", lambda w: CHOOSE(w) + ["--labels", w.pseudo, "--false-rate", "nan"],
     ["--false-rate"], []),
    ("choose-threshold --frames 0", lambda w: CHOOSE(w) + ["--labels", w.pseudo, "--frames", "0", "--json", "o.json"],
     ["--frames", "between 1"], ["o.json"]),
    ("choose-threshold --labels not a label folder", lambda w: CHOOSE(w) + ["--labels", w.frame],
     ["--labels", "labels.npz"], []),
    ("choose-threshold --labels missing", lambda w: CHOOSE(w) + ["--labels", "nowhere"], ["nowhere", "not found"], []),
    ("choose-threshold --json under a file", lambda w: CHOOSE(w) + ["--labels", w.pseudo, "--json",
                                                                    w.a_file / "c.json"], ["a_file.txt"], []),
    ("choose-threshold --prompts and --bank", lambda w: CHOOSE(w) + ["--labels", w.pseudo, "--prompts", "ow",
                                                                     "--bank", "ow"], ["--bank", "not both"], []),
    ("demo --bogus", lambda w: ["demo", "--bogus"], ["--bogus"], []),
    ("train-real: dataroot missing", lambda w: ["train-real", "no_such_root", "o"], ["no_such_root"], ["o"]),
    ("train-real --steps 0", lambda w: ["train-real", w.data, "o", "--steps", "0"], ["--steps"], ["o"]),
    ("train-real without box tables", lambda w: ["train-real", w.no_boxes, "o"], ["sample_annotation.json", "boxes"],
     ["o"]),
    ("train-real --moving sweep", lambda w: ["train-real", w.data, "o", "--moving", "sweep"], ["--moving", "sweep"],
     ["o"]),
    ("vlm-files no --detector folder", lambda w: ["vlm-files", "--data", w.data, "--out", "o", "--prompts", "cw",
                                                  "--detector", "no_such_folder", "--sam", "no_sam"],
     ["--detector", "no such folder", "grounding-dino"], ["o"]),
    ("vlm-files --detector of another architecture", lambda w: ["vlm-files", "--data", w.data, "--out", "o",
                                                                "--prompts", "cw", "--detector", w.bundle, "--sam", "x"],
     ["--detector", "config.json"], ["o"]),
    ("retrieve no --phrase", lambda w: ["retrieve", "--images", w.frame], ["--phrase", "missing"], []),
    ("retrieve empty phrase", lambda w: ["retrieve", "--images", w.frame, "--phrase", " ", "--bundle", w.bundle,
                                         "--out", "o"], ["--phrase"], ["o"]),
    ("prompts build no file", lambda w: ["prompts", "build"], ["PROMPT_FILE", "missing"], []),
    ("prompts build no -o", lambda w: ["prompts", "build", "cw"], ["--output", "missing"], []),
    ("prompts build --template", lambda w: ["prompts", "build", "cw", "-o", "b.npz", "--template", "x"],
     ["template"], ["b.npz"]),
    ("prompts show --bogus", lambda w: ["prompts", "show", "cw", "--bogus"], ["--bogus"], []),
    ("prompts export-encoder --bogus", lambda w: ["prompts", "export-encoder", "--bogus"], ["--bogus"], []),
    ("prompts noise --bogus", lambda w: ["prompts", "noise", "--bogus"], ["--bogus"], []),
    ("prompts unknown sub-verb", lambda w: ["prompts", "flatten"], ["flatten"], []),
    ("show --view", lambda w: ["show", w.gt, "--view", "sideways", "--out", "o.png"], ["--view"], ["o.png"]),
    ("show --classes missing", lambda w: ["show", w.gt, "--classes", "nope.json", "--out", "o.png"],
     ["nope.json", "class table not found"], ["o.png"]),
    ("show --index text", lambda w: ["show", w.data, "--index", "one"], ["--index"], []),
    ("show no path", lambda w: ["show"], ["PATH", "missing"], []),
    ("metric no --pred", lambda w: ["metric", "--gt", w.data / "gts"], ["--pred", "missing"], []),
    ("pseudo-labels --limit -1", lambda w: ["pseudo-labels", "--data", w.data, "--out", "o", "--limit", "-1"],
     ["--limit"], ["o"]),
    ("pseudo-labels --moving sweep", lambda w: ["pseudo-labels", "--data", w.data, "--out", "o", "--moving", "sweep"],
     ["--moving", "sweep"], ["o"]),
    ("pseudo-labels --moving track without box tables", lambda w: ["pseudo-labels", "--data", w.no_boxes, "--out", "o",
                                                                   "--moving", "track", "--grid", "20x20x4"],
     ["--moving", "box tables", "sample_annotation"], ["o"]),
    ("pseudo-labels --keyframes 0", lambda w: ["pseudo-labels", "--data", w.data, "--out", "o", "--keyframes", "0"],
     ["--keyframes"], ["o"]),
    ("pseudo-labels --interval 0", lambda w: ["pseudo-labels", "--data", w.data, "--out", "o", "--interval", "0"],
     ["--interval"], ["o"]),
    ("pseudo-labels --sweeps without sweeps", lambda w: ["pseudo-labels", "--data", w.data, "--out", "o",
                                                         "--sweeps", "3", "--grid", "20x20x4"], ["--sweeps"], ["o"]),
    ("pseudo-labels --segmenter", lambda w: ["pseudo-labels", "--data", w.data, "--out", "o", "--segmenter", "sam"],
     ["--segmenter", "sam"], ["o"]),
    ("pseudo-labels --grid", lambda w: ["pseudo-labels", "--data", w.data, "--out", "o", "--grid", "10x10"],
     ["--grid"], ["o"]),
    ("pseudo-labels --split", lambda w: ["pseudo-labels", "--data", w.data, "--out", "o", "--split", "test",
                                         "--grid", "20x20x4"], ["splits.json", "test"], ["o"]),
    ("pseudo-labels no --data", lambda w: ["pseudo-labels", "--out", "o"], ["--data", "missing"], ["o"]),
    ("seen-gt no --prompts", lambda w: ["seen-gt", "--data", w.data, "--pseudo", w.pseudo, "--out", "o"],
     ["--prompts", "missing"], ["o"]),
    ("seen-gt other classes", lambda w: ["seen-gt", "--data", w.data, "--pseudo", w.pseudo, "--prompts", "ow_pretrain",
                                         "--out", "o", "--split", "all"], ["meta.json", "classes"], ["o"]),
    ("seen-gt --pseudo a file", lambda w: ["seen-gt", "--data", w.data, "--pseudo", w.a_file, "--prompts", "veon_9_8",
                                           "--out", "o", "--split", "all"], ["meta.json"], ["o"]),
    ("seen-gt --split", lambda w: ["seen-gt", "--data", w.data, "--pseudo", w.pseudo, "--prompts", "veon_9_8",
                                   "--out", "o", "--split", "test"], ["splits.json", "test"], ["o"]),
    ("train --set lr=-1", lambda w: ["train", "--config", "tiny", "--set", "lr=-1", "--out", "o"], ["--set", "lr"], ["o"]),
    ("train --set epochs=abc", lambda w: ["train", "--config", "tiny", "--set", "epochs=abc", "--out", "o"],
     ["epochs"], ["o"]),
    ("train --set model.hidden_dim=0", lambda w: ["train", "--config", "tiny", "--set", "model.hidden_dim=0",
                                                  "--out", "o"], ["model.hidden_dim"], ["o"]),
    ("train --set unknown key", lambda w: ["train", "--config", "tiny", "--set", "learning_rate=1", "--out", "o"],
     ["learning_rate"], ["o"]),
    ("train --set device", lambda w: ["train", "--config", "tiny", "--set", 'device="tpu9"', "--out", "o"],
     ["tpu9"], ["o"]),
    ("train --set loss.class_balance=5", lambda w: ["train", "--config", "tiny", "--set", "loss.class_balance=5",
                                                    "--out", "o"], ["--set", "loss.class_balance"], ["o"]),
    ("train --config missing.json", lambda w: ["train", "--config", "missing.json"], ["missing.json"], []),
    ("train --bogus", lambda w: ["train", "--bogus"], ["--bogus"], []),
    ("eval --max-frames -1", lambda w: ["eval", "--ckpt", w.ckpt, "--data", w.data, "--split", "all",
                                        "--max-frames", "-1", "--out", "o"], ["--max-frames"], ["o"]),
    ("eval --device tpu9", lambda w: ["eval", "--ckpt", w.ckpt, "--data", w.data, "--split", "all", "--device",
                                      "tpu9", "--out", "o"], ["--device", "tpu9"], ["o"]),
    ("eval no --data", lambda w: ["eval", "--ckpt", w.ckpt], ["--data", "missing"], []),
    ("eval --readout fine", lambda w: ["eval", "--ckpt", w.ckpt, "--data", w.data, "--split", "all", "--readout",
                                       "fine", "--out", "o"], ["--readout", "fine"], ["o"]),
    ("calibrate not a run folder", lambda w: ["calibrate", w.data], ["not a finished"], []),
    ("calibrate missing folder", lambda w: ["calibrate", "no_such_run"], ["no_such_run"], []),
    ("open-world --k 0", lambda w: ["open-world", "--pseudo-pretrain", w.pseudo, "--k", "0", "--out", "o"],
     ["--k"], ["o"]),
    ("open-world --seeds", lambda w: ["open-world", "--pseudo-pretrain", w.pseudo, "--stage", "pretrain", "--seeds",
                                      "a,b", "--out", "o"],
     ["--seeds"], ["o"]),
    ("open-world --stage", lambda w: ["open-world", "--pseudo-pretrain", w.pseudo, "--stage", "later", "--out", "o"],
     ["--stage"], ["o"]),
    ("experiments run --profile", lambda w: ["experiments", "run", "--profile", "huge", "--out", "o"], ["huge"], ["o"]),
    ("experiments run unknown name", lambda w: ["experiments", "run", "tab9", "--out", "o"], ["tab9"], ["o"]),
    ("experiments report --bogus", lambda w: ["experiments", "report", "--bogus"], ["--bogus"], []),
    ("experiments list --profile", lambda w: ["experiments", "list", "--profile", "huge"], ["huge"], []),
    ("export no checkpoint", lambda w: ["export"], ["CHECKPOINT", "missing"], []),
    ("export --bogus", lambda w: ["export", w.ckpt, "--bogus"], ["--bogus"], []),
    ("export --card-json missing", lambda w: ["export", w.ckpt, "-o", "b", "--card-json", "nope.json"],
     ["nope.json"], ["b"]),

    # ---- output paths, checked before the work
    ("synth --out /sys", lambda w: ["synth", "--out", "/sys/ago-test", "--scenes", "1", "--frames", "1"],
     ["/sys/ago-test", "cannot write"], []),
    ("synth --out a file", lambda w: ["synth", "--out", w.a_file], ["a_file.txt", "not a folder"], []),
    ("synth --out under a file", lambda w: ["synth", "--out", w.a_file / "x"], ["a_file.txt", "not a folder"], []),
    ("pseudo-labels --out /proc", lambda w: ["pseudo-labels", "--data", w.data, "--out", "/proc/ago-test/x"],
     ["/proc/ago-test/x", "cannot write"], []),
    ("infer --out /sys", lambda w: ["infer", "--images", w.frame, "--bundle", w.bundle, "--out", "/sys/ago-test"],
     ["/sys/ago-test"], []),
    ("infer --out a file", lambda w: ["infer", "--images", w.frame, "--bundle", w.bundle, "--out", w.a_file],
     ["a_file.txt"], []),
    ("demo --out /sys", lambda w: ["demo", "--out", "/sys/ago-test"], ["/sys/ago-test"], []),
    ("retrieve --out /sys", lambda w: ["retrieve", "--images", w.frame, "--phrase", "car", "--bundle", w.bundle,
                                       "--out", "/sys/ago-test"], ["/sys/ago-test"], []),
    ("show --out /sys", lambda w: ["show", w.gt, "--out", "/sys/ago-test.png"], ["/sys/ago-test.png"], []),
    ("show --out a folder", lambda w: ["show", w.gt, "--out", w.root], ["is a folder"], []),
    ("show --out /dev/null", lambda w: ["show", w.gt, "--out", "/dev/null"], ["/dev/null", "not a regular file"], []),
    ("metric --json /sys", lambda w: ["metric", "--pred", w.data / "gts", "--gt", w.data / "gts", "--json",
                                      "/sys/ago-test.json"], ["/sys/ago-test.json"], []),
    ("metric --md a folder", lambda w: ["metric", "--pred", w.data / "gts", "--gt", w.data / "gts", "--md", w.root],
     ["is a folder"], []),
    ("prompts build -o /sys", lambda w: ["prompts", "build", "cw", "-o", "/sys/ago-test.npz"], ["/sys/ago-test.npz"], []),
    ("prompts noise -o /sys", lambda w: ["prompts", "noise", "-o", "/sys/ago-test.npz"], ["/sys/ago-test.npz"], []),
    ("prompts export-encoder -o /sys", lambda w: ["prompts", "export-encoder", "-o", "/sys/ago-test.onnx"],
     ["/sys/ago-test.onnx"], []),
    ("train --out /sys", lambda w: ["train", "--config", "tiny", "--out", "/sys/ago-test"], ["/sys/ago-test"], []),
    ("eval --out /sys", lambda w: ["eval", "--ckpt", w.ckpt, "--data", w.data, "--split", "all", "--out",
                                   "/sys/ago-test"], ["/sys/ago-test"], []),
    ("open-world --out /sys", lambda w: ["open-world", "--pseudo-pretrain", w.pseudo, "--out", "/sys/ago-test"],
     ["/sys/ago-test"], []),
    ("experiments run --out /sys", lambda w: ["experiments", "run", "--profile", "tiny", "--out", "/sys/ago-test"],
     ["/sys/ago-test"], []),
    ("experiments report --out a file", lambda w: ["experiments", "report", "--out", w.a_file], ["a_file.txt"], []),
    ("export -o /sys", lambda w: ["export", w.ckpt, "-o", "/sys/ago-test"], ["/sys/ago-test"], []),
    ("export -o a file", lambda w: ["export", w.ckpt, "-o", w.a_file], ["a_file.txt"], []),

    # ---- images and calibration
    ("JPEG header claims 30000x16875", lambda w: ["infer", "--images", w.bomb, "--bundle", w.bundle, "--out", "o"],
     ["CAM_FRONT.jpg", "30000x16875"], ["o"]),
    ("JPEG with scrambled middle bytes", lambda w: ["infer", "--images", w.scrambled, "--bundle", w.bundle,
                                                    "--out", "o"], ["CAM_FRONT.jpg", "corrupt"], ["o"]),
    ("truncated JPEG", lambda w: ["infer", "--images", w.truncated, "--bundle", w.bundle, "--out", "o"],
     ["CAM_BACK.jpg"], ["o"]),
    ("negative focal length", lambda w: ["infer", "--images", w.negfocal, "--bundle", w.bundle, "--out", "o"],
     ["calib.json", "focal"], ["o"]),
    ("cam2ego not a rotation", lambda w: ["infer", "--images", w.scaled, "--bundle", w.bundle, "--out", "o"],
     ["calib.json", "rotation"], ["o"]),
    ("images folder missing", lambda w: ["infer", "--images", "nowhere", "--bundle", w.bundle, "--out", "o"],
     ["nowhere"], ["o"]),
    ("--sample not in the dataset", lambda w: ["infer", "--images", w.data, "--sample", "nosuchtoken", "--bundle",
                                               w.bundle, "--out", "o"], ["nosuchtoken"], ["o"]),
    ("--sample on an images folder", lambda w: ["infer", "--images", w.frame, "--sample", "x", "--bundle", w.bundle,
                                                "--out", "o"], ["--sample"], ["o"]),

    # ---- pickles, banks, bundles, npz
    ("info pickle allocating 3 GB", lambda w: ["infer", "--info", w.pkl_bomb, "--bundle", w.bundle, "--out", "o"],
     ["bomb.pkl", "bytearray"], ["o"]),
    ("info pickle running code", lambda w: ["infer", "--info", w.pkl_code, "--bundle", w.bundle, "--out", "o"],
     ["code.pkl", "refusing"], ["o"]),
    ("info pickle of repeated references", lambda w: ["infer", "--info", w.pkl_laughs, "--bundle", w.bundle,
                                                      "--out", "o"], ["laughs.pkl"], ["o"]),
    ("5000-class prompt file", lambda w: ["infer", "--images", w.frame, "--bundle", w.bundle, "--prompts",
                                          w.big_prompts, "--out", "o"], ["big5000.txt", "5000 classes"], ["o"]),
    ("bank of another encoder", lambda w: ["infer", "--images", w.frame, "--bundle", w.bundle, "--bank",
                                           w.foreign_bank, "--out", "o"], ["foreign.npz", "some-other-encoder"], ["o"]),
    ("heads of other widths", lambda w: ["infer", "--images", w.frame, "--bundle", w.bad_heads, "--out", "o"],
     ["heads.npz"], ["o"]),
    ("bundle folder missing", lambda w: ["infer", "--images", w.frame, "--bundle", "nobundle", "--out", "o"],
     ["nobundle"], ["o"]),
    ("show a broken npz", lambda w: ["show", w.bad_npz, "--out", "o.png"], ["bad.npz"], ["o.png"]),
    ("show --index out of range", lambda w: ["show", w.data, "--index", "99", "--out", "o.png"], ["--index 99"],
     ["o.png"]),
    ("metric on a missing folder", lambda w: ["metric", "--pred", "nopred", "--gt", w.data / "gts"], ["nopred"], []),

    # ---- checkpoints and runs
    ("eval on a raw pickle", lambda w: ["eval", "--ckpt", w.raw_pickle, "--data", w.data, "--split", "all",
                                        "--out", "o"], ["raw.pt", "not a loadable"], ["o"]),
    ("eval on weights not fitting their config", lambda w: ["eval", "--ckpt", w.mismatched, "--data", w.data,
                                                            "--split", "all", "--out", "o"],
     ["mismatched.pt", "do not fit"], ["o"]),
    ("export of weights not fitting their config", lambda w: ["export", w.mismatched, "-o", "b", "--no-real-frame"],
     ["mismatched.pt"], ["b"]),
    ("train --resume with another model size", lambda w: ["train", "--config", "tiny", "--resume", "--out",
                                                          w.resume_run, "--set", "model.hidden_dim=24", *TRAIN(w)],
     ["last.pt", "model settings differ", "hidden_dim"], []),
    ("train init_from another size", lambda w: ["train", "--config", "tiny", "--out", "o", "--set",
                                                f'init_from="{w.other_size}"', *TRAIN(w)],
     ["other_size.pt", "do not fit"], ["o"]),
    ("train on a truncated labels.npz", lambda w: ["train", "--config", "tiny", "--out", "o", "--data", w.data,
                                                   "--pseudo", w.broken_pseudo, "--set", 'train_split="all"',
                                                   "--set", f'noise_bank="{w.noise}"', "--set", 'device="cpu"'],
     ["labels.npz", "truncated"], ["o"]),
]


@pytest.mark.parametrize("row", ROWS, ids=[r[0] for r in ROWS])
def test_bad_input_row(w, row, tmp_path):
    _, make_args, needles, outputs = row
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    before = snapshot(w.root)
    r = run_ago(make_args(w), cwd)
    assert_one_error_line(r, *[str(n) for n in needles])
    assert not any(cwd.iterdir()), f"written into the working directory: {sorted(os.listdir(cwd))}"
    for rel in outputs:
        assert not (cwd / rel).exists()
    assert snapshot(w.root) == before, "an input changed"


def test_the_table_covers_every_verb():
    """Each verb of `ago --help` (and each prompts / experiments sub-verb) has rows in the table."""
    import typer.main

    from ago_runtime.cli import app

    class AnyInput:
        def __getattr__(self, name):
            return Path("x")

    group = typer.main.get_command(app)
    verbs = []
    for name, cmd in group.commands.items():
        sub = getattr(cmd, "commands", None)
        verbs += [[name, s] for s in sub] if sub else [[name]]
    starts = [[str(a) for a in row[1](AnyInput())] for row in ROWS]
    missing = [" ".join(v) for v in verbs if not any(s[:len(v)] == v for s in starts)]
    assert len(verbs) >= 18 and not missing, f"verbs without a bad-input row: {missing}"


# ------------------------------------------------------------------------------------ rows that are not exit 2
def test_usage_error_classes_are_the_ones_typer_raises():
    """The handler catches the classes typer exports: a usage error of the click typer runs on (typer._click
    for typer >= 0.26, else click) is a CLICK_ERROR with click's usage exit code, a bad value a typer.BadParameter."""
    import typer.main

    from ago_runtime.cli import CLICK_ERROR, USAGE_EXIT_CODE, build_app

    assert issubclass(typer.BadParameter, CLICK_ERROR)
    command = typer.main.get_command(build_app("show"))
    with pytest.raises(CLICK_ERROR) as e:
        command.main(args=["show", "--bogus"], prog_name="ago", standalone_mode=False)
    assert e.value.exit_code == USAGE_EXIT_CODE
    with pytest.raises(typer.BadParameter):
        command.main(args=["show", "x", "--view", "sideways"], prog_name="ago", standalone_mode=False)


def test_scrambled_jpegs_are_refused_as_measured():
    """decode_image refuses 2 000-byte scrambles of the middle of a real-size JPEG, with and without 0xFF
    bytes in the junk, where cv2.imdecode alone returns an image for each (benchmarks/results/corrupt_jpeg.md)."""
    from ago_runtime.errors import AgoInputError
    from ago_runtime.formats.image_files import decode_image

    data = (Path(__file__).resolve().parents[1] / "ago_runtime" / "assets" / "demo_frame" / "CAM_FRONT.jpg").read_bytes()
    assert decode_image(data, "ok.jpg").shape[2] == 3
    for seed in range(6):
        bad = scrambled(data, 2000, seed, no_ff=bool(seed % 2))
        assert cv2.imdecode(np.frombuffer(bad, np.uint8), cv2.IMREAD_COLOR) is not None   # what cv2 alone does
        with pytest.raises(AgoInputError, match="corrupt image data"):
            decode_image(bad, f"scrambled{seed}.jpg")


def test_png_header_size_is_checked_before_decoding(tmp_path):
    from ago_runtime.errors import AgoInputError
    from ago_runtime.formats.synthetic_maps import read_png

    ok, png = cv2.imencode(".png", np.zeros((4, 4), np.uint8))
    b = bytearray(png.tobytes())
    b[16:24] = struct.pack(">II", 100000, 100000)     # IHDR claims 10^10 pixels
    (tmp_path / "big.png").write_bytes(bytes(b))
    with pytest.raises(AgoInputError, match="100000x100000"):
        read_png(tmp_path / "big.png", np.uint8)


def test_pseudo_label_resume_remakes_a_truncated_file(w, tmp_path):
    out = tmp_path / "pl"
    args = ["pseudo-labels", "--data", w.data, "--out", out, "--grid", "20x20x4", "--keyframes", "1", "--split", "all"]
    assert run_ago(args, tmp_path).code == 0
    victim = next(out.glob("*/*/labels.npz"))
    good = victim.read_bytes()
    victim.write_bytes(good[: len(good) // 3])
    r = run_ago(args, tmp_path)
    assert r.code == 0 and "1 damaged ones remade" in r.stdout, r.stdout + r.stderr
    from ago_train.pseudo.generate import PseudoLabelDir

    d = PseudoLabelDir(out)
    assert all(d.sample_problem(s, t) is None for s, t in d.samples())


def test_train_on_a_truncated_file_writes_no_run_files(w, tmp_path):
    out = tmp_path / "run"
    r = run_ago(["train", "--config", "tiny", "--out", out, "--data", w.data, "--pseudo", w.broken_pseudo,
                 "--set", 'train_split="all"', "--set", f'noise_bank="{w.noise}"', "--set", 'device="cpu"'], tmp_path)
    assert_one_error_line(r, str(w.broken_labels.name))
    assert not (out / "config.json").exists() and not (out / "log.jsonl").exists()


def test_export_cleans_temp_folders_of_killed_exports(w, tmp_path):
    """A killed export's `.NAME.tmp-PID-*` folder is removed by the next export; the bundle is swapped in
    without ever being missing (atomic exchange), and a fallback swap killed between its renames is undone."""
    from ago_runtime.atomic import clean_stale_dirs, replace_dir
    import ago_runtime.atomic as atomic

    out = tmp_path / "bundle"
    dead = 2 ** 22 + 12345                     # above the default pid_max: no such process
    stale = tmp_path / f".bundle.tmp-{dead}-abc"
    stale.mkdir()
    (stale / "planes.onnx").write_bytes(b"half")
    alive = tmp_path / f".bundle.tmp-{os.getpid()}-xyz"     # a running export's folder is left alone
    alive.mkdir()
    r = run_ago(["export", w.ckpt, "-o", out, "--no-real-frame", "--train-bank-only"], tmp_path)
    assert r.code == 0, r.stderr
    assert not stale.exists() and alive.exists() and (out / "bundle.json").is_file()
    alive.rmdir()
    card = json.loads((out / "card.json").read_text())
    assert card["format"] == "ago-bundle-card" and card["label_space"]["name"] == "cw"

    # the swap: old contents replaced, never absent; the fallback path's kill is repaired
    new = tmp_path / "new"
    new.mkdir()
    (new / "bundle.json").write_text("{}")
    replace_dir(new, out)
    assert (out / "bundle.json").read_text() == "{}" and not new.exists()
    moved = tmp_path / f".bundle.old-{dead}"
    out.rename(moved)                          # as if killed after `out -> .old`, before `tmp -> out`
    clean_stale_dirs(out)
    assert (out / "bundle.json").is_file() and not moved.exists()
    assert atomic._exchange(tmp_path / "nope-a", tmp_path / "nope-b") is False


def test_pseudo_labels_default_carve_is_grazing(w):
    """`ago pseudo-labels` without --carve casts rays under the grazing rule, and records it."""
    meta = json.loads((w.pseudo / "meta.json").read_text())
    assert meta["carve"] == "grazing" and meta["config"]["carve"] == {"margin": 0.5, "column": True}


def test_bundle_card_line_and_default_bundle_without_card(w):
    from ago_runtime.predict.bundle import DEFAULT_BUNDLE_DIR, Bundle, card_line

    b = Bundle.load(w.bundle)
    assert b.card is not None and card_line(b).startswith("bundle: trained on")
    if (DEFAULT_BUNDLE_DIR / "bundle.json").is_file() and not (DEFAULT_BUNDLE_DIR / "card.json").is_file():
        line = card_line(Bundle.load(DEFAULT_BUNDLE_DIR, verify_hashes=False))
        assert "no bundle card" in line and "SYNTHETIC" in line


def test_card_from_a_training_run(tmp_path):
    """make_card reads the run: synthetic data, frames of the split, steps, eval-val/metrics.json, a note."""
    pytest.importorskip("torch")
    from ago_export.card import make_card
    from ago_export.testing import random_checkpoint
    from ago_train.checkpoint import CheckpointContract

    data = tmp_path / "data"
    (data / "v1.0-trainval").mkdir(parents=True)
    (data / "v1.0-trainval" / "scene.json").write_text(json.dumps(
        [{"token": "s1", "name": "a", "description": "ago synth seed 0 scene 0"},
         {"token": "s2", "name": "b", "description": "ago synth seed 0 scene 1"}]))
    (data / "v1.0-trainval" / "sample.json").write_text(json.dumps(
        [{"token": f"t{i}", "scene_token": "s1" if i < 3 else "s2"} for i in range(5)]))
    (data / "v1.0-trainval" / "sample_data.json").write_text(json.dumps(
        [{"token": "l0", "fileformat": "pcd", "width": 0, "height": 0},
         {"token": "c0", "fileformat": "jpg", "width": 352, "height": 198}]))
    (data / "splits.json").write_text(json.dumps({"train": ["a"], "val": ["b"]}))
    run = tmp_path / "run"
    (run / "eval-val").mkdir(parents=True)
    (run / "eval-val" / "metrics.json").write_text(json.dumps({"mIoU": 7.84, "split": "val", "frames": 2}))
    ckpt = dataclasses.replace(
        CheckpointContract.load(random_checkpoint(tmp_path / "r.pt", "tiny", prompts="cw")), step=384, epoch=3,
        train_config={"data": str(data), "train_split": "train", "val_split": "val", "name": "cpu",
                      "pseudo": str(tmp_path / "none")})
    card = make_card(ckpt, run / "last.pt", note="demo only", extra={"val_scores": {"mIoU": 8.0}})
    assert card["trained_on"]["kind"] == "synthetic" and card["trained_on"]["frames"] == 3
    assert card["trained_on"]["image_size"] == [352, 198]   # the first camera record's, not the LiDAR's
    assert card["val_scores"]["mIoU"] == 8.0 and card["val_scores"]["split"] == "val"
    s = card["summary"]
    assert "SYNTHETIC" in s and "3 frames of 352x198" in s and "384 steps" in s and "val mIoU 8.0 %" in s
    assert s.endswith("not a nuScenes model; demo only")


# ------------------------------------------------------------------------------------ round two (issue 36)
@pytest.fixture(scope="module")
def h(w, tmp_path_factory):
    """Inputs of issue 36's cases: deep and empty info files and calibrations, files outside the data root,
    huge prompt lines, a dataset whose sample_data.json names files outside it."""
    root = tmp_path_factory.mktemp("hostile2")
    x = types.SimpleNamespace(root=root, w=w)
    x.outside = root / "outside"                       # a valid JPEG outside every data root
    x.outside.mkdir()
    shutil.copy(w.frame / "CAM_FRONT.jpg", x.outside / "CAM_FRONT.jpg")
    x.info_root = root / "info_root"
    x.info_root.mkdir()

    def info(name, change):
        rig = Rig.nuscenes_like(400, 225)
        sample = {"token": "t0", "timestamp": 0.0, "ego2global": np.eye(4).tolist(), "images": {},
                  "lidar_points": {"lidar_path": "x.bin", "lidar2ego": np.eye(4).tolist(), "num_pts_feats": 5}}
        for cam in rig:
            sample["images"][cam.name] = {"img_path": f"{cam.name}.jpg", "cam2img": cam.intrinsics.tolist(),
                                          "cam2ego": cam.cam2ego.tolist()}
        d = {"metainfo": {}, "data_list": [sample]}
        change(d, sample)
        p = root / name
        p.write_bytes(pickle.dumps(d, protocol=4))
        return p

    def passwd(d, s):
        s["images"]["CAM_FRONT"]["img_path"] = "../../../../etc/passwd"
        s["lidar_points"]["lidar_path"] = "/etc/hostname"

    x.info_passwd = info("passwd.pkl", passwd)
    x.info_outside = info("outside.pkl", lambda d, s: s["images"]["CAM_FRONT"].update(
        img_path=str(x.outside / "CAM_FRONT.jpg")))
    x.info_empty = info("empty.pkl", lambda d, s: d.update(data_list=[]))
    x.info_deep = root / "deep.pkl"     # {"data_list": [[[...]]]} 3000 deep, by opcodes (EMPTY_LIST, APPEND)
    x.info_deep.write_bytes(b"\x80\x02}X\x09\x00\x00\x00data_list" + b"]" * 3000 + b"a" * 2999 + b"s.")
    x.deep_calib = shutil.copytree(w.frame, root / "deep_calib")
    (x.deep_calib / "calib.json").write_text("[" * 100000 + "]" * 100000)
    x.far_calib = shutil.copytree(w.frame, root / "far_calib")
    calib = json.loads((x.far_calib / "calib.json").read_text())
    calib["cameras"]["CAM_BACK"]["cam2ego"][0][3] = 1e308
    (x.far_calib / "calib.json").write_text(json.dumps(calib))
    x.long_line = root / "long_line.txt"
    x.long_line.write_text("car: " + " ".join(["word"] * 200000) + "\n")
    x.nul_prompts = root / "nul.txt"
    x.nul_prompts.write_bytes(b"car: car\x00boat\n")
    x.outside_data = shutil.copytree(w.data, root / "outside_data")     # sample_data names ../outside/CAM_FRONT.jpg
    table = next(x.outside_data.glob("v1.0-*")) / "sample_data.json"
    records = json.loads(table.read_text())
    for r in records:
        if r["filename"].startswith("samples/CAM_FRONT/"):
            r["filename"] = "../outside/CAM_FRONT.jpg"
    table.write_text(json.dumps(records))
    return x


ROWS2 = [
    # 1. tracebacks
    ("synth --scenes 10^20", lambda h: ["synth", "--scenes", "99999999999999999999", "--out", "o"], ["--scenes"], ["o"]),
    ("synth --image-size 100000x100000", lambda h: ["synth", "--image-size", "100000x100000", "--out", "o"],
     ["--image-size", "4096"], ["o"]),
    ("synth --grid 100000x100000x100", lambda h: ["synth", "--grid", "100000x100000x100", "--out", "o"],
     ["--grid"], ["o"]),
    ("synth --scenes 100000 --frames 100000", lambda h: ["synth", "--scenes", "100000", "--frames", "100000",
                                                         "--out", "o"], ["--scenes"], ["o"]),
    ("synth --frames 100000", lambda h: ["synth", "--frames", "100000", "--out", "o"], ["--frames"], ["o"]),
    ("train --set model.grid shape 0", lambda h: ["train", "--config", "tiny", "--set",
                                                   'model.grid={"shape":[0,0,0]}', "--out", "o"],
     ["--set", "model.grid"], ["o"]),
    ("train --set model.grid of 0 m voxels", lambda h: [
        "train", "--config", "tiny", "--set",
        'model.grid={"range_min":[-40,-40,-1],"range_max":[40,40,5.4],"voxel_size":[0,0,0]}', "--out", "o"],
     ["--set", "model.grid", "voxel sizes"], ["o"]),
    ("train --set deeply nested value", lambda h: ["train", "--config", "tiny", "--set",
                                                   "epochs=" + "[" * 30000 + "]" * 30000, "--out", "o"],
     ["--set", "epochs", "nested"], ["o"]),
    ("infer --info with an empty data_list", lambda h: ["infer", "--info", h.info_empty, "--bundle", h.w.bundle,
                                                        "--out", "o"], ["empty.pkl", "data_list is empty"], ["o"]),
    ("infer --info of a pickle nested 3000 deep", lambda h: ["infer", "--info", h.info_deep, "--bundle", h.w.bundle,
                                                             "--out", "o"], ["deep.pkl", "nested"], ["o"]),
    ("calib.json of 100000 nested [", lambda h: ["infer", "--images", h.deep_calib, "--bundle", h.w.bundle,
                                                 "--out", "o"], ["calib.json", "nested"], ["o"]),
    # 2. a hang
    ("prompt line of 200000 words", lambda h: ["infer", "--images", h.w.frame, "--bundle", h.w.bundle, "--prompts",
                                               h.long_line, "--out", "o"], ["long_line.txt", "characters"], ["o"]),
    ("--phrase of 1 MB", lambda h: ["retrieve", "--images", h.w.frame, "--bundle", h.w.bundle, "--phrase",
                                    "cone " * 200000, "--out", "o"], ["--phrase", "characters"], ["o"]),
    # 3. paths outside the data
    ("info naming /etc/passwd and /etc/hostname", lambda h: ["infer", "--info", h.info_passwd, "--images", h.info_root,
                                                             "--bundle", h.w.bundle, "--out", "o"],
     ["passwd.pkl", "outside the data root"], ["o"]),
    ("info naming a valid JPEG outside the root", lambda h: ["infer", "--info", h.info_outside, "--images",
                                                             h.info_root, "--bundle", h.w.bundle, "--out", "o"],
     ["outside.pkl", "CAM_FRONT.img_path", "absolute"], ["o"]),
    ("sample_data naming a valid JPEG outside", lambda h: ["infer", "--images", h.outside_data, "--bundle",
                                                           h.w.bundle, "--out", "o"],
     ["sample_data.json", "outside the data root"], ["o"]),
    ("show of a dataset naming files outside", lambda h: ["show", h.outside_data, "--index", "0", "--out", "o.png"],
     ["sample_data.json", "outside the data root"], ["o.png"]),
    # 4. one line, before the work
    ("eval --gts missing", lambda h: ["eval", "--ckpt", h.w.ckpt, "--data", h.w.data, "--split", "all", "--gts",
                                      "nogts", "--out", "o"], ["--gts", "nogts"], ["o"]),
    ("export --parity-frame missing", lambda h: ["export", h.w.ckpt, "-o", "b", "--parity-frame", "noframe"],
     ["--parity-frame", "noframe"], ["b"]),
    ("calibration translation 1e308", lambda h: ["infer", "--images", h.far_calib, "--bundle", h.w.bundle,
                                                 "--out", "o"], ["calib.json", "CAM_BACK"], ["o"]),
    # 5. the right option named
    ("open-world --seeds a,b", lambda h: ["open-world", "--pseudo-pretrain", h.w.pseudo, "--seeds", "a,b",
                                          "--out", "o"], ["--seeds"], ["o"]),
    ("open-world --seeds ''", lambda h: ["open-world", "--pseudo-pretrain", h.w.pseudo, "--seeds", "", "--out", "o"],
     ["--seeds"], ["o"]),
    ("open-world --pseudo-pretrain missing", lambda h: ["open-world", "--pseudo-pretrain", "nope", "--out", "o"],
     ["--pseudo-pretrain", "nope"], ["o"]),
    ("prompts build --template with two {}", lambda h: ["prompts", "build", "cw", "-o", "b.npz", "--template",
                                                        "a {} {}"], ["--template"], ["b.npz"]),
    # 6. bad input accepted before
    ("synth --out ''", lambda h: ["synth", "--out", "", "--scenes", "1", "--frames", "1"], ["--out", "empty"], []),
    ("export --bank-prompts missing", lambda h: ["export", h.w.ckpt, "-o", "b", "--no-real-frame", "--bank-prompts",
                                                 "nofile.txt"], ["--bank-prompts", "nofile.txt"], ["b"]),
    ("export --readout-grid coarser", lambda h: ["export", h.w.ckpt, "-o", "b", "--no-real-frame", "--readout-grid",
                                                 "10x10x4"], ["--readout-grid", "coarser"], ["b"]),
    ("export --parity-frame with --no-real-frame", lambda h: ["export", h.w.ckpt, "-o", "b", "--no-real-frame",
                                                              "--parity-frame", h.w.frame], ["--parity-frame"], ["b"]),
    ("metric --json and --md on one path", lambda h: ["metric", "--pred", h.w.data / "gts", "--gt", h.w.data / "gts",
                                                      "--json", "x.json", "--md", "x.json"], ["x.json", "--md"],
     ["x.json"]),
    ("show --out o.jpg", lambda h: ["show", h.w.gt, "--out", "o.jpg"], ["--out", "o.jpg", ".png"], ["o.jpg"]),
    ("retrieve --phrase a,b", lambda h: ["retrieve", "--images", h.w.frame, "--bundle", h.w.bundle, "--phrase", "a,b",
                                         "--out", "o"], ["--phrase", "commas"], ["o"]),
    ("retrieve --phrase with control characters", lambda h: ["retrieve", "--images", h.w.frame, "--bundle",
                                                             h.w.bundle, "--phrase", "cone\x1b[2J", "--out", "o"],
     ["--phrase", "control character"], ["o"]),
    ("prompt file with a NUL byte", lambda h: ["infer", "--images", h.w.frame, "--bundle", h.w.bundle, "--prompts",
                                               h.nul_prompts, "--out", "o"], ["nul.txt", "NUL"], ["o"]),
    # 8. no silent fallback
    ("--prompts in a missing folder", lambda h: ["infer", "--images", h.w.frame, "--bundle", h.w.bundle, "--prompts",
                                                 "no/such/dir/ow.txt", "--out", "o"],
     ["error: --prompts: no/such/dir/ow.txt", "prompt file not found"], ["o"]),
    ("--prompts an unknown shipped name", lambda h: ["infer", "--images", h.w.frame, "--bundle", h.w.bundle,
                                                     "--prompts", "prompts/nope.txt", "--out", "o"],
     ["--prompts", "prompts/nope.txt", "shipped"], ["o"]),
    ("--prompts a folder", lambda h: ["infer", "--images", h.w.frame, "--bundle", h.w.bundle, "--prompts",
                                      h.w.root, "--out", "o"], ["--prompts", "is a folder"], ["o"]),
]


def check_row(x, row, tmp_path, quiet_stdout: bool = False) -> None:
    """One row against the fixture `x` (with x.w the first round's): one error line naming the needles, nothing
    written, every input of both fixtures unchanged; quiet_stdout: stdout holds `note:` lines only."""
    _, make_args, needles, outputs = row
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    before = snapshot(x.w.root), snapshot(x.root)
    r = run_ago(make_args(x), cwd)
    assert_one_error_line(r, *[str(n) for n in needles])
    if quiet_stdout:
        assert not [ln for ln in r.stdout.splitlines() if ln.strip() and not ln.startswith("note: ")], r.stdout
    assert not any(cwd.iterdir()), f"written into the working directory: {sorted(os.listdir(cwd))}"
    for rel in outputs:
        assert not (cwd / rel).exists()
    assert (snapshot(x.w.root), snapshot(x.root)) == before, "an input changed"


@pytest.mark.parametrize("row", ROWS2, ids=[r[0] for r in ROWS2])
def test_bad_input_row_round_two(h, row, tmp_path):
    check_row(h, row, tmp_path)


def test_the_path_rule_allows_outside_only_when_asked(h, tmp_path):
    """The one path rule (ago_runtime.paths.inside_root): relative names stay, `..` and absolute names are
    refused; `--allow-outside-root` lets the valid JPEG outside the data root be read (the run then fails
    later only for the LiDAR file the info names, which does not exist)."""
    from ago_runtime.errors import AgoInputError
    from ago_runtime.paths import inside_root

    assert inside_root(tmp_path, "samples/CAM_FRONT/a.jpg", "t.json") == tmp_path / "samples/CAM_FRONT/a.jpg"
    for bad in ("../a.jpg", "samples/../../a.jpg", "/etc/passwd", "C:\\x.jpg", "..\\a.jpg", "a\x00b", "", 5):
        with pytest.raises(AgoInputError, match="t.json"):
            inside_root(tmp_path, bad, "t.json")
    assert inside_root(tmp_path, "/etc/hostname", "t.json", allow_outside=True) == Path("/etc/hostname")
    r = run_ago(["infer", "--info", h.info_outside, "--images", h.info_root, "--bundle", h.w.bundle, "--out", "o",
                 "--allow-outside-root"], tmp_path)
    line = assert_one_error_line(r)
    assert "outside" not in line and "CAM_FRONT_RIGHT.jpg" in line       # CAM_FRONT (outside) was accepted


def test_prompts_shipped_names_say_which_file(h, tmp_path):
    """`--prompts cw`, `cw.txt` or `prompts/cw.txt` with no such file in the working folder take the shipped
    file and say so in one `note:` line on stdout (stderr has no warning); a file of that name in the working
    folder is taken as it is, with no note."""
    for name in ("cw", "cw.txt", "prompts/cw.txt"):
        r = run_ago(["infer", "--images", h.w.frame, "--bundle", h.w.bundle, "--prompts", name, "--out", "o",
                     "--picture", "none"], tmp_path)
        assert r.code == 0, r.stderr
        notes = [ln for ln in r.stdout.splitlines() if ln.startswith("note: ")]
        assert len(notes) == 1 and f"--prompts {name}" in notes[0] and "shipped" in notes[0], r.stdout
        assert "warning:" not in r.stderr, r.stderr
    (tmp_path / "cw.txt").write_text("fire hydrant: fire hydrant\nmailbox: mailbox\n")
    r = run_ago(["infer", "--images", h.w.frame, "--bundle", h.w.bundle, "--prompts", "cw.txt", "--out", "o2",
                 "--picture", "none"], tmp_path)
    assert r.code == 0 and "note: " not in r.stdout, r.stdout + r.stderr
    with np.load(next((tmp_path / "o2").glob("*.npz"))) as z:
        assert list(z["class_names"])[:2] == ["fire hydrant", "mailbox"]   # the local file, not the shipped one


def test_infer_over_a_dataset_resumes_whole_frames_only(h, tmp_path):
    """Frames whose npz and PNG are whole and of the same settings are skipped (checked: every array read, the
    PNG decoded); a truncated npz or a missing PNG is made again; other settings remake every frame."""
    w = h.w
    args = ["infer", "--images", w.data, "--bundle", w.bundle, "--out", "out", "--picture", "bev", "--workers", "1"]
    r = run_ago(args, tmp_path)
    assert r.code == 0, r.stderr
    out = tmp_path / "out"
    npzs = sorted(out.glob("*.npz"))
    assert len(npzs) == 2 and len(list(out.glob("*.png"))) == 2
    stamp = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    r = run_ago(args, tmp_path)
    assert r.code == 0 and "resuming: 2 frames already whole" in r.stdout, r.stdout + r.stderr
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == stamp       # nothing rewritten

    first, second = npzs
    data = first.read_bytes()
    first.write_bytes(data[: len(data) // 2])                                  # a torn npz
    second.with_suffix(".png").unlink()                                        # an npz without its PNG
    r = run_ago(args, tmp_path)
    assert r.code == 0 and "to predict" not in r.stdout, r.stdout + r.stderr   # neither frame was whole
    assert first.read_bytes() != data[: len(data) // 2] and second.with_suffix(".png").is_file()
    from ago_runtime.predict.cli import frame_is_whole

    with np.load(first) as z:
        key = str(z["run_key"])
    assert all(frame_is_whole(out, p.stem, key, (20, 20, 4), "bev") for p in npzs)
    r = run_ago([*args, "--identifier", "max-conf"], tmp_path)                 # other settings: all remade
    assert r.code == 0 and "resuming" not in r.stdout
    r = run_ago([*args, "--no-resume"], tmp_path)
    assert r.code == 0 and "resuming" not in r.stdout


def test_kill_9_during_infer_leaves_only_whole_files(h, tmp_path):
    """`ago infer` over a dataset killed with SIGKILL mid-run: every npz / PNG left under its own name is whole
    (files are written to a hidden temp name and renamed), and the re-run completes the rest."""
    import signal
    import subprocess
    import sys
    import time

    w = h.w
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "ago_runtime.cli", "infer", "--images", str(w.data), "--bundle", str(w.bundle),
           "--out", str(out), "--picture", "full", "--workers", "1"]
    env = {**os.environ, "AGO_NO_PROGRESS": "1"}
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    deadline = time.time() + 60
    while time.time() < deadline and proc.poll() is None and not any(out.glob("*.png")):
        time.sleep(0.005)
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    from ago_runtime.formats.occ3d import load_semantics

    for p in out.glob("*.npz") if out.is_dir() else []:
        if not p.name.startswith("."):
            load_semantics(p)                                                  # whole, or this raises
    for p in out.glob("*.png") if out.is_dir() else []:
        if not p.name.startswith("."):
            assert cv2.imread(str(p)) is not None
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    assert len([p for p in out.glob("*.npz") if not p.name.startswith(".")]) == 2
    assert not [p.name for p in out.iterdir() if p.name.startswith(".") and ".tmp" in p.name]   # temp files gone


# ------------------------------------------------------------------------------------ round three (issue 54)
def _tampered_bundle(w, root: Path, name: str, change) -> Path:
    """A copy of the tiny bundle with bundle.json changed by `change(meta, folder)`; the sha256 entries of the files
    it rewrites are recomputed (a tamperer can), so only the values give it away."""
    from ago_runtime.predict.bundle import file_sha256

    d = shutil.copytree(w.bundle, root / name)
    meta = json.loads((d / "bundle.json").read_text())
    change(meta, d)
    for entry in meta["files"].values():
        p = d / entry["path"]
        if p.is_file() and entry["sha256"] != "keep":
            entry.update(sha256=file_sha256(p), size=p.stat().st_size)
    (d / "bundle.json").write_text(json.dumps(meta))
    return d


def _npz_of_header(path: Path, shape: str, member: str = "semantics") -> Path:
    """An npz whose one member is an .npy header declaring `shape` (uint8) and no data."""
    import zipfile

    header = ("{'descr': '|u1', 'fortran_order': False, 'shape': %s, }" % shape).encode()
    header = header + b" " * (118 - len(header)) + b"\n"
    with zipfile.ZipFile(path, "w") as z:
        z.writestr(f"{member}.npy", b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header)
    return path


def _stage_of_other_widths(path: Path, a: int, b: int) -> None:
    """A valid ONNX graph x (n, a) -> y (n, b): a voxel stage of another bundle."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    graph = helper.make_graph([helper.make_node("MatMul", ["x", "W"], ["y"])], "other",
                              [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["n", a])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["n", b])],
                              [numpy_helper.from_array(np.zeros((a, b), np.float32), "W")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, str(path))


@pytest.fixture(scope="module")
def r3(w, tmp_path_factory):
    """Inputs of issue 54's cases: bundles tampered by value (hashes recomputed), checkpoints with configs out of
    range, npz headers declaring huge dimensions over no data."""
    pytest.importorskip("onnx")
    import copy

    import torch

    root = tmp_path_factory.mktemp("hostile3")
    x = types.SimpleNamespace(root=root, w=w)

    def stage_swap(m, d):
        st = m["voxel_stages"][0]
        _stage_of_other_widths(d / m["files"][st["file"]]["path"], st["output_dim"], st["input_dim"])

    for name, change in (
        ("pre_huge", lambda m, d: m["preprocess"].update(width=10 ** 9)),
        ("pre_zero", lambda m, d: m["preprocess"].update(height=0)),
        ("std_zero", lambda m, d: m["preprocess"].update(std=[0.0, 0.224, 0.225])),
        ("mean_nan", lambda m, d: m["preprocess"].update(mean=[float("nan"), 0.456, 0.406])),
        ("hidden_huge", lambda m, d: m.update(hidden_dim=10 ** 9)),
        ("grid_consistent_lie", lambda m, d: m["grid"].update(shape=[40, 40, 8], voxel_size=[2.0, 2.0, 0.8])),
        ("rig_nan", lambda m, d: m["training_rig"]["cameras"][0]["intrinsics"][0].__setitem__(0, float("nan"))),
        ("default_bank", lambda m, d: m.update(default_bank="nope")),
        ("stage_swap", stage_swap),
        ("planes_swap", lambda m, d: shutil.copy(d / m["files"][m["voxel_stages"][0]["file"]]["path"],
                                                 d / m["files"]["planes"]["path"])),
    ):
        setattr(x, name, _tampered_bundle(w, root, name, change))
    ck = torch.load(w.ckpt, weights_only=True)
    for name, change in (
        ("ck_hidden_huge", lambda c: c["model_config"].update(hidden_dim=10 ** 9)),
        ("ck_grid_huge", lambda c: c["model_config"].update(grid={"range_min": [-40, -40, -1], "range_max": [40, 40, 5.4],
                                                                  "voxel_size": [1e-4, 1e-4, 1e-4]})),
        ("ck_rig_nan", lambda c: c["rig"]["cameras"][0]["intrinsics"][0].__setitem__(0, float("nan"))),
        ("ck_rig_three", lambda c: c["rig"].update(cameras=c["rig"]["cameras"][:3])),
    ):
        c = copy.deepcopy(ck)
        c.setdefault("rig", Rig.nuscenes_like(1600, 900).to_dict())   # the record a training run writes
        change(c)
        torch.save(c, root / f"{name}.pt")
        setattr(x, name, root / f"{name}.pt")
    x.huge_dims = _npz_of_header(root / "huge_dims.npz", "(0, 1000000000000, 100000)")
    x.empty_grid = _npz_of_header(root / "empty_grid.npz", "(0, 0, 0)")
    x.huge_names = _npz_of_header(root / "huge_names.npz", "(1000000000000,)", "class_names")
    return x


INFER3 = lambda r, b: ["infer", "--images", r.w.frame, "--bundle", b, "--out", "o"]   # noqa: E731

ROWS3 = [
    # 1. a bundle checked by value before any work (hashes recomputed by the tamperer)
    ("bundle preprocess width 10^9", lambda r: INFER3(r, r.pre_huge), ["bundle.json: preprocess.width", "16384"], ["o"]),
    ("bundle preprocess height 0", lambda r: INFER3(r, r.pre_zero), ["bundle.json: preprocess.height"], ["o"]),
    ("bundle preprocess std 0", lambda r: INFER3(r, r.std_zero), ["bundle.json: preprocess.std", "> 0"], ["o"]),
    ("bundle preprocess mean NaN", lambda r: INFER3(r, r.mean_nan), ["bundle.json: preprocess.mean", "finite"], ["o"]),
    ("bundle hidden_dim 10^9", lambda r: INFER3(r, r.hidden_huge), ["bundle.json: hidden_dim"], ["o"]),
    ("bundle training_rig NaN", lambda r: INFER3(r, r.rig_nan), ["bundle.json: training_rig", "NaN"], ["o"]),
    ("bundle default_bank not a bank", lambda r: INFER3(r, r.default_bank), ["bundle.json: default_bank"], ["o"]),
    ("bundle grid that is not the graphs'", lambda r: INFER3(r, r.grid_consistent_lie),
     ["planes.onnx: planes", "plane_xy", "40, 40"], ["o"]),
    ("bundle voxel stage of other widths", lambda r: INFER3(r, r.stage_swap), ["voxels_0.onnx: voxel_stages[0]"], ["o"]),
    ("bundle planes swapped for a stage", lambda r: ["retrieve", "--images", r.w.frame, "--phrase", "car", "--bundle",
                                                     r.planes_swap, "--out", "o"], ["planes.onnx: planes", "inputs"], ["o"]),
    # ... and a checkpoint's config
    ("checkpoint hidden_dim 10^9", lambda r: ["export", r.ck_hidden_huge, "-o", "b", "--no-real-frame"],
     ["ck_hidden_huge.pt: model_config", "hidden_dim"], ["b"]),
    ("checkpoint grid of 10^12 voxels", lambda r: ["eval", "--ckpt", r.ck_grid_huge, "--data", r.w.data, "--split",
                                                   "all", "--out", "o"], ["ck_grid_huge.pt: model_config", "model.grid"],
     ["o"]),
    ("checkpoint rig NaN", lambda r: ["export", r.ck_rig_nan, "-o", "b", "--no-real-frame"], ["ck_rig_nan.pt: rig", "NaN"],
     ["b"]),
    ("checkpoint rig of 3 cameras", lambda r: ["train", "--config", "tiny", "--out", "o", "--set",
                                               f'init_from="{r.ck_rig_three}"', *TRAIN(r.w)],
     ["ck_rig_three.pt: rig", "num_cameras"], ["o"]),
    # 2. free text bounded
    ("export --card-note of 400 characters", lambda r: ["export", r.w.ckpt, "-o", "b", "--no-real-frame", "--card-note",
                                                        "n" * 400], ["--card-note", "at most 300"], ["b"]),
    ("export --card-note of two lines", lambda r: ["export", r.w.ckpt, "-o", "b", "--no-real-frame", "--card-note",
                                                   "a\nb"], ["--card-note", "control character"], ["b"]),
    ("infer --sample of 5000 characters", lambda r: ["infer", "--images", r.w.data, "--sample", "t" * 5000, "--bundle",
                                                     r.w.bundle, "--out", "o"], ["--sample", "at most 300"], ["o"]),
    ("pseudo-labels --split with an escape", lambda r: ["pseudo-labels", "--data", r.w.data, "--out", "o", "--split",
                                                        "all\x1b[2J"], ["--split", "control character"], ["o"]),
    ("eval --out of 6000 characters", lambda r: ["eval", "--ckpt", r.w.ckpt, "--data", r.w.data, "--out", "d/" * 3000],
     ["--out", "at most 4096"], []),
    ("show PATH of 6000 characters", lambda r: ["show", "d/" * 3000, "--out", "o.png"], ["PATH", "at most 4096"],
     ["o.png"]),
    # 3. headers before data
    ("show an npz declaring (0, 10^12, 10^5)", lambda r: ["show", r.huge_dims, "--out", "o.png"],
     ["huge_dims.npz: semantics.npy", "declares shape"], ["o.png"]),
    ("show an npz of an empty grid", lambda r: ["show", r.empty_grid, "--out", "o.png"],
     ["empty_grid.npz", "empty grid"], ["o.png"]),
    ("show an npz declaring 10^12 class names", lambda r: ["show", r.huge_names, "--out", "o.png"],
     ["huge_names.npz: class_names.npy", "declares shape"], ["o.png"]),
    # 4. degenerate values refused with the minimum; options that do not apply refused
    ("synth --grid 1x1x1", lambda r: ["synth", "--grid", "1x1x1", "--out", "o", "--scenes", "1", "--frames", "1"],
     ["--grid", "1x1x1", "20x20x4"], ["o"]),
    ("synth --grid 20x20x3", lambda r: ["synth", "--grid", "20x20x3", "--out", "o"], ["--grid", "20x20x4"], ["o"]),
    ("pseudo-labels --grid 10x10x2", lambda r: ["pseudo-labels", "--data", r.w.data, "--out", "o", "--grid", "10x10x2"],
     ["--grid", "20x20x4"], ["o"]),
    ("show FILE --sample x", lambda r: ["show", r.w.gt, "--sample", "x", "--out", "o.png"],
     ["--sample", "does not apply to a labels file"], ["o.png"]),
    ("show FILE --index 0", lambda r: ["show", r.w.gt, "--index", "0", "--out", "o.png"], ["--index", "does not apply"],
     ["o.png"]),
    ("show DATASET --gt FILE", lambda r: ["show", r.w.data, "--index", "0", "--gt", r.w.gt, "--out", "o.png"],
     ["--gt", "does not apply to a dataset folder"], ["o.png"]),
    ("show DATASET --view bev", lambda r: ["show", r.w.data, "--index", "0", "--view", "bev", "--out", "o.png"],
     ["--view", "does not apply"], ["o.png"]),
    ("infer an images folder --allow-outside-root", lambda r: ["infer", "--images", r.w.frame, "--allow-outside-root",
                                                               "--bundle", r.w.bundle, "--out", "o"],
     ["--allow-outside-root", "images folder"], ["o"]),
    ("infer --prompts and --bank", lambda r: ["infer", "--images", r.w.frame, "--prompts", "cw", "--bank", "train",
                                              "--bundle", r.w.bundle, "--out", "o"], ["--bank", "not both"], ["o"]),
]


@pytest.mark.parametrize("row", ROWS3, ids=[r[0] for r in ROWS3])
def test_bad_input_row_round_three(r3, row, tmp_path):
    check_row(r3, row, tmp_path, quiet_stdout=True)


def test_min_model_grid_is_the_tiny_presets():
    """The minimum `--grid` comes from the presets (ago_train.model.config.min_model_grid), not a constant."""
    pytest.importorskip("torch")
    from ago_train.model.config import ModelConfig, min_model_grid

    assert min_model_grid() == ModelConfig.preset("tiny").grid_obj().shape == (20, 20, 4)


def test_progress_bars_only_on_a_terminal(w, tmp_path, monkeypatch):
    """With stderr redirected to a file, a verb that draws a bar and then fails leaves exactly its one error line
    (AGO_NO_PROGRESS unset); progress_enabled is False for a non-terminal stream."""
    import subprocess
    import sys

    from ago_runtime import progress

    monkeypatch.delenv("AGO_NO_PROGRESS", raising=False)
    monkeypatch.setattr(sys, "stderr", io.StringIO())
    assert not progress.progress_enabled()
    pred = tmp_path / "pred"                      # the GT's frames, the last one's prediction broken
    shutil.copytree(w.data / "gts", pred)
    last = sorted(pred.glob("*/*/labels.npz"))[-1]
    last.write_bytes(last.read_bytes()[:100])
    env = {k: v for k, v in os.environ.items() if k != "AGO_NO_PROGRESS"}
    env["PYTHONPATH"] = str(Path(__file__).resolve().parents[1]) + os.pathsep + env.get("PYTHONPATH", "")
    log = tmp_path / "stderr.log"
    with open(log, "w") as f:
        rc = subprocess.run([sys.executable, "-m", "ago_runtime.cli", "metric", "--pred", str(pred), "--gt",
                             str(w.data / "gts")], stdout=subprocess.DEVNULL, stderr=f, env=env, timeout=120).returncode
    lines = log.read_text().splitlines()
    assert rc == 2 and len(lines) == 1 and lines[0].startswith("error: ") and "labels.npz" in lines[0], lines


def test_graph_signature_check_names_the_graph(w):
    """check_graph compares an opened session's inputs and outputs with the contract's signature, without running it."""
    from ago_runtime.predict.bundle import Bundle
    from ago_runtime.predict.contract import check_graph, planes_signature, stage_signature
    import onnxruntime as ort

    b = Bundle.load(w.bundle)
    c = b.contract
    planes = ort.InferenceSession(str(b.file("planes").path), providers=["CPUExecutionProvider"])
    sig = planes_signature(len(c.rig.cameras), b.preprocess.height, b.preprocess.width, b.grid.shape,
                           c.voxel_stages[0].input_dim)
    check_graph(planes, sig, "planes.onnx", "planes")           # the bundle's own graph fits
    with pytest.raises(Exception, match="planes.onnx: voxel_stages\\[0\\]: graph inputs"):
        check_graph(planes, stage_signature(c.voxel_stages[0]), "planes.onnx", "voxel_stages[0]")
    bigger = planes_signature(len(c.rig.cameras), b.preprocess.height, b.preprocess.width,
                              tuple(2 * n for n in b.grid.shape), c.voxel_stages[0].input_dim)
    with pytest.raises(Exception, match="plane_xy"):
        check_graph(planes, bigger, "planes.onnx", "planes")


def test_option_bounds_are_one_rule_for_every_verb(tmp_path):
    """ago_runtime.cli.value_problem: names and notes at most 300 characters, paths 4096, no control characters
    except JSON white space in --set; run by every verb's command class (CheckedValues) on click's own parse of
    options and arguments, before the verb runs."""
    from ago_runtime.cli import value_problem

    assert value_problem("--set", 'model.grid={\n"shape": [20, 20, 4]}') is None
    assert value_problem("--set", "epochs=1\x00") == "holds the control character '\\x00'"
    assert value_problem("--card-note", "n" * 300) is None
    assert value_problem("--card-note", "n" * 301) == "is 301 characters long (at most 300)"
    assert value_problem("PATH", "p" * 4096) is None
    assert value_problem("PATH", "p" * 4097) == "is 4097 characters long (at most 4096)"
    assert value_problem("--out", " ") == "is empty"
    # through the CLI: an option's value, an argument, and `--opt=value`, each one line naming it, nothing run
    assert_one_error_line(run_ago(["train", "--set", "epochs=1\x00", "--out", "o"], tmp_path), "--set", "control")
    assert_one_error_line(run_ago(["export", "x.pt", "-o", "b", "--card-note", "n" * 301], tmp_path), "--card-note",
                          "at most 300")
    assert_one_error_line(run_ago(["show", "p" * 4097, "--out", "o.png"], tmp_path), "PATH", "at most 4096")
    assert_one_error_line(run_ago(["show", "x.npz", "--out=" + " "], tmp_path), "--out", "is empty")
    assert not (tmp_path / "o").exists() and not (tmp_path / "b").exists()
