"""`ago train-real DATAROOT OUT`: from a nuScenes dataroot to OUT/bundle/ in one command, with the recipe
meant for scenes the model never saw (docs/training.md, "Training on your own data").

Stages, each an `ago` verb run as a subprocess (what a user would type; its output in OUT/work/<stage>.log),
each timed and printed, each reusing what an earlier (interrupted) run left after checking it:

1. split    time split of DATAROOT (time_split.py) -> OUT/work/real: per scene the last `test_share` of its
            keyframes "test", the `val_share` before them "val", the rest "train"; at most `max_scenes` scenes
            (a big official dataroot is subsampled by whole scenes, evenly over its scene list). Reused when
            its split.json records the same source and settings.
2. town     `ago synth`: a small synthetic town on the same six-camera rig -> OUT/work/town (reused when
            town.json records the same settings and the town's splits.json is there).
3. pseudo   `ago pseudo-labels` on the preset model's grid: the town's (simulated segmenter, all frames), the real train frames' and the
            real val frames' (the dataset's 3D boxes + LiDAR ground, `--segmenter boxes`); the verb resumes.
4. train    `ago train --config cpu` from both sources at once (`sources`): the ImageNet backbone frozen
            (its maps cached), the real and the synthetic frames weighted to half of the steps each, mirror and
            half-turn augmentation; snapshots every `steps / 4` steps; resumes from last.pt.
5. select   `ago eval` of every snapshot on the real val frames against their boxes pseudo-labels; the
            length is the snapshot with the highest (mIoU + geometry IoU) / 2 (ties: fewer steps). A rule
            fixed before any run; OUT/work/select.json keeps the scores (a snapshot's score is reused when
            its metrics.json is newer than the snapshot).
6. export   `ago export` of the chosen snapshot, read out on 200x200x16 -> OUT/bundle (made under a
            temporary name and renamed; reused when OUT/bundle/train_real.json names the same snapshot).

The test frames are never read here: benchmarks/train_real.py scores them (`ago infer` + `ago metric --lidar`).
OUT/train_real.json records the settings, the split, each stage's wall time and the machine's load (rewritten
after every stage; a rerun keeps the earlier invocations' times under `earlier_invocations`).
"""

from __future__ import annotations

import json
import os
import shlex
import shutil
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from ago_runtime.atomic import write_json
from ago_runtime.errors import AgoInputError


@dataclass
class RealRecipe:
    """The settings of `ago train-real` (each a `--option` of the verb)."""

    max_scenes: int = 3          # real scenes used at most (a big dataroot: evenly spaced whole scenes)
    val_share: float = 0.15      # per scene, this share of keyframes before the test block: choose the length
    test_share: float = 0.2      # per scene, the last keyframes: never trained on nor used to choose
    town_scenes: int = 8         # synthetic town mixed in: scenes x keyframes
    town_frames: int = 8
    town_image_size: str = "352x198"
    keyframes: int = 3           # real pseudo-labels: keyframes superimposed (benchmarks/results/real_chain_selected.md)
    steps: int = 4000            # training steps (the longest; the val block picks a snapshot;
                                 # benchmarks/results/train_real_grazing.md: still rising at 2000)
    snapshots: int = 4           # snapshots taken at steps/snapshots intervals (each costs an eval on the val block)
    preset: str = "cpu"
    readout_grid: str = "200x200x16"
    jobs: int = 2
    carve: str = "grazing"       # pseudo-labels' free-space rule (`ago pseudo-labels --carve`: all | grazing)
    moving: str = "aggregate"    # pseudo-labels' moving classes (`ago pseudo-labels --moving`: aggregate | keyframe | track)


STAGE_NAMES = ("split", "town", "pseudo", "train", "select", "export")


