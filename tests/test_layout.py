"""The layout rules of the package, read from the source (docs/architecture.md): the layers and
the direction imports may go between them, no import cycle, no private name imported from
another package folder, no file over 600 lines, no module outside torchgi/backends importing the
C or Triton kernels, and every public function outside the back ends on a screen (at most 60
lines of code, its docstring, comments and blank lines not counted). Function-level imports
count like module-level ones."""

from __future__ import annotations

import ast
import io
import tokenize
from pathlib import Path

from torchgi import methods

PACKAGE = Path(__file__).resolve().parents[1] / "torchgi"
KERNELS = ("c_kernels", "triton_kernels", "_native")
MAX_LINES = 60
MAX_FILE_LINES = 600

# bottom to top: a module may import its own unit and the units of lower layers only; units of
# one layer do not import each other. A unit is torchgi's first-level module or package
# ("" is torchgi/__init__.py, the top-level API).
LAYERS = (
    ("core", "settings"),
    ("light", "geometry"),
    ("backends",),
    ("io", "metrics", "supersample"),
    ("buffers",),
    ("filters",),
    ("render",),
    ("sampling",),
    ("methods",),
    ("deployed",),
    ("denoise",),
    ("temporal", "data", "progressive"),
    ("export", "demo"),
    ("",),
    ("cli",),
)
LAYER = {unit: i for i, units in enumerate(LAYERS) for unit in units}


def _modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        if "backends" not in path.relative_to(PACKAGE).parts:
            yield path


def _name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> list[tuple[str, str, int]]:
    """``(module, imported name or "", line)`` of every ``torchgi`` import in ``path``, relative
    imports resolved, at any depth (function-level imports included)."""
    here = _name(path)
    package = here if path.name == "__init__.py" else here.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = package.split(".")[: len(package.split(".")) - node.level + 1] if node.level else []
            module = ".".join([*base, node.module] if node.module else base) if node.level else node.module or ""
            out += [(module, a.name, node.lineno) for a in node.names if module.split(".")[0] == "torchgi"]
        elif isinstance(node, ast.Import):
            out += [(a.name, "", node.lineno) for a in node.names if a.name.split(".")[0] == "torchgi"]
    return out


