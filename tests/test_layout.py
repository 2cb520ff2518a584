"""The layout rules of the back-end seam, read from the source: no module of torchgi outside
torchgi/backends imports the C or Triton kernels, and every public function outside the back
ends fits on a screen (at most 60 lines of code, its docstring, comments and blank lines not
counted)."""

from __future__ import annotations

import ast
import io
import tokenize
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "torchgi"
KERNELS = ("c_kernels", "triton_kernels", "_native")
MAX_LINES = 60


def _modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        if "backends" not in path.relative_to(PACKAGE).parts:
            yield path


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