def _run(name: str, args: list, work: Path, say) -> float:
    """`python -m ago_runtime ARGS` with its output in work/<name>.log; its wall time in seconds."""
    cmd = [sys.executable, "-m", "ago_runtime", *[str(a) for a in args]]
    say(f"   $ ago {' '.join(shlex.quote(str(a)) for a in args)}")
    t = time.perf_counter()
    with open(work / f"{name}.log", "a") as log:
        r = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, env={**os.environ, "AGO_NO_PROGRESS": "1"})
    if r.returncode != 0:
        tail = (work / f"{name}.log").read_text().strip().splitlines()[-2:]
        raise AgoInputError(work / f"{name}.log", f"stage {name} failed (exit {r.returncode}): {' | '.join(tail)}")
    return time.perf_counter() - t


def _marker_matches(path: Path, asked: dict) -> bool:
    if not path.is_file():
        return False
    try:
        return json.loads(path.read_text()) == asked
    except (OSError, json.JSONDecodeError):
        return False


def mix_weights(n_real: int, n_town: int) -> tuple[float, float]:
    """(real weight, town weight): each source gets half of the frames seen per epoch (the smaller one repeated)."""
    if n_real <= 0 or n_town <= 0:
        raise ValueError("both sources need frames")
    if n_real < n_town:
        return n_town / n_real, 1.0
    return 1.0, n_real / n_town


def snapshot_steps(steps: int, count: int) -> list[int]:
    """`count` evenly spaced steps ending at `steps` (distinct, >= 1)."""
    return sorted({max(1, round(steps * k / count)) for k in range(1, count + 1)})


def select_snapshot(scores: dict[int, dict]) -> int:
    """The step with the highest (mIoU + geometry IoU) / 2 on the val frames; ties: fewer steps."""
    def value(step):
        s = scores[step]
        return (s["mIoU"] + s["geometry_IoU"]) / 2.0
    return max(sorted(scores), key=lambda st: (value(st), -st))


