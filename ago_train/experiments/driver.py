"""Run the named experiments: make (or reuse) the data, train (or reuse / resume) the runs, score them.

    ago experiments run [tab1 tab2 ...] --profile cpu --out runs/experiments
    ago experiments report --out runs/experiments        (tables + figures from what is there)

Folder `<out>` (everything is cached there; rerunning a command skips what is done):
    profile.json                 the profile the folder was made with (a different one is refused)
    synth/, pseudo_*/            data (profiles that generate it)
    synth_waymo/, pseudo_waymo_*/  the Occ3D-Waymo city and its pseudo-labels (Tab. G and H)
    runs/<run name>/             one training run each (config.json, log.jsonl, last.pt)
    runs/<run name>/views.json   its scores under the views the experiments asked for (+ stats)
    runs/<run name>/kept/*.npz   predicted volumes of the first val frames (for the renders)
    results.json, results.md, figures/*.png    written by `report` (and at the end of `run`)

Experiments (EXPERIMENTS): tab1 (closed world), tab2 (open world, 3 stages), tab3 (paradigms),
tab4 (identifier), tab5 (noise prompts, L_occ), supp (adapter depth, align loss), figures, and on
the Occ3D-Waymo city tabG (closed world) and tabH (open world: pretraining, zero-shot, few-shot).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ago_runtime.atomic import write_json
from ago_runtime.errors import AgoInputError
from ago_runtime.geometry.grid import Grid
from ago_runtime.predict.decision import Identifier
from ago_runtime.readers import read_json

from . import records
from .plan import (ADAPTED_SCALES, FEWSHOT_VARIANTS, PARADIGMS, PROMPTS, WAYMO_PRETRAIN_EVAL, ExperimentProfile,
                   RunSpec, cw_run, fewshot_run, ow_run, profile_differences, shipped_prompts, waymo_run)
from .view_eval import View

EXPERIMENTS = ("tab1", "tab2", "tab3", "tab4", "tab5", "supp", "figures", "tabG", "tabH")


# ---------------------------------------------------------------------------------------------
# which runs and which views each experiment needs
def runs_for(experiment: str, profile: ExperimentProfile) -> list[RunSpec]:
    """The runs `experiment` needs: each closed-/open-world run once per seed of the profile, the few-shot
    runs one per seed (plan.py); the figures use seed 0's runs."""
    seeds = profile.seeds
    if experiment == "tab1":
        return [cw_run("ago", seed=s) for s in seeds]
    if experiment == "tab2":
        return ([ow_run(v, seed=s) for v in FEWSHOT_VARIANTS for s in seeds]
                + [fewshot_run(v, s) for v in FEWSHOT_VARIANTS for s in seeds])
    if experiment == "tab3":
        return [cw_run(v, seed=s) for v in PARADIGMS for s in seeds] + [ow_run(v, seed=s) for v in PARADIGMS
                                                                       for s in seeds]
    if experiment == "tab4":
        return [ow_run("ago", seed=s) for s in seeds] + [fewshot_run("ago", s) for s in seeds]
    if experiment == "tab5":
        return [cw_run("ago", seed=s, **loss) for loss in ({}, {"use_noise": False}, {"use_occ": False},
                                                           {"use_noise": False, "use_occ": False}) for s in seeds]
    if experiment == "supp":
        return ([ow_run("ago", adapter_depth=d, seed=s) for d in (1, 2, 3, 4) for s in seeds]
                + [ow_run("ago", align_loss=a, seed=s) for a in ("mse", "l1") for s in seeds])
    if experiment == "figures":
        return [cw_run("ago"), ow_run("ago")]
    if experiment == "tabG":
        return [waymo_run("cw", s) for s in seeds]
    if experiment == "tabH":
        return [waymo_run("ow", s) for s in seeds] + [waymo_run("fewshot", s) for s in seeds]
    raise AgoInputError(None, f"unknown experiment {experiment!r}; choose from {list(EXPERIMENTS)}")


