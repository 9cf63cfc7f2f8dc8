"""`ago pseudo-labels`: 3-D pseudo-labels (and voxel image embeddings) from 2-D masks and features.

Reads a nuScenes-format dataset, labels every keyframe of a split with a segmenter (`files`: masks
written by Grounded SAM, see docs/vlm_files.md; `sim`: the SIMULATED segmenter, synthetic data only),
lifts image features with an embedder (`files`, `sim` or `none`), and writes the folder
described in ago_train/pseudo/generate.py. Resumable: rerun the same command to finish.
Needs numpy + opencv only (no torch).
"""

from __future__ import annotations

import shlex
import sys
from pathlib import Path

import typer


def parse_grid(text: str):
    from ago_runtime.errors import AgoInputError
    from ago_runtime.grid import Grid

    parts = str(text).lower().split("x")
    try:
        shape = tuple(int(p) for p in parts)
    except ValueError:
        shape = ()
    if len(shape) != 3 or min(shape) <= 0:
        raise AgoInputError("--grid", f"expected XxYxZ voxel counts like 100x100x8, got {text!r}")
    return Grid.with_shape(shape)


def build_backends(prompts: str, segmenter: str, masks: Path | None, embedder: str, feats: Path | None,
                   seed: int):
    """(label_space, segmenter, embedder or None) from the CLI choices."""
    from ago_runtime.errors import AgoInputError
    from ago_runtime.prompts import parse_prompt_file, resolve_prompt_file

    from .pseudo.backends import FileImageEmbedder, FileSegmenter
    from .pseudo.simulated import (SimEmbedderConfig, SimSegmenterConfig, SimulatedImageEmbedder,
                                   SimulatedSegmenter)

    space = parse_prompt_file(resolve_prompt_file(prompts))
    if segmenter == "files":
        if masks is None:
            raise AgoInputError("--masks", "--segmenter files needs --masks DIR (layout: docs/vlm_files.md)")
        seg = FileSegmenter(masks, space)
    elif segmenter == "sim":
        seg = SimulatedSegmenter(space, SimSegmenterConfig(seed=seed))
    else:
        raise AgoInputError("--segmenter", f"expected sim or files, got {segmenter!r}")
    if embedder == "none":
        emb = None
    elif embedder == "files":
        if feats is None:
            raise AgoInputError("--feats", "--embedder files needs --feats DIR (layout: docs/vlm_files.md)")
        emb = FileImageEmbedder(feats)
    elif embedder == "sim":
        class_text, sky = simulated_text_embeddings()
        emb = SimulatedImageEmbedder(class_text, SimEmbedderConfig(seed=seed), sky_text=sky)
    else:
        raise AgoInputError("--embedder", f"expected sim, files or none, got {embedder!r}")
    return space, seg, emb


def simulated_text_embeddings():
    """(class_text (17, 384), sky (384,)): MiniLM embeddings of cw.txt's phrases and of "sky"."""
    from ago_runtime.bank import bank_for_prompts
    from ago_runtime.text_encoder import default_text_encoder

    from .pseudo.simulated import class_text_from_bank

    encoder = default_text_encoder()
    bank = bank_for_prompts("cw", encoder=encoder)
    return class_text_from_bank(bank), encoder.encode(["sky"])[0]


def register(app: typer.Typer) -> None:
    @app.command("pseudo-labels")
    def pseudo_labels(
        data: Path = typer.Option(..., "--data", help="nuScenes-format dataset folder (real or `ago synth`)."),
        out: Path = typer.Option(..., "--out", help="Output folder (resumable; refused if made with other settings)."),
        prompts: str = typer.Option("cw", "--prompts", help="Prompt file (path or shipped name: cw, ow_pretrain, ow)."),
        segmenter: str = typer.Option("sim", "--segmenter", help="sim (SIMULATED, synthetic data only) or files."),
        masks: Path = typer.Option(None, "--masks", help="Label-map folder for --segmenter files."),
        embedder: str = typer.Option("none", "--embedder", help="sim (SIMULATED), files or none."),
        feats: Path = typer.Option(None, "--feats", help="Feature-map folder for --embedder files."),
        grid: str = typer.Option("100x100x8", "--grid", help="Voxel counts XxYxZ over the Occ3D range."),
        sweeps: int = typer.Option(10, "--sweeps", help="Keyframes superimposed, the keyframe included (paper: 30)."),
        interval: int = typer.Option(1, "--interval", help="Keyframe stride between them (paper: 2)."),
        split: str = typer.Option("train", "--split", help="train, val or all (scenes from splits.json)."),
        raycast: bool = typer.Option(True, "--raycast/--no-raycast", help="Free space from LiDAR rays (else: every empty voxel is free)."),
        seed: int = typer.Option(0, "--seed", help="Seed of the simulated backends."),
        limit: int = typer.Option(0, "--limit", help="Only the first N samples of the split (0 = all)."),
    ):
        """Lift 2-D masks (and image features) into 3-D pseudo-labels with the LiDAR."""
        from ago_runtime.errors import AgoInputError
        from ago_runtime.nuscenes import NuScenesDataset

        from .pseudo.generate import PseudoLabelConfig, generate

        if sweeps < 1 or interval < 1:
            raise AgoInputError("--sweeps/--interval", f"need >= 1, got {sweeps} / {interval}")
        space, seg, emb = build_backends(prompts, segmenter, masks, embedder, feats, seed)
        needs_extras = segmenter == "sim" or embedder == "sim"
        ds = NuScenesDataset(data, load_images=False, load_extras=needs_extras)
        indices = ds.split(split)
        if limit > 0:
            indices = indices[:limit]
        config = PseudoLabelConfig(grid=parse_grid(grid), num_sweeps=sweeps, interval=interval, raycast=raycast)
        command = "ago " + " ".join(shlex.quote(a) for a in sys.argv[1:])
        result = generate(ds, indices, out, space, seg, emb, config, command=command)
        typer.echo(f"pseudo-labels: {result['written']} written, {result['skipped']} already there "
                   f"({result['frames_per_s']} frames/s) -> {out}")
