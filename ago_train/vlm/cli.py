"""`ago vlm-files`: the paper's first stage (Grounded SAM label maps, MaskCLIP features) from the user's weights.

Writes OUT/masks and OUT/feats in the layout `ago pseudo-labels --segmenter files --embedder files` reads
(ago_train/vlm/files.py, docs/vlm_files.md). Every check (folders, tokenizer, device, dataset, prompts) runs before
the first image; nothing is written before the first image has been computed. Torch, transformers and the models
are imported inside the command.
"""

from __future__ import annotations

import shlex
import sys
from pathlib import Path

import typer

from ago_train.vlm.loading import TorchDevice

from .maskclip import DEFAULT_WIDTH


def register(app: typer.Typer) -> None:
    @app.command("vlm-files")
    def vlm_files(
        data: Path = typer.Option(..., "--data", help="dataset folder, nuScenes or Occ3D-Waymo layout (real or `ago synth`)."),
        out: Path = typer.Option(..., "--out", help="output folder: OUT/masks and OUT/feats (resumable)."),
        prompts: str = typer.Option(..., "--prompts", help="prompt file (path or shipped name: cw, ow_pretrain, ow): "
                                    "every phrase, subclass phrases included, is detected."),
        detector: Path = typer.Option(..., "--detector", help="GroundingDINO save_pretrained folder "
                                      "(IDEA-Research/grounding-dino-tiny or -base)."),
        sam: Path = typer.Option(..., "--sam", help="SAM save_pretrained folder (facebook/sam-vit-base, -large, -huge)."),
        clip: Path = typer.Option(None, "--clip", help="CLIP save_pretrained folder (openai/clip-vit-base-patch16): "
                                  "also write MaskCLIP features to OUT/feats."),
        device: TorchDevice = typer.Option(TorchDevice.CPU, "--device", help="where the 2D models run."),
        split: str = typer.Option(None, "--split", help="train, val, ... or all (default: all keyframes; "
                                  "pseudo-labels of a split also need its neighbours' images)."),
        limit: int = typer.Option(0, "--limit", min=0, help="only the first N keyframes (0 = all)."),
        shard: str = typer.Option(None, "--shard", help="K/N: the K-th of N contiguous runs of the keyframes "
                                  "(one process per GPU or machine; ago_runtime/shards.py)."),
        max_boxes: int = typer.Option(64, "--max-boxes", min=1, max=1000, help="boxes kept per image after NMS."),
        box_threshold: float = typer.Option(0.2, "--box-threshold", min=0.0, max=1.0, help="paper: 0.2."),
        text_threshold: float = typer.Option(0.15, "--text-threshold", min=0.0, max=1.0, help="paper: 0.15."),
        nms_iou: float = typer.Option(0.5, "--nms-iou", min=0.0, max=1.0, help="IoU above which the weaker box goes."),
        clip_width: int = typer.Option(DEFAULT_WIDTH, "--clip-width", min=1, max=4096, help="CLIP input width (height "
                                       "follows the image; 768 -> 432 for 1600x900, a 27x48 map at ViT-B/16)."),
    ):
        """Grounded SAM label maps and MaskCLIP features for every camera image (docs/vlm_files.md)."""
        from ago_runtime.errors import AgoInputError, require_torch

        require_torch("vlm-files")
        from ago_runtime.formats.datasets import check_label_table, open_dataset
        from ago_runtime.outputs import check_output_dir
        from ago_runtime.shards import parse_shard, shard_indices
        from ago_runtime.vocab.prompts import parse_prompt_file, resolve_prompt_file

        from ago_train.pseudo.cli import resolve_split

        from .backends import vlm_backends
        from .files import write_vlm_files
        from .grounded_sam import GroundedSamConfig

        check_output_dir(out, "--out")
        shard_kn = parse_shard(shard)
        space = parse_prompt_file(resolve_prompt_file(prompts))
        config = GroundedSamConfig(box_threshold=box_threshold, text_threshold=text_threshold, nms_iou=nms_iou,
                                   max_boxes=max_boxes)
        ds = open_dataset(data, load_images=False, load_extras=False)
        check_label_table(ds, space)
        indices, _ = resolve_split(ds, split or "all")
        if limit > 0:
            indices = indices[:limit]
        if shard_kn is not None:
            indices = shard_indices(indices, shard_kn)
            if not indices:
                raise AgoInputError("--shard", f"shard {shard} of these keyframes is empty (fewer than N)")
        seg, emb = vlm_backends(space, detector, sam, clip, device.value, config, clip_width)
        command = "ago " + " ".join(shlex.quote(a) for a in sys.argv[1:])
        r = write_vlm_files(ds, indices, out, space, seg, emb, command=command)
        rate = f" ({r['images_per_s']} images/s)" if r.get("images_per_s") else ""
        remade = f", {r['remade']} damaged ones remade" if r.get("remade") else ""
        feats = " and feature maps" if emb is not None else ""
        typer.echo(f"vlm-files: label maps{feats} of {r['images']} camera images: {r['written']} written, "
                   f"{r['skipped']} already there{remade}{rate} -> {out}")