def views_for(spec: RunSpec, ow_prompts: str) -> list[View]:
    """Every way a run is scored by any experiment (one forward pass per frame covers all)."""
    if spec.dataset == "waymo":
        return waymo_views(spec)
    variant = dict(spec.loss).get("variant", "ago")
    if spec.setting == "cw":
        views = [View("cw", "cw", Identifier.NONE)]
        if variant == "ago":
            views += [View("cw-min-entropy", "cw", Identifier.MIN_ENTROPY)]
        return views
    views = [View("ow-none", ow_prompts, Identifier.NONE)]
    if variant == "grounding" and spec.setting == "ow":
        views.append(View("ow-closed", ow_prompts, Identifier.NONE, closed_set=True))
    if variant in ("ago", "grounding+align"):
        views += [View("ow-max-conf", ow_prompts, Identifier.MAX_CONF),
                  View("ow-min-entropy", ow_prompts, Identifier.MIN_ENTROPY),
                  View("ow-adapted", ow_prompts, Identifier.ADAPTED)]
    if variant == "ago" and not dict(spec.model) and len(spec.loss) == 1:   # the main ago runs (Tab. 2 / 4)
        views += [View(f"ow-min-entropy-x{s:g}", ow_prompts, Identifier.MIN_ENTROPY, adapted_scale=s)
                  for s in ADAPTED_SCALES]
    return views


def waymo_views(spec: RunSpec) -> list[View]:
    """Tab. G: the closed-world run on the 15 Occ3D-Waymo classes. Tab. H: the pretraining run on the pretraining
    stage's label space ("ow-pretrain": cycle whole, the unknown classes beside it) and zero-shot on the 14
    classes of ow_waymo ("ow-min-entropy", AGO's identifier; "ow-none" without it); the few-shot runs on the 14."""
    if spec.setting == "cw":
        return [View("cw", shipped_prompts(PROMPTS["waymo"]["cw"]), Identifier.NONE)]
    ow = shipped_prompts(PROMPTS["waymo"]["ow"])
    views = [View("ow-min-entropy", ow, Identifier.MIN_ENTROPY), View("ow-none", ow, Identifier.NONE)]
    if spec.setting == "ow":
        views.insert(0, View("ow-pretrain", shipped_prompts(WAYMO_PRETRAIN_EVAL), Identifier.MIN_ENTROPY))
    return views


def main_view(spec: RunSpec) -> str:
    """The view a run is reported under in the main tables (the method's own inference rule)."""
    variant = dict(spec.loss).get("variant", "ago")
    if spec.setting == "cw":
        return "cw"
    return "ow-min-entropy" if variant == "ago" else "ow-none"


