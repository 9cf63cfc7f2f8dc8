"""Run records: the small files of finished runs, portable to another machine.

A whole `cpu` profile takes longer than some machines live (a CI-like box, a lent machine, a laptop
closed at night). `ago experiments run ... --records DIR` keeps, beside the experiments folder, a copy of
what each finished run contributes to the tables - its scores (`views.json`), its training summary
(`done.json`), the predicted volumes kept for the renders (`kept/*.npz`) and the recipe it was trained
with (`recipe.json`) - and no checkpoints or data. A later `run` with the same `--records DIR`, on this or
another machine, puts those files into its own folder first, so it trains and scores only the runs that
are missing.

What a reuse checks:
- `DIR/records.json` names the profile and a fingerprint of the generated data (the dataset's metadata
  tables: scenes, sample tokens, poses, calibration); another profile or other data is refused.
- each run's `recipe.json` (its full training config, with the machine's own paths written as names)
  must equal the recipe this code builds for that run now; a run whose recipe changed is trained again.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

from ago_runtime.atomic import write_json
from ago_runtime.errors import AgoInputError
from ago_runtime.readers import read_json

from .plan import profile_differences

RUN_FILES = ("views.json", "done.json")


def data_fingerprint(data: Path) -> str:
    """sha256 over the dataset's JSON metadata (tables, splits): the same scenes, tokens, poses and rig."""
    h = hashlib.sha256()
    files = sorted(p for p in data.rglob("*.json") if p.is_file())
    if not files:
        raise AgoInputError(data, "no dataset metadata (*.json) to fingerprint")
    for p in files:
        h.update(p.relative_to(data).as_posix().encode())
        h.update(p.read_bytes())
    return h.hexdigest()


def recipe(runner, spec) -> dict:
    """The run's training config as a dict, with the machine's own paths written as names: the experiments
    folder as `<out>`, the dataset as `<data>`, each pseudo-label folder as `<pseudo:SPACE>`."""
    places = {str(runner.out): "<out>", str(runner.data): "<data>", str(runner.data_of("waymo")): "<data:waymo>"}
    places.update({str(runner.pseudo(space)): f"<pseudo:{space}>" for space in runner.profile.pseudo})
    places.update({str(runner.pseudo(space, "waymo")): f"<pseudo:waymo:{space}>"
                   for space in runner.profile.waymo.pseudo})
    longest_first = sorted(places, key=len, reverse=True)

    def rel(v):
        if isinstance(v, str):
            for place in longest_first:
                if v == place or v.startswith(place + "/"):
                    return places[place] + v[len(place):]
            return v
        if isinstance(v, dict):
            return {k: rel(x) for k, x in v.items()}
        if isinstance(v, list):
            return [rel(x) for x in v]
        return v

    return json.loads(json.dumps(rel(runner.train_config(spec).to_dict())))   # tuples -> lists, as read back


def check_profile(runner, records: Path) -> None:
    """Before any work: refuse a records folder made with another profile."""
    path = records / "records.json"
    if path.is_file() and profile_differences(read_json(path).get("profile") or {}, runner.profile.to_dict()):
        raise AgoInputError(records, "these run records were made with another profile; use another --records")


def check_data(runner, records: Path) -> None:
    """Once the data exists: refuse records made on other data; start a records folder that does not exist."""
    path = records / "records.json"
    mine = {"profile": runner.profile.to_dict()}
    # one fingerprint per dataset that exists here ("data": the nuScenes-layout city, "data_waymo": the Waymo one)
    for key, dataset in (("data", "nuscenes"), ("data_waymo", "waymo")):
        if runner.data_of(dataset).is_dir():
            mine[key] = data_fingerprint(runner.data_of(dataset))
    if path.is_file():
        saved = read_json(path)
        if any(k in saved and saved[k] != mine[k] for k in ("data", "data_waymo") if k in mine):
            raise AgoInputError(records, "these run records were made on other data (the dataset's metadata "
                                "differs); use another --records")
        if any(k not in saved for k in mine) or saved["profile"] != mine["profile"]:
            write_json(path, {**saved, **mine})   # a dataset (or profile key) this folder did not have yet
    else:
        records.mkdir(parents=True, exist_ok=True)
        write_json(path, mine)


def import_records(runner, records: Path, specs) -> list[str]:
    """Copy the record of every run in `specs` that this folder has not scored into it; returns their names.
    A record whose recipe differs from today's is left out (logged) and that run is trained again."""
    taken = []
    for spec in specs:
        src = records / "runs" / spec.name
        dst = runner.run_dir(spec.name)
        if not (src / "views.json").is_file() or (dst / "views.json").is_file():
            continue
        saved = read_json(src / "recipe.json") if (src / "recipe.json").is_file() else None
        now = recipe(runner, spec)
        if saved != now:
            diff = sorted(k for k in set(saved or {}) | set(now) if (saved or {}).get(k) != now.get(k))
            runner.log(f"record {spec.name} not reused: its recipe differs in {diff}")
            continue
        dst.mkdir(parents=True, exist_ok=True)
        if (src / "kept").is_dir():
            shutil.copytree(src / "kept", dst / "kept", dirs_exist_ok=True)
        for name in ("done.json", "views.json"):   # views.json last: it marks the run scored
            if (src / name).is_file():
                shutil.copyfile(src / name, dst / name)
        taken.append(spec.name)
    if taken:
        runner.log(f"reused {len(taken)} run record(s) from {records}: {taken}")
    return taken


def save_record(runner, records: Path, spec) -> None:
    """Write the run's record (views, done, kept volumes, recipe) into `records`, replacing an older one
    whole (written beside it, then renamed)."""
    src = runner.run_dir(spec.name)
    dst = records / "runs" / spec.name
    tmp = dst.with_name("." + dst.name + ".new")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for name in RUN_FILES:
        if (src / name).is_file():
            shutil.copyfile(src / name, tmp / name)
    if (src / "kept").is_dir():
        shutil.copytree(src / "kept", tmp / "kept")
    write_json(tmp / "recipe.json", recipe(runner, spec))
    old = dst.with_name("." + dst.name + ".old")
    shutil.rmtree(old, ignore_errors=True)
    if dst.exists():
        dst.rename(old)
    tmp.rename(dst)
    shutil.rmtree(old, ignore_errors=True)
