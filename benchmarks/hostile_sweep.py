"""Adversarial sweep of `ago` (issue 36): every verb x every hostile input kind, against the contract.

The contract (README, docs/bad_inputs.md): bad input gives exit 2, exactly one stderr line
`error: <file or option>: <problem>` naming the file or option, no traceback, no hang, nothing written
(the working folder stays empty, the named outputs absent, the inputs unchanged).

Groups: bundles (bundle.json lying about grid, classes, files, preprocess sizes, mean / std, widths, the
training rig; swapped, truncated ONNX, a stage of other widths; files outside the bundle), nuScenes tables (truncated, huge, wrong types, deep nesting, `filename` traversal), checkpoints
(truncated, zero bytes, random bytes, code in the pickle, another config), npz / banks (wrong width,
NaN / inf, object arrays, huge declared shapes, pickles), outputs (an existing file as the folder, a
dangling symlink, /sys and /proc, a folder as the file, two outputs on one path), info files and
calibrations (paths leaving the data root, deep nesting, empty lists), options (issue 54: a grid below the
smallest model grid, options that do not apply to the input, free text over its bound or with control characters).
Every input handed to a verb is snapshot before and after (the whole work folder); stdout may hold `note:` lines only.

    python -m benchmarks.hostile_sweep [--work DIR] [--only GROUP] [--out benchmarks/results/hostile_sweep.md]

Each case runs in this process through `ago_runtime.cli.run` (the console script's function) with a
60 s alarm (a hang is a failure). Writes a markdown table (case, exit code, the error line, verdict) and
a summary per group; exit status 1 when any case breaks the contract.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import shutil
import signal
import sys
import tempfile
import time
import types
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
os.environ.pop("AGO_NO_PROGRESS", None)   # bars on: each case's stderr is not a terminal, so none may be drawn

CASE_TIMEOUT_S = 60
DEFAULT_WORK = Path(tempfile.gettempdir()) / "ago_hostile_sweep"


class Hang(Exception):
    pass


def run_ago(args, cwd: Path, timeout: int = CASE_TIMEOUT_S):
    from ago_runtime.cli import run

    out, err = io.StringIO(), io.StringIO()
    old = os.getcwd()

    def alarm(signum, frame):
        raise Hang()

    previous = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(timeout)
    t = time.perf_counter()
    try:
        os.chdir(cwd)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = run([str(a) for a in args])
            except SystemExit as e:
                code = e.code if isinstance(e.code, int) else 1
            except Hang:
                code = "hang"
            except BaseException as e:  # noqa: BLE001 - a traceback is a finding
                import traceback

                traceback.print_exc()
                code = f"traceback ({type(e).__name__})"
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
        os.chdir(old)
    return types.SimpleNamespace(code=code, stdout=out.getvalue(), stderr=err.getvalue(),
                                 seconds=time.perf_counter() - t)


SKIP_IN_SNAPSHOT = ("cache", "setup_cwd")     # ago's own cache; the fixtures' working folder


def snapshot(root: Path) -> dict:
    """Every file and link under the sweep's work folder (the dataset, the bundle, the checkpoint, every hostile
    copy): path -> (size, mtime) or the link's target; the cases' working folders (cwd-*) and the cache are left out."""
    out = {}
    for p in root.rglob("*"):
        rel = p.relative_to(root)
        if rel.parts[0] in SKIP_IN_SNAPSHOT or rel.parts[0].startswith("cwd-"):
            continue
        if p.is_symlink():
            out[str(rel)] = ("link", os.readlink(p))
        elif p.is_file():
            st = p.stat()
            out[str(rel)] = (st.st_size, st.st_mtime_ns)
    return out


def vacuous(needles, root: Path) -> list:
    """Needles that would prove nothing: empty or blank ones, and ones the work folder's path holds (every
    path of every case contains it)."""
    return [n for n in needles if not str(n).strip() or str(n) in str(root)]


def verdict(r, needles, cwd: Path, outputs, before, after, argv, root: Path) -> str:
    """'' when the contract holds, else what broke. Needles are looked for in the error line with the absolute
    folders the case passed cut out (a needle must come from what ago says, not from the name of a hostile copy),
    except a needle that is a path the case passed, or its name, which the line must say as given;
    `outputs` are names relative to the case's working folder or absolute targets (a dangling link's target);
    stdout may hold `note:` lines only."""
    if r.code == "hang":
        return "hang"
    if r.code != 2:
        return f"exit {r.code}"
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    if "Traceback" in r.stderr + r.stdout:
        return "traceback"
    if len(lines) != 1:
        return f"{len(lines)} stderr lines"
    if not lines[0].startswith("error: "):
        return "no 'error:' line"
    bad_needles = vacuous(needles, root)
    if bad_needles:
        return f"vacuous needles {bad_needles}"
    said = lines[0]
    for a in sorted((str(a) for a in argv if str(a).startswith("/") and len(str(a)) > 1), key=len, reverse=True):
        cut = a if os.path.isdir(a) else str(Path(a).parent)   # a folder whole, a file's folder (its name stays)
        said = said.replace(cut, "<arg>") if len(cut) > 1 else said
    given = {str(a) for a in argv} | {Path(str(a)).name for a in argv if str(a).startswith("/")}
    missing = [n for n in needles if str(n) not in (lines[0] if str(n) in given else said)]
    if missing:
        return f"does not name {missing}"
    chatter = [ln for ln in r.stdout.splitlines() if ln.strip() and not ln.startswith("note: ")]
    if chatter:
        return f"stdout: {chatter[0][:80]!r}"
    if any(cwd.iterdir()):
        return f"wrote {sorted(os.listdir(cwd))}"
    for rel in outputs:
        if os.path.lexists(cwd / rel):
            return f"wrote {rel}"
    if before != after:
        changed = sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k))
        return f"an input changed: {changed[:3]}"
    return ""


# ------------------------------------------------------------------------------------ fixtures
def build_fixtures(work: Path):
    """A tiny synthetic dataset, its pseudo-labels, a tiny checkpoint and its bundle, an images folder."""
    from ago_runtime.formats.random_frame import write_random_frame as write_frame

    import torch

    from ago_export.export import export_bundle
    from ago_export.testing import random_checkpoint
    from ago_runtime.vocab.bank import PromptBank

    work.mkdir(parents=True, exist_ok=True)
    os.environ["AGO_CACHE_DIR"] = str(work / "cache")
    x = types.SimpleNamespace(root=work)
    setup = work / "setup_cwd"
    setup.mkdir(exist_ok=True)
    x.data = work / "synth"
    if not (x.data / "splits.json").is_file():
        r = run_ago(["synth", "--out", x.data, "--scenes", "1", "--frames", "2", "--image-size", "96x54",
                     "--grid", "20x20x4"], setup, timeout=600)
        assert r.code == 0, r.stderr
    x.pseudo = work / "pseudo"
    if not x.pseudo.is_dir():
        r = run_ago(["pseudo-labels", "--data", x.data, "--out", x.pseudo, "--grid", "20x20x4", "--keyframes", "1",
                     "--split", "all"], setup, timeout=600)
        assert r.code == 0, r.stderr
    x.frame = write_frame(work / "frame", 160, 90)
    x.ckpt = work / "tiny.pt"
    if not x.ckpt.is_file():
        random_checkpoint(x.ckpt, "tiny", prompts="cw", seed=1)
    x.bundle = work / "bundle"
    if not (x.bundle / "bundle.json").is_file():
        export_bundle(x.ckpt, x.bundle, bank_prompts=[], real_frame=False, log=lambda s: None)
    x.bank = x.bundle / "banks" / "train.npz"
    x.gt = next((x.data / "gts").glob("*/*/labels.npz"))
    x.outside = work / "outside"             # a valid file outside every data root
    x.outside.mkdir(exist_ok=True)
    shutil.copy(x.frame / "CAM_FRONT.jpg", x.outside / "CAM_FRONT.jpg")
    x.ck = torch.load(x.ckpt, weights_only=True)
    x.PromptBank = PromptBank
    return x


def hostile(root: Path, name: str) -> Path:
    p = root / "hostile" / name
    p.parent.mkdir(parents=True, exist_ok=True)
    return p


def edit_bundle(x, name: str, change) -> Path:
    """A copy of the bundle with bundle.json changed by `change(meta, folder)` (hashes left as they are)."""
    d = hostile(x.root, "bundles") / name
    if d.exists():
        shutil.rmtree(d)
    shutil.copytree(x.bundle, d)
    meta = json.loads((d / "bundle.json").read_text())
    if change(meta, d) is not False:     # False: the change wrote bundle.json itself
        (d / "bundle.json").write_text(json.dumps(meta))
    return d


def rehash(meta, d, key):
    from ago_runtime.predict.bundle import file_sha256

    p = d / meta["files"][key]["path"]
    meta["files"][key].update(sha256=file_sha256(p), size=p.stat().st_size)


def edit_dataset(x, name: str, table: str | None, change) -> Path:
    """A copy of the synthetic dataset with v1.0-*/TABLE.json's text or records changed."""
    d = hostile(x.root, "datasets") / name
    if d.exists():
        shutil.rmtree(d)
    shutil.copytree(x.data, d, symlinks=True)
    if table is not None:
        tdir = next(d.glob("v1.0-*"))
        path = tdir / f"{table}.json"
        change(path)
    return d


