"""`ago export`: a training checkpoint -> a self-describing, parity-checked bundle folder.

Takes a checkpoint written by ago_train (read by `ago_train.checkpoint.CheckpointContract.load`: weights
only, checked by value). Gives a bundle folder (layout: ago_runtime/predict/bundle.py,
docs/runtime.md):

1. the camera-to-voxel encoder plus the modality adapter's hidden layers as ONNX graphs
   (bundle format 5, ago_runtime/predict/encoder.py; the traced modules are ago_export/graphs.py):
   `planes.onnx` (images (1,6,3,H,W) + ego2img (1,6,4,4) -> the three TPV planes at the grid's
   resolution, times the decoder's first linear layer, channels last) and `voxels_<i>.onnx`, the
   per-voxel MLP's remaining linear layers, one graph per layer (the runtime applies the softplus
   activations between them and computes the bank products itself), so the runtime streams slabs and
   never holds the grid's features at once; their input and output names are the contract's
   (ago_runtime/predict/contract.py PLANES_INPUTS ...); bundle.json is the one record of what they are
   (no ONNX metadata_props: nothing read them, and a second copy of the grid or text encoder could only drift);
2. the linear heads (`heads.npz`, exactly the arrays contract.HEADS_NPZ declares) and the learnt free embedding,
   for bank folding at run time;
3. banks: "train" (the label-space embeddings saved in the checkpoint) and one per shipped prompt
   file the installed text encoder could build; a checkpoint trained with a CLIP folder's text tower ships
   that tower (text_encoder.onnx + tokenizer, parity-checked: ago_export/text_tower.py), which builds them;
4. checks: onnx.checker, then parity ORT vs torch on one frame (a real nuScenes keyframe when one
   is found, else a synthetic frame): ago_export.parity; optional int8 copy (the contract's "int8" variant),
   parity-checked too.

Everything is written into a temporary folder next to the target and renamed into place only when
every check passed; a failed check raises AgoInputError (the CLI exits 2) and writes nothing.
"""

from __future__ import annotations

import datetime as _dt
import shutil
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn

import ago_runtime
from ago_runtime.atomic import replace_dir, temp_dir_beside, write_json
from ago_runtime.vocab.bank import load_prompt_bank
from ago_runtime.errors import AgoInputError
from ago_runtime.formats.calibration import find_camera_images, load_images_folder
from ago_runtime.geometry.camera import CAMERA_NAMES, Rig
from ago_runtime.geometry.grid import Grid
from ago_runtime.geometry.preprocess import Preprocess
from ago_runtime.predict.contract import (BUNDLE_JSON, PLANES_INPUTS, PLANES_OUTPUTS, STAGE_INPUT, STAGE_OUTPUT,
                                          BundleContract, CameraSlot, CheckpointRecord, FileEntry, LabelClass,
                                          LabelSpaceSpec, ModelRecord, ParityCheck, ParityReport, RigSpec,
                                          TextEncoderSpec, TowerParity, VariantSpec, VoxelStageSpec, check_bank_fits,
                                          file_sha256, record_from_dict, record_to_dict)
from ago_runtime.predict.decision import Identifier
from ago_runtime.predict.encoder import INT8, SplitEncoder, StageGraph
from ago_runtime.predict.heads import HeadWeights
from ago_runtime.vocab.prompts import LabelSpace, shipped_label_spaces
from ago_runtime.vocab.text_encoder import OnnxTextEncoder

from .card import write_card
from .graphs import PlanesGraph, VoxelStageGraph, voxel_stages
from .parity import FP32_TOLERANCE, INT8_TOLERANCE, Tolerance, check_parity, describe
from .text_tower import clip_folder_for, export_text_tower, is_clip_bank

OPSET = 17
DEFAULT_REAL_FRAME = Path(__file__).resolve().parents[2] / "shared" / "data" / "nuscenes-sample"


# ---- model ---------------------------------------------------------------------------------
def load_model(checkpoint: str | Path):
    """checkpoint -> (AGOModel in eval mode, its CheckpointContract, ModelConfig)."""
    from ago_train.checkpoint import CheckpointContract

    ckpt = CheckpointContract.load(checkpoint)
    return ckpt.build_model(checkpoint), ckpt, ckpt.model_config   # every weight from the checkpoint


