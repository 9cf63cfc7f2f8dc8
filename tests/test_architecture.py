"""The layout rules of docs/architecture.md, checked on the source (ast; nothing is imported but in the
tests that run the code in a child process):

- no import circles among the modules of ago_runtime, ago_train and ago_export, counting module-level
  imports and, separately, every import (inside functions too; `if TYPE_CHECKING:` blocks excluded);
- the direction: ago_runtime imports neither ago_train nor ago_export, ago_train does not import
  ago_export (ago_export exports ago_train's model, so it imports ago_train);
- inside ago_runtime, each subpackage imports only the ones below it (the table ALLOWED), a verb
  module (`<subpackage>/cli.py`) anything in ago_runtime;
- every package opens with a docstring saying what it holds (and, in ago_runtime, what it may import);
- no module is only an alias: no `sys.modules[...] = ...`, no module (other than a package's __init__)
  whose body is only imports;
- importing every ago_runtime module and building the whole `ago` app loads no torch;
- `ago infer` (its verb module, `ago infer --help`) loads no ago_train / ago_export module and no other
  verb module, and VERB_MODULES says where each verb is (these import the code, in a child process);
- one prediction engine: inside ago_runtime only the slab loop (predict/classifier.py) calls the voxel
  decision's steps (predict/decision.py), `FoldedHeads` is data, and the export's parity check
  (`runtime_labels`) and `ago retrieve` (`Predictor.predict_hidden`) reach the decision through
  `VoxelClassifier`.
"""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("ago_runtime", "ago_train", "ago_export")

BASICS = {"errors", "atomic", "readers", "outputs", "paths", "progress", "classes", "cache", "providers", "openvino_session",
          "shards", "volumes"}
# subpackage -> the ago_runtime parts its (non-cli) modules may import; "basics" = the top-level modules above
ALLOWED = {
    "basics": {"basics"},
    "geometry": {"basics", "geometry"},
    "formats": {"basics", "geometry", "formats"},
    "vocab": {"basics", "vocab"},
    "scoring": {"basics", "scoring"},
    "predict": {"basics", "geometry", "formats", "vocab", "predict"},
    "pictures": {"basics", "geometry", "formats", "pictures"},
}


def _modules() -> dict[str, tuple[Path, bool]]:
    """module name -> (file, is a package __init__)."""
    out = {}
    for pkg in PACKAGES:
        for p in sorted((REPO / pkg).rglob("*.py")):
            parts = list(p.relative_to(REPO).with_suffix("").parts)
            is_pkg = parts[-1] == "__init__"
            out[".".join(parts[:-1] if is_pkg else parts)] = (p, is_pkg)
    return out


