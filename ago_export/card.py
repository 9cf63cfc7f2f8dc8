"""The bundle card: what an exported model was trained on, written by `ago export` as `card.json`.

`ago infer` and `ago demo` print its one-line `summary`, e.g.

    bundle: trained on the SYNTHETIC world of `ago synth` (128 frames, 10 scenes), 384 steps, label
    space cw (17 classes), val mIoU 7.84 % - not a nuScenes model

so nobody mistakes a demo model for a real one. The card's schema is ago_runtime/predict/card.py (`BundleCard`:
written here through `write_card_file`, read by `Bundle.load` through `read_card`); the format is in docs/runtime.md.

`make_card(ckpt, checkpoint_path, note=None, extra=None)` fills the card from what the checkpoint (an
`ago_train.checkpoint.CheckpointContract`) and its run folder say:
- the checkpoint: step, epoch, train_config (data, pseudo, split, preset name, epochs / max_steps),
  label space (name, classes), the text encoder of its bank (a CLIP tower: what the export says of it);
- the training data folder named in train_config, when it still exists at export time: synthetic
  (`ago synth` output: scene descriptions "ago synth ..." or a synthetic/ folder) or a nuScenes-layout
  dataset (taken as real data), scenes and frames of the training split;
- the pseudo-label folder's meta.json: segmenter / embedder ("simulated" or "files");
- the run folder: the last line of log.jsonl (last loss), `eval-<val split>/metrics.json` next to
  the checkpoint when `ago eval` wrote one (mIoU, geometry IoU).
`extra` (a dict from `ago export --card-json FILE`, e.g. {"val_scores": {"mIoU": 7.84}}) is merged over
it and `note` (`--card-note TEXT`) added; the summary is then written from the merged card.
"""

from __future__ import annotations

import json
from pathlib import Path

from ago_runtime.errors import AgoInputError
from ago_runtime.predict.card import CARD_FILE, CARD_FORMAT, CARD_VERSION, BundleCard, write_card_file
from ago_runtime.readers import read_json


def _plain(obj):
    """Tensors / tuples in checkpoint dicts -> plain JSON values."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if hasattr(obj, "tolist"):
        return obj.tolist()
    return obj


def _json_or_none(path: Path):
    try:
        return json.loads(path.read_text(encoding="utf-8")) if path.is_file() else None
    except (OSError, ValueError, UnicodeDecodeError):
        return None


def describe_data(data: str | None, split: str | None) -> dict:
    """{"kind": "synthetic" | "nuscenes" | "unknown", "path", "scenes", "frames", "split", "image_size"} of a
    training data folder, from its scene/sample/sample_data tables and splits.json (nothing else is read)."""
    out: dict = {"kind": "unknown", "path": data, "split": split, "scenes": None, "frames": None}
    if not data:
        return out
    root = Path(data)
    tables = sorted(p for p in root.glob("v1.0-*") if p.is_dir()) if root.is_dir() else []
    if not tables:
        out["note"] = "data folder not found at export time"
        return out
    scenes = _json_or_none(tables[0] / "scene.json") or []
    samples = _json_or_none(tables[0] / "sample.json") or []
    synthetic = (root / "synthetic").is_dir() or any(str(s.get("description", "")).startswith("ago synth")
                                                    for s in scenes if isinstance(s, dict))
    out["kind"] = "synthetic" if synthetic else "nuscenes"
    names = {s.get("token"): s.get("name") for s in scenes if isinstance(s, dict)}
    wanted = None
    splits = _json_or_none(root / "splits.json")
    if split and split != "all" and isinstance(splits, dict) and isinstance(splits.get(split), list):
        wanted = set(splits[split])
    used = [s for s in samples if isinstance(s, dict) and (wanted is None or names.get(s.get("scene_token")) in wanted)]
    out["frames"] = len(used)
    out["scenes"] = len({s.get("scene_token") for s in used})
    if split in ("train", "val") and splits is None and not (root / "splits.json").is_file():
        from ago_runtime.formats.nuscenes import default_split_positions   # the reader's default split

        per_scene: dict = {}
        for s in used:
            per_scene[s.get("scene_token")] = per_scene.get(s.get("scene_token"), 0) + 1
        out["frames"] = sum(len(default_split_positions(n, split)) for n in per_scene.values())
    # the camera images' size (width, height) as rendered or recorded: the first camera record that has one
    # (read only from a table small enough to parse in a moment: nuScenes trainval's is ~0.5 GB)
    sd = tables[0] / "sample_data.json"
    records = _json_or_none(sd) if sd.is_file() and sd.stat().st_size <= 64 * 2**20 else None
    for rec in records if isinstance(records, list) else []:
        if isinstance(rec, dict) and rec.get("fileformat") == "jpg" and rec.get("width") and rec.get("height"):
            out["image_size"] = [int(rec["width"]), int(rec["height"])]
            break
    return out


def text_encoder_record(ckpt) -> dict:
    """What the checkpoint's bank says of its text encoder: {"id", "variant", "dim"}."""
    return {"id": ckpt.bank.encoder_id, "variant": ckpt.bank.encoder_variant, "dim": ckpt.bank.dim}


