"""`ago pseudo-labels`: 3-D pseudo-labels (and voxel image embeddings) from 2-D masks and features.

Reads a dataset (nuScenes or Occ3D-Waymo layout: `ago_runtime.formats.datasets.open_dataset`; the prompt
file's class table must be the data's), labels every keyframe of a split with a segmenter (`files`: masks
written by Grounded SAM, see docs/vlm_files.md; `sim`: the SIMULATED segmenter, synthetic data only),
lifts image features with an embedder (`files`, `sim` or `none`), and writes the folder
described in ago_train/pseudo/generate.py. Two counts set the LiDAR used per sample: `--keyframes`
(keyframes superimposed, each labelled with its own images) and `--sweeps` (non-key LiDAR sweeps
added per keyframe, labelled with its images; default: all the dataset lists). Defaults fit the
data (resolve_defaults, resolve_split, resolve_sweeps) and are printed as `note:` lines.
Resumable: rerun the same command to finish (damaged files are remade).
Needs numpy + opencv only (no torch).
"""

from __future__ import annotations

import shlex
import sys
from enum import Enum
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from ago_train.vlm.loading import TorchDevice
from ago_train.model.config import CPU_GRID_SHAPE


class Segmenter(str, Enum):
    """`ago pseudo-labels --segmenter`: where each image's 2-D label map comes from."""

    FILES = "files"
    GROUNDED_SAM = "grounded-sam"
    SIM = "sim"
    BOXES = "boxes"


class Embedder(str, Enum):
    """`ago pseudo-labels --embedder`: where each image's dense features come from."""

    FILES = "files"
    MASKCLIP = "maskclip"
    SIM = "sim"
    NONE = "none"


class Moving(str, Enum):
    """`ago pseudo-labels --moving`: where the moving classes' points come from."""

    AGGREGATE = "aggregate"
    KEYFRAME = "keyframe"
    TRACK = "track"


class Carve(str, Enum):
    """`ago pseudo-labels --carve`: which voxels a LiDAR ray calls free."""

    ALL = "all"
    GRAZING = "grazing"


# what each choice does, printed in --help (a KeyError at import if a choice has none)
SEGMENTER_HELP = {Segmenter.FILES: "label maps, docs/vlm_files.md",
                  Segmenter.GROUNDED_SAM: "GroundingDINO + SAM from --detector / --sam, on the fly",
                  Segmenter.SIM: "SIMULATED, `ago synth` data only",
                  Segmenter.BOXES: "painted from the dataset's 3D boxes and LiDAR ground: not a VLM; "
                                   "ago_train/pseudo/boxes.py"}
CARVE_HELP = {Carve.ALL: "every voxel a ray crosses before its hit voxel",
              Carve.GRAZING: "a ray descending to its hit stops half a voxel height above the lowest hit voxel of "
                             "the hit's column, so rays grazing far ground do not call it free; the default; "
                             "ago_train/pseudo/raycast.py"}
MOVING_HELP = {Moving.AGGREGATE: "from every superimposed keyframe, like the static classes (a moving object is "
                                  "labelled along its track: benchmarks/results/pseudo_aggregation_smear.md); the default",
               Moving.KEYFRAME: "only from the sample's own keyframe and its own sweeps (vehicles, cycles, pedestrians: "
                                "ago_train/pseudo/generate.py MOVING_TABLE_CLASSES)",
               Moving.TRACK: "the other keyframes' carried along their objects' annotated box tracks (parked ones "
                             "stay), those in no annotated box dropped as with keyframe; needs the sample_annotation "
                             "table"}
EMBEDDER_HELP = {Embedder.FILES: "feature maps, docs/vlm_files.md", Embedder.MASKCLIP: "--clip, on the fly",
                 Embedder.SIM: "SIMULATED", Embedder.NONE: "no features: training will not align the adapter"}


def choices_help(choices: type[Enum], meaning: dict) -> str:
    """'a (what a does), b (...)' for every member of `choices`, in their order."""
    return ", ".join(f"{c.value} ({meaning[c]})" for c in choices)