def load_average() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def train_real(dataroot: str | Path, out: str | Path, recipe: RealRecipe | None = None, say=print,
               run_verb=_run) -> dict:
    """Run the stages (module docstring); returns the record written to OUT/train_real.json. `run_verb(stage
    name, ago arguments, work folder, say)` runs one verb (tests pass a stand-in)."""
    from ago_runtime.formats.nuscenes import NuScenesDataset, find_version
    from ago_runtime.formats.nuscenes_boxes import box_tables_missing

    from .time_split import time_split

    r = recipe or RealRecipe()
    if r.steps < 1 or r.snapshots < 1 or r.town_scenes < 2 or r.town_frames < 2 or r.max_scenes < 1:
        raise AgoInputError("train-real", f"steps, snapshots, max-scenes >= 1 and town scenes/frames >= 2 needed, got {r}")
    dataroot, out = Path(dataroot), Path(out)
    if not dataroot.is_dir():
        raise AgoInputError(dataroot, "nuScenes dataroot not found")
    if not any(p.is_dir() for p in dataroot.glob("v1.0-*")):
        raise AgoInputError(dataroot, "not a nuScenes dataroot (no v1.0-* table folder)")
    missing = box_tables_missing(dataroot)   # the real keyframes' labels are painted from the boxes (and --moving track)
    if missing:
        raise AgoInputError(dataroot / find_version(dataroot) / f"{missing[0]}.json", "train-real labels the real "
                            f"keyframes from the dataset's 3D boxes (--segmenter boxes); missing: "
                            f"{', '.join(t + '.json' for t in missing)}")
    work = out / "work"
    work.mkdir(parents=True, exist_ok=True)
    earlier = []   # the stage times of earlier (interrupted or finished) invocations on this OUT
    if (out / "train_real.json").is_file():
        try:
            old = json.loads((out / "train_real.json").read_text())
            earlier = old.get("earlier_invocations", []) + [{k: old.get(k) for k in ("stages", "load_average_start",
                                                                                      "load_average_end", "started")}]
        except (OSError, json.JSONDecodeError, AttributeError):
            earlier = []
    record: dict = {"dataroot": str(dataroot.resolve()), "recipe": asdict(r), "load_average_start": load_average(),
                    "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "stages": {},
                    "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
                    "earlier_invocations": earlier}
    t_all = time.perf_counter()

    def stage(n: int, name: str, what: str):
        say(f"== {n}/{len(STAGE_NAMES)} {name}: {what}")
        return time.perf_counter()

    def done(name: str, t0: float, note: str = ""):
        sec = round(time.perf_counter() - t0, 1)
        record["stages"][name] = {"seconds": sec, **({"note": note} if note else {})}
        say(f"   {name}: {sec:.1f} s{' (' + note + ')' if note else ''}; {time.perf_counter() - t_all:.0f} s so far")
        record["load_average_end"] = load_average()
        write_json(out / "train_real.json", record)   # after every stage: an interrupted run keeps its times

    # 1. split by time
    t0 = stage(1, "split", f"time split of {dataroot} (val {r.val_share}, test {r.test_share}, <= {r.max_scenes} scenes)")
    real = work / "real"
    reused = (real / "split.json").is_file()
    split = time_split(dataroot, real, r.val_share, r.test_share, r.max_scenes)
    record["split"] = {name: {p: len(v) for p, v in parts.items()} for name, parts in split["scenes"].items()}
    record["scenes_in_source"] = split["scenes_in_source"]
    done("split", t0, "reused (same source and settings)" if reused else "")

    # 2. synthetic town
    town = work / "town"
    asked = {"scenes": r.town_scenes, "frames": r.town_frames, "seed": 0, "image_size": r.town_image_size,
             "grid": "200x200x16", "rig": "nuscenes"}
    t0 = stage(2, "town", f"ago synth {r.town_scenes} scenes x {r.town_frames} keyframes at {r.town_image_size}")
    if _marker_matches(work / "town.json", asked) and (town / "splits.json").is_file():
        done("town", t0, "reused (town.json: same settings)")
    else:
        shutil.rmtree(town, ignore_errors=True)
        (work / "town.json").unlink(missing_ok=True)
        run_verb("town", ["synth", "--out", town, "--scenes", r.town_scenes, "--frames", r.town_frames, "--seed", 0,
                      "--image-size", r.town_image_size, "--grid", "200x200x16", "--jobs", r.jobs, "--rig", "nuscenes"],
             work, say)
        write_json(work / "town.json", asked)
        done("town", t0)

    # 3. pseudo-labels on the preset model's grid (the verb skips the frames already written and checks its
    # folder's settings)
    from .model import ModelConfig

    grid = "x".join(map(str, ModelConfig.preset(r.preset).grid_obj().shape))
    record["grid"] = grid
    t0 = stage(3, "pseudo", "pseudo-labels: town (simulated segmenter), real train + val (dataset boxes + LiDAR ground)")
    run_verb("pseudo", ["pseudo-labels", "--data", town, "--out", work / "town-pseudo", "--prompts", "cw", "--grid",
                    grid, "--carve", r.carve, "--moving", r.moving, "--split", "all", "--segmenter", "sim", "--embedder",
                    "none", "--keyframes", 10, "--jobs", r.jobs], work, say)
    for part in ("train", "val"):
        run_verb("pseudo", ["pseudo-labels", "--data", real, "--out", work / f"real-pseudo-{part}", "--prompts", "cw",
                        "--grid", grid, "--carve", r.carve, "--moving", r.moving, "--split", part, "--segmenter", "boxes",
                        "--embedder", "none", "--keyframes", r.keyframes, "--jobs", r.jobs], work, say)
    done("pseudo", t0)

    # 4. train from both sources
    n_real = len(NuScenesDataset(real, load_images=False, load_extras=False).split("train"))
    n_town = len(NuScenesDataset(town, load_images=False, load_extras=False).split("all"))
    w_real, w_town = mix_weights(n_real, n_town)
    sources = [{"data": str(real), "pseudo": str(work / "real-pseudo-train"), "weight": round(w_real, 4), "split": "train"},
               {"data": str(town), "pseudo": str(work / "town-pseudo"), "weight": round(w_town, 4), "split": "all"}]
    snaps = snapshot_steps(r.steps, r.snapshots)
    record["train"] = {"real_frames": n_real, "town_frames": n_town, "sources": sources, "snapshot_steps": snaps}
    run = work / "train"
    t0 = stage(4, "train", f"{r.preset} preset, {r.steps} steps, {n_real} real frames x {w_real:.2f} + "
                           f"{n_town} town frames x {w_town:.2f} per epoch")
    resume = (run / "last.pt").is_file()
    run_verb("train", ["train", "--config", r.preset, "--out", run, "--set", "sources=" + json.dumps(sources),
                   "--set", f"max_steps={r.steps}", "--set", "ckpt_every=200",
                   "--set", "snapshot_steps=" + json.dumps(snaps), *(["--resume"] if resume else [])], work, say)
    done("train", t0, "resumed from last.pt" if resume else "")

    # 5. choose the length on the val block
    t0 = stage(5, "select", f"ago eval of {len(snaps)} snapshots on the real val frames (boxes pseudo-labels)")
    scores, reused_n = {}, 0
    for step in snaps:
        snap = run / "snapshots" / f"step_{step:06d}.pt"
        if not snap.is_file():
            raise AgoInputError(snap, "snapshot missing after training (remove OUT/work/train to retrain)")
        ev = work / "select" / f"step_{step:06d}"
        if not ((ev / "metrics.json").is_file() and (ev / "metrics.json").stat().st_mtime > snap.stat().st_mtime):
            run_verb("select", ["eval", "--ckpt", snap, "--data", real, "--split", "val", "--gts", work / "real-pseudo-val",
                            "--out", ev, "--readout", "model"], work, say)
        else:
            reused_n += 1
        m = json.loads((ev / "metrics.json").read_text())
        scores[step] = {"mIoU": m["mIoU"], "geometry_IoU": m["geometry_IoU"]}
        say(f"   step {step}: val mIoU {m['mIoU']}, geometry IoU {m['geometry_IoU']}")
    chosen = select_snapshot(scores)
    record["select"] = {"rule": "highest (mIoU + geometry IoU) / 2 on the val frames against their boxes "
                                "pseudo-labels; ties: fewer steps", "scores": scores, "chosen_step": chosen}
    write_json(work / "select.json", record["select"])
    done("select", t0, f"chosen step {chosen}" + (f"; {reused_n} scores reused" if reused_n else ""))

    # 6. export the chosen snapshot
    snap = run / "snapshots" / f"step_{chosen:06d}.pt"
    bundle = out / "bundle"
    asked = {"snapshot": str(snap.resolve()), "mtime": snap.stat().st_mtime, "readout_grid": r.readout_grid}
    t0 = stage(6, "export", f"ago export step {chosen} -> {bundle}")
    if _marker_matches(bundle / "train_real.json", asked):
        done("export", t0, "reused (same snapshot)")
    else:
        tmp = work / "bundle.tmp"
        shutil.rmtree(tmp, ignore_errors=True)
        run_verb("export", ["export", snap, "-o", tmp, "--parity-frame", real, "--readout-grid", r.readout_grid,
                        "--train-bank-only", "--card-note",
                        f"trained by `ago train-real` on {n_real} real keyframes ({dataroot.name}, boxes pseudo-labels) "
                        f"mixed with a {n_town}-frame synthetic town; length {chosen} steps chosen on a val block"],
             work, say)
        write_json(tmp / "train_real.json", asked)
        shutil.rmtree(bundle, ignore_errors=True)
        os.replace(tmp, bundle)
        done("export", t0)
    record["bundle"] = str(bundle)
    record["seconds_total"] = round(time.perf_counter() - t_all, 1)
    record["load_average_end"] = load_average()
    write_json(out / "train_real.json", record)
    say(f"done: {bundle} in {record['seconds_total'] / 60:.1f} min (load average {record['load_average_end']})")
    return record