# ---------------------------------------------------------------------------------------------
class ExperimentRunner:
    def __init__(self, profile: ExperimentProfile, out: str | Path, quiet: bool = False,
                 records: str | Path | None = None):
        self.profile = profile
        self.out = Path(out)
        self.quiet = quiet
        self.records = Path(records) if records is not None else None   # run records (records.py)
        self.log_path = self.out / "driver.log"

    # ---- bookkeeping -------------------------------------------------------------------
    def log(self, msg: str) -> None:
        line = f"{time.strftime('%Y-%m-%d %H:%M:%S')} {msg}"
        if not self.quiet:
            print(line, flush=True)
        self.out.mkdir(parents=True, exist_ok=True)
        with open(self.log_path, "a", encoding="utf-8") as f:
            f.write(line + "\n")

    def check_profile(self) -> None:
        path = self.out / "profile.json"
        mine = self.profile.to_dict()
        if path.is_file():
            saved = read_json(path)
            diff = profile_differences(saved, mine)
            if diff:
                raise AgoInputError(path, f"this folder was made with another profile (differs in {diff}); "
                                    "use another --out")
            if saved != mine:
                write_json(path, mine)   # a folder made before the profile had some keys (plan.ADDED_KEYS)
        else:
            write_json(path, mine)

    def path(self, p: str) -> Path:
        q = Path(p)
        return q if q.is_absolute() or self.profile.external_data else self.out / q

    @property
    def data(self) -> Path:
        return self.path(self.profile.data)

    def data_of(self, dataset: str) -> Path:
        """The dataset folder of "nuscenes" (the profile's city) or "waymo" (its Occ3D-Waymo city)."""
        return self.data if dataset == "nuscenes" else self.path(self.profile.waymo.data)

    def pseudo(self, space: str, dataset: str = "nuscenes") -> Path:
        folders = self.profile.pseudo if dataset == "nuscenes" else self.profile.waymo.pseudo
        return self.path(folders[space])

    def run_dir(self, name: str) -> Path:
        return self.out / "runs" / name

    # ---- data ------------------------------------------------------------------------------
    def _ago(self, *args: str) -> None:
        cmd = [sys.executable, "-m", "ago_runtime.cli", *args]
        self.log("$ ago " + " ".join(args))
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0:
            raise AgoInputError(None, f"`ago {' '.join(args)}` failed: {(r.stderr or r.stdout).strip()[-400:]}")

    def ensure_data(self, spaces: set[str], dataset: str = "nuscenes") -> None:
        """The dataset folder and the pseudo-labels of `spaces` ("cw", "ow_pretrain", "ow") of `dataset`."""
        p = self.profile
        data = self.data_of(dataset)
        if p.external_data:
            for need in [data] + [self.pseudo(s, dataset) for s in sorted(spaces)]:
                if not need.exists():
                    raise AgoInputError(need, f"profile {p.name!r} uses external data: make this folder first "
                                        "(docs/experiments.md)")
            return
        # worker processes for synth and pseudo-labels: the data is the same for any number
        jobs = str(max(1, min(os.cpu_count() or 1, 8)))
        if not (data / "synth.done").is_file():
            args = ["synth", "--out", str(data)]
            for k, v in (p.synth if dataset == "nuscenes" else p.waymo.synth).items():
                args += [f"--{k}", str(v)]
            self._ago(*args, "--jobs", jobs)
        (data / "synth.done").write_text("done\n")
        for space in sorted(spaces):
            out = self.pseudo(space, dataset)
            done = out / "complete.json"
            if done.is_file():
                continue
            split = "all" if space == "cw" else p.train_split   # cw pseudo-labels on val too: their own mIoU
            self._ago("pseudo-labels", "--data", str(data), "--out", str(out), "--prompts", PROMPTS[dataset][space],
                      "--segmenter", "sim", "--embedder", "sim", "--grid", p.pseudo_grid, "--carve", p.pseudo_carve,
                      "--keyframes", str(p.sweeps), "--interval", str(p.interval), "--split", split, "--jobs", jobs)
            write_json(done, {"split": split})

    def ensure_data_scores(self) -> dict:
        """The cw pseudo-labels' own scores on the val frames (Tab. 1) and the simulated VLM embeddings'
        cosine to each class text per GT class (the E_3D panel of the modality-gap figure)."""
        path = self.out / "data_scores.json"
        if path.is_file():
            return read_json(path)
        from ago_runtime.scoring.metric import OccupancyMetric, upsample_nearest
        from ago_runtime.formats.datasets import open_dataset
        from ago_runtime.vocab.prompts import parse_prompt_file

        from ..pseudo.generate import load_pseudo_labels, load_voxel_embeds
        from ..trainer import build_text_bank

        pdir = self.pseudo("cw")
        ds = open_dataset(self.data, load_images=False)
        metric = OccupancyMetric()
        space = parse_prompt_file("cw")
        bank = build_text_bank(space)
        emb, pc = bank.embeddings.numpy().astype(np.float32), bank.phrase_class.numpy()
        text = np.stack([emb[pc == k].mean(0) for k in range(space.num_classes)])
        text /= np.linalg.norm(text, axis=1, keepdims=True)
        K = space.num_classes
        cos, count = np.zeros((K, K)), np.zeros(K)
        frames = 0
        for i in ds.split(self.profile.eval_split):
            scene, token = ds.scene_of(i), ds.sample_tokens[i]
            if not (pdir / scene / token / "labels.npz").is_file():
                continue
            gt = ds[i].gt
            sem, _ml, _mc = load_pseudo_labels(pdir, scene, token)
            fac = tuple(g // p for g, p in zip(gt.semantics.shape, sem.shape))
            sem = np.where(sem == 255, 17, sem).astype(np.uint8)   # unlabelled counts as free (as in the ladder)
            metric.update(upsample_nearest(sem, fac), gt.semantics, gt.mask_camera.astype(bool))
            index, e = load_voxel_embeds(pdir, scene, token)
            g = gt.semantics[:: fac[0], :: fac[1], :: fac[2]].reshape(-1)[index]
            keep = g < K
            e = e[keep].astype(np.float32)
            e /= np.maximum(np.linalg.norm(e, axis=1, keepdims=True), 1e-8)
            s = e @ text.T
            for k in range(K):
                cos[:, k] += np.bincount(g[keep], weights=s[:, k], minlength=K)[:K]
            count += np.bincount(g[keep], minlength=K)[:K]
            frames += 1
        summ = metric.summary()
        r = {"pseudo_cw_val": {"mIoU": summ["mIoU"], "mIoU_star": summ["mIoU_star"],
                               "geometry_IoU": summ["geometry_IoU"], "iou": summ["iou"], "frames": frames},
             "gap_e3d": {"classes": list(space.class_names), "voxels": count.tolist(),
                         "cos": np.round(cos / np.maximum(count, 1)[:, None], 4).tolist()}}
        write_json(path, r)
        return r

    def ensure_waymo_pseudo_score(self) -> dict:
        """The Waymo cw pseudo-labels' own scores on the val frames of the Waymo city (Tab. G's reference row),
        in the closed Waymo label space: unlabelled voxels count as free, as in Tab. 1's row."""
        path = self.out / "data_scores_waymo.json"
        if path.is_file():
            return read_json(path)
        from ago_runtime.formats.datasets import open_dataset
        from ago_runtime.scoring.metric import OccupancyMetric, upsample_nearest
        from ago_runtime.vocab.prompts import parse_prompt_file

        from ..pseudo.generate import load_pseudo_labels

        pdir = self.pseudo("cw", "waymo")
        space = parse_prompt_file(shipped_prompts(PROMPTS["waymo"]["cw"]))
        K = space.num_classes
        metric = OccupancyMetric(list(space.class_names) + ["free"], free_index=K)
        lut = space.gt_lut(free_index=K)
        ds = open_dataset(self.data_of("waymo"), load_images=False)
        frames = 0
        for i in ds.split(self.profile.eval_split):
            scene, token = ds.scene_of(i), ds.sample_tokens[i]
            try:
                sem, _ml, _mc = load_pseudo_labels(pdir, scene, token)
            except AgoInputError:
                continue                                   # a frame without pseudo-labels
            gt = ds[i].gt
            fac = tuple(g // q for g, q in zip(gt.semantics.shape, sem.shape))
            sem = np.where(sem < K, sem, K).astype(np.uint8)   # the pseudo format's free (17) and unknown (255)
            metric.update(upsample_nearest(sem, fac), lut[gt.semantics], gt.mask_camera.astype(bool))
            frames += 1
        summ = metric.summary()
        r = {"pseudo_cw_val": {"mIoU": summ["mIoU"], "geometry_IoU": summ["geometry_IoU"], "iou": summ["iou"],
                               "frames": frames}}
        write_json(path, r)
        return r

    # ---- training ----------------------------------------------------------------------
    def train_config(self, spec: RunSpec):
        from ..losses import LossConfig
        from ..model import ModelConfig
        from ..train_config import TrainConfig

        p = self.profile
        cfg = TrainConfig.preset(p.train_preset)
        if p.train_set:
            cfg = TrainConfig.from_dict({**cfg.to_dict(), **p.train_set})
        ow_loss = p.ow_loss if spec.setting in ("ow", "fewshot") else {}
        loss = LossConfig(**{**cfg.loss.to_dict(), **ow_loss, **dict(spec.loss)})
        rig_model = p.waymo.model if spec.dataset == "waymo" else {}   # the Waymo rig's canvas
        grid = Grid.parse(p.pseudo_grid, "pseudo_grid").to_dict()   # the model trains on its pseudo-labels' grid
        model = ModelConfig.from_dict({**cfg.model.to_dict(), "grid": grid, **rig_model, **dict(spec.model)})
        changes = dict(data=str(self.data_of(spec.dataset)), pseudo=str(self.pseudo(spec.space, spec.dataset)),
                       prompts=spec.prompts,
                       out=str(self.run_dir(spec.name)), train_split=p.train_split, loss=loss, model=model,
                       seed=spec.seed, frame_tokens=None, init_from=None)
        if spec.setting == "fewshot":
            changes.update(init_from=str(self.run_dir(spec.init_from) / "last.pt"),
                           frame_tokens=self.kshot_tokens(spec.seed, spec.dataset), epochs=p.fewshot_epochs,
                           max_steps=p.fewshot_steps)
        elif p.steps is not None:
            changes.update(max_steps=p.steps, epochs=max(cfg.epochs, 1000))
        if p.steps is not None:
            changes.update(ckpt_every=max(10, (p.steps or 100) // 4))
        return replace(cfg, **changes)

    def kshot_tokens(self, seed: int, dataset: str = "nuscenes") -> list[str]:
        from ago_runtime.vocab.prompts import parse_prompt_file

        from ..dataset import PseudoLabelSet
        from ..open_world import select_kshot
        from ..sources import open_split

        folder = self.out / "kshot" if dataset == "nuscenes" else self.out / "kshot" / dataset
        path = folder / f"seed{seed}.json"
        if path.is_file():
            return read_json(path)["tokens"]
        space = parse_prompt_file(shipped_prompts(PROMPTS[dataset]["ow"]))
        pseudo = PseudoLabelSet.open(self.pseudo("ow", dataset))
        ds, indices = open_split(str(self.data_of(dataset)), None, self.profile.train_split)
        frames = [(ds.scene_of(i), ds.sample_tokens[i]) for i in indices]
        tokens, counts = select_kshot(pseudo, frames, space.num_classes, self.profile.k, seed)
        write_json(path, {"seed": seed, "k": self.profile.k, "tokens": tokens,
                          "class_frames": {space.class_names[c]: n for c, n in counts.items()}})
        return tokens

    def is_trained(self, spec: RunSpec) -> bool:
        ckpt = self.run_dir(spec.name) / "last.pt"
        status = self.run_dir(spec.name) / "done.json"
        return ckpt.is_file() and status.is_file()

    def ensure_trained(self, spec: RunSpec) -> None:
        from ..trainer import train

        if self.is_trained(spec):
            return
        if spec.init_from:
            self.ensure_trained(RunSpec(spec.init_from, "ow", spec.loss, spec.model, seed=spec.seed,
                                        dataset=spec.dataset))
        cfg = self.train_config(spec)
        resume = (self.run_dir(spec.name) / "last.pt").is_file()
        self.log(f"train {spec.name}{' (resume)' if resume else ''}")
        t0 = time.time()
        r = train(cfg, resume=resume, quiet=self.quiet)
        write_json(self.run_dir(spec.name) / "done.json",
                   {"steps": r["step"], "final_loss": r["losses"][-1] if r["losses"] else None,
                    "wall_s_last_session": round(time.time() - t0, 1)})
        self.log(f"trained {spec.name}: {r['step']} steps in {time.time() - t0:.0f} s")

    # ---- scoring -----------------------------------------------------------------------
    def ensure_scored(self, spec: RunSpec) -> dict:
        from ago_runtime.vocab.prompts import resolve_prompt_file

        from ..open_world import OpenWorldConfig, known_prompt_file
        from .view_eval import evaluate_views

        path = self.run_dir(spec.name) / "views.json"
        ow_prompts = str(self.out / "ow_known.txt")
        # ow.txt with `@known:` = the classes ow_pretrain covers (the nuScenes runs' open-world label space)
        if spec.dataset == "nuscenes" and not Path(ow_prompts).is_file():
            known_prompt_file(OpenWorldConfig(base=None, pseudo_pretrain="", pseudo_full=""), self.out)
        views = [v if v.prompts != "cw" else replace(v, prompts=str(resolve_prompt_file("cw")))
                 for v in views_for(spec, ow_prompts)]
        if path.is_file():
            saved = read_json(path)
            if sorted(saved["views"]) == sorted(v.name for v in views):
                return saved
        self.ensure_trained(spec)
        stats_view = {"cw": "cw", "ow": None, "fewshot": None}[spec.setting]
        if spec.setting == "ow" and any(v.name == "ow-min-entropy" for v in views):
            stats_view = "ow-min-entropy"
        if spec.dataset == "waymo":
            stats_view = None          # the figures are drawn from the nuScenes runs only
        self.log(f"score {spec.name}: {[v.name for v in views]}")
        t0 = time.time()
        r = evaluate_views(self.run_dir(spec.name) / "last.pt", str(self.data_of(spec.dataset)), views,
                           split=self.profile.eval_split,
                           max_frames=self.profile.eval_max_frames, stats_view=stats_view,
                           keep_frames=self.profile.render_frames, quiet=self.quiet)
        kept_dir = self.run_dir(spec.name) / "kept"
        kept_dir.mkdir(parents=True, exist_ok=True)
        for view, frames in r.pop("kept").items():
            for scene, token, labels in frames:
                tmp = kept_dir / f".{view}__{token}.npz"
                with open(tmp, "wb") as f:
                    np.savez_compressed(f, labels=labels, scene=scene, token=token)
                tmp.replace(kept_dir / f"{view}__{token}.npz")
        r["eval_s"] = round(time.time() - t0, 1)
        write_json(path, r)
        return r

    # ---- experiments -------------------------------------------------------------------
    def run(self, experiments: list[str]) -> None:
        for e in experiments:
            if e not in EXPERIMENTS:
                raise AgoInputError(None, f"unknown experiment {e!r}; choose from {list(EXPERIMENTS)}")
        self.check_profile()
        if self.records is not None:
            records.check_profile(self, self.records)
        specs: dict[str, RunSpec] = {}
        for e in experiments:
            for s in runs_for(e, self.profile):
                specs.setdefault(s.name, s)
        spaces = {"cw" if s.setting == "cw" else "ow_pretrain" for s in specs.values() if s.dataset == "nuscenes"}
        if any(s.setting == "fewshot" and s.dataset == "nuscenes" for s in specs.values()):
            spaces.add("ow")
        if "tab1" in experiments or "figures" in experiments:
            spaces.add("cw")
        if spaces:
            self.ensure_data(spaces)
        waymo_spaces = {s.space for s in specs.values() if s.dataset == "waymo"}
        if "ow" in waymo_spaces:
            waymo_spaces.add("ow_pretrain")   # a few-shot run fine-tunes the pretraining run
        if waymo_spaces:
            self.ensure_data(waymo_spaces, "waymo")
        if "tabG" in experiments and not self.profile.external_data:
            self.ensure_waymo_pseudo_score()
        if "cw" in spaces and not self.profile.external_data:
            self.ensure_data_scores()
        if self.records is not None:
            records.check_data(self, self.records)
            records.import_records(self, self.records, specs.values())
        # in the order the experiments were named, each few-shot run right after its pretraining run (whose
        # checkpoint it starts from: a machine that stops between the two does not have to retrain it)
        order = []
        for s in specs.values():
            if s.setting == "fewshot" and s.init_from in specs:
                continue                                    # placed right after its pretraining run
            order.append(s)
            order += [f for f in specs.values() if f.setting == "fewshot" and f.init_from == s.name]
        from ago_runtime.progress import track

        for spec in (order if self.quiet else track(order, description="experiment runs", total=len(order))):
            self.ensure_scored(spec)
            if self.records is not None:
                records.save_record(self, self.records, spec)
        from .report import write_report

        write_report(self.out, self.profile)
        self.log(f"done: {experiments}; written {self.out}/results.md")