def make_card(ckpt, checkpoint_path: str | Path, note: str | None = None, extra: dict | None = None,
              readout: tuple[list[int], list[int]] | None = None, text_encoder: dict | None = None) -> dict:
    """The card dict for a checkpoint (module docstring). readout: (the bundle's read-out grid shape, the
    model's training grid shape), recorded as "readout" and named in the summary when they differ.
    text_encoder: what the export says of the bundle's text encoder (a CLIP tower: ago_export/text_tower.py);
    default: the checkpoint bank's id, variant and width."""
    checkpoint_path = Path(checkpoint_path)
    tc = _plain(ckpt.train_config or {})   # the run's recorded settings
    ls = ckpt.label_space
    data = describe_data(tc.get("data"), tc.get("train_split"))
    if tc.get("max_frames") and data.get("frames"):
        data["frames"] = min(int(data["frames"]), int(tc["max_frames"]))
    if tc.get("frame_tokens"):
        data["frames"] = len(tc["frame_tokens"])
    pseudo_meta = _json_or_none(Path(tc["pseudo"]) / "meta.json") if tc.get("pseudo") else None
    pseudo = None
    if isinstance(pseudo_meta, dict):
        seg, emb = pseudo_meta.get("segmenter") or {}, pseudo_meta.get("embedder") or {}
        pseudo = {"path": tc.get("pseudo"), "segmenter": seg.get("name"), "embedder": emb.get("name"),
                  "keyframes": pseudo_meta.get("num_keyframes", pseudo_meta.get("num_sweeps")),
                  "nonkey_sweeps": pseudo_meta.get("nonkey_sweeps", 0)}
        if seg.get("name") == "simulated" and data["kind"] == "unknown":
            data["kind"] = "synthetic"    # the simulated segmenter only runs on `ago synth` data
    log_last = None
    log_path = checkpoint_path.parent / "log.jsonl"
    if log_path.is_file():
        try:
            lines = [ln for ln in log_path.read_text(encoding="utf-8").splitlines() if ln.strip()]
            log_last = json.loads(lines[-1]) if lines else None
        except (OSError, ValueError, UnicodeDecodeError):
            log_last = None
    val = None
    val_split = tc.get("val_split") or "val"
    metrics = _json_or_none(checkpoint_path.parent / f"eval-{val_split}" / "metrics.json")
    if isinstance(metrics, dict) and metrics.get("mIoU") is not None:
        val = {"mIoU": metrics.get("mIoU"), "geometry_IoU": metrics.get("geometry_IoU"),
               "split": metrics.get("split", val_split), "frames": metrics.get("frames"),
               "readout": metrics.get("readout", "model"),
               "source": str(checkpoint_path.parent / f"eval-{val_split}" / "metrics.json")}
    card = {
        "format": CARD_FORMAT, "version": CARD_VERSION,
        "trained_on": data,
        "pseudo_labels": pseudo,
        "training": {"preset": tc.get("name"), "steps": ckpt.step,
                     "epochs": ckpt.epoch, "batch_size": tc.get("batch_size"),
                     "init_from": tc.get("init_from"),
                     "last_log": {k: log_last[k] for k in ("step", "loss", "total") if k in log_last}
                     if isinstance(log_last, dict) else None},
        "label_space": {"name": ls.name, "classes": list(ls.class_names), "known": list(ls.known)},
        "val_scores": val,
        "text_encoder": text_encoder or text_encoder_record(ckpt),
        "readout": None if readout is None else {"grid": list(readout[0]), "model_grid": list(readout[1])},
        "note": note,
    }
    if extra:
        for key, value in extra.items():
            if isinstance(value, dict) and isinstance(card.get(key), dict):
                card[key] = {**card[key], **value}
            else:
                card[key] = value
    card["summary"] = summary(card)
    return card


