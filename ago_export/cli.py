"""`ago export model.ckpt -o BUNDLE [--int8 [--calibration-data DIR] [--int8-float MODULE ...]] [--parity-frame DIR | --no-real-frame] [--card-note TEXT]
[--card-json FILE] [--readout-grid XxYxZ] [--text-encoder DIR]` (needs torch; a CLIP text tower needs the vlm extra)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def register(app: typer.Typer) -> None:
    @app.command("export")
    def export_cmd(
        checkpoint: Path = typer.Argument(..., help="checkpoint written by `ago train` (.pt)"),
        out: Path = typer.Option(Path("ago_bundle"), "-o", "--out", help="bundle folder to write"),
        int8: bool = typer.Option(False, "--int8", help="also write the int8 variant: planes graph static QDQ "
                                  "(calibrated on training frames), voxel stages dynamic; docs/runtime.md"),
        calibration_data: Optional[Path] = typer.Option(
            None, "--calibration-data",
            help="with --int8: the dataset whose train split calibrates the int8 planes graph (default: the "
                 "checkpoint's training data)"),
        int8_float: Optional[list[str]] = typer.Option(
            None, "--int8-float",
            help="with --int8: a torch module whose convolutions stay float32 in the int8 planes graph (repeatable; "
                 "e.g. backbone.stem and backbone.stage8, the layers int8 hurts most: more labels kept, less speed; "
                 "docs/runtime.md)"),
        parity_frame: Optional[Path] = typer.Option(
            None, "--parity-frame",
            help="frame for the ORT-vs-torch parity check: an images folder (CAM_*.jpg + calib.json), a "
                 "folder with mmdet3d_info.pkl, or a dataset root (nuScenes or Occ3D-Waymo layout: its first keyframe); "
                 "default: the real "
                 "nuScenes keyframe in ../shared when present (printed as a note)"),
        no_real_frame: bool = typer.Option(False, "--no-real-frame", help="check parity on a synthetic frame"),
        bank: Optional[list[str]] = typer.Option(
            None, "--bank-prompts",
            help="prompt file(s) to pre-build banks for (repeatable); default: every shipped prompt file"),
        train_bank_only: bool = typer.Option(False, "--train-bank-only",
                                             help="ship only the training label space's bank"),
        card_note: Optional[str] = typer.Option(None, "--card-note",
                                                help="one line added to the bundle card (card.json)"),
        readout_grid: Optional[str] = typer.Option(
            None, "--readout-grid",
            help="XxYxZ grid the bundle predicts on, over the model's range (default: the model's training grid); "
                 "e.g. 200x200x16 reads a 100x100x8 model's TPV planes at Occ3D's 0.4 m voxel centres "
                 "(as `ago eval --readout gt`; docs/training.md)"),
        card_json: Optional[Path] = typer.Option(
            None, "--card-json", help='JSON object merged into the bundle card, e.g. {"val_scores": {"mIoU": 7.8}} '
                                      "(default: filled from the checkpoint, its log and <ckpt dir>/eval-val)"),
        static_sampling: bool = typer.Option(
            False, "--static-sampling",
            help="planes.onnx samples every camera at every pillar point (the ones a camera does not see weighted "
                 "by 0) instead of only the seen ones: the same function, no data-dependent shapes (NonZero), "
                 "for runtimes that need static shapes; slower on CPU"),
        text_encoder: Optional[Path] = typer.Option(
            None, "--text-encoder",
            help="the CLIP save_pretrained folder a checkpoint was trained with (`ago train --text-encoder`); its "
                 "text tower ships in the bundle as ONNX (default: the folder the checkpoint records)"),
    ) -> None:
        """Export a checkpoint to a self-describing ONNX bundle, parity-checked against torch."""
        from ago_runtime.errors import require_torch

        require_torch("export")
        from ago_runtime.errors import AgoInputError
        from ago_runtime.geometry.grid import Grid
        from ago_runtime.outputs import check_output_dir

        from .card import read_card_options
        from .export import export_bundle

        card = read_card_options(card_note, card_json)
        readout = None if readout_grid is None else Grid.parse(readout_grid, "--readout-grid")
        if not checkpoint.is_file():
            raise AgoInputError(checkpoint, "checkpoint not found")
        if parity_frame is not None and no_real_frame:
            raise AgoInputError("--parity-frame", "and --no-real-frame ask for two parity frames; give one")
        if parity_frame is not None and not parity_frame.is_dir():   # before any export work
            raise AgoInputError("--parity-frame", f"{parity_frame}: folder not found (an images folder, a folder "
                                "with mmdet3d_info.pkl, or a dataset root)")
        if calibration_data is not None and not int8:
            raise AgoInputError("--calibration-data", "calibrates the int8 graphs; give --int8 too")
        if bank and train_bank_only:
            raise AgoInputError("--bank-prompts", "and --train-bank-only contradict each other; give one")
        for name in bank or []:   # every prompt file named must exist and parse, before the export
            from ago_runtime.vocab.prompts import parse_prompt_file

            try:
                parse_prompt_file(name)
            except AgoInputError as e:
                raise AgoInputError("--bank-prompts", str(e)) from None
        check_output_dir(out, "-o")
        check_output_dir(out.parent, "-o (the bundle is built beside it)")
        prompts = [] if train_bank_only else bank
        export_bundle(checkpoint, out, int8=int8, parity_frame_dir=parity_frame,
                      real_frame=not no_real_frame, bank_prompts=prompts,
                      log=lambda s: typer.echo(s, err=True), card=card, readout_grid=readout,
                      static_sampling=static_sampling, text_encoder=text_encoder, calibration_data=calibration_data,
                      int8_float=tuple(int8_float or ()))