def records(fn):
    def change(path: Path):
        recs = json.loads(path.read_text())
        fn(recs)
        path.write_text(json.dumps(recs))
    return change


def bundle_cases(x) -> list:
    cases = []
    B = lambda d: ["infer", "--images", x.frame, "--bundle", d, "--out", "o"]   # noqa: E731
    R = lambda d: ["retrieve", "--images", x.frame, "--phrase", "car", "--bundle", d, "--out", "o"]   # noqa: E731

    def grid_lie(m, d):
        m["grid"]["shape"] = [40, 40, 8]

    def grid_lie_consistent(m, d):   # shape, range and voxel size agree, the ONNX graphs do not
        m["grid"]["shape"] = [40, 40, 8]
        m["grid"]["voxel_size"] = [v / 2 for v in m["grid"]["voxel_size"]]

    def grid_zero(m, d):
        m["grid"]["shape"] = [0, 0, 0]

    def grid_huge(m, d):
        m["grid"]["shape"] = [100000, 100000, 100]

    def classes_lie(m, d):
        m["label_space"]["classes"] = m["label_space"]["classes"][:2]

    def classes_many(m, d):
        m["label_space"]["classes"] = [{"name": f"c{i}", "table_ids": [], "known": True, "phrases": []}
                                       for i in range(100000)]

    def dim_lie(m, d):
        m["text_encoder"]["dim"] = 7

    def file_outside(m, d):
        m["files"]["heads"]["path"] = str(x.bundle / "heads.npz")

    def file_dotdot(m, d):
        m["files"]["heads"]["path"] = "../../bundle/heads.npz"

    def bank_outside(m, d):
        m["banks"]["train"] = "../../../bundle/banks/train.npz"

    def bank_abs(m, d):
        m["banks"]["train"] = str(x.bank)

    def file_missing(m, d):
        m["files"]["planes"]["path"] = "nothing.onnx"

    def stages_bogus(m, d):
        m["voxel_stages"] = [{"file": "nope"}]

    def stages_many(m, d):
        m["voxel_stages"] = m["voxel_stages"] * 100000

    def swapped(m, d):
        a, b = d / m["files"]["planes"]["path"], d / m["files"][m["voxel_stages"][0]["file"]]["path"]
        ta = a.read_bytes()
        a.write_bytes(b.read_bytes())
        b.write_bytes(ta)
        rehash(m, d, "planes")
        rehash(m, d, m["voxel_stages"][0]["file"])

    def truncated_rehashed(m, d):
        p = d / m["files"]["planes"]["path"]
        p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
        rehash(m, d, "planes")

    def truncated(m, d):
        p = d / m["files"]["planes"]["path"]
        p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])

    def garbage_onnx(m, d):
        p = d / m["files"]["planes"]["path"]
        p.write_bytes(os.urandom(4096))
        rehash(m, d, "planes")

    def not_json(m, d):
        (d / "bundle.json").write_text("[" * 100000 + "]" * 100000)
        return False

    def deep_json(m, d):
        m["grid"] = json.loads("[" * 50 + "]" * 50)
        m["extra"] = "x"

    def meta_types(m, d):
        m["files"] = ["planes.onnx"]

    def heads_nan(m, d):
        p = d / m["files"]["heads"]["path"]
        with np.load(p) as z:
            arrays = {k: z[k] for k in z.files}
        arrays["W_dec"] = arrays["W_dec"] * np.nan
        np.savez(p, **arrays)
        rehash(m, d, "heads")

    def external_data(m, d):
        """planes.onnx re-saved with its weights as external data named outside the bundle."""
        import onnx

        p = d / m["files"]["planes"]["path"]
        model = onnx.load(str(p))
        for t in model.graph.initializer:
            if t.raw_data and len(t.raw_data) > 1024:
                t.data_location = onnx.TensorProto.EXTERNAL
                del t.external_data[:]
                for k, v in (("location", "../../../../etc/hostname"), ("offset", "0"), ("length", "16")):
                    e = t.external_data.add()
                    e.key, e.value = k, v
                t.ClearField("raw_data")
                break
        p.write_bytes(model.SerializeToString())
        rehash(m, d, "planes")

    def big_bank_names(m, d):
        bank = x.PromptBank.load(x.bank)
        n = 300
        bank.class_names = [f"c{i}" for i in range(n)]
        bank.phrases = [f"p{i}" for i in range(n)]
        bank.phrase_class = np.arange(n, dtype=np.int64)
        bank.embeddings = np.tile(bank.embeddings[:1], (n, 1))
        bank.known = list(bank.class_names)
        bank.occ3d_ids = [()] * n
        bank.save(d / "banks" / "train.npz")
        m["banks"]["train"] = "banks/train.npz"

    # issue 54: tampered values (bundle.json is not in its own manifest; ONNX hashes recomputed)
    def pre_huge(m, d):
        m["preprocess"]["width"] = 10 ** 9

    def pre_zero(m, d):
        m["preprocess"]["height"] = 0

    def std_zero(m, d):
        m["preprocess"]["std"] = [0.0, 0.224, 0.225]

    def mean_nan(m, d):
        m["preprocess"]["mean"] = [float("nan"), 0.456, 0.406]

    def hidden_huge(m, d):
        m["hidden_dim"] = 10 ** 9

    def rig_nan(m, d):
        m["training_rig"]["cameras"][0]["intrinsics"][0][0] = float("nan")

    def sha_not_hex(m, d):
        m["files"]["heads"]["sha256"] = "../../etc/passwd"

    def default_bank_missing(m, d):
        m["default_bank"] = "nope"

    def stage_other_widths(m, d):
        """voxels_0.onnx replaced by a valid graph x (n, 64) -> y (n, 32) (a stage of another bundle), rehashed."""
        import onnx
        from onnx import TensorProto, helper, numpy_helper

        st = m["voxel_stages"][0]
        a, b = st["output_dim"], st["input_dim"]          # the widths swapped: x (n, a) @ W (a, b) -> y (n, b)
        w = numpy_helper.from_array(np.zeros((a, b), np.float32), "W")
        graph = helper.make_graph([helper.make_node("MatMul", ["x", "W"], ["y"])], "other",
                                  [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["n", a])],
                                  [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["n", b])], [w])
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
        model.ir_version = 8
        onnx.save(model, str(d / m["files"][st["file"]]["path"]))
        rehash(m, d, st["file"])

    for name, change, needles in (
        ("bundle.json grid lies (40x40x8)", grid_lie, ["bundle.json", "grid"]),
        ("bundle.json grid lies consistently (40x40x8)", grid_lie_consistent, ["planes.onnx", "plane_xy"]),
        ("bundle.json grid 0x0x0", grid_zero, ["bundle.json", "grid"]),
        ("bundle.json grid 10^12 voxels", grid_huge, ["bundle.json", "grid"]),
        ("bundle.json lists 2 classes", classes_lie, ["bundle.json", "label_space"]),
        ("bundle.json lists 100000 classes", classes_many, ["bundle.json", "label_space"]),
        ("bundle.json text width 7", dim_lie, ["heads.npz", "C 7"]),
        ("bundle.json preprocess width 10^9", pre_huge, ["bundle.json", "preprocess.width"]),
        ("bundle.json preprocess height 0", pre_zero, ["bundle.json", "preprocess.height"]),
        ("bundle.json preprocess std 0", std_zero, ["bundle.json", "preprocess.std"]),
        ("bundle.json preprocess mean NaN", mean_nan, ["bundle.json", "preprocess.mean"]),
        ("bundle.json hidden_dim 10^9", hidden_huge, ["bundle.json", "hidden_dim"]),
        ("bundle.json training_rig NaN intrinsics", rig_nan, ["bundle.json", "training_rig"]),
        ("bundle.json sha256 not hex", sha_not_hex, ["bundle.json", "sha256"]),
        ("bundle.json default_bank not a bank", default_bank_missing, ["bundle.json", "default_bank"]),
        ("voxel stage of other widths (hash updated)", stage_other_widths, ["voxels_0.onnx", "voxel_stages[0]"]),
        ("bundle.json file: absolute path outside", file_outside, ["bundle.json", "outside"]),
        ("bundle.json file: ../ path", file_dotdot, ["bundle.json", "outside"]),
        # a bank names an entry of the bundle's own file table (format 5), so a path is refused as not listed there
        ("bundle.json bank: ../ path", bank_outside, ["bundle.json", "banks['train']", "files does not list"]),
        ("bundle.json bank: absolute path", bank_abs, ["bundle.json", "banks['train']", "files does not list"]),
        ("bundle.json names a missing file", file_missing, ["nothing.onnx"]),
        ("bundle.json voxel_stages bogus", stages_bogus, ["bundle.json"]),
        ("bundle.json 100000 voxel stages", stages_many, ["bundle.json"]),
        ("bundle.json files of the wrong type", meta_types, ["bundle.json"]),
        ("bundle.json 100000 nested [", not_json, ["bundle.json"]),
        ("bundle.json grid a nested list", deep_json, ["bundle.json"]),
        ("ONNX files swapped (hashes updated)", swapped, ["planes.onnx", "planes"]),
        ("ONNX truncated (hash updated)", truncated_rehashed, ["planes.onnx"]),
        ("ONNX truncated (hash stale)", truncated, ["planes.onnx"]),
        ("ONNX random bytes (hash updated)", garbage_onnx, ["planes.onnx"]),
        ("ONNX external data outside the bundle", external_data, ["planes.onnx"]),
        ("heads NaN (hash updated)", heads_nan, ["heads.npz"]),
        ("bundle bank of 300 classes", big_bank_names, ["train.npz"]),
    ):
        def make(change=change, name=name):
            return edit_bundle(x, name.replace(" ", "_").replace("/", "_"), change)
        cases.append(("bundles", f"infer: {name}", lambda make=make: B(make()), needles, ["o"]))
        cases.append(("bundles", f"retrieve: {name}", lambda make=make: R(make()), needles, ["o"]))
    return cases


