"""`ago infer`, `ago demo`, `ago retrieve`: run an exported bundle on camera images (no torch); `ago
choose-threshold`: the unexplained-obstacle threshold for a prompt file, chosen on labelled frames
(ago_runtime/predict/threshold.py).

Inputs (`--images DIR`):
- an images folder: one image per camera of the bundle's rig, named by camera (`CAM_FRONT.jpg` ...), and a `calib.json`
  (docs/runtime.md; without it the bundle's training rig is used, with a warning);
- a dataset (a nuScenes layout with its `v1.0-*` table folder, or the Occ3D-Waymo layout with its
  `cam_infos.json`: `formats.datasets.open_dataset`): every keyframe, or `--sample TOKEN|SCENE`
  (repeatable: several tokens and/or scene names in one run, the bundle loaded once);
- with `--info PKL`: an mmdetection3d info file, DIR (default: the pkl's folder) the data root.

Outputs per frame, in `--out` (all written atomically): `<name>.npz` (Occ3D format: `semantics`
uint8 with free = 17 when every class is one Occ3D class, else bank class indices with free = K;
`class_names`, `free_index`; with --save-volumes also `entropy`, `confidence`, `branch` and the
unexplained-obstacle volumes `unexplained` (score), `unexplained_mask`, `unexplained_threshold`) and
`<name>.png` (--picture full: BEV of the classes, entropy BEV, camera mosaic, legend; bev: the class
BEV and legend; none: no PNG). Reading, inference and writing overlap (`Predictor.predict_many`
over `open_frames`, the library API: docs/runtime.md). Over a dataset or an
info file a re-run resumes: frames whose outputs are whole and of the same settings are skipped
(frame_is_whole; docs/bad_inputs.md). File names in the data files stay under the data root
(ago_runtime.paths) unless --allow-outside-root.
"""

from __future__ import annotations

import contextlib
from enum import Enum
from pathlib import Path
from typing import List, Optional

import numpy as np
import typer

from ago_runtime.errors import AgoInputError, one_line_warnings
from ago_runtime.predict.decision import Identifier
from ago_runtime.providers import Device, Precision, check_int8


def choose_bank(bundle, prompts: Optional[str], bank: Optional[str]):
    """The bank infer / demo / retrieve use, checked against the bundle once: --bank FILE (its text encoder,
    width and class count: `contract.check_bank_fits`, naming the bank file) or a bank the bundle ships; --prompts FILE or a shipped
    name (`parse_prompt_file`'s one lookup, then `load_prompt_bank`: the class count before any encoding,
    the bundle's own bank or the cache, else encoded with the bundle's text encoder); else the bundle's
    default bank."""
    from ago_runtime.predict.contract import check_bank_fits
    from ago_runtime.vocab.bank import PromptBank, load_prompt_bank
    from ago_runtime.vocab.prompts import parse_prompt_file

    if prompts and bank:
        raise AgoInputError("--bank", "give --prompts or --bank, not both")
    if bank:
        if Path(bank).is_file():
            loaded = PromptBank.load(bank)
            check_bank_fits(loaded, bundle.contract.text_encoder, bank)   # naming the bank: it is what is rebuilt
            return loaded
        if bank in bundle.banks:
            return bundle.load_bank(bank)
        raise AgoInputError(bank, f"prompt bank file not found (the bundle ships {sorted(bundle.banks)})")
    if prompts:
        return load_prompt_bank(parse_prompt_file(prompts, option="--prompts"), bundle=bundle)
    return bundle.load_bank()


class Picture(str, Enum):
    """`ago infer --picture`: the PNG per frame."""

    FULL = "full"   # BEVs, legend, cameras
    BEV = "bev"     # the class BEV and the legend (cheap)
    NONE = "none"   # no PNG


PICTURES = tuple(p.value for p in Picture)