def summary(card: dict) -> str:
    """One line: what the model was trained on and how well it scored, ending with a plain warning
    when it is not a model of real camera data."""
    data = card.get("trained_on") or {}
    kind = data.get("kind")
    wh = data.get("image_size")
    of = f" of {wh[0]}x{wh[1]}" if isinstance(wh, list) and len(wh) == 2 else ""
    sizes = ", ".join(x for x in (f"{data['frames']} frames{of}" if data.get("frames") else "",
                                   f"{data['scenes']} scenes" if data.get("scenes") else "") if x)
    where = {"synthetic": "the SYNTHETIC world of `ago synth`", "nuscenes": "a nuScenes-layout dataset"}.get(
        kind, "data not recorded")
    parts = [f"trained on {where}" + (f" ({sizes})" if sizes else "")]
    tr = card.get("training") or {}
    if tr.get("steps"):
        parts.append(f"{tr['steps']} steps")
    ls = card.get("label_space") or {}
    if ls.get("name"):
        parts.append(f"label space {ls['name']}" + (f" ({len(ls['classes'])} classes)" if ls.get("classes") else ""))
    te = card.get("text_encoder") or {}
    if te.get("id"):
        name = f"CLIP text tower {te['id']}" if te.get("kind") == "clip" else str(te["id"])
        parts.append(f"text encoder {name}" + (f" ({te['dim']}-d)" if te.get("dim") else ""))
    val = card.get("val_scores") or {}
    ro = card.get("readout") or {}
    fine = bool(ro.get("grid") and ro.get("model_grid")) and list(ro["grid"]) != list(ro["model_grid"])
    if isinstance(val, dict) and val.get("mIoU") is not None:
        # scores of `ago eval --readout gt` describe a bundle read out on the GT grid, not one on the model grid
        other = val.get("readout") == "gt" and not fine
        parts.append(f"val mIoU {val['mIoU']} %" + (" (of the read-out on the GT grid, not this bundle's)" if other else ""))
    if fine:
        parts.append("read out at {} (trained at {})".format("x".join(map(str, ro["grid"])),
                                                             "x".join(map(str, ro["model_grid"]))))
    pl = card.get("pseudo_labels") or {}
    line = ", ".join(parts)
    if pl.get("segmenter") == "boxes":
        line += "; labels from dataset boxes (projected 3D boxes + LiDAR ground, no VLM)"
    if card.get("pseudo_labels") and not pl.get("embedder"):
        line += "; modality adapter never aligned (pseudo-labels without image embeddings: --embedder none)"
    if kind == "synthetic" or pl.get("segmenter") == "simulated":
        line += " - not a nuScenes model"
    if card.get("note"):
        line += f"; {card['note']}"
    return line


def read_card_options(note: str | None, card_json: str | Path | None) -> dict:
    """`ago export --card-note TEXT --card-json FILE` -> {"note", "extra"} (the JSON file: an object)."""
    extra = read_json(card_json, missing="card JSON file not found", expect=dict) if card_json else None
    if extra is not None:
        BundleCard.check_extra(extra, card_json)   # only what the card declares (before the export runs)
    if note is not None and ("\n" in note or not note.strip()):
        raise AgoInputError("--card-note", "must be one non-empty line")
    return {"note": note, "extra": extra}


def write_card(bundle_dir: str | Path, ckpt: dict, checkpoint_path: str | Path, note: str | None = None,
               extra: dict | None = None, readout: tuple[list[int], list[int]] | None = None,
               text_encoder: dict | None = None) -> Path:
    """Write `card.json` into a bundle folder (the export's temporary folder); gives its path."""
    return write_card_file(Path(bundle_dir) / CARD_FILE, make_card(ckpt, checkpoint_path, note=note, extra=extra,
                                                                   readout=readout, text_encoder=text_encoder))
