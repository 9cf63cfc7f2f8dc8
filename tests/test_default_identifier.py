"""The identifier a prompt bank gets when none is asked for: the same rule in `ago infer` (runtime) and
`ago eval` (torch), "none" for a closed-world bank, the bundle's open-world identifier otherwise."""

from __future__ import annotations

import numpy as np

from ago_runtime.predict.heads import default_identifier
from ago_runtime.vocab.bank import PromptBank
from ago_runtime.vocab.prompts import parse_prompt_text

TRAINED = ["car", "road", "building"]


def test_rule_on_hand_made_banks():
    # the training classes themselves, in any order: closed world
    assert default_identifier(["road", "car"], [], TRAINED) == "none"
    # a class the model never had a label for
    assert default_identifier(["car", "trash bin"], [], TRAINED) == "min-entropy"
    # the bank's own known list wins over the training classes (an open-world prompt file's @known)
    assert default_identifier(["car", "road"], ["car"], TRAINED) == "min-entropy"
    # a file without @known calls every class known; a class the model never saw stays unknown
    assert default_identifier(["car", "trash bin"], ["car", "trash bin"], TRAINED) == "min-entropy"
    assert default_identifier(["car", "road"], ["car", "road"], TRAINED) == "none"
    # the bundle's open-world identifier is passed through
    assert default_identifier(["car", "trash bin"], [], TRAINED, open_world="max-conf") == "max-conf"


def test_torch_evaluation_uses_the_runtime_rule():
    from ago_train.evaluate import default_identifier as eval_rule

    closed = parse_prompt_text("car: car\nroad: road\n", name="c")
    novel = parse_prompt_text("car: car\ntrash bin: trash bin\n", name="n")
    known = parse_prompt_text("@known: car\ncar: car\nroad: road\n", name="k")
    assert eval_rule(closed, TRAINED) == "none"
    assert eval_rule(novel, TRAINED) == "min-entropy"
    assert eval_rule(known, TRAINED) == "min-entropy"
    assert eval_rule(novel) == "none"          # without the model's classes: the label space itself
    assert eval_rule(known) == "min-entropy"


def test_shipped_bundle_picks_none_for_its_own_classes_and_min_entropy_for_new_ones():
    from ago_runtime.predict.bundle import DEFAULT_BUNDLE_DIR, Bundle

    b = Bundle.load(DEFAULT_BUNDLE_DIR, verify_hashes=False)
    own = b.load_bank()
    assert b.identifier_for(own) == "none"
    new = PromptBank(embeddings=own.embeddings[:2], phrases=["car", "street lamp"],
                     class_names=["car", "street lamp"], phrase_class=np.array([0, 1]),
                     encoder_id=own.encoder_id, encoder_variant=own.encoder_variant,
                     encoder_hash=own.encoder_hash, dim=own.dim)
    assert b.identifier_for(new) == b.identifier == "min-entropy"