def head_weights(model, calibration=None) -> HeadWeights:
    """The linear heads, with the identifier's branch scales from the checkpoint's calibration (1, 1 without)
    and, when the calibration has them, the adapted branch's standardisation statistics."""
    def f(t):
        return t.detach().cpu().numpy().astype(np.float32)

    scales = np.array([1.0, 1.0] if calibration is None else calibration.scales, np.float32)
    heads = HeadWeights(f(model.decoder_out.weight), f(model.decoder_out.bias), f(model.adapter_out.weight),
                        f(model.adapter_out.bias), f(model.free_embedding), scales)
    if getattr(model, "free_bias", None) is not None:
        heads.free_bias = float(model.free_bias.detach())
    if calibration is not None and calibration.adapted_mean is not None:   # the adapted branch's phrase
        heads.adapted_mean = calibration.adapted_mean.numpy().astype(np.float32)   # standardisation (calibrate.py)
        heads.adapted_cov = calibration.adapted_cov.numpy().astype(np.float32)
    return heads


def _finish_onnx(path: Path, doc: str) -> None:
    import onnx

    proto = onnx.load(str(path))
    del proto.metadata_props[:]   # bundle.json says what each graph is (module docstring)
    proto.producer_name = "ago export"
    proto.doc_string = doc
    onnx.save(proto, str(path))
    try:
        onnx.checker.check_model(str(path), full_check=True)
    except onnx.checker.ValidationError as e:
        raise AgoInputError(path, f"onnx.checker refused the exported graph: {str(e).splitlines()[0]}") from None


def export_onnx(model: nn.Module, out_dir: Path, cfg, grid_shape: tuple[int, int, int] | None = None,
                static_sampling: bool = False) -> tuple[dict[str, str], list[VoxelStageSpec]]:
    """Write planes.onnx and voxels_<i>.onnx (ago_export.graphs) into out_dir; returns ({key: file}, the
    voxel stages' contract entries, each with its file key). grid_shape: the read-out grid planes.onnx
    upsamples to (default the model's). static_sampling: see ago_export.graphs.ExportTPV."""
    images = torch.zeros(1, cfg.num_cameras, 3, cfg.image_height, cfg.image_width)
    ego2img = torch.eye(4).expand(1, cfg.num_cameras, 4, 4).contiguous()
    planes = BundleContract.PLANES
    files, specs = {planes: f"{planes}.onnx"}, []
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        torch.onnx.export(PlanesGraph(model, grid_shape, static_sampling).eval(), (images, ego2img), str(out_dir / files[planes]), dynamo=False,
                          opset_version=OPSET, input_names=list(PLANES_INPUTS),
                          output_names=list(PLANES_OUTPUTS), do_constant_folding=True)
        for i, stage in enumerate(voxel_stages(model)):
            key = f"voxels_{i}"
            torch.onnx.export(VoxelStageGraph(stage).eval(), (torch.zeros(2, stage.linear.in_features),),
                              str(out_dir / f"{key}.onnx"), dynamo=False, opset_version=OPSET,
                              input_names=[STAGE_INPUT], output_names=[STAGE_OUTPUT],
                              dynamic_axes={STAGE_INPUT: {0: "voxels"}, STAGE_OUTPUT: {0: "voxels"}},
                              do_constant_folding=True)
            files[key] = f"{key}.onnx"
            specs.append(stage.spec(key))
    _finish_onnx(out_dir / files[planes],
                 "ago camera-to-TPV encoder: images (1,6,3,H,W) + ego2img (1,6,4,4) -> plane_xy (X,Y,Dh), "
                 "plane_xz (X,Z,Dh), plane_yz (Y,Z,Dh): the TPV planes at the grid resolution times the decoder's "
                 "first linear layer (its bias in plane_xy), channels last")
    for spec in specs:
        _finish_onnx(out_dir / files[spec.file],
                     "ago per-voxel MLP stage: x (n, d_in) -> y = x W^T + b (n, d_out), the next pre-activation")
    return files, specs