def _names(choices: type[Enum]) -> str:
    return ", ".join(c.value for c in choices)


def grounded_sam_config(box_threshold: float, text_threshold: float, nms_iou: float, max_boxes: int):
    """The Grounded SAM settings (a dataclass of ago_train/vlm; importing it imports no torch)."""
    from ago_train.vlm.grounded_sam import GroundedSamConfig

    return GroundedSamConfig(box_threshold=box_threshold, text_threshold=text_threshold, nms_iou=nms_iou,
                             max_boxes=max_boxes)


def parse_grid(text: str):
    from ago_runtime.geometry.grid import Grid

    from ..model.config import check_min_grid

    grid = Grid.parse(text, "--grid")
    check_min_grid(grid.shape, "--grid")
    return grid


def build_backends(prompts: str, segmenter: str, masks: Path | None, embedder: str, feats: Path | None,
                   seed: int, data: Path | None = None, write_masks: Path | None = None, text_encoder=None,
                   vlm: dict | None = None):
    """(label_space, segmenter, embedder or None) from the CLI choices; `write_masks`: the folder the boxes
    segmenter also writes its label maps to (docs/vlm_files.md layout); `text_encoder`: a CLIP folder whose text
    space the simulated embedder's features live in (None: the ONNX MiniLM's); `vlm`: the weight options of
    `--segmenter grounded-sam` / `--embedder maskclip` (detector, sam, clip, device, config, clip_width;
    ago_train/vlm/backends.py), whose models are loaded here so that a bad folder fails before any work."""
    from ago_runtime.errors import AgoInputError
    from ago_runtime.vocab.prompts import parse_prompt_file, resolve_prompt_file

    from .backends import FileImageEmbedder, FileSegmenter
    from .simulated import (SimEmbedderConfig, SimSegmenterConfig, SimulatedImageEmbedder,
                                   SimulatedSegmenter)

    space = parse_prompt_file(resolve_prompt_file(prompts))
    if write_masks is not None and segmenter != "boxes":
        raise AgoInputError("--write-masks", f"only --segmenter boxes writes label maps (this run: {segmenter})")
    vlm = vlm or {}
    for option, key, used in (("--detector", "detector", segmenter == "grounded-sam"),
                              ("--sam", "sam", segmenter == "grounded-sam"), ("--clip", "clip", embedder == "maskclip")):
        if vlm.get(key) is not None and not used:
            raise AgoInputError(option, f"only used by --segmenter grounded-sam / --embedder maskclip (this run: "
                                f"--segmenter {segmenter} --embedder {embedder})")
    if segmenter == "grounded-sam":
        if vlm.get("detector") is None or vlm.get("sam") is None:
            raise AgoInputError("--detector" if vlm.get("detector") is None else "--sam", "--segmenter grounded-sam "
                                "needs --detector DIR (GroundingDINO) and --sam DIR (SAM), save_pretrained folders "
                                "(docs/vlm_files.md)")
    if embedder == "maskclip" and vlm.get("clip") is None:
        raise AgoInputError("--clip", "--embedder maskclip needs --clip DIR (a CLIP save_pretrained folder)")
    if segmenter == "grounded-sam" or embedder == "maskclip":
        from ago_runtime.errors import require_torch

        require_torch("pseudo-labels --segmenter grounded-sam / --embedder maskclip")
        from ago_train.vlm.backends import vlm_backends

        vlm_seg, vlm_emb = vlm_backends(space, vlm.get("detector") if segmenter == "grounded-sam" else None,
                                        vlm.get("sam") if segmenter == "grounded-sam" else None,
                                        vlm.get("clip") if embedder == "maskclip" else None, vlm["device"],
                                        vlm["config"], vlm["clip_width"], load=False)   # loaded by load_models
    if segmenter == "grounded-sam":
        seg = vlm_seg
    elif segmenter == "files":
        if masks is None:
            raise AgoInputError("--masks", "--segmenter files needs --masks DIR (layout: docs/vlm_files.md)")
        seg = FileSegmenter(masks, space)
    elif segmenter == "sim":
        seg = SimulatedSegmenter(space, SimSegmenterConfig.for_table(space.class_table, seed=seed))
    elif segmenter == "boxes":
        from .boxes import BoxSegmenter

        seg = BoxSegmenter(data, space, masks_out=write_masks)
    else:
        raise AgoInputError("--segmenter", f"expected {_names(Segmenter)}, got {segmenter!r}")
    if embedder == "none":
        emb = None
    elif embedder == "maskclip":
        emb = vlm_emb
    elif embedder == "files":
        if feats is None:
            raise AgoInputError("--feats", "--embedder files needs --feats DIR (layout: docs/vlm_files.md)")
        emb = FileImageEmbedder(feats)
    elif embedder == "sim":
        text = None
        if text_encoder is not None:   # features simulated in a CLIP folder's text space
            from ago_runtime.vocab.model_folder import clip_text_encoder

            text = clip_text_encoder(text_encoder, verb="pseudo-labels")
        class_text, sky = simulated_text_embeddings(space.class_table, text)
        emb = SimulatedImageEmbedder(class_text, SimEmbedderConfig(seed=seed), sky_text=sky, ids=space.class_table.ids,
                                     text_encoder=None if text is None else text.encoder_id)
    else:
        raise AgoInputError("--embedder", f"expected {_names(Embedder)}, got {embedder!r}")
    return space, seg, emb