def dataset_cases(x) -> list:
    cases = []
    I = lambda d: ["infer", "--images", d, "--bundle", x.bundle, "--out", "o"]           # noqa: E741,E731
    S = lambda d: ["show", d, "--index", "0", "--out", "o.png"]                           # noqa: E731
    P = lambda d: ["pseudo-labels", "--data", d, "--out", "o", "--grid", "20x20x4", "--split", "all"]  # noqa: E731

    def truncate(path):
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])

    def huge(path):     # 5 GiB, sparse: refused by its size before a byte is read (the bound is 4 GiB)
        with open(path, "r+b") as f:
            f.truncate(5 << 30)

    def deep(path):
        path.write_text("[" * 100000 + "]" * 100000)

    def not_list(path):
        path.write_text('{"token": "x"}')

    def fn_traversal(recs):
        for r in recs:
            if str(r.get("filename", "")).startswith("samples/CAM_FRONT"):
                r["filename"] = "../../../../../../etc/hostname"

    def fn_absolute(recs):
        for r in recs:
            if str(r.get("filename", "")).startswith("samples/CAM_FRONT"):
                r["filename"] = str(x.outside / "CAM_FRONT.jpg")

    def fn_outside_jpeg(recs):
        for r in recs:
            if str(r.get("filename", "")).startswith("samples/CAM_FRONT"):
                r["filename"] = "../outside/CAM_FRONT.jpg"

    def wrong_types(recs):
        for r in recs:
            r["translation"] = "north"

    def token_int(recs):
        for r in recs:
            r["token"] = 5

    def intrinsic_nan(recs):
        for r in recs:
            if r.get("camera_intrinsic"):
                r["camera_intrinsic"] = [[float("nan")] * 3] * 3

    def pose_huge(recs):
        for r in recs:
            r["translation"] = [1e308, 1e308, 1e308]

    def fn_int(recs):
        for r in recs:
            r["filename"] = 12

    def lidar_huge(path):   # every keyframe LiDAR file grown to 2 GiB (sparse): refused by size, unread
        for f in (path.parents[1] / "samples" / "LIDAR_TOP").glob("*.bin"):
            with open(f, "r+b") as fh:
                fh.truncate(2 << 30)

    def null_records(recs):
        recs[:] = [None] * len(recs)

    for name, table, change, needles in (
        ("sample_data.json truncated", "sample_data", truncate, ["sample_data.json"]),
        ("sample.json truncated", "sample", truncate, ["sample.json"]),
        ("ego_pose.json over the size bound", "ego_pose", huge, ["ego_pose.json"]),
        ("sample.json 100000 nested [", "sample", deep, ["sample.json"]),
        ("scene.json an object", "scene", not_list, ["scene.json"]),
        ("sample_data filename ../ traversal", "sample_data", records(fn_traversal), ["sample_data.json", "outside"]),
        ("sample_data filename absolute", "sample_data", records(fn_absolute), ["sample_data.json", "outside"]),
        ("sample_data filename: a valid JPEG outside", "sample_data", records(fn_outside_jpeg),
         ["sample_data.json", "outside"]),
        ("sample_data filename a number", "sample_data", records(fn_int), ["sample_data.json"]),
        ("ego_pose translation a string", "ego_pose", records(wrong_types), ["ego_pose.json"]),
        ("ego_pose translation 1e308", "ego_pose", records(pose_huge), ["ego_pose.json"]),
        ("sample token a number", "sample", records(token_int), ["sample.json"]),
        ("calibrated_sensor intrinsics NaN", "calibrated_sensor", records(intrinsic_nan), ["calibrated_sensor.json"]),
        ("calibrated_sensor records null", "calibrated_sensor", records(null_records), ["calibrated_sensor.json"]),
        ("LiDAR .pcd.bin of 2 GiB", "sample_data", lidar_huge, [".pcd.bin", "bytes"]),
    ):
        def make(table=table, change=change, name=name):
            return edit_dataset(x, name.replace(" ", "_").replace("/", "_"), table, change)
        for verb, args in (("infer", I), ("show", S), ("pseudo-labels", P)):
            cases.append(("nuScenes tables", f"{verb}: {name}", lambda make=make, args=args: args(make()),
                          needles, ["o", "o.png"]))
    return cases