def _targets(module: str, is_pkg: bool, node: ast.AST) -> list[str]:
    """The module names an import statement may load (for `from x import y`: x and x.y)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    base = module.split(".") if is_pkg else module.split(".")[:-1]
    if node.level:
        base = base[: len(base) - (node.level - 1)]
        prefix = ".".join(base + ([node.module] if node.module else []))
    else:
        prefix = node.module or ""
    return [prefix] + [f"{prefix}.{a.name}" for a in node.names]


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING")


def _imports(tree: ast.Module, everywhere: bool):
    """Import nodes at module level (also under if / try), or everywhere; never under `if TYPE_CHECKING:`."""
    def walk(body, top):
        for n in body:
            if isinstance(n, (ast.Import, ast.ImportFrom)):
                yield n
            elif isinstance(n, ast.If) and _is_type_checking(n):
                continue
            elif isinstance(n, (ast.If, ast.Try, ast.With)) or (everywhere and hasattr(n, "body")):
                for field in ("body", "orelse", "finalbody"):
                    yield from walk(getattr(n, field, []) or [], top)
                for h in getattr(n, "handlers", []):
                    yield from walk(h.body, top)
    yield from walk(tree.body, True)


def import_graph(everywhere: bool) -> dict[str, set[str]]:
    mods = _modules()
    graph = {}
    for name, (path, is_pkg) in mods.items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        deps = set()
        for node in _imports(tree, everywhere):
            deps |= {t for t in _targets(name, is_pkg, node) if t in mods and t != name}
        graph[name] = deps
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index, low, on_stack, stack, out = {}, {}, set(), [], []
    counter = 0
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            for w in children:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return out


def _part(module: str) -> str | None:
    """The part of ago_runtime a module is in: a subpackage's name, "basics", "top" (cli, __main__, an old
    import path), or None outside ago_runtime and for the package itself."""
    parts = module.split(".")
    if parts[0] != "ago_runtime" or len(parts) == 1:
        return None
    if len(parts) > 2 or (REPO / "ago_runtime" / parts[1] / "__init__.py").is_file():
        return parts[1]
    return "basics" if parts[1] in BASICS else "top"


def test_no_import_circles_at_module_level():
    assert cycles(import_graph(everywhere=False)) == []


def test_no_import_circles_counting_imports_inside_functions():
    assert cycles(import_graph(everywhere=True)) == []


def test_dependencies_point_down():
    graph = import_graph(everywhere=True)
    up = [(m, d) for m, deps in graph.items() for d in deps
          if (m.startswith("ago_runtime") and d.split(".")[0] in ("ago_train", "ago_export"))
          or (m.startswith("ago_train") and d.startswith("ago_export"))]
    assert up == [], f"imports that point up: {up}"


def test_ago_runtime_subpackages_import_only_what_is_below_them():
    subpackages = {p.name for p in (REPO / "ago_runtime").iterdir() if (p / "__init__.py").is_file()}
    assert subpackages == set(ALLOWED) - {"basics"}, "a subpackage missing from ALLOWED (or one gone)"
    bad = []
    for m, deps in import_graph(everywhere=True).items():
        part = _part(m)
        if part in (None, "top") or m.endswith(".cli"):   # verb modules may import anything in ago_runtime
            continue
        bad += [f"{m} -> {d}" for d in deps if _part(d) is not None and _part(d) not in ALLOWED[part]]
    assert bad == [], f"imports across the layers of ago_runtime (see ALLOWED): {bad}"


def test_every_package_says_what_it_holds():
    missing = []
    for init in sorted(p for pkg in PACKAGES for p in (REPO / pkg).rglob("__init__.py")):
        doc = ast.get_docstring(ast.parse(init.read_text(encoding="utf-8")))
        rel = init.parent.relative_to(REPO)
        if not doc or (rel.parts[0] == "ago_runtime" and len(rel.parts) == 2 and "May import" not in doc):
            missing.append(str(rel))
    assert missing == [], f"packages without a docstring (ago_runtime's: with 'May import'): {missing}"


def test_runtime_and_the_whole_cli_load_no_torch():
    """Every ago_runtime module imported, and the `ago` app built with all its verbs (the training verbs'
    modules included): torch is not loaded."""
    names = sorted(m for m in _modules() if m.startswith("ago_runtime") and not m.endswith("__main__"))
    code = (f"import importlib, sys, typer.main\nfor n in {names!r}: importlib.import_module(n)\n"
            "from ago_runtime.cli import app\ngroup = typer.main.get_command(app)\n"
            "assert {'train', 'export', 'prompts'} <= set(group.commands), sorted(group.commands)\n"
            "assert 'torch' not in sys.modules, 'torch was imported'\n"
            "assert 'tokenizers' not in sys.modules, 'tokenizers was imported (only a CLIP tokenizer needs it)'\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 0, r.stderr


def _assigns_sys_modules(node: ast.AST) -> bool:
    targets = node.targets if isinstance(node, ast.Assign) else [getattr(node, "target", None)]
    return any(isinstance(t, ast.Subscript) and isinstance(t.value, ast.Attribute) and t.value.attr == "modules"
               and isinstance(t.value.value, ast.Name) and t.value.value.id == "sys" for t in targets)


def test_no_module_is_only_an_alias():
    """An old import path kept as `sys.modules[__name__] = moved` or a module that only re-exports names
    is a second name for code that lives elsewhere: refused (packages' __init__ may gather names)."""
    aliases = []
    for name, (path, is_pkg) in _modules().items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        if any(isinstance(n, (ast.Assign, ast.AugAssign, ast.AnnAssign)) and _assigns_sys_modules(n)
               for n in ast.walk(tree)):
            aliases.append(f"{name}: assigns sys.modules")
        body = [n for n in tree.body if not (isinstance(n, ast.Expr) and isinstance(n.value, ast.Constant))]
        only_imports = all(isinstance(n, (ast.Import, ast.ImportFrom)) or (
            isinstance(n, ast.Assign) and all(isinstance(t, ast.Name) and t.id == "__all__" for t in n.targets))
            for n in body)
        if body and only_imports and not is_pkg:
            aliases.append(f"{name}: only imports")
    assert aliases == [], f"modules that are only aliases: {aliases}"


def _loaded_after(code: str) -> list[str]:
    """The ago modules a child python has loaded after running `code` (this tree first on the path)."""
    code += ("\nimport json, sys\nprint(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in "
             "('ago_runtime', 'ago_train', 'ago_export'))))")
    env = dict(os.environ, PYTHONPATH=str(REPO))
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, env=env)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_the_infer_path_imports_only_what_it_runs():
    from ago_runtime.cli import VERB_MODULES

    verb_modules = {m for modules in VERB_MODULES.values() for m in modules}
    for code in ("from ago_runtime.cli import run\nrun(['infer', '--help'])", "import ago_runtime.predict.cli"):
        loaded = _loaded_after(code)
        assert [m for m in loaded if not m.startswith("ago_runtime")] == [], (code, loaded)
        assert [m for m in loaded if m in verb_modules] == ["ago_runtime.predict.cli"], (code, loaded)