def _all_files():
    return {_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def _resolve(module: str, name: str, files: dict[str, Path]) -> str:
    """The torchgi module an import reaches: ``module.name`` when that is a module, else ``module``."""
    return f"{module}.{name}" if f"{module}.{name}" in files else module


def _unit(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def _graph() -> dict[str, set[str]]:
    files = _all_files()
    return {m: {_resolve(mod, n, files) for mod, n, _ in _imports(p)} - {m} for m, p in files.items()}


def test_every_unit_has_a_layer():
    units = {_unit(m) for m in _all_files()}
    assert units - set(LAYER) == set(), "add the new module or package to LAYERS (and docs/architecture.md)"


def test_imports_go_down_the_layers():
    files = _all_files()
    wrong = []
    for m, p in files.items():
        for mod, n, line in _imports(p):
            src, dst = _unit(m), _unit(_resolve(mod, n, files))
            if src != dst and not LAYER[dst] < LAYER[src]:
                wrong.append(f"{p.relative_to(PACKAGE)}:{line} ({src or 'torchgi'}) imports {mod} ({dst or 'torchgi'})")
    assert wrong == []


def test_no_import_cycle():
    graph = _graph()
    cycles, state = [], {}

    def visit(m: str, stack: list[str]) -> None:
        state[m] = "open"
        for t in sorted(graph.get(m, ())):
            if state.get(t) == "open":
                cycles.append(" -> ".join([*stack[stack.index(t):], t]))
            elif t not in state:
                visit(t, [*stack, t])
        state[m] = "done"

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert cycles == []


def test_no_private_name_from_another_package_folder():
    files = _all_files()
    wrong = []
    for p in files.values():
        for mod, n, line in _imports(p):
            target = _resolve(mod, n, files)
            private = n.startswith("_") and not n.startswith("__")
            if not private and not any(part.startswith("_") for part in mod.split(".")[1:]):
                continue
            owner = files[target].parent if target in files else None
            if owner != p.parent:
                wrong.append(f"{p.relative_to(PACKAGE)}:{line} takes {mod}.{n}")
    assert wrong == []


def test_no_file_is_over_600_lines():
    """Every source file of the package (Python, C); its data (meshes, weights) are not code."""
    long = [f"{p.relative_to(PACKAGE)}: {n}" for p in sorted(PACKAGE.rglob("*"))
            if p.is_file() and p.suffix in (".py", ".c", ".h") and "__pycache__" not in p.parts
            and (n := len(p.read_bytes().splitlines())) > MAX_FILE_LINES]
    assert long == []


def test_the_back_ends_import_only_what_lies_below():
    """Stated on its own, as the issue that made the seam put it: core, settings, the light maths
    and the back ends' own package."""
    allowed = {"core", "settings", "light", "geometry", "backends"}
    files = _all_files()
    wrong = [f"{p.relative_to(PACKAGE)}:{line} imports {mod}" for m, p in files.items() if _unit(m) == "backends"
             for mod, n, line in _imports(p) if _unit(_resolve(mod, n, files)) not in allowed]
    assert wrong == []


def test_no_module_outside_the_back_ends_imports_a_kernel():
    offenders = [f"{p.relative_to(PACKAGE)}: {k}" for p in _modules() for k in KERNELS if k in p.read_text()]
    assert offenders == []


def _code_lines(source: str, node: ast.FunctionDef) -> int:
    """Lines of ``node`` that hold code: not its docstring, not blank, not only a comment."""
    doc = node.body[0] if node.body and isinstance(node.body[0], ast.Expr) and \
        isinstance(getattr(node.body[0], "value", None), ast.Constant) and isinstance(node.body[0].value.value, str) \
        else None
    skip = set(range(doc.lineno, doc.end_lineno + 1)) if doc is not None else set()
    lines = set()
    segment = "\n".join(source.splitlines()[node.lineno - 1 : node.end_lineno])
    for tok in tokenize.generate_tokens(io.StringIO(segment).readline):
        if tok.type not in (tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT,
                            tokenize.ENDMARKER):
            lines.update(range(tok.start[0] + node.lineno - 1, tok.end[0] + node.lineno))
    return len(lines - skip)


def test_public_functions_fit_on_a_screen():
    long = []
    for path in _modules():
        source = path.read_text()
        tree = ast.parse(source)
        scopes = [tree] + [n for n in tree.body if isinstance(n, ast.ClassDef) and not n.name.startswith("_")]
        for scope in scopes:
            for node in scope.body:
                if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and not node.name.startswith("_"):
                    n = _code_lines(source, node)
                    if n > MAX_LINES:
                        long.append(f"{path.relative_to(PACKAGE)}:{node.lineno} {node.name}: {n} lines")
    assert long == []


def test_every_module_imports_first_in_a_fresh_process():
    """No import cycle, whatever a user imports first (the back ends import the filters' helpers)."""
    import subprocess
    import sys

    names = [".".join(p.relative_to(PACKAGE.parent).with_suffix("").parts) for p in sorted(PACKAGE.rglob("*.py"))]
    names = [n.removesuffix(".__init__") for n in names if not n.endswith("__main__")]
    code = "import importlib, sys\nfor n in sys.argv[1:]:\n    importlib.import_module(n)\n    " \
           "[sys.modules.pop(m) for m in list(sys.modules) if m == 'torchgi' or m.startswith('torchgi.')]\n"
    proc = subprocess.run([sys.executable, "-c", code, *names], capture_output=True, text=True, timeout=300,
                          check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_no_method_name_is_compared_outside_the_methods_package():
    """What a Denoiser method is lives in its class (torchgi/methods/): the shared pipeline, its
    deployed form and the TemporalDenoiser ask the class, never compare the method's name."""
    found = []
    for path in _modules():
        if "methods" in path.relative_to(PACKAGE).parts:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Compare):
                names = [n for n in [node.left, *node.comparators]
                         if isinstance(n, ast.Attribute) and n.attr in ("method", "spatial_method")
                         or isinstance(n, ast.Name) and n.id in ("method", "spatial")]
                strings = [n for n in ast.walk(node) if isinstance(n, ast.Constant) and n.value in methods.names()]
                if names and strings:
                    found.append(f"{path.relative_to(PACKAGE)}:{node.lineno}")
    assert found == []


def test_the_denoiser_class_keeps_the_shared_pipeline_only():
    tree = ast.parse((PACKAGE / "denoise.py").read_text())
    (cls,) = [n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "Denoiser"]
    assert cls.end_lineno - cls.lineno + 1 <= 200


def test_no_test_monkeypatches_a_settings_global():
    """Tests pass ``settings=`` (a :class:`torchgi.settings.Settings`) instead."""
    groups = ("PIPELINE", "GUIDED", "ATROUS", "BILATERAL", "TEMPORAL", "DEFAULTS")
    found = []
    for path in sorted((PACKAGE.parent / "tests").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "setattr"
                    and any(isinstance(a, ast.Constant) and a.value in groups for a in node.args)):
                found.append(f"{path.name}:{node.lineno}")
    assert found == []

