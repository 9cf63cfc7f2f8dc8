"""The CLI on typer's public API (ago_runtime/cli.py): options with fixed values are Enums whose every value
`--help` lists and whose check refuses anything else; an empty value is refused in every form click accepts
(`--out ''`, `--out=`, `-o ''`, a repeated option, blanks), naming the option; a group alone prints its help and
exits 2. Each refusal is one `error: <option>: <problem>` line, exit 2 (tests/test_bad_inputs.py's contract).
scripts/check_typer_range.sh runs these tests on other typer versions."""

from __future__ import annotations

import pytest
from test_bad_inputs import assert_one_error_line, run_ago

from ago_runtime.predict.decision import Identifier
from ago_runtime.providers import Device, Precision


@pytest.mark.parametrize("verb, option, values", [
    (["infer"], "--identifier", [i.value for i in Identifier]),
    (["infer"], "--picture", ["full", "bev", "none"]),
    (["infer"], "--device", [d.value for d in Device]),
    (["retrieve"], "--precision", [p.value for p in Precision]),
    (["show"], "--view", ["bev", "voxels", "both"]),
    (["eval"], "--identifier", [i.value for i in Identifier]),
    (["open-world"], "--stage", ["pretrain", "zeroshot", "fewshot", "all"]),
    (["synth"], "--rig", ["nuscenes", "waymo", "front"]),
    (["pseudo-labels"], "--segmenter", ["files", "grounded-sam", "sim", "boxes"]),
    (["pseudo-labels"], "--embedder", ["files", "maskclip", "sim", "none"]),
    (["experiments", "list"], "--profile", ["tiny", "cpu", "full"]),
])
def test_an_enum_option_lists_its_values_and_refuses_others(tmp_path, monkeypatch, verb, option, values):
    monkeypatch.setenv("COLUMNS", "250")   # wide enough that the help table wraps no value list
    shown = run_ago([*verb, "--help"], tmp_path)
    assert shown.code == 0
    (row,) = [ln for ln in shown.stdout.splitlines() if ln.lstrip("│ ").startswith(f"{option} ")]
    for value in values:
        assert value in row.replace("[", "|").replace("]", "|").replace("<", "|").replace(">", "|").split("|"), row
    r = run_ago([*verb, option, "sideways"], tmp_path)
    line = assert_one_error_line(r, option, "'sideways' is not one of", repr(values[0]))
    assert "Value error" not in line
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("args, option", [
    (["infer", "--out", ""], "--out"),
    (["infer", "--out="], "--out"),
    (["infer", "-o", "  "], "--out"),
    (["infer", "--images", "x", "--sample", "a", "--sample", ""], "--sample"),
    (["show", "x.npz", "--classes", ""], "--classes"),
    (["prompts", "build", "cw", "-o", ""], "--output"),
    (["metric", "--pred", "p", "--gt", ""], "--gt"),
])
def test_an_empty_value_is_refused_naming_its_option(tmp_path, args, option):
    r = run_ago(args, tmp_path)
    assert_one_error_line(r, f"error: {option}: is empty")
    assert list(tmp_path.iterdir()) == []


def test_an_empty_argument_is_refused_by_its_name(tmp_path):
    """Arguments are values too (CheckedValues): an empty positional argument is one line naming it."""
    r = run_ago(["show", ""], tmp_path)
    assert_one_error_line(r, "error: PATH: is empty")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("args", [[], ["prompts"], ["experiments"]])
def test_a_group_alone_prints_its_help_and_exits_2(tmp_path, args):
    r = run_ago(args, tmp_path)
    assert r.code == 2 and "Usage: ago" in r.stdout and r.stderr == ""