def info_calib_cases(x) -> list:
    import pickle

    cases = []
    root = hostile(x.root, "info")
    root.mkdir(exist_ok=True)

    def info_with(name, mutate):
        import copy

        sample = {"token": "t0", "timestamp": 0.0, "ego2global": np.eye(4).tolist(),
                  "lidar_points": {"lidar_path": "x.bin", "lidar2ego": np.eye(4).tolist(), "num_pts_feats": 5},
                  "images": {}}
        from ago_runtime.geometry.camera import Rig

        rig = Rig.nuscenes_like(160, 90)
        for cam in rig:
            sample["images"][cam.name] = {"img_path": f"{cam.name}.jpg", "cam2img": cam.intrinsics.tolist(),
                                          "cam2ego": cam.cam2ego.tolist()}
        info = {"metainfo": {}, "data_list": [copy.deepcopy(sample)]}
        mutate(info)
        p = root / name
        p.write_bytes(pickle.dumps(info))
        return p

    def data_root_with_frame():
        d = root / "data"
        for cam in ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT"):
            (d / "samples" / cam).mkdir(parents=True, exist_ok=True)
            shutil.copy(x.frame / f"{cam}.jpg", d / "samples" / cam / f"{cam}.jpg")
        (d / "samples" / "LIDAR_TOP").mkdir(parents=True, exist_ok=True)
        np.zeros((10, 5), np.float32).tofile(d / "samples" / "LIDAR_TOP" / "x.bin")
        return d

    d = data_root_with_frame()

    def passwd(info):
        info["data_list"][0]["images"]["CAM_FRONT"]["img_path"] = "../../../../etc/passwd"
        info["data_list"][0]["lidar_points"]["lidar_path"] = "/etc/hostname"

    def outside_jpeg(info):
        info["data_list"][0]["images"]["CAM_FRONT"]["img_path"] = str(x.outside / "CAM_FRONT.jpg")

    def outside_rel(info):
        info["data_list"][0]["images"]["CAM_FRONT"]["img_path"] = "../../outside/CAM_FRONT.jpg"

    def empty(info):
        info["data_list"] = []

    def deep(info):
        v = []
        for _ in range(5000):
            v = [v]
        info["data_list"][0]["token"] = v

    def path_list(info):
        info["data_list"][0]["images"]["CAM_FRONT"]["img_path"] = ["a", "b"]

    for name, mutate, needles in (
        ("img_path ../../etc/passwd, lidar /etc/hostname", passwd, ["outside"]),
        ("img_path a valid JPEG, absolute, outside", outside_jpeg, ["outside"]),
        ("img_path a valid JPEG, ../ outside", outside_rel, ["outside"]),
        ("empty data_list", empty, ["data_list"]),
        ("img_path a list", path_list, ["img_path"]),
    ):
        p = info_with(name.split(" ")[0] + str(abs(hash(name)) % 1000) + ".pkl", mutate)
        cases.append(("info files", f"infer --info: {name}",
                      lambda p=p: ["infer", "--info", p, "--images", d, "--bundle", x.bundle, "--out", "o"],
                      [p.name, *needles], ["o"]))
    deep_pkl = root / "deep.pkl"      # MARK x 50000, LIST x 50000: lists nested 50000 deep
    nest = b"\x80\x02" + b"(" * 50000 + b"l" * 50000 + b"."
    deep_pkl.write_bytes(nest)
    cases.append(("info files", "infer --info: 50000 nested lists", lambda: ["infer", "--info", deep_pkl,
                                                                           "--bundle", x.bundle, "--out", "o"],
                  ["deep.pkl"], ["o"]))
    calib = shutil.copytree(x.frame, root / "deep_calib", dirs_exist_ok=True)
    (calib / "calib.json").write_text("[" * 100000 + "]" * 100000)
    cases.append(("info files", "infer: calib.json of 100000 nested [", lambda: ["infer", "--images", calib,
                                                                               "--bundle", x.bundle, "--out", "o"],
                  ["calib.json"], ["o"]))
    far = shutil.copytree(x.frame, root / "far_calib", dirs_exist_ok=True)
    c = json.loads((far / "calib.json").read_text())
    for cam in c["cameras"].values():
        cam["cam2ego"][0][3] = 1e308
    (far / "calib.json").write_text(json.dumps(c))
    cases.append(("info files", "infer: calib.json translation 1e308", lambda: ["infer", "--images", far,
                                                                              "--bundle", x.bundle, "--out", "o"],
                  ["calib.json"], ["o"]))
    return cases