def run_key(bundle, bank, identifier: str, picture: str, save_volumes: bool, int8: bool,
            device: str = "cpu", precision: str = "fp32", html: bool = False,
            unexplained_threshold: float | None = None) -> str:
    """What a prediction file was made with (bundle, bank, identifier, outputs), as a sha256: stored in each
    npz `ago infer` writes (`run_key`), so a resumed run keeps only frames made by the same settings."""
    import hashlib
    import json

    from ago_runtime.predict.bundle import BUNDLE_JSON, file_sha256

    d = {"bundle": file_sha256(bundle.root / BUNDLE_JSON), "bank": [bank.source_hash, bank.encoder_hash,
                                                                    list(bank.class_names), bank.template],
         "identifier": identifier, "picture": picture, "volumes": bool(save_volumes), "int8": bool(int8)}
    if (device, precision) != ("cpu", "fp32"):   # (keys of CPU fp32 runs stay as they were)
        d["device"] = [device, precision]
    if html:   # (keys of runs without --html stay as they were)
        d["html"] = True
    if unexplained_threshold is not None:   # (and of runs without --unexplained-threshold)
        d["unexplained_threshold"] = float(unexplained_threshold)
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()


PNG_END = b"IEND\xaeB`\x82"


def frame_is_whole(out: Path, name: str, key: str, grid_shape, picture: str) -> bool:
    """Whether `out/<name>.npz` (and its PNG unless picture is none) are whole outputs of the run `key`:
    every array of the npz reads (zip CRCs checked), `run_key` is `key`, `semantics` has the grid's shape;
    the PNG has its signature and end chunk and decodes. Checked, not trusted by name. `ago infer` writes the
    PNG before the npz, so a whole npz of this key means its PNG was written too."""
    import cv2

    from ago_runtime.readers import open_npz

    try:
        with open_npz(out / f"{name}.npz") as z:
            arrays = {k: z[k] for k in z.files}
    except AgoInputError:
        return False
    if str(arrays.get("run_key", "")) != key or tuple(arrays["semantics"].shape) != tuple(grid_shape):
        return False
    if picture == "none":
        return True
    try:
        data = (out / f"{name}.png").read_bytes()
    except OSError:
        return False
    return (data.startswith(b"\x89PNG\r\n\x1a\n") and data.endswith(PNG_END)
            and cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) is not None)