def test_verb_modules_table_says_where_each_verb_is():
    """build_app(verb) holds that verb (its modules only); build_app() holds exactly the table's verbs."""
    code = ("import json, typer.main\nfrom ago_runtime.cli import VERB_MODULES, build_app\n"
            "print(json.dumps({v: sorted(typer.main.get_command(build_app(v)).commands) for v in VERB_MODULES}))\n"
            "print(json.dumps(sorted(typer.main.get_command(build_app()).commands)))")
    env = dict(os.environ, PYTHONPATH=str(REPO))
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, env=env)
    assert r.returncode == 0, r.stderr
    per_verb, every = (json.loads(line) for line in r.stdout.strip().splitlines()[-2:])
    missing = [v for v, verbs in per_verb.items() if v not in verbs]
    assert missing == [], f"VERB_MODULES names modules that do not define these verbs: {missing}"
    assert sorted(per_verb) == every


# ---- one prediction engine ----------------------------------------------------------------------------
# the steps of ago_runtime.predict.decision that turn scores into labels (fold / score_rows only prepare data)
DECISION_STEPS = {"class_scores", "main_free", "adapted_voxels", "decide", "softmax_stats", "user_confidence",
                  "occupied_probability"}
ENGINE = "ago_runtime/predict/classifier.py"


def _decision_step_uses(tree: ast.AST) -> list[str]:
    """The decision steps a piece of code calls: `decision.<step>` and steps imported by name."""
    found = []
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and node.attr in DECISION_STEPS and isinstance(node.value, ast.Name)
                and node.value.id == "decision"):
            found.append(f"decision.{node.attr} (line {node.lineno})")
        if isinstance(node, ast.ImportFrom) and (node.module or "").endswith("decision"):
            found += [f"import {a.name} (line {node.lineno})" for a in node.names if a.name in DECISION_STEPS]
    return found


def _function(path: Path, qualname: str) -> ast.AST:
    tree = ast.parse(path.read_text())
    node = tree
    for name in qualname.split("."):
        node = next(n for n in node.body if isinstance(n, (ast.FunctionDef, ast.ClassDef)) and n.name == name)
    return node


def _calls(node: ast.AST) -> set[str]:
    """Names called in `node`: f(...) -> "f", a.b.f(...) -> "f"."""
    out = set()
    for n in ast.walk(node):
        if isinstance(n, ast.Call):
            f = n.func
            out.add(f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else "")
    return out


def test_only_the_classifier_drives_the_decision_in_the_runtime():
    drivers = {}
    for path in sorted((REPO / "ago_runtime").rglob("*.py")):
        rel = str(path.relative_to(REPO))
        if rel in (ENGINE, "ago_runtime/predict/decision.py"):
            continue
        uses = _decision_step_uses(ast.parse(path.read_text()))
        if uses:
            drivers[rel] = uses
    assert drivers == {}, f"only {ENGINE} may drive the voxel decision: {drivers}"
    assert _decision_step_uses(ast.parse((REPO / ENGINE).read_text())), "the classifier no longer drives it?"
    # FoldedHeads is data: its only methods build it or describe it
    heads = _function(REPO / "ago_runtime/predict/heads.py", "FoldedHeads")
    methods = {n.name for n in heads.body if isinstance(n, ast.FunctionDef)}
    assert methods <= {"fold", "num_classes", "num_rows", "width"}, methods


def test_parity_and_retrieve_go_through_the_classifier():
    """parity.runtime_labels (the export's check of what `ago infer` gives) and `ago retrieve`
    (run_retrieve -> Predictor.predict_hidden) call VoxelClassifier and no decision step themselves."""
    runtime_labels = _function(REPO / "ago_export/parity.py", "runtime_labels")
    assert _decision_step_uses(runtime_labels) == []
    assert {"VoxelClassifier", "classify", "branch_labels"} <= _calls(runtime_labels)
    predict_hidden = _function(REPO / "ago_runtime/predict/predictor.py", "Predictor.predict_hidden")
    assert "classify_hidden" in _calls(predict_hidden)
    assert "predict_hidden" in _calls(_function(REPO / "ago_runtime/predict/cli.py", "run_retrieve"))
    classifier = _function(REPO / ENGINE, "VoxelClassifier")
    for method in ("classify", "classify_hidden"):
        body = next(n for n in classifier.body if isinstance(n, ast.FunctionDef) and n.name == method)
        assert "decide_block" in _calls(body), method


def test_training_names_a_decision_without_the_bundle_contract():
    """ago_train imports Identifier / Branch from the decision module, never the bundle contract."""
    offenders = []
    for path in sorted((REPO / "ago_train").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module == "ago_runtime.predict.contract":
                names = {a.name for a in node.names} & {"Identifier", "Branch"}
                if names:
                    offenders.append(f"{path.relative_to(REPO)}: {sorted(names)}")
    assert offenders == []