def load_models(*backends) -> None:
    """Load the models of the backends that have any (grounded-sam, maskclip): after the cheap checks, before work."""
    for backend in backends:
        if backend is not None and hasattr(backend, "load"):
            backend.load()


def check_embedder_fits_bank(emb, option: str, bank_encoder_id: str | None = None, bank_dim: int | None = None
                             ) -> None:
    """Image features must be in the text bank's space (same width, same encoder when recorded). The bank is the
    one training will use: MiniLM's (all-MiniLM-L6-v2, 384-d) unless another text encoder's id and width are given
    (a CLIP folder's: `clip_encoder_id`, its projection width)."""
    from ago_runtime.vocab.text_encoder import MINILM_DIM, MINILM_ID

    from .backends import check_features_fit_bank, embedder_encoder_id

    bank_encoder_id = bank_encoder_id or MINILM_ID
    bank_dim = bank_dim or MINILM_DIM
    channels = emb.probe_channels() if hasattr(emb, "probe_channels") else getattr(emb, "channels", None)
    check_features_fit_bank(f"the image features ({emb.name})", embedder_encoder_id(emb), channels,
                            "the text bank training uses", bank_encoder_id, bank_dim, option)


# the closed label space of each shipped class table, its classes in id order (the simulated embedder's texts)
CLOSED_PROMPTS = {"occ3d_nuscenes": "cw", "occ3d_waymo": "waymo/cw_waymo"}


def default_prompts_for_data(data: Path) -> str:
    """The shipped closed prompt file of the class table `data`'s labels use (its layout's, or its own
    class_table.json); a table of one's own has none, so the user must name one (AgoInputError on --prompts)."""
    from ago_runtime.errors import AgoInputError
    from ago_runtime.formats.datasets import open_dataset

    table = open_dataset(data, load_extras=False).class_table
    if table.name not in CLOSED_PROMPTS:
        raise AgoInputError("--prompts", f"{data} holds labels of its own class table {table.name!r}, which has no "
                            "shipped prompt file: give --prompts FILE (with an '@table:' line naming that table)")
    from ago_runtime.vocab.prompts import PROMPTS_DIR

    return str(PROMPTS_DIR / f"{CLOSED_PROMPTS[table.name]}.txt")