def prediction_picture(pred, images: dict | None, title: str = "", kind: str = "full") -> np.ndarray:
    """The PNG of one prediction. kind "full": class BEV, entropy BEV, adapted-branch share, legend and
    the rig's cameras; "bev": the class BEV and the legend only (a few ms)."""
    from ago_runtime.pictures import render
    from ago_runtime.predict.decision import Identifier

    colors = render.palette_for(pred.class_names)
    colors = np.concatenate([colors, np.array([[240, 240, 240]], np.uint8)])
    scale = max(3, 360 // max(pred.semantics.shape[:2]))
    bev = render.bev_image(pred.semantics, colors=colors, free_index=pred.free_index, grid=pred.grid, scale=scale)
    panels = [(f"classes ({pred.identifier})", bev)]
    if kind == "full":
        occupied = pred.semantics != pred.free_index
        ent = render.scalar_bev(pred.entropy, mask=occupied, label="entropy (nats)", grid=pred.grid, scale=scale)
        panels.append(("entropy, max over z", ent))
        if pred.identifier != Identifier.NONE:
            share = render.scalar_bev(pred.branch.astype(np.float32), reduce="mean", mask=occupied, vmin=0, vmax=1,
                                      label="adapted share", grid=pred.grid, scale=scale)
            panels.append(("identifier: adapted branch share", share))
        if pred.unexplained is not None:
            unexp = render.scalar_bev(pred.unexplained, reduce="max", mask=pred.occupancy > 0.5, vmin=0, vmax=1,
                                      label="unexplained score", grid=pred.grid, scale=scale)
            panels.append((f"unexplained obstacles (> {pred.unexplained_threshold:g} = flagged)", unexp))
    top = render.side_by_side(panels)
    parts = [top, render.legend(pred.class_names, colors[:-1], width=top.shape[1])]
    if images and kind == "full":
        parts.append(render.rig_mosaic(images, width=top.shape[1]))
    picture = render.stack_vertical(parts)
    return render.with_title(picture, title) if title else picture   # the full name, wrapped, never cut


def infer_writer(out: Path, key: str, picture: str, volumes: bool, html: bool = False,
                 unexplained_threshold: float | None = None):
    """`ago infer`'s write(name, images, prediction), called per frame of `predict_many`: `out/<name>.png` (unless
    picture is none) and `out/<name>.html` (with html: pictures.html_viewer), then `out/<name>.npz` with `run_key` (a whole
    npz means a whole frame: frame_is_whole), each written atomically; a killed run's temporary files of the frame are removed first
    (the folder is scanned for them once, here: a scan per frame would grow with the files written). Gives the files."""
    from ago_runtime.atomic import save_npz
    from ago_runtime.pictures.render import save_png

    stale = list(out.glob(".*.tmp.*")) if out.is_dir() else []

    def write(name: str, images: dict, pred) -> list[Path]:
        if unexplained_threshold is not None:
            pred.unexplained_threshold = float(unexplained_threshold)
        npz = out / f"{name}.npz"
        for p in [p for p in stale if p.name.startswith(f".{name}.")]:
            p.unlink(missing_ok=True)
            stale.remove(p)
        files = [npz]
        if picture != "none":
            files.append(save_png(out / f"{name}.png", prediction_picture(pred, images, name, picture)))
        if html:
            from ago_runtime.pictures.html_viewer import write_prediction_page

            files.append(write_prediction_page(out / f"{name}.html", pred.output_arrays(volumes=True), pred.grid,
                                               images, name))
        save_npz(npz, compresslevel=1, run_key=np.array(key), **pred.output_arrays(volumes=volumes))
        t = pred.timings
        typer.echo(f"{name}: {' '.join(map(str, files))} (preprocess {t['preprocess']:.2f} s, encoder "
                   f"{t['encoder']:.2f} s, heads {t['heads']:.2f} s)", err=True)
        return files

    return write


def run_infer(images, prompts, bank, bundle, out, identifier, save_volumes, sample=None, info=None,
              int8=False, picture: str = "full", warm_up: bool = False, workers: int | None = None,
              resume: bool = True, allow_outside_root: bool = False, shard: str | None = None,
              device: str = "cpu", precision: str = "fp32", html: bool = False,
              unexplained_threshold: float | None = None) -> list[Path]:
    """`ago infer`: check the options, load the bundle and choose the bank, open the frames (a resumed run
    leaves out the frames whose outputs in `out` are whole and were made with the same bundle, bank and
    settings: frame_is_whole), then predict them with `Predictor.predict_many` and write each (reading, prediction
    and writing overlap; ago_runtime/predict/pipeline.py). Gives the files written."""
    from ago_runtime.outputs import check_output_dir
    from ago_runtime.predict.bundle import Bundle, card_line, resolve_bundle
    from ago_runtime.predict.frames import open_frames
    from ago_runtime.predict.pipeline import auto_workers
    from ago_runtime.predict.predictor import Predictor
    from ago_runtime.providers import check_device, parse_device, parse_precision
    from ago_runtime.shards import parse_shard

    one_line_warnings()
    if identifier is not None:
        identifier = Identifier.parse(identifier, "--identifier")
    if picture not in PICTURES:
        raise AgoInputError("--picture", f"must be one of {', '.join(PICTURES)}, got {picture!r}")
    if workers is not None and not 1 <= int(workers) <= 64:
        raise AgoInputError("--workers", f"must be between 1 and 64, got {workers}")
    if unexplained_threshold is not None:
        t = float(unexplained_threshold)
        if not 0.0 < t < 1.0:   # (NaN fails this too)
            raise AgoInputError("--unexplained-threshold", f"must be between 0 and 1 (exclusive), got {t}")
        if not save_volumes:
            raise AgoInputError("--unexplained-threshold", "the unexplained-obstacle mask is made only with "
                                "--save-volumes; add it or leave this option out")
    parse_shard(shard)   # a bad --shard before any work
    device, precision = parse_device(device), parse_precision(precision)
    check_device(device, precision)   # a provider this onnxruntime lacks, before any work
    if int8:
        check_int8(device, precision)
    check_output_dir(out, "--out")   # before any work
    b = Bundle.load(resolve_bundle(bundle))
    chosen = choose_bank(b, prompts, bank)   # checked against the bundle here, once
    identifier = identifier or b.identifier_for(chosen)   # none for a closed-world bank
    key = run_key(b, chosen, identifier, picture, save_volumes, int8, device.value, precision.value, html,
                  unexplained_threshold)
    out = Path(out)
    kept: list[str] = []

    def whole(name: str) -> bool:
        if frame_is_whole(out, name, key, b.grid.shape, picture):
            kept.append(name)
            return True
        return False

    frames = open_frames(Path(images) if images else None, sample, Path(info) if info else None, b.rig,
                         skip=whole if resume and out.is_dir() else None,
                         allow_outside_root=allow_outside_root, shard=parse_shard(shard))
    count = len(frames)
    if shard is not None:
        typer.echo(f"note: using shard {shard}: {count + len(kept)} frames")
    if kept:
        typer.echo(f"resuming: {len(kept)} frames already whole in {out} (same bundle, bank and settings), "
                   f"{count} to predict")
    if count == 0:
        typer.echo(card_line(b))
        return []
    predictor = Predictor(b, int8=int8, warm_up=warm_up, device=device, precision=precision,
                          workers=int(workers) if workers is not None else auto_workers(count))
    write = infer_writer(out, key, picture, save_volumes, html, unexplained_threshold)
    written: list[Path] = []
    with contextlib.closing(predictor.predict_many(frames, chosen, identifier, volumes=save_volumes,
                                                   progress="predicting")) as predictions:
        for frame, pred in predictions:
            if not written:   # stdout: information, once every input is checked (the first frame read and
                typer.echo(card_line(b))   # predicted); a failure before leaves stdout empty, stderr one line
            written += write(frame.name, frame.images, pred)
    return written


def register(app: typer.Typer) -> None:
    @app.command("infer")
    def infer_cmd(
        images: Optional[Path] = typer.Option(None, "--images", help="images folder, dataset (nuScenes or Occ3D-Waymo layout), or data root for --info"),
        prompts: Optional[str] = typer.Option(None, "--prompts", help="prompt file (e.g. prompts/ow.txt); default: the bundle's training classes"),
        bank: Optional[str] = typer.Option(None, "--bank", help="a prompt bank .npz, or the name of a bank in the bundle"),
        bundle: Optional[Path] = typer.Option(None, "--bundle", help="bundle folder (default: $AGO_BUNDLE, then the shipped one)"),
        out: Path = typer.Option(Path("ago_out"), "--out", "-o", help="output folder"),
        identifier: Optional[Identifier] = typer.Option(None, "--identifier", help="how each voxel's branch is chosen "
                                                        "(default: the bundle's open-world identifier when the prompts hold "
                                                        "classes it was not trained on, else none)"),
        save_volumes: bool = typer.Option(False, "--save-volumes", help="also save entropy, confidence, branch and the unexplained-obstacle score and mask (drawn in the PNG)"),
        sample: Optional[List[str]] = typer.Option(None, "--sample", help="a dataset's sample token or scene name "
                                                   "(repeatable: several frames, one bundle load)"),
        info: Optional[Path] = typer.Option(None, "--info", help="mmdetection3d info .pkl"),
        int8: bool = typer.Option(False, "--int8", help="use the bundle's int8 encoder (needs a bundle exported "
                                  "with `ago export --int8`; on the CPU or with --device openvino; faster, less exact: "
                                  "docs/runtime.md)"),
        picture: Picture = typer.Option(Picture.FULL, "--picture", help="PNG per frame: full (BEVs, legend, "
                                        "cameras), bev (class BEV + legend, cheap) or none"),
        workers: Optional[int] = typer.Option(None, "--workers", help="frames predicted at once (default: 2 over "
                                              "a dataset on a multi-core CPU, else 1; each worker holds a frame's "
                                              "activations)"),
        resume: bool = typer.Option(True, "--resume/--no-resume", help="over a dataset or info file: skip frames "
                                    "whose outputs in --out are whole and made with the same bundle, bank and "
                                    "settings (checked: every array read, the PNG decoded)"),
        allow_outside_root: bool = typer.Option(False, "--allow-outside-root", help="let file names in the data "
                                                "files (info .pkl, sample_data.json) leave the data root: absolute "
                                                "or with '..' (refused by default)"),
        shard: Optional[str] = typer.Option(None, "--shard", help="K/N: only the K-th of N contiguous runs of the "
                                            "dataset's frames (N machines, no coordination; ago_runtime/shards.py)"),
        device: Device = typer.Option(Device.CPU, "--device", help="where the encoder graphs run (an onnxruntime "
                                      "build with that provider: scripts/setup.sh --device; the heads stay on the CPU)"),
        precision: Precision = typer.Option(Precision.FP32, "--precision", help="fp16 with --device tensorrt|openvino; bf16 with --device openvino (a CPU with avx512_bf16 or amx_bf16)"),
        html: bool = typer.Option(False, "--html", help="also write <name>.html beside the PNG: the prediction in 3-D "
                                  "(one self-contained file, no network needed; docs/metric_and_pictures.md)"),
        unexplained_threshold: Optional[float] = typer.Option(
            None, "--unexplained-threshold", help="with --save-volumes: flag an occupied voxel as an unexplained "
            "obstacle when its score is above this (default 0.5; choose one per prompt file on training frames: "
            "docs/runtime.md, Unexplained obstacles)"),
    ) -> None:
        """Predict 3D occupancy for camera images with an exported bundle (numpy + onnxruntime)."""
        run_infer(images, prompts, bank, bundle, out, identifier.value if identifier else None, save_volumes, sample,
                  info, int8, picture.value, workers=workers, resume=resume, allow_outside_root=allow_outside_root,
                  shard=shard, device=device.value, precision=precision.value, html=html,
                  unexplained_threshold=unexplained_threshold)

    @app.command("choose-threshold")
    def choose_threshold_cmd(
        images: Path = typer.Option(..., "--images", help="the dataset (nuScenes or Occ3D-Waymo layout) holding the "
                                    "labelled frames"),
        labels: Path = typer.Option(..., "--labels", help="their labels: an `ago pseudo-labels` folder (what "
                                    "training on your own data gives) or Occ3D ground truth (<scene>/<token>/labels.npz)"),
        prompts: Optional[str] = typer.Option(None, "--prompts", help="the prompt file `ago infer` will use (the "
                                              "threshold is for this file); default: the bundle's training classes"),
        bank: Optional[str] = typer.Option(None, "--bank", help="a prompt bank .npz, or the name of a bank in the bundle"),
        bundle: Optional[Path] = typer.Option(None, "--bundle", help="bundle folder (default: $AGO_BUNDLE, then the "
                                              "shipped one)"),
        false_rate: float = typer.Option(0.05, "--false-rate", help="the share of voxels labelled with a prompted class "
                                         "the mask may flag (0 <= r < 1)"),
        frames: int = typer.Option(40, "--frames", help="labelled frames used, spread over those the dataset holds"),
        json_out: Optional[Path] = typer.Option(None, "--json", help="also write the choice and its rates as JSON"),
    ) -> None:
        """Choose `ago infer --unexplained-threshold` for a prompt file on labelled frames (pseudo-labels or GT)."""
        run_choose_threshold(images, labels, prompts, bank, bundle, false_rate, frames, json_out)

    @app.command("demo")
    def demo_cmd(
        out: Path = typer.Option(Path("ago_demo"), "--out", "-o", help="output folder"),
        bundle: Optional[Path] = typer.Option(None, "--bundle", help="bundle folder (default: the shipped one)"),
        prompts: Optional[str] = typer.Option(None, "--prompts", help="prompt file (default: the bundle's classes)"),
        device: Device = typer.Option(Device.CPU, "--device", help="where the encoder graphs run (an onnxruntime "
                                      "build with that provider: scripts/setup.sh --device; the heads stay on the CPU)"),
        precision: Precision = typer.Option(Precision.FP32, "--precision", help="fp16 with --device tensorrt|openvino; bf16 with --device openvino (a CPU with avx512_bf16 or amx_bf16)"),
        html: bool = typer.Option(False, "--html", help="also write <name>.html beside the PNG: the prediction in 3-D "
                                  "(one self-contained file, no network needed; docs/metric_and_pictures.md)"),
    ) -> None:
        """Run `ago infer` on the shipped demo frame with the shipped default bundle."""
        from ago_runtime.predict.bundle import DEMO_FRAME_DIR, HOW_TO_MAKE_DEFAULT

        if not DEMO_FRAME_DIR.is_dir():
            raise AgoInputError(DEMO_FRAME_DIR, f"no demo frame installed; {HOW_TO_MAKE_DEFAULT}")
        written = run_infer(DEMO_FRAME_DIR, prompts, None, bundle, out, None, True, device=device.value,
                            precision=precision.value, html=html)
        typer.echo(f"demo written to {out}/ ({', '.join(p.name for p in written)})")

    @app.command("retrieve")
    def retrieve_cmd(
        phrase: str = typer.Option(..., "--phrase", help='what to look for, e.g. "traffic cone"'),
        images: Path = typer.Option(..., "--images", help="images folder (six CAM_*.jpg + calib.json) or a "
                                    "dataset root (nuScenes or Occ3D-Waymo layout)"),
        sample: Optional[str] = typer.Option(None, "--sample", help="a dataroot's sample token or scene name "
                                             "(default: its first keyframe)"),
        bundle: Optional[Path] = typer.Option(None, "--bundle", help="bundle folder"),
        out: Path = typer.Option(Path("ago_retrieve"), "--out", "-o", help="output folder"),
        device: Device = typer.Option(Device.CPU, "--device", help="where the encoder graphs run (an onnxruntime "
                                      "build with that provider: scripts/setup.sh --device; the heads stay on the CPU)"),
        precision: Precision = typer.Option(Precision.FP32, "--precision", help="fp16 with --device tensorrt|openvino; bf16 with --device openvino (a CPU with avx512_bf16 or amx_bf16)"),
        html: bool = typer.Option(False, "--html", help="also write the .html beside the PNG: the similarity in 3-D "
                                  "as heat colours with a threshold slider (one self-contained file)"),
    ) -> None:
        """Similarity of every voxel to a phrase (cosine, on the adapted VLM-aligned branch) + a BEV picture."""
        run_retrieve(phrase, images, bundle, out, sample, device.value, precision.value, html)


def run_choose_threshold(images: Path, labels: Path, prompts: Optional[str], bank: Optional[str], bundle,
                         false_rate: float = 0.05, frames: int = 40, json_out: Path | None = None):
    """`ago choose-threshold`: check the options, open the labels and the bank, pick up to `frames` labelled
    frames of the dataset (spread evenly over them, in the label folder's order), predict them and choose the
    threshold (ago_runtime/predict/threshold.py); prints it and the rates it gives. Gives the ThresholdChoice."""
    from ago_runtime.atomic import write_json
    from ago_runtime.outputs import check_output_file
    from ago_runtime.predict.bundle import Bundle, resolve_bundle
    from ago_runtime.predict.frames import open_frames
    from ago_runtime.predict.predictor import UNEXPLAINED_THRESHOLD, Predictor
    from ago_runtime.predict.threshold import LabelFolder, choose_for_prompts

    one_line_warnings()
    if not 0.0 <= float(false_rate) < 1.0:   # (NaN fails this too)
        raise AgoInputError("--false-rate", f"must be at least 0 and below 1, got {false_rate}")
    if not 1 <= int(frames) <= 100_000:
        raise AgoInputError("--frames", f"must be between 1 and 100000, got {frames}")
    if json_out is not None:
        check_output_file(json_out, "--json")   # before any work
    folder = LabelFolder.open(labels)
    b = Bundle.load(resolve_bundle(bundle))
    chosen_bank = choose_bank(b, prompts, bank)
    present: list[str] = []

    def unlabelled(token: str) -> bool:
        if token in folder.files:
            present.append(token)
            return False
        return True

    open_frames(images, rig=b.rig, skip=unlabelled)   # which labelled frames the dataset holds (nothing decoded)
    if not present:
        raise AgoInputError("--labels", f"none of the {len(folder.files)} labelled frames of {labels} is a keyframe of "
                            f"{images}")
    order = {t: i for i, t in enumerate(folder.files)}
    present.sort(key=order.__getitem__)
    picked = {present[int(k)] for k in np.linspace(0, len(present) - 1, min(int(frames), len(present)))}
    predictor = Predictor(b)
    choice = choose_for_prompts(predictor, chosen_bank, open_frames(images, rig=b.rig, skip=lambda t: t not in picked),
                                folder, float(false_rate))

    def pct(x) -> str:
        return "-" if x is None else f"{100 * x:.1f} %"

    what = f"--prompts {prompts}" if prompts else f"--bank {bank}" if bank else "the bundle's training classes"
    typer.echo(f"unexplained threshold for {what}: {choice.threshold:.3f}")
    typer.echo(f"  chosen on {len(choice.frames)} frames ({folder.kind} in {labels}): the lowest threshold that "
               f"flags at most {100 * choice.false_rate:g} % of the {choice.explained_voxels} voxels labelled "
               f"{', '.join(choice.explained_classes)}")
    others = (f"{pct(choice.flagged_other)} of the {choice.other_voxels} voxels labelled with other classes "
              f"({', '.join(choice.other_classes)})" if choice.other_voxels else "no voxel is labelled with another class")
    typer.echo(f"  flagged at {choice.threshold:.3f}: {pct(choice.flagged_explained)} of those; {others}; at "
               f"{UNEXPLAINED_THRESHOLD}: {pct(choice.default_flagged_explained)}"
               + (f" and {pct(choice.default_flagged_other)}" if choice.other_voxels else ""))
    typer.echo(f"  use: ago infer --save-volumes --unexplained-threshold {choice.threshold:.3f}"
               + (f" --prompts {prompts}" if prompts else f" --bank {bank}" if bank else ""))
    if json_out is not None:
        write_json(json_out, {**choice.to_dict(), "labels": str(labels), "images": str(images),
                              "prompts": prompts, "bank": bank, "bundle": str(b.root)})
    return choice


def run_retrieve(phrase: str, images: Path, bundle, out: Path, sample: str | None = None, device: str = "cpu",
                 precision: str = "fp32", html: bool = False) -> list[Path]:
    from ago_runtime.pictures import render
    from ago_runtime.atomic import save_npz
    from ago_runtime.predict.bundle import Bundle, resolve_bundle
    from ago_runtime.predict.frames import open_frames
    from ago_runtime.predict.heads import phrase_similarity
    from ago_runtime.predict.predictor import Predictor
    from ago_runtime.vocab.text_encoder import bundle_text_encoder

    from ago_runtime.outputs import check_output_dir

    from ago_runtime.providers import check_device, parse_device, parse_precision
    from ago_runtime.vocab.prompts import check_phrase

    one_line_warnings()
    phrase = check_phrase(phrase, "--phrase")    # no control characters (NUL...), a bounded length
    if "," in phrase:
        raise AgoInputError("--phrase", f"{phrase[:60]!r}: give one phrase, without commas (a comma separates "
                                        "phrases in a prompt file)")
    check_output_dir(out, "--out")
    device, precision = parse_device(device), parse_precision(precision)
    check_device(device, precision)
    b = Bundle.load(resolve_bundle(bundle))
    direction = np.asarray(bundle_text_encoder(b).encode([phrase]), np.float32)[0]
    predictor = Predictor(b, device=device, precision=precision)
    bank = choose_bank(b, None, None)
    predictor.fold(bank)
    frames = open_frames(Path(images), sample, None, b.rig)
    name, imgs, rig, source = next(iter(frames))   # a dataset: the first keyframe (of --sample)
    if len(frames) > 1:
        typer.echo(f"note: using keyframe {name}, the first of {len(frames)} (--sample TOKEN picks another)")
    h, g = predictor.encode_arrays(*predictor.prepare(imgs, rig, source))
    pred = predictor.predict_hidden(h, g, bank, b.identifier)
    # the adapted branch F~_3D everywhere: it is the embedding aligned with the VLM's image space, the one that
    # can know phrases no training class had (benchmarks/results/retrieval_ap.md compares the branches)
    sim = phrase_similarity(b.heads, h, g, np.ones(h.shape[0], np.uint8), direction).reshape(b.grid.shape)
    occupied = pred.semantics != pred.free_index
    slug = "".join(c if c.isalnum() else "_" for c in phrase.strip().lower())[:40]
    npz = out / f"{name}_{slug}.npz"
    save_npz(npz, similarity=sim, occupied=occupied.astype(np.uint8), phrase=np.array(phrase))
    colors = np.concatenate([render.palette_for(pred.class_names), np.array([[240, 240, 240]], np.uint8)])
    scale = max(3, 360 // max(b.grid.shape[:2]))
    picture = render.side_by_side([
        (f'similarity to "{phrase}" (occupied, max over z)',
         render.scalar_bev(sim, mask=occupied, label="cosine", grid=b.grid, scale=scale)),
        ("classes", render.bev_image(pred.semantics, colors=colors, free_index=pred.free_index, grid=b.grid,
                                     scale=scale))])
    png = render.save_png(out / f"{name}_{slug}.png", render.stack_vertical([picture, render.rig_mosaic(imgs, width=picture.shape[1])]))
    written = [npz, png]
    if html:
        from ago_runtime.pictures.html_viewer import write_prediction_page

        written.append(write_prediction_page(out / f"{name}_{slug}.html", {**pred.output_arrays(volumes=True),
                                             "similarity": sim}, b.grid, imgs, f'{name}: "{phrase}"', "similarity"))
    typer.echo(" ".join(map(str, written)), err=True)
    return written
