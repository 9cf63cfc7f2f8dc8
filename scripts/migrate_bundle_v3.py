"""Rewrite a format-3 bundle as format 4, for a bundle whose checkpoint is not at hand.

    python scripts/migrate_bundle_v3.py OLD_BUNDLE NEW_BUNDLE [--old-src DIR]

`ago export CKPT -o DIR` makes a format-4 bundle directly; this script exists for the shipped default
bundle, whose checkpoint is not kept. What it changes:

- voxel stages: each stage graph keeps only x -> y (the bank input and the bank-product output `s`, which
  the runtime fed a zero row and discarded, are cut with onnx.utils.Extractor); a stage with no linear
  layer (the adapted bank product alone, `voxels_1.onnx` of the default bundle) is dropped; every stage
  is labelled with its branch ("main" before h, "adapted" from h to g);
- bundle.json: format_version 4, the typed contract (ago_runtime/predict/contract.py): `rig` = the
  cameras and their input image size, the old `rig` calibration as `training_rig`, `hidden_dim`,
  `adapted_dim`, new sha256 / size of the rewritten files.

planes.onnx, heads.npz and the banks are copied byte for byte. With --old-src (a checkout of ago that
reads format 3), the old bundle's labels (old runtime) and the new bundle's (this runtime) are compared on
the demo frame for every identifier; the script fails unless they are identical. The new folder is written
under a temporary name and renamed into place only then.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from ago_runtime.atomic import replace_dir, temp_dir_beside, write_json  # noqa: E402
from ago_runtime.predict.contract import (BUNDLE_FORMAT_VERSION, BUNDLE_JSON, Branch, BundleContract,  # noqa: E402
                                          CameraSlot, FileEntry, Identifier, LabelSpaceSpec, RigSpec,
                                          TextEncoderSpec, VoxelStageSpec)


def cut_stage_graph(src: Path, dst: Path, spec: dict) -> None:
    """A format-3 stage graph -> x -> y only, with format-4 metadata."""
    import onnx
    from onnx.utils import Extractor

    model = onnx.load(str(src))
    cut = Extractor(model).extract_model(["x"], ["y"])
    cut.ir_version, cut.producer_name, cut.doc_string = model.ir_version, model.producer_name, \
        "ago per-voxel MLP stage: x (n, d_in) -> y = x W^T + b (n, d_out), the next pre-activation"
    del cut.opset_import[:]
    cut.opset_import.extend(model.opset_import)
    for p in model.metadata_props:
        value = p.value
        if p.key == "ago.format_version":
            value = str(BUNDLE_FORMAT_VERSION)
        elif p.key == "ago.voxel_stage":
            value = json.dumps(spec)
        elif p.key == "ago.outputs":
            value = "planes: the TPV planes at the grid (times the decoder's first linear); voxels_<i>: one layer " \
                    "of the per-voxel MLP (y = x W^T + b)"
        cut.metadata_props.add(key=p.key, value=value)
    onnx.checker.check_model(cut, full_check=True)
    onnx.save(cut, str(dst))


def migrate(old: Path, new_tmp: Path) -> dict:
    meta = json.loads((old / BUNDLE_JSON).read_text())
    if meta.get("format_version") != 3:
        raise SystemExit(f"error: {old / BUNDLE_JSON}: format_version {meta.get('format_version')}, not 3")
    roles = [st.get("bank") for st in meta["voxel_stages"]]
    main_index = roles.index("main")               # the stage whose input is h: the first adapter stage
    hidden_dim = int(meta["voxel_stages"][main_index]["input_dim"])
    adapted_dim = int(meta["voxel_stages"][-1]["input_dim"])   # the last stage (bank "adapted") takes g
    old_files = meta["files"]
    files: dict[str, FileEntry] = {}
    stages: list[VoxelStageSpec] = []
    for i, st in enumerate(meta["voxel_stages"]):
        if st.get("linear") is None:
            continue                                # a bank product alone: the runtime computes it itself
        spec = VoxelStageSpec(st["file"], int(st["linear"][0]), int(st["linear"][1]), st["activation"],
                              Branch.MAIN if i < main_index else Branch.ADAPTED)
        for suffix in ("", "_int8"):
            key = st["file"] + suffix
            if key in old_files:
                cut_stage_graph(old / old_files[key]["path"], new_tmp / old_files[key]["path"], spec.to_dict())
                files[key] = FileEntry.of(new_tmp, old_files[key]["path"])
        stages.append(spec)
    copied = ["planes", "planes_int8", "heads"] + [k for k in old_files if k.startswith("bank/")]
    for key in copied:
        if key in old_files:
            rel = old_files[key]["path"]
            (new_tmp / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(old / rel, new_tmp / rel)
            files[key] = FileEntry.of(new_tmp, rel)
    if (old / "card.json").is_file():
        shutil.copy2(old / "card.json", new_tmp / "card.json")
    pre = meta["preprocess"]
    rig = RigSpec([CameraSlot(c["name"], int(pre["width"]), int(pre["height"])) for c in meta["rig"]["cameras"]])
    contract = BundleContract(
        grid=meta["grid"], model_grid=meta.get("model_grid", meta["grid"]), preprocess=pre, rig=rig,
        training_rig=meta["rig"], label_space=LabelSpaceSpec.from_dict(meta["label_space"]),
        text_encoder=TextEncoderSpec.from_dict(meta["text_encoder"]), files=files, voxel_stages=stages,
        hidden_dim=hidden_dim, adapted_dim=adapted_dim, banks=meta["banks"], default_bank=meta.get("default_bank", "train"),
        bank_notes=meta.get("bank_notes", {}), checkpoint=meta.get("checkpoint", {}), model=meta.get("model", {}),
        parity={**meta.get("parity", {}), "migrated_from_format_3": True}, ago_version=meta.get("ago_version", ""),
        created_utc=meta.get("created_utc", ""), rig_source=meta.get("rig_source", ""))
    contract.identifier = Identifier(meta.get("identifier", Identifier.MIN_ENTROPY.value))
    out = contract.to_dict()
    BundleContract.from_dict(out, new_tmp / BUNDLE_JSON)    # the result reads back as a valid contract
    write_json(new_tmp / BUNDLE_JSON, out)
    return out


def load_old_runtime(src: Path, dest: Path):
    """The `ago_runtime` package of a format-3 checkout `src`, importable in this process as `ago_runtime_v3`
    (a copy under `dest` with its imports renamed)."""
    import importlib

    target = dest / "ago_runtime_v3"
    if not target.is_dir():
        shutil.copytree(src / "ago_runtime", target, ignore=shutil.ignore_patterns("__pycache__", "assets"))
        (target / "assets").symlink_to((src / "ago_runtime" / "assets").resolve())
        for py in target.rglob("*.py"):
            text = py.read_text()
            py.write_text(text.replace("ago_runtime.", "ago_runtime_v3.").replace("import ago_runtime\n",
                                                                                  "import ago_runtime_v3\n"))
    if str(dest) not in sys.path:
        sys.path.insert(0, str(dest))
    return importlib.import_module("ago_runtime_v3.predict.predictor")


def demo_inputs():
    from ago_runtime.formats.calibration import load_images_folder
    from ago_runtime.predict.bundle import DEMO_FRAME_DIR

    images, rig, _ = load_images_folder(DEMO_FRAME_DIR)
    return images, rig


def compare_labels(old_bundle: Path, new_bundle: Path, old_src: Path, work: Path) -> list[str]:
    """Labels of the old bundle (old runtime) and the new (this runtime) on the demo frame, per identifier."""
    import numpy as np

    from ago_runtime.predict.predictor import Predictor

    old_mod = load_old_runtime(old_src, work)
    images, rig = demo_inputs()
    old_p, new_p = old_mod.Predictor(old_bundle), Predictor(new_bundle)
    x, m = new_p.prepare(images, rig)
    bank = new_p.bundle.load_bank()
    old_bank = old_p.bundle.load_bank()
    lines = []
    for ident in Identifier:
        a = old_p.predict_arrays(x, m, old_bank, ident.value).semantics
        b = new_p.predict_arrays(x, m, bank, ident).semantics
        same = int(np.sum(a == b))
        lines.append(f"{ident.value}: {same}/{a.size} voxels with the same label")
        if same != a.size:
            raise SystemExit(f"error: {new_bundle}: labels differ from the old bundle's ({lines[-1]})")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("old", type=Path)
    ap.add_argument("new", type=Path)
    ap.add_argument("--old-src", type=Path, help="a checkout of ago that reads format 3, for the label check")
    args = ap.parse_args(argv)
    tmp = temp_dir_beside(args.new)
    try:
        migrate(args.old, tmp)
        if args.old_src is not None:
            work = temp_dir_beside(args.new.parent / "old_runtime")
            try:
                for line in compare_labels(args.old, tmp, args.old_src, work):
                    print(line)
            finally:
                shutil.rmtree(work, ignore_errors=True)
        replace_dir(tmp, args.new)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    print(f"wrote {args.new}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
