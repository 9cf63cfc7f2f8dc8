"""Random-weight checkpoints in the trainer's format, for tests and benchmarks (needs torch).

`random_checkpoint(path, config)` writes what `ago train` writes (model state_dict, model_config,
label_space with its prompt text, the label space's bank), with freshly initialised weights and the
bank encoded by the installed ONNX text encoder. Useful to exercise export and runtime without
training; the predictions are meaningless.
"""

from __future__ import annotations

from pathlib import Path


def random_checkpoint(path: str | Path, config="tiny", prompts: str = "cw", seed: int = 0, rig=None) -> Path:
    """config: a ModelConfig or a preset name ("tiny", "cpu", "full"; "cpu"/"full" without ImageNet weights).
    rig: the training rig to record (a `Rig`; the model then takes its cameras), else none is recorded
    (export falls back to nuScenes' six)."""
    import torch

    from ago_runtime.vocab.bank import load_prompt_bank
    from ago_runtime.vocab.prompts import label_space_record, parse_prompt_file
    from ago_train.checkpoint import save_checkpoint
    from ago_train.model import ModelConfig

    if isinstance(config, str):
        config = ModelConfig.preset(config)
        config.pretrained = False
    if rig is not None:
        config.num_cameras = len(rig.cameras)
    torch.manual_seed(seed)
    model = config.build()
    space = parse_prompt_file(prompts)
    bank = load_prompt_bank(space)
    extra = {"rig": rig.to_dict()} if rig is not None else {}
    return save_checkpoint(path, {
        **extra,
        "model": model.state_dict(), "model_config": config.to_dict(), "step": 0, "epoch": 0,
        "label_space": label_space_record(space, Path(space.source).read_text(encoding="utf-8")),
        "bank": {"encoder_id": bank.encoder_id, "encoder_hash": bank.encoder_hash,
                 "embeddings": torch.from_numpy(bank.embeddings), "phrase_class": torch.from_numpy(bank.phrase_class),
                 "class_names": list(bank.class_names)},
    })