def checkpoint_cases(x) -> list:
    import pickle
    import zipfile

    cases = []
    root = hostile(x.root, "checkpoints")
    root.mkdir(exist_ok=True)
    good = x.ckpt.read_bytes()
    (root / "truncated.pt").write_bytes(good[: len(good) // 2])
    (root / "empty.pt").write_bytes(b"")
    (root / "random.pt").write_bytes(os.urandom(8192))
    (root / "code.pt").write_bytes(pickle.dumps(types.SimpleNamespace(a=1)))

    class Evil:
        def __reduce__(self):
            return (os.system, ("echo pwned > /tmp/ago_pwned",))

    import torch

    torch.save({"model": Evil()}, root / "evil.pt")
    ck = dict(x.ck)
    ck["model_config"] = {"kind": "nonsense"}
    torch.save(ck, root / "other_config.pt")
    ck = dict(x.ck)
    ck["model"] = {k: v * float("nan") if v.is_floating_point() else v for k, v in ck["model"].items()}
    torch.save(ck, root / "nan_weights.pt")
    for name, change in (   # issue 54: the config by value
            ("hidden_dim_huge.pt", lambda c: c["model_config"].update(hidden_dim=10 ** 9)),
            ("grid_huge.pt", lambda c: c["model_config"].update(grid={"range_min": [-40, -40, -1], "range_max": [40, 40, 5.4],
                                                                      "voxel_size": [1e-4, 1e-4, 1e-4]})),
            ("rig_nan.pt", lambda c: c["rig"]["cameras"][0]["intrinsics"][0].__setitem__(0, float("nan"))),
            ("rig_three_cameras.pt", lambda c: c["rig"].update(cameras=c["rig"]["cameras"][:3]))):
        import copy

        from ago_runtime.geometry.camera import Rig

        ck = copy.deepcopy(x.ck)
        ck.setdefault("rig", Rig.nuscenes_like(1600, 900).to_dict())   # the record a training run writes
        change(ck)
        torch.save(ck, root / name)
    with zipfile.ZipFile(root / "zip_of_nothing.pt", "w") as z:
        z.writestr("archive/data.pkl", b"\x80\x02}q\x00.")
    (root / "folder.pt").mkdir(exist_ok=True)
    names = ["truncated.pt", "empty.pt", "random.pt", "code.pt", "evil.pt", "other_config.pt", "nan_weights.pt",
             "zip_of_nothing.pt", "folder.pt", "hidden_dim_huge.pt", "grid_huge.pt", "rig_nan.pt", "rig_three_cameras.pt"]
    for n in names:
        p = root / n
        cases.append(("checkpoints", f"eval: {n}", lambda p=p: ["eval", "--ckpt", p, "--data", x.data, "--split", "all",
                                                              "--out", "o"], [n], ["o"]))
        cases.append(("checkpoints", f"export: {n}", lambda p=p: ["export", p, "-o", "b", "--no-real-frame",
                                                                "--train-bank-only"], [n], ["b"]))
        cases.append(("checkpoints", f"train init_from: {n}", lambda p=p: [
            "train", "--config", "tiny", "--out", "o", "--data", x.data, "--pseudo", x.pseudo, "--set",
            'train_split="all"', "--set", 'device="cpu"', "--set", f'init_from="{p}"'],
            [n], ["o"]))
    return cases


def npz_cases(x) -> list:
    cases = []
    root = hostile(x.root, "npz")
    root.mkdir(exist_ok=True)
    bank = x.PromptBank.load(x.bank)

    def bank_variant(name, change):
        b = x.PromptBank.load(x.bank)
        change(b)
        return b.save(root / name)

    def wide(b):
        b.embeddings = np.concatenate([b.embeddings, b.embeddings[:, :5]], axis=1)
        b.dim = b.embeddings.shape[1]

    def nan(b):
        b.embeddings = b.embeddings.copy()
        b.embeddings[0, 0] = np.nan

    def inf(b):
        b.embeddings = b.embeddings.copy()
        b.embeddings[1, :] = np.inf

    def zero_rows(b):
        b.embeddings = np.zeros_like(b.embeddings)

    def lie_dim(b):
        b.dim = 7

    files = {
        "wide.npz": bank_variant("wide.npz", wide),
        "nan.npz": bank_variant("nan.npz", nan),
        "inf.npz": bank_variant("inf.npz", inf),
        "zero_embeddings.npz": bank_variant("zero_embeddings.npz", zero_rows),
        "dim_lies.npz": bank_variant("dim_lies.npz", lie_dim),
    }
    obj = root / "object_array.npz"
    np.savez(obj, embeddings=np.array([{"a": 1}], dtype=object), phrases=np.array(["a"]))
    files["object_array.npz"] = obj
    # an .npy header declaring 10^12 float32 (4 TB) with 16 bytes of data
    big = root / "huge_shape.npz"
    import zipfile

    header = b"{'descr': '<f4', 'fortran_order': False, 'shape': (1000000, 1000000), }"
    header = header + b" " * (118 - len(header)) + b"\n"
    npy = b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header + b"\x00" * 16
    with zipfile.ZipFile(big, "w") as z:
        for k in ("embeddings", "phrases", "class_names", "phrase_class", "meta", "semantics"):
            z.writestr(f"{k}.npy", npy)
    files["huge_shape.npz"] = big
    bomb = root / "zip_bomb.npz"     # 400 MB of zeros in a ~400 kB deflated member
    with zipfile.ZipFile(bomb, "w", compression=zipfile.ZIP_DEFLATED) as z:
        header = b"{'descr': '|u1', 'fortran_order': False, 'shape': (400000000,), }"
        header = header + b" " * (118 - len(header)) + b"\n"
        with z.open("semantics.npy", "w", force_zip64=True) as f:
            f.write(b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header)
            chunk = b"\x00" * (1 << 20)
            for _ in range(400000000 // len(chunk)):
                f.write(chunk)
            f.write(b"\x00" * (400000000 % len(chunk)))
    files["zip_bomb.npz"] = bomb
    pk = root / "pickle.npz"
    import pickle

    pk.write_bytes(pickle.dumps({"semantics": 1}))
    files["pickle.npz"] = pk
    for n, p in files.items():
        if n != "wide.npz":   # a bank of another width is a valid bank to show; infer refuses it
            cases.append(("npz / banks", f"prompts show {n}", lambda p=p: ["prompts", "show", p], [n], []))
        cases.append(("npz / banks", f"infer --bank {n}", lambda p=p: ["infer", "--images", x.frame, "--bundle", x.bundle,
                                                                       "--bank", p, "--out", "o"], [n], ["o"]))
    # labels npz for show / metric
    sem = root / "sem"
    for n, arrays in (
        ("float_semantics.npz", {"semantics": np.full((20, 20, 4), np.nan, np.float32)}),
        ("2d_semantics.npz", {"semantics": np.zeros((20, 20), np.uint8)}),
        ("no_semantics.npz", {"other": np.zeros(3)}),
    ):
        p = sem / n
        p.parent.mkdir(exist_ok=True)
        np.savez(p, **arrays)
        cases.append(("npz / banks", f"show {n}", lambda p=p: ["show", p, "--out", "o.png"], [n], ["o.png"]))
    for n, shape in (("huge_dims_no_data.npz", "(0, 1000000000000, 100000)"), ("empty_grid.npz", "(0, 0, 0)")):
        header = ("{'descr': '|u1', 'fortran_order': False, 'shape': %s, }" % shape).encode()
        header = header + b" " * (118 - len(header)) + b"\n"
        with zipfile.ZipFile(root / n, "w") as z:
            z.writestr("semantics.npy", b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header)
        files[n] = root / n
    for n in ("huge_shape.npz", "zip_bomb.npz", "pickle.npz", "object_array.npz", "huge_dims_no_data.npz",
              "empty_grid.npz"):
        cases.append(("npz / banks", f"show {n}", lambda n=n: ["show", files[n], "--out", "o.png"], [n], ["o.png"]))
    # metric --pred a folder whose prediction is hostile
    pred = root / "pred"
    rel = x.gt.relative_to(x.data / "gts")
    (pred / rel).parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(files["zip_bomb.npz"], pred / rel)
    late = root / "pred_late"    # every frame's prediction whole but the last: the verb fails after its bar began
    if late.exists():
        shutil.rmtree(late)
    shutil.copytree(x.data / "gts", late)
    last = sorted(late.glob("*/*/labels.npz"))[-1]
    last.write_bytes(last.read_bytes()[:100])
    cases.append(("npz / banks", "metric --pred whose last prediction is truncated (bars on)", lambda: [
        "metric", "--pred", late, "--gt", x.data / "gts"], [str(last.relative_to(late))], []))
    cases.append(("npz / banks", "metric --pred with a zip-bomb prediction", lambda: [
        "metric", "--pred", pred, "--gt", x.data / "gts", "--allow-missing"], ["labels.npz"], []))
    # choose-threshold --labels: a pseudo-label folder with one hostile labels.npz, or a hostile meta.json
    CT = lambda labels: ["choose-threshold", "--images", x.data, "--bundle", x.bundle, "--labels", labels]  # noqa: E731
    for n in ("zip_bomb.npz", "huge_shape.npz", "pickle.npz", "huge_dims_no_data.npz", "empty_grid.npz"):
        d = root / f"ct_{n[:-4]}"
        if d.exists():
            shutil.rmtree(d)
        shutil.copytree(x.pseudo, d)
        target = sorted(d.glob("*/*/labels.npz"))[0]
        shutil.copy(files[n], target)
        cases.append(("npz / banks", f"choose-threshold --labels with a {n[:-4]} labels.npz",
                      lambda d=d: CT(d), [str(target.relative_to(d))], []))
    for n, change in (("classes a string", lambda m: m["label_space"].__setitem__("classes", "car")),
                      ("free_index text", lambda m: m.__setitem__("free_index", "x")),
                      ("free = ignore", lambda m: m.__setitem__("free_index", 255)),
                      ("grid range of 2 axes", lambda m: m["grid"].__setitem__("range_min", [0, 0])),
                      ("10^5 nested lists", lambda m: m.__setitem__("deep", json.loads("[" * 100000 + "]" * 100000)))):
        d = root / f"ct_meta_{n.replace(' ', '_').replace('^', '')}"
        if d.exists():
            shutil.rmtree(d)
        shutil.copytree(x.pseudo, d)
        meta = json.loads((d / "meta.json").read_text())
        if n == "10^5 nested lists":
            (d / "meta.json").write_text(json.dumps(meta)[:-1] + ', "deep": ' + "[" * 100000 + "]" * 100000 + "}")
        else:
            change(meta)
            (d / "meta.json").write_text(json.dumps(meta))
        cases.append(("npz / banks", f"choose-threshold --labels meta.json: {n}", lambda d=d: CT(d), ["meta.json"], []))
    return cases


def output_cases(x) -> list:
    cases = []
    root = hostile(x.root, "outputs")
    root.mkdir(exist_ok=True)
    a_file = root / "a_file"
    a_file.write_text("x")
    dangling, dangling_file = root / "dangling", root / "dangling.png"
    for link, target in ((dangling, root / "no" / "where"), (dangling_file, root / "nowhere.png")):
        if os.path.lexists(link):
            os.unlink(link)
        os.symlink(target, link)
    folder_verbs = {
        "synth": lambda o: ["synth", "--out", o, "--scenes", "1", "--frames", "1"],
        "pseudo-labels": lambda o: ["pseudo-labels", "--data", x.data, "--out", o, "--grid", "20x20x4"],
        "infer": lambda o: ["infer", "--images", x.frame, "--bundle", x.bundle, "--out", o],
        "demo": lambda o: ["demo", "--out", o],
        "retrieve": lambda o: ["retrieve", "--images", x.frame, "--phrase", "car", "--bundle", x.bundle, "--out", o],
        "train": lambda o: ["train", "--config", "tiny", "--out", o],
        "eval": lambda o: ["eval", "--ckpt", x.ckpt, "--data", x.data, "--split", "all", "--out", o],
        "export": lambda o: ["export", x.ckpt, "-o", o, "--no-real-frame"],
        "open-world": lambda o: ["open-world", "--pseudo-pretrain", x.pseudo, "--out", o],
        "experiments run": lambda o: ["experiments", "run", "--profile", "tiny", "--out", o],
        "seen-gt": lambda o: ["seen-gt", "--data", x.data, "--pseudo", x.pseudo, "--prompts", "veon_9_8",
                              "--out", o, "--split", "all"],
    }
    file_verbs = {
        "show": lambda o: ["show", x.gt, "--out", o],
        "metric --json": lambda o: ["metric", "--pred", x.data / "gts", "--gt", x.data / "gts", "--json", o],
        "choose-threshold --json": lambda o: ["choose-threshold", "--images", x.data, "--bundle", x.bundle, "--labels",
                                              x.pseudo, "--json", o],
        "prompts build": lambda o: ["prompts", "build", "cw", "-o", o],
        "prompts noise": lambda o: ["prompts", "noise", "-o", o],
        "prompts export-encoder": lambda o: ["prompts", "export-encoder", "-o", o],
    }
    for verb, make in folder_verbs.items():
        for kind, path, needle in (("an existing file", a_file, "a_file"), ("a dangling symlink", dangling, "dangling"),
                                   ("under /proc", Path("/proc/ago-sweep/x"), "/proc/ago-sweep/x"),
                                   ("empty string", "", "--out" if verb != "export" else "-o")):
            cases.append(("outputs", f"{verb} --out {kind}", lambda make=make, path=path: make(path), [needle],
                          [root / "no" / "where"] if path == dangling else []))
    for verb, make in file_verbs.items():
        for kind, path, needle in (("an existing folder", root, str(root)), ("a dangling symlink", dangling_file,
                                                                            "dangling.png"),
                                   ("/dev/null", Path("/dev/null"), "/dev/null"),
                                   ("under /sys", Path("/sys/ago-sweep.x"), "/sys/ago-sweep.x"),
                                   ("empty string", "", None)):
            option = "--out" if verb == "show" else "--json" if verb.endswith("--json") else "-o"
            cases.append(("outputs", f"{verb} -o {kind}", lambda make=make, path=path: make(path), [needle or option],
                          [root / "nowhere.png"] if path == dangling_file else []))
    cases.append(("outputs", "metric --json x.json --md x.json", lambda: [
        "metric", "--pred", x.data / "gts", "--gt", x.data / "gts", "--json", "x.json", "--md", "x.json"],
        ["x.json"], ["x.json"]))
    cases.append(("outputs", "show --out an existing file is left as it was", lambda: ["show", x.gt, "--out", a_file],
                  ["a_file", ".png"], []))
    cases.append(("outputs", "show --out o.jpg", lambda: ["show", x.gt, "--out", "o.jpg"], ["--out", "o.jpg"],
                  ["o.jpg"]))
    return cases


def option_cases(x) -> list:
    """Issue 54: degenerate values refused with the minimum, options that do not apply refused, free text bounded."""
    long_note, long_name, long_path = "n" * 400, "t" * 5000, "d/" * 3000
    gt = x.gt
    return [
        ("options", "synth --grid 1x1x1", lambda: ["synth", "--grid", "1x1x1", "--out", "o", "--scenes", "1", "--frames", "1"],
         ["--grid", "20x20x4"], ["o"]),
        ("options", "synth --grid 19x20x4", lambda: ["synth", "--grid", "19x20x4", "--out", "o"], ["--grid", "20x20x4"], ["o"]),
        ("options", "pseudo-labels --grid 10x10x2", lambda: ["pseudo-labels", "--data", x.data, "--out", "o", "--grid",
                                                             "10x10x2"], ["--grid", "20x20x4"], ["o"]),
        ("options", "show FILE --sample x", lambda: ["show", gt, "--sample", "x", "--out", "o.png"],
         ["--sample", "does not apply"], ["o.png"]),
        ("options", "show FILE --index 0", lambda: ["show", gt, "--index", "0", "--out", "o.png"],
         ["--index", "does not apply"], ["o.png"]),
        ("options", "show DATASET --gt FILE", lambda: ["show", x.data, "--index", "0", "--gt", gt, "--out", "o.png"],
         ["--gt", "does not apply"], ["o.png"]),
        ("options", "show DATASET --view bev", lambda: ["show", x.data, "--index", "0", "--view", "bev", "--out", "o.png"],
         ["--view", "does not apply"], ["o.png"]),
        ("options", "infer an images folder --allow-outside-root", lambda: [
            "infer", "--images", x.frame, "--allow-outside-root", "--bundle", x.bundle, "--out", "o"],
         ["--allow-outside-root", "images folder"], ["o"]),
        ("options", "infer --prompts and --bank", lambda: ["infer", "--images", x.frame, "--prompts", "cw", "--bank", "train",
                                                           "--bundle", x.bundle, "--out", "o"], ["--bank", "not both"], ["o"]),
        ("options", "export --card-note of 400 characters", lambda: ["export", x.ckpt, "-o", "b", "--no-real-frame",
                                                                     "--card-note", long_note], ["--card-note", "300"], ["b"]),
        ("options", "export --card-note with a newline", lambda: ["export", x.ckpt, "-o", "b", "--no-real-frame",
                                                                  "--card-note", "a\nb"], ["--card-note", "control"], ["b"]),
        ("options", "infer --sample of 5000 characters", lambda: ["infer", "--images", x.data, "--sample", long_name,
                                                                  "--bundle", x.bundle, "--out", "o"], ["--sample", "300"], ["o"]),
        ("options", "pseudo-labels --split with an escape", lambda: ["pseudo-labels", "--data", x.data, "--out", "o",
                                                                     "--split", "all\x1b[2J"], ["--split", "control"], ["o"]),
        ("options", "eval --out of 6000 characters", lambda: ["eval", "--ckpt", x.ckpt, "--data", x.data, "--out",
                                                              long_path], ["--out", "4096"], []),
        ("options", "show PATH of 6000 characters", lambda: ["show", long_path, "--out", "o.png"], ["PATH", "4096"], ["o.png"]),
        ("options", "prompts build --template of 400 characters", lambda: ["prompts", "build", "cw", "-o", "b.npz",
                                                                           "--template", "{} " + "x" * 400],
         ["--template", "300"], ["b.npz"]),
    ]


def new_verb_cases(x) -> list:
    """Issues 47, 48, 49, 53: the verbs and options added after round three (vlm-files, train-real, --text-encoder,
    --html): missing or wrong model folders, a pickle-only folder, a device without a GPU, bad HTML targets."""
    pickle_only = x.root / "hostile" / "new" / "pickle_only"
    if not pickle_only.is_dir():
        pickle_only.mkdir(parents=True)
        (pickle_only / "config.json").write_text('{"model_type": "clip"}')
        (pickle_only / "pytorch_model.bin").write_bytes(b"not read")
    return [
        ("new verbs", "vlm-files --detector missing", lambda: ["vlm-files", "--data", x.data, "--out", "o", "--prompts",
                                                                "cw", "--detector", "nope", "--sam", "nope"],
         ["--detector", "no such folder"], ["o"]),
        ("new verbs", "vlm-files --detector is a bundle", lambda: ["vlm-files", "--data", x.data, "--out", "o",
                                                                    "--prompts", "cw", "--detector", x.bundle, "--sam",
                                                                    "nope"], ["--detector", "config.json"], ["o"]),
        ("new verbs", "vlm-files --device cuda", lambda: ["vlm-files", "--data", x.data, "--out", "o", "--prompts", "cw",
                                                           "--detector", "nope", "--sam", "nope", "--device", "gpu0"],
         ["--device"], ["o"]),
        ("new verbs", "pseudo-labels --text-encoder a pickle-only folder", lambda: [
            "pseudo-labels", "--data", x.data, "--out", "o", "--text-encoder", pickle_only],
         ["--text-encoder", "pickle"], ["o"]),
        ("new verbs", "prompts build --text-encoder missing", lambda: ["prompts", "build", "cw", "-o", "b.npz",
                                                                        "--text-encoder", "nope"],
         ["--text-encoder", "no such folder"], ["b.npz"]),
        ("new verbs", "train --text-encoder is a bundle", lambda: ["train", "--config", "tiny", "--data", x.data,
                                                                    "--pseudo", x.pseudo, "--out", "o",
                                                                    "--text-encoder", x.bundle],
         ["--text-encoder", "config.json"], ["o"]),
        ("new verbs", "show --html o.png", lambda: ["show", x.gt, "--html", "o.png"], ["--html", ".html"], ["o.png"]),
        ("new verbs", "infer --html --picture nope", lambda: ["infer", "--images", x.frame, "--bundle", x.bundle,
                                                                      "--out", "o", "--html", "--picture", "nope"],
         ["--picture"], ["o"]),
        ("new verbs", "train-real a missing dataroot", lambda: ["train-real", "nope", "o"], ["nope"], ["o"]),
        ("new verbs", "train-real --steps 0", lambda: ["train-real", x.data, "o", "--steps", "0"], ["--steps"], ["o"]),
    ]


GROUPS = {"bundles": bundle_cases, "nuScenes tables": dataset_cases, "info files": info_calib_cases,
          "checkpoints": checkpoint_cases, "npz / banks": npz_cases, "outputs": output_cases,
          "options": option_cases, "new verbs": new_verb_cases}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=DEFAULT_WORK)
    ap.add_argument("--only", action="append", help="run only these groups")
    ap.add_argument("--match", help="run only cases whose name contains this")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "hostile_sweep.md")
    args = ap.parse_args()
    x = build_fixtures(args.work)
    rows, t0 = [], time.perf_counter()
    for group, make in GROUPS.items():
        if args.only and group not in args.only:
            continue
        for g, name, make_args, needles, outputs in make(x):
            if args.match and args.match not in name:
                continue
            cwd = Path(tempfile.mkdtemp(prefix="cwd-", dir=args.work))
            argv = make_args()
            before = snapshot(x.root)
            r = run_ago(argv, cwd)
            bad = verdict(r, needles, cwd, outputs, before, snapshot(x.root), argv, x.root)
            line = next((ln for ln in r.stderr.splitlines() if ln.startswith("error: ")), "")
            if bad:
                tail = (r.stderr.strip().splitlines() or [""])[-1]
                line = line or tail
            rows.append((g, name, r.code, line, bad, r.seconds))
            detail = " | ".join(r.stderr.strip().splitlines()[-3:]) if bad else line
            print(f"{'FAIL' if bad else 'ok  '} [{g}] {name}: {bad} {detail}"[:600], flush=True)
            shutil.rmtree(cwd, ignore_errors=True)
    if os.path.exists("/tmp/ago_pwned"):
        rows.append(("checkpoints", "no code ran", 0, "/tmp/ago_pwned exists", "CODE RAN", 0))
    write_report(rows, args.out, time.perf_counter() - t0, args)
    fails = [r for r in rows if r[4]]
    print(f"{len(rows)} cases, {len(rows) - len(fails)} per contract, {len(fails)} not")
    return 1 if fails else 0


def write_report(rows, out: Path, seconds: float, args) -> None:
    from collections import Counter

    def cell(s):
        return str(s).replace("|", "\\|").replace("\n", " ")[:160]

    per = Counter(r[0] for r in rows)
    bad = Counter(r[0] for r in rows if r[4])
    import subprocess

    def git(*a):
        return subprocess.run(["git", "-C", str(REPO), *a], capture_output=True, text=True).stdout.strip()

    dirty = [ln for ln in git("status", "--porcelain").splitlines() if "benchmarks/results/" not in ln]
    options = "".join(f" --only '{g}'" for g in args.only or []) + (f" --match '{args.match}'" if args.match else "")
    if args.work != DEFAULT_WORK:
        options += f" --work {args.work}"
    load = os.getloadavg()
    lines = ["# Hostile-input sweep (issues 36, 54)", "",
             f"Command: `python -m benchmarks.hostile_sweep{options}`"
             f" at commit `{git('rev-parse', 'HEAD')}`{' (with uncommitted changes)' if dirty else ''}, "
             f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {seconds:.0f} s on a shared 2-core machine "
             f"(load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} at the end).", "",
             "Contract per case: exit 2, one `error: <file or option>: <problem>` line naming it (needles looked for "
             "with the folders the case passed cut out, a path the case passed as given; no empty needle, none the "
             "work folder's path holds), "
             "no traceback, no hang (60 s), stdout holding `note:` lines only, nothing written (the working folder "
             "empty, the named outputs and absolute targets such as a dangling link's target absent), every input "
             "(dataset, bundle, checkpoint, hostile copies) unchanged.", "",
             "| group | cases | per contract |", "|---|---:|---:|"]
    for g in per:
        lines.append(f"| {g} | {per[g]} | {per[g] - bad[g]} |")
    lines.append(f"| **all** | **{len(rows)}** | **{len(rows) - sum(bad.values())}** |")
    lines += ["", "| group | case | exit | error line | verdict |", "|---|---|---|---|---|"]
    for g, name, code, line, v, s in rows:
        lines.append(f"| {g} | {cell(name)} | {code} | {cell(line)} | {cell(v) or 'ok'} |")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    sys.exit(main())