def simulated_text_embeddings(table="occ3d_nuscenes", encoder=None):
    """(class_text (K, C), sky (C,)): text embeddings (`encoder`, default the ONNX MiniLM, C = 384) of the phrases of
    the class table's closed label space (cw.txt: K = 17; waymo/cw_waymo.txt: K = 15), one row per class in the
    table's order, and of "sky". `table`: a ClassTable or a shipped table's name; a table that is not shipped has no
    closed prompt file, so its rows embed the class names themselves ("traffic_light" -> "traffic light")."""
    from ago_runtime.classes import SHIPPED_TABLES, shipped_name
    from ago_runtime.vocab.bank import load_prompt_bank
    from ago_runtime.vocab.prompts import PROMPTS_DIR
    from ago_runtime.vocab.text_encoder import default_text_encoder

    from .simulated import class_text_from_bank

    table = SHIPPED_TABLES[table] if isinstance(table, str) else table
    encoder = encoder if encoder is not None else default_text_encoder()
    sky = encoder.encode(["sky"])[0]
    if shipped_name(table) is None:
        text = np.asarray(encoder.encode([n.replace("_", " ") for n in table.names]), dtype=np.float32)
        return text / np.linalg.norm(text, axis=1, keepdims=True), sky
    bank = load_prompt_bank(str(PROMPTS_DIR / f"{CLOSED_PROMPTS[table.name]}.txt"), encoder=encoder)
    return class_text_from_bank(bank, table.num_classes), sky


def resolve_defaults(data: Path, segmenter: str | None, masks: Path | None, embedder: str | None,
                     feats: Path | None) -> tuple[str, Path | None, str, Path | None, list[str]]:
    """The segmenter / embedder (and their folders) to use when not given, from what `data` holds:
    - --masks / --feats default to <data>/masks and <data>/feats when those folders exist;
    - --segmenter: `files` when there are masks, `sim` on `ago synth` data (it has synthetic/semantic/),
      else an error saying what to give;
    - --embedder: `files` when there are feature maps, else `none`.
    Gives (segmenter, masks, embedder, feats, notes for the user)."""
    from ago_runtime.errors import AgoInputError

    notes = []
    if masks is None and (data / "masks").is_dir() and segmenter in (None, "files"):
        masks = data / "masks"
        notes.append(f"--masks {masks} (found in the dataset folder)")
    if feats is None and (data / "feats").is_dir() and embedder in (None, "files"):
        feats = data / "feats"
        notes.append(f"--feats {feats} (found in the dataset folder)")
    synthetic = (data / "synthetic" / "semantic").is_dir()
    if segmenter is None:
        if masks is not None:
            segmenter = "files"
        elif synthetic:
            segmenter = "sim"
        else:
            raise AgoInputError("--segmenter", f"{data} has no label maps (<data>/masks) and is not `ago synth` "
                                "data: give --segmenter files --masks DIR (layout: docs/vlm_files.md), or "
                                "--segmenter boxes (labels painted from the dataset's own 3D boxes, no VLM)")
        notes.append(f"--segmenter {segmenter}")
    if embedder is None:
        embedder = "files" if feats is not None else "none"
        notes.append("--embedder files" if feats is not None else
                     f"--embedder none (no feature maps: {data / 'feats'} not found; training will not align the "
                     "modality adapter, and the bundle card says so)")
    return segmenter, masks, embedder, feats, notes


def resolve_split(ds, split: str | None) -> tuple[list[int], str | None]:
    """Indices of --split (default: "train" when splits.json has one, else every sample) and a note."""
    if split is not None:
        return ds.split(split), None
    if (ds.root / "splits.json").is_file():
        return ds.split("train"), None
    return ds.split("all"), f"--split all ({ds.root}/splits.json not found, so every sample)"


def resolve_sweeps(ds, sweeps: int | None) -> tuple[int, str | None]:
    """--sweeps: the non-key LiDAR sweeps per keyframe. Default: all the dataset lists between two keyframes
    (nuScenes ~9) when their files are there, else 0. An explicit count on a dataset without them is refused."""
    from ago_runtime.errors import AgoInputError

    listed = ds.max_nonkey_sweeps() if ds.num_nonkey_lidar else 0
    if sweeps is None:
        if not listed:
            return 0, None
        if not ds.nonkey_sweep_files_present():
            return 0, (f"--sweeps 0: sample_data.json lists {ds.num_nonkey_lidar} non-key LiDAR sweeps but "
                       "their files (sweeps/LIDAR_TOP) are missing; only keyframe LiDAR is used")
        return listed, f"--sweeps {listed} (the non-key LiDAR sweeps listed between two keyframes)"
    if sweeps > 0 and not listed:
        raise AgoInputError("--sweeps", f"{ds.table_dir}/sample_data.json lists no non-key LiDAR sweeps, so "
                            f"--sweeps {sweeps} has nothing to add (--keyframes sets how many keyframes are "
                            "superimposed; before this option existed --sweeps meant that)")
    return sweeps, None