def open_split_encoder(root: Path, files: dict[str, str], specs: list[VoxelStageSpec], grid: Grid, heads: HeadWeights,
                       variant: VariantSpec | None = None) -> SplitEncoder:
    """The encoder of a bundle folder being written (parity checks): its float32 graphs, or `variant`'s."""
    keys = [BundleContract.PLANES] + [s.file for s in specs]
    graphs = dict(zip(keys, keys)) if variant is None else variant.graphs   # float32 graph key -> the graph to open
    stages = [StageGraph(s, root / files[graphs[s.file]]) for s in specs]
    return SplitEncoder(root / files[graphs[BundleContract.PLANES]], stages, grid, heads.hidden_dim, heads.adapted_dim)


def _parity(model, encoder, heads, bank, x, m, tolerance: Tolerance, frame_name: str, checkpoint, what: str,
            log) -> ParityCheck:
    """One parity check of the graphs `what` ("fp32", a variant) (ago_export.parity.check_parity) as the contract's
    record, logged; a failed one is refused naming the checkpoint."""
    check = record_from_dict(ParityCheck, check_parity(model, encoder, heads, bank, x, m, tolerance, frame_name),
                             f"{what} parity")
    line = describe(record_to_dict(check))
    log(f"parity {what}: {line}")
    if not check.ok:
        raise AgoInputError(checkpoint, f"{what} parity check failed on {frame_name}: {line}")
    return check


# ---- label space and banks -----------------------------------------------------------------
def label_space_spec(space: LabelSpace) -> LabelSpaceSpec:
    return LabelSpaceSpec(space.name, space.sha256,
                          [LabelClass(c.name, [int(i) for i in c.occ3d_ids], c.name in space.known, list(c.phrases))
                           for c in space.classes], space.class_table)


