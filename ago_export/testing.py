"""Random-weight checkpoints in the trainer's format, for tests and benchmarks (needs torch).

`random_checkpoint(path, config)` writes a model-only `CheckpointContract` as `ago train`'s snapshots do
(model state_dict, model_config, label_space with its prompt text, the label space's bank; no training
state), with freshly initialised weights and the bank encoded by the installed ONNX text encoder. Useful to exercise export and runtime without
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
    from ago_runtime.vocab.prompts import parse_prompt_file
    from ago_train.checkpoint import BankRecord, CheckpointContract, LabelSpaceRecord
    from ago_train.model import ModelConfig

    if isinstance(config, str):
        config = ModelConfig.preset(config)
        config.pretrained = False
    if rig is not None:
        config.num_cameras = len(rig.cameras)
    torch.manual_seed(seed)
    model = config.build()
    space = parse_prompt_file(prompts)
    return CheckpointContract(
        model=model.state_dict(), model_config=config,
        label_space=LabelSpaceRecord.of_space(space, Path(space.source).read_text(encoding="utf-8")),
        bank=BankRecord.of_bank(load_prompt_bank(space)), rig=rig).save(path)