def register(app: typer.Typer) -> None:
    @app.command("pseudo-labels")
    def pseudo_labels(
        data: Path = typer.Option(..., "--data", help="dataset folder, nuScenes or Occ3D-Waymo layout (real or `ago synth`)."),
        out: Path = typer.Option(..., "--out", help="Output folder (resumable; refused if made with other settings)."),
        prompts: str = typer.Option(None, "--prompts", help="Prompt file (path or shipped name: cw, ow_pretrain, "
                                    "ow). Default: the closed prompt file of the data's label table (cw for "
                                    "Occ3D-nuScenes, waymo/cw_waymo for Occ3D-Waymo)."),
        segmenter: Optional[Segmenter] = typer.Option(None, "--segmenter", help=choices_help(Segmenter, SEGMENTER_HELP)
                                                      + ". Default: files when there are label maps (--masks, or "
                                                      "<data>/masks), sim on `ago synth` data."),
        masks: Path = typer.Option(None, "--masks", help="Label-map folder for --segmenter files (default <data>/masks)."),
        embedder: Optional[Embedder] = typer.Option(None, "--embedder", help=choices_help(Embedder, EMBEDDER_HELP)
                                                    + ". Default: files when there are feature maps (--feats, or "
                                                    "<data>/feats), else none."),
        feats: Path = typer.Option(None, "--feats", help="Feature-map folder for --embedder files (default <data>/feats)."),
        grid: str = typer.Option("x".join(map(str, CPU_GRID_SHAPE)), "--grid", help="Voxel counts XxYxZ over the "
                                "Occ3D range (default: the cpu preset model's grid)."),
        keyframes: int = typer.Option(10, "--keyframes", min=1, help="KEYFRAMES superimposed per sample, the "
                                      "sample's own included, each labelled with its own images (paper: 30)."),
        interval: int = typer.Option(1, "--interval", min=1, help="Keyframe stride between them (paper: 2)."),
        sweeps: int = typer.Option(None, "--sweeps", min=0, help="NON-KEY LiDAR sweeps added per superimposed "
                                   "keyframe: those recorded just before it (sample_data.json, sweeps/LIDAR_TOP), "
                                   "labelled with that keyframe's images. Default: all listed between two "
                                   "keyframes (nuScenes ~9), 0 when the dataset has none."),
        split: str = typer.Option(None, "--split", help="train, val, ... (scenes from splits.json) or all. "
                                  "Default: train when splits.json exists, else all."),
        raycast: bool = typer.Option(True, "--raycast/--no-raycast", help="Free space from LiDAR rays (else: every empty voxel is free)."),
        carve: Carve = typer.Option(None, "--carve", help="With --raycast: " + choices_help(Carve, CARVE_HELP) + "."),
        moving: Moving = typer.Option(Moving.AGGREGATE, "--moving", help="Points of the moving classes: "
                                      + choices_help(Moving, MOVING_HELP) + "."),
        seed: int = typer.Option(0, "--seed", min=0, help="Seed of the simulated backends."),
        limit: int = typer.Option(0, "--limit", min=0, help="Only the first N samples of the split (0 = all)."),
        jobs: int = typer.Option(1, "--jobs", min=1, max=64, help="Worker processes labelling scenes in parallel "
                                 "(the same pseudo-labels for any value)."),
        shard: str = typer.Option(None, "--shard", help="K/N: only the K-th of N contiguous runs of the split's "
                                  "keyframes (N machines, no coordination; ago_runtime/shards.py)."),
        write_masks: Path = typer.Option(None, "--write-masks", help="--segmenter boxes: also write every label "
                                         "map it paints to this folder in the file layout (docs/vlm_files.md), "
                                         "readable back with --segmenter files --masks DIR."),
        text_encoder: Path = typer.Option(None, "--text-encoder", help="a CLIP save_pretrained folder: the text "
                                          "space of the bank the features go with (--embedder sim simulates "
                                          "features in it; needs torch + the vlm extra). Default: MiniLM."),
        detector: Path = typer.Option(None, "--detector", help="--segmenter grounded-sam: GroundingDINO "
                                      "save_pretrained folder (IDEA-Research/grounding-dino-tiny or -base)."),
        sam: Path = typer.Option(None, "--sam", help="--segmenter grounded-sam: SAM save_pretrained folder "
                                 "(facebook/sam-vit-base, -large, -huge)."),
        clip: Path = typer.Option(None, "--clip", help="--embedder maskclip: CLIP save_pretrained folder "
                                  "(openai/clip-vit-base-patch16)."),
        device: TorchDevice = typer.Option(TorchDevice.CPU, "--device", help="grounded-sam / maskclip: where the 2D models run."),
        max_boxes: int = typer.Option(64, "--max-boxes", min=1, max=1000, help="grounded-sam: boxes per image after NMS."),
        box_threshold: float = typer.Option(0.2, "--box-threshold", min=0.0, max=1.0, help="grounded-sam (paper 0.2)."),
        text_threshold: float = typer.Option(0.15, "--text-threshold", min=0.0, max=1.0, help="grounded-sam (paper 0.15)."),
        nms_iou: float = typer.Option(0.5, "--nms-iou", min=0.0, max=1.0, help="grounded-sam: NMS IoU."),
        clip_width: int = typer.Option(768, "--clip-width", min=1, max=4096, help="maskclip: CLIP input width."),
    ):
        """Lift 2-D masks (and image features) into 3-D pseudo-labels with the LiDAR (keyframes + non-key sweeps)."""
        from ago_runtime.formats.datasets import check_label_table, open_dataset
        from ago_runtime.outputs import check_output_dir

        from .generate import PseudoLabelConfig, check_track_tables, generate
        from .raycast import GrazingRule

        from ago_runtime.errors import AgoInputError
        from ago_runtime.shards import parse_shard, shard_indices

        check_output_dir(out, "--out")
        if carve is not None and not raycast:
            raise AgoInputError("--carve", f"--carve {carve.value} is a ray-casting rule; --no-raycast casts no rays")
        if carve is None:   # the default: grazing (benchmarks/results/grid_height.md, pseudo_far_ground.md)
            carve = Carve.GRAZING if raycast else Carve.ALL
        if write_masks is not None:
            check_output_dir(write_masks, "--write-masks")
        shard_kn = parse_shard(shard)
        pgrid = parse_grid(grid)
        if text_encoder is not None:   # a wrong folder is one line before anything runs
            from ago_runtime.vocab.model_folder import read_model_config

            read_model_config(text_encoder, "--text-encoder", "clip")
        segmenter, masks, embedder, feats, notes = resolve_defaults(
            Path(data), segmenter.value if segmenter else None, masks, embedder.value if embedder else None, feats)
        if prompts is None:   # the label space follows the data: its table's closed prompt file
            prompts = default_prompts_for_data(Path(data))
            notes.append(f"--prompts {prompts} (the closed prompt file of the data's label table)")
        vlm = {"detector": detector, "sam": sam, "clip": clip, "device": device.value, "clip_width": clip_width,
               "config": grounded_sam_config(box_threshold, text_threshold, nms_iou, max_boxes)}
        space, seg, emb = build_backends(prompts, segmenter, masks, embedder, feats, seed, Path(data), write_masks,
                                         text_encoder, vlm)
        if emb is not None:
            bank_id = bank_dim = None
            if text_encoder is not None:   # the bank training will use is this CLIP folder's text tower
                from ago_runtime.vocab.model_folder import clip_encoder_id, read_model_config

                bank_dim = int(read_model_config(text_encoder, "--text-encoder", "clip")["projection_dim"])
                bank_id = clip_encoder_id(text_encoder)
            check_embedder_fits_bank(emb, {"files": "--feats", "maskclip": "--clip"}.get(embedder, "--embedder"),
                                     bank_id, bank_dim)
        needs_extras = segmenter == "sim" or embedder == "sim"
        ds = open_dataset(data, load_images=False, load_extras=needs_extras)
        check_label_table(ds, space)
        if not ds.has_lidar():
            raise AgoInputError(data, "no LiDAR files (kitti_format/<split>/velodyne/<sample>.bin): pseudo-labels "
                                "lift 2-D masks with the LiDAR")
        indices, split_note = resolve_split(ds, split)
        nonkey, sweep_note = resolve_sweeps(ds, sweeps)
        notes += [n for n in (split_note, sweep_note) if n]
        if limit > 0:
            indices = indices[:limit]
        if shard_kn is not None:
            indices = shard_indices(indices, shard_kn)
            notes.append(f"shard {shard_kn[0]}/{shard_kn[1]}: {len(indices)} keyframes")
            if not indices:
                raise AgoInputError("--shard", f"shard {shard} of this split has no keyframes (fewer than N)")
        if moving is Moving.TRACK:   # the box tables, before the models load
            check_track_tables(ds)
        load_models(seg, emb)   # the models (grounded-sam, maskclip) once every cheap check has passed
        for n in notes:
            typer.echo(f"note: using {n}")
        config = PseudoLabelConfig(grid=pgrid, num_keyframes=keyframes, interval=interval, nonkey_sweeps=nonkey,
                                   raycast=raycast, carve=GrazingRule() if carve is Carve.GRAZING else None,
                                   moving=moving.value)
        command = "ago " + " ".join(shlex.quote(a) for a in sys.argv[1:])
        result = generate(ds, indices, out, space, seg, emb, config, command=command, jobs=jobs)
        remade = f", {result['remade']} damaged ones remade" if result.get("remade") else ""
        rate = f" ({result['frames_per_s']} frames/s)" if result.get("frames_per_s") else ""
        typer.echo(f"pseudo-labels: {result['written']} written, {result['skipped']} already there{remade}"
                   f"{rate} -> {out}")

    @app.command("seen-gt")
    def seen_gt(
        data: Path = typer.Option(..., "--data", help="the dataset the pseudo-labels were made from (with gts/)."),
        pseudo: Path = typer.Option(..., "--pseudo", help="an `ago pseudo-labels` folder."),
        prompts: str = typer.Option(..., "--prompts", help="prompt file whose @known classes are the SEEN ones "
                                    "(e.g. veon_9_8); same classes as the pseudo-labels."),
        out: Path = typer.Option(..., "--out", help="output pseudo-label folder (resumable)."),
        split: str = typer.Option(None, "--split", help="train, val, ... or all (default: train when splits.json "
                                  "exists)."),
    ):
        """Pseudo-labels with GT for the seen classes (VEON's X/Y protocol, the paper's Tab. F): a voxel whose GT
        holds a seen class gets it, one the pseudo-labels call a seen class without GT support is ignored, the
        rest stays (ago_train/pseudo/seen_gt.py)."""
        from ago_runtime.formats.datasets import check_label_table, open_dataset
        from ago_runtime.outputs import check_output_dir
        from ago_runtime.progress import track
        from ago_runtime.vocab.prompts import parse_prompt_file, resolve_prompt_file

        from .seen_gt import write_seen_gt_folder

        check_output_dir(out, "--out")
        space = parse_prompt_file(resolve_prompt_file(prompts))
        ds = open_dataset(data, load_images=False, load_extras=False)
        check_label_table(ds, space)
        indices, split_note = resolve_split(ds, split)
        if split_note:
            typer.echo(f"note: using {split_note}")
        counts = write_seen_gt_folder(ds, pseudo, out, space, indices,
                                      progress=lambda xs: track(xs, "mixing seen-class GT", total=len(xs)))
        typer.echo(f"seen-gt: {counts['samples']} written, {counts['skipped']} already there; seen "
                   f"{len(counts['seen'])} classes; {counts['from_gt']} voxels from GT, {counts['ignored']} ignored of {counts['voxels']} "
                   f"-> {out}")