# ---- parity frame --------------------------------------------------------------------------
def synthetic_frame(rig: Rig, seed: int = 0) -> tuple[dict[str, np.ndarray], Rig, str]:
    """Smooth random images (low-frequency noise) for the rig, each camera at a quarter of its native size."""
    import cv2

    rng = np.random.default_rng(seed)
    small = Rig([c.scaled(max(32, c.width // 4), max(32, c.height // 4)) for c in rig])
    images = {}
    for cam in small:
        w, h = cam.width, cam.height
        coarse = rng.uniform(0, 255, size=(h // 8 + 1, w // 8 + 1, 3)).astype(np.float32)
        images[cam.name] = np.clip(cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC), 0, 255).astype(np.uint8)
    return images, small, f"synthetic (seed {seed})"


def parity_frame(spec: str | Path | None, real_frame: bool, rig: Rig) -> tuple[dict[str, np.ndarray], Rig, str]:
    """The frame parity runs on: an images folder, a folder with an mmdet3d_info.pkl or a dataset root (nuScenes or
    Occ3D-Waymo layout: its first keyframe); by default the real nuScenes keyframe next to the repo when present, else a synthetic frame."""
    if (spec is None and real_frame and (DEFAULT_REAL_FRAME / "mmdet3d_info.pkl").is_file()
            and sorted(rig.names) == sorted(CAMERA_NAMES)):   # the real keyframe has nuScenes' six cameras
        spec = DEFAULT_REAL_FRAME
    if spec is None:
        return synthetic_frame(rig)
    spec = Path(spec)
    if not spec.is_dir():
        raise AgoInputError("--parity-frame", f"{spec}: folder not found (an images folder, a folder with "
                            "mmdet3d_info.pkl, a nuScenes dataroot or an Occ3D-Waymo layout root)")
    from ago_runtime.formats.datasets import dataset_layout, open_dataset

    if dataset_layout(spec) is not None:   # a nuScenes or Occ3D-Waymo dataset root: its first keyframe
        frame = open_dataset(spec, load_extras=False)[0]
        return frame.images, frame.rig, f"{spec} (sample {frame.token})"
    if (spec / "mmdet3d_info.pkl").is_file():
        from ago_runtime.formats.mmdet3d_info import load_mmdet3d_info

        frame = load_mmdet3d_info(spec / "mmdet3d_info.pkl", spec)[0]
        return frame.images, frame.rig, f"{spec} (sample {frame.token})"
    find_camera_images(spec, rig.names)   # a clear error when it is neither layout
    images, frame_rig, _ = load_images_folder(spec, fallback_rig=rig)
    return images, frame_rig, str(spec)


def int8_calibration_frames(ckpt, calibration_data: str | Path | None, rig: Rig, log=print) -> list:
    """The static int8 graph's calibration frames: CALIBRATION_FRAMES frames of the training split (the
    checkpoint's train_config train_split, else "train") of `calibration_data`, default the checkpoint's
    training data (train_config data, or its first source's). Training frames only: the frames a model is
    scored on never set its ranges. One AgoInputError naming --calibration-data when there are none."""
    from .calibration_frames import CALIBRATION_FRAMES, OPTION, read_frames

    tc = ckpt.train_config if isinstance(ckpt.train_config, dict) else {}
    first = (tc.get("sources") or [{}])[0] if isinstance(tc.get("sources"), list) else {}
    split = str(first.get("split") or tc.get("train_split") or "train")
    source = calibration_data or first.get("data") or tc.get("data")
    if source is None:
        raise AgoInputError(OPTION, "the checkpoint records no training data; --int8 needs --calibration-data DIR "
                            "(the dataset the model was trained on: its train split calibrates the int8 graph)")
    if calibration_data is None and not Path(source).is_dir():
        raise AgoInputError(OPTION, f"the checkpoint's training data {source} is not here; --int8 needs "
                            "--calibration-data DIR (the dataset the model was trained on)")
    frames = read_frames(source, CALIBRATION_FRAMES, rig, split=split)
    log(f"note: int8 calibration: {len(frames)} frames of split {split!r} of {source}")
    return frames


# ---- the bundle ----------------------------------------------------------------------------
def _replace_dir(tmp: Path, out: Path) -> None:
    """Move the finished temp folder onto `out` (an existing bundle there is replaced; never missing)."""
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not (out / BUNDLE_JSON).is_file())):
        raise AgoInputError(out, "exists and is not an ago bundle; choose another -o")
    replace_dir(tmp, out)


def export_bundle(checkpoint: str | Path, out: str | Path, int8: bool = False,
                  parity_frame_dir: str | Path | None = None, real_frame: bool = True,
                  bank_prompts: list[str] | None = None, tolerance: Tolerance = FP32_TOLERANCE,
                  int8_tolerance: Tolerance = INT8_TOLERANCE, log=print, parity: bool = True,
                  card: dict | None = None, readout_grid: Grid | None = None, static_sampling: bool = False,
                  text_encoder: str | Path | None = None, calibration_data: str | Path | None = None,
                  int8_float: tuple[str, ...] = ()) -> dict:
    """Write a bundle for `checkpoint` at `out`; returns bundle.json's content.

    parity=False skips the ORT-vs-torch check (benchmarks only; not offered by the CLI);
    bundle.json then records a parity report with "skipped": true.

    bank_prompts: prompt files (paths or shipped names) to pre-build banks for; None = every
    shipped prompt file (skipped with a note when no text encoder is installed).

    card: {"note": str, "extra": dict} for the bundle card (ago_export/card.py).

    readout_grid: the grid the bundle predicts on, over the model's range (`ago export --readout-grid`):
    default the model's training grid; a finer one (e.g. Occ3D's 200x200x16 for a 100x100x8 model) reads
    the same TPV planes at finer voxel centres (bilinear, as `ago eval --readout gt`). bundle.json "grid"
    is then the read-out grid, "model_grid" the training grid, and the card says both.

    static_sampling (`ago export --static-sampling`): planes.onnx samples every (camera, pillar point) entry
    instead of only those a camera sees (no data-dependent shapes; slower): ago_export.graphs.ExportTPV.

    text_encoder (`ago export --text-encoder DIR`): the CLIP folder of a checkpoint trained with one (default: its
    train_config text_encoder); its text tower ships in the bundle (ago_export/text_tower.py).

    int8 (`ago export --int8`): also the int8 variant (ago_export.quantize.quantize_int8_graphs), its planes graph
    calibrated on frames of the training split of `calibration_data` (`--calibration-data DIR`; default the
    checkpoint's training data), parity-checked with the int8 tolerance. int8_float (`--int8-float`): torch module
    names whose convolutions stay float32 in the int8 planes graph (e.g. "backbone.stem", "backbone.stage8";
    ago_export.quantize.convs_in_modules; the variant's method records them).
    """
    checkpoint, out = Path(checkpoint), Path(out)
    model, ckpt, cfg = load_model(checkpoint)
    space = ckpt.space
    bank = ckpt.bank.prompt_bank(space)   # checked against the label space when the checkpoint was read
    clip_folder = None
    if is_clip_bank(bank):   # the tower ships in the bundle: its folder is checked before any work
        clip_folder = clip_folder_for(ckpt.text_encoder, checkpoint, bank, text_encoder)
    elif text_encoder is not None:
        raise AgoInputError("--text-encoder", f"{checkpoint} was trained with the text encoder {bank.encoder_id}, "
                            "not a CLIP folder's; leave --text-encoder out")
    if int8_float:
        if not int8:
            raise AgoInputError("--int8-float", "keeps convolutions of the int8 variant in float32; give --int8 too")
        from .quantize import check_float_modules

        check_float_modules(model, tuple(int8_float))
    heads = head_weights(model, ckpt.calibration)
    if heads.embed_dim != bank.dim:
        raise AgoInputError(checkpoint, f"model embedding width {heads.embed_dim} differs from its bank's {bank.dim}")
    model_grid = cfg.grid_obj()
    grid = model_grid if readout_grid is None else readout_grid
    if (tuple(grid.range_min), tuple(grid.range_max)) != (tuple(model_grid.range_min), tuple(model_grid.range_max)):
        raise AgoInputError("--readout-grid", f"must cover the model's range {model_grid.range_min}-{model_grid.range_max}")
    if any(r < m for r, m in zip(grid.shape, model_grid.shape)):
        raise AgoInputError("--readout-grid", f"{'x'.join(map(str, grid.shape))} is coarser than the model's grid "
                            f"{'x'.join(map(str, model_grid.shape))} along an axis (a read-out grid may only be finer)")
    pre = Preprocess(width=cfg.image_width, height=cfg.image_height)
    if ckpt.rig is not None:
        rig, rig_source = ckpt.rig, "checkpoint"
    else:
        rig, rig_source = Rig.nuscenes_like(1600, 900), "Rig.nuscenes_like(1600, 900) (checkpoint has no rig)"
    if len(rig.cameras) != cfg.num_cameras:
        raise AgoInputError(checkpoint, f"the model takes {cfg.num_cameras} cameras, its rig has {len(rig.cameras)}")
    encoder_spec = TextEncoderSpec(bank.encoder_id, bank.encoder_hash, int(bank.dim), bank.encoder_variant)
    images, frame_rig, frame_name = parity_frame(parity_frame_dir, real_frame, rig)   # checked before any work
    calibration = int8_calibration_frames(ckpt, calibration_data, rig, log) if int8 else []
    frame_rig = frame_rig.ordered_as(rig.names, frame_name)
    if parity_frame_dir is None:
        log(f"note: using parity frame {frame_name} (--parity-frame DIR chooses one, --no-real-frame a synthetic one)")
    tmp = temp_dir_beside(out)   # removes the temp folders of killed exports first
    try:
        log(f"exporting the encoder to ONNX (opset {OPSET}) ...")
        files, stages = export_onnx(model, tmp, cfg, grid.shape, static_sampling)
        files[BundleContract.HEADS] = "heads.npz"
        np.savez(tmp / files[BundleContract.HEADS], **heads.to_arrays())
        tower, bank_encoder = None, None
        if clip_folder is not None:
            tower = export_text_tower(clip_folder, tmp, bank, int8, checkpoint, log)
            files.update(tower["files"])
            bank_encoder = OnnxTextEncoder(tmp / tower["files"]["text_encoder"])
        (tmp / "banks").mkdir()
        bank.save(tmp / "banks" / "train.npz")
        banks = {"train": "banks/train.npz"}
        bank_notes = {}
        for name in (shipped_label_spaces() if bank_prompts is None else bank_prompts):
            key = Path(name).stem
            try:
                b = load_prompt_bank(name, encoder=bank_encoder)
                check_bank_fits(b, encoder_spec, checkpoint)
            except AgoInputError as e:
                bank_notes[key] = f"not built: {e}"
                log(f"note: bank {key!r} not built ({e})")
                continue
            b.save(tmp / "banks" / f"{key}.npz")
            banks[key] = f"banks/{key}.npz"

        x = pre.images(images, frame_rig, frame_name)[None]
        m = pre.ego2img(frame_rig)[None]
        report = ParityReport(skipped=not parity, fp32=None, text_encoder=None if tower is None else
                              record_from_dict(TowerParity, tower["parity"], "text tower parity"))
        if parity:
            log("checking parity onnxruntime vs torch ...")
            report.fp32 = _parity(model, open_split_encoder(tmp, files, stages, grid, heads), heads, bank, x, m,
                                  tolerance, frame_name, checkpoint, "fp32", log)
        variants = {}
        if int8:
            from .calibration_frames import planes_feeds
            from .quantize import SAMPLED_FEATURES_FLOAT, convs_in_modules, quantize_int8_graphs

            log(f"quantising the encoder to int8 (planes static QDQ, calibrated on {len(calibration)} training "
                "frames; voxel stages dynamic) ...")
            keep = (convs_in_modules(tmp / files[BundleContract.PLANES], {n for n, _ in model.named_modules()},
                                     tuple(int8_float)) if int8_float else None)
            files.update(quantize_int8_graphs(tmp, files, [st.file for st in stages], planes_feeds(calibration, pre),
                                              keep))
            method = (f"static-qdq; {SAMPLED_FEATURES_FLOAT}" + (f"; float32: {', '.join(int8_float)}" if int8_float
                                                               else ""))
            variant = VariantSpec(INT8, method, {k: f"{k}_{INT8}" for k in [BundleContract.PLANES] +
                                                 [st.file for st in stages]}, None)
            if parity:
                variant.parity = _parity(model, open_split_encoder(tmp, files, stages, grid, heads, variant), heads,
                                         bank, x, m, int8_tolerance, frame_name, checkpoint, INT8, log)
            variants[INT8] = variant
        file_entries = {k: FileEntry.of(tmp, v) for k, v in files.items()}
        file_entries.update({BundleContract.bank_key(k): FileEntry.of(tmp, v) for k, v in banks.items()})
        contract = BundleContract(
            grid=grid, model_grid=model_grid, preprocess=pre,
            rig=RigSpec([CameraSlot(c.name, w, h) for c, (w, h) in zip(rig, pre.camera_sizes(rig))]),
            training_rig=rig, rig_source=rig_source, label_space=label_space_spec(space),
            text_encoder=encoder_spec, files=file_entries, voxel_stages=stages,
            hidden_dim=heads.hidden_dim, adapted_dim=heads.adapted_dim, identifier=Identifier.MIN_ENTROPY,
            banks={k: BundleContract.bank_key(k) for k in banks}, default_bank="train", bank_notes=bank_notes,
            checkpoint=CheckpointRecord(str(checkpoint), file_sha256(checkpoint), ckpt.step, ckpt.epoch),
            model=ModelRecord(cfg.to_dict(), OPSET), variants=variants,
            parity=report, ago_version=ago_runtime.__version__,
            created_utc=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"))
        meta = contract.to_dict()
        BundleContract.from_dict(meta, tmp / BUNDLE_JSON)   # what is written is what Bundle.load reads
        write_card(tmp, ckpt, checkpoint, readout=(list(grid.shape), list(model_grid.shape)),
                   text_encoder=None if tower is None else tower["card"], **(card or {}))   # card.json: what it was trained on (ago_export/card.py)
        write_json(tmp / BUNDLE_JSON, meta)
        for p in [tmp, *tmp.rglob("*")]:
            p.chmod(0o755 if p.is_dir() else 0o644)
        _replace_dir(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    log(f"wrote {out}")
    return meta
