"""Triangle meshes from OBJ and PLY files, read with numpy (other formats through trimesh).

Reading the Stanford bunny (69k triangles) this way takes tens of milliseconds; importing trimesh
alone (with scipy) costs about a second, which a short render would otherwise pay on every
start. Polygons are cut into triangles as trimesh cuts them, in its order.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from torchgi.core.check import require
from torchgi.core.errors import ConfigError

__all__ = ["PACKAGE_MESHES", "mesh_root", "read_mesh"]

PACKAGE_MESHES = Path(__file__).resolve().parents[1] / "meshes"
"""The meshes shipped as package data (pyproject.toml): the Cornell box and the Stanford models."""

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
    "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}


def read_mesh(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """The vertices ``(V, 3)`` float64 and triangles ``(F, 3)`` int64 (0-based) of a mesh file.

    OBJ (``v`` and ``f`` lines; ``i``, ``i/j``, ``i//k``, ``i/j/k`` and negative indices) and PLY
    (ASCII or binary, either byte order) are read here; any other format through trimesh. Raises
    ``FileNotFoundError`` for a missing file and :class:`~torchgi.core.ConfigError` naming the
    file for one that cannot be read.

    Example:
        >>> import tempfile
        >>> with tempfile.NamedTemporaryFile("w", suffix=".obj", delete=False) as f:
        ...     _ = f.write("v 0 0 0\\nv 1 0 0\\nv 1 1 0\\nv 0 1 0\\nf 1 2 3 4\\n")
        >>> v, faces = read_mesh(f.name)
        >>> v.shape, faces.tolist()
        ((4, 3), [[0, 1, 2], [2, 3, 0]])
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"mesh file {path!r} does not exist")
    ext = os.path.splitext(path)[1].lower()
    try:
        if ext == ".obj":
            return _obj(path)
        if ext == ".ply":
            return _ply(path)
    except (ValueError, IndexError, KeyError, UnicodeDecodeError) as exc:
        raise ConfigError(f"could not read mesh {path!r}: {exc}") from exc
    trimesh = require("trimesh", "render")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise ConfigError(f"could not read mesh {path!r}: {exc}") from exc
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


def _fans(polygons: list[list[int]]) -> np.ndarray:
    """Triangles of polygons in trimesh's order (so scenes render as they did through trimesh):
    the triangles, then every quad's ``(0, 1, 2)``, then every quad's ``(2, 3, 0)``, then the fans
    ``(0, k, k + 1)`` of larger polygons."""
    tri = [p for p in polygons if len(p) == 3]
    quad = np.array([p for p in polygons if len(p) == 4], dtype=np.int64).reshape(-1, 4)
    fans = [(p[0], p[k], p[k + 1]) for p in polygons if len(p) > 4 for k in range(1, len(p) - 1)]
    return np.concatenate([np.array(tri, dtype=np.int64).reshape(-1, 3), quad[:, [0, 1, 2]], quad[:, [2, 3, 0]],
                           np.array(fans, dtype=np.int64).reshape(-1, 3)])


def _numbers(lines: list[str], dtype: type, per_line: int, joined: str | None = None) -> np.ndarray | None:
    """The numbers of ``lines`` (each with ``per_line`` of them; ``joined``: the lines joined by
    spaces, when the caller has it), or None where that fails."""
    if not lines:
        return np.zeros((0, per_line), dtype=dtype)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # numpy's note on text it could not read to the end
        values = np.fromstring(" ".join(lines) if joined is None else joined, dtype=dtype, sep=" ")
    return values.reshape(-1, per_line) if values.size == per_line * len(lines) else None


def _obj(path: str) -> tuple[np.ndarray, np.ndarray]:
    with open(path, encoding="utf-8", errors="strict") as fh:
        lines = fh.read().splitlines()
    vs = [ln[2:] for ln in lines if ln.startswith(("v ", "v\t"))]
    vertices = _numbers(vs, np.float64, 3)
    if vertices is None:  # a w coordinate or vertex colours: the first three numbers of each line
        rows = [v.split()[:3] for v in vs]
        if any(len(r) != 3 for r in rows):
            raise ValueError("a vertex line without 3 coordinates")
        vertices = np.array(rows, dtype=np.float64).reshape(-1, 3)
    faces = [ln[2:] for ln in lines if ln.startswith(("f ", "f\t"))]
    joined = " ".join(faces)
    if "/" not in joined and all(f.strip().count(" ") == 2 for f in faces):  # triangles "i j k": one parse
        idx = _numbers(faces, np.int64, 3, joined)
        if idx is not None:
            return vertices, _resolve(idx, len(vertices))
    polygons = [[int(t.split("/")[0]) for t in f.split()] for f in faces]
    return vertices, _resolve(_fans([p for p in polygons if len(p) >= 3]), len(vertices))


def _resolve(idx: np.ndarray, n: int) -> np.ndarray:
    """OBJ's 1-based (negative: from the end) indices -> 0-based, all within ``n`` vertices."""
    idx = np.where(idx < 0, idx + n, idx - 1)
    if idx.size and (idx.min() < 0 or idx.max() >= n):
        raise ValueError(f"a face index outside the {n} vertices")
    return idx


def _ply(path: str) -> tuple[np.ndarray, np.ndarray]:
    with open(path, "rb") as fh:
        data = fh.read()
    end = data.index(b"end_header")
    body = data[data.index(b"\n", end) + 1 :]
    header = data[:end].decode("ascii").splitlines()
    if not header or header[0].strip() != "ply":
        raise ValueError("not a PLY file")
    fmt, elements = "", []  # [name, count, [(property, type) | (property, count type, index type)]]
    for line in header[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append([words[1], int(words[2]), []])
        elif words[0] == "property":
            elements[-1][2].append((words[-1], *words[1:-1]))
    if fmt == "ascii":
        return _ply_ascii(body, elements)
    order = {"binary_little_endian": "<", "binary_big_endian": ">"}[fmt]
    vertices = faces = None
    offset = 0
    for name, count, props in elements:
        if all(p[1] != "list" for p in props):
            dtype = np.dtype([(p[0], order + _PLY_TYPES[p[1]]) for p in props])
            table = np.frombuffer(body, dtype, count, offset)
            offset += count * dtype.itemsize
            if name == "vertex":
                vertices = np.stack([table[c].astype(np.float64) for c in ("x", "y", "z")], 1)
        elif name == "face" and len(props) == 1:
            faces, offset = _ply_faces(body, offset, count, order, props[0])
        else:
            raise ValueError(f"PLY element {name!r} with list properties is not supported here")
    if vertices is None or faces is None:
        raise ValueError("no vertex or face element")
    return vertices, _checked(faces, len(vertices))


def _ply_faces(body: bytes, offset: int, count: int, order: str, prop: tuple) -> tuple[np.ndarray, int]:
    n_type, i_type = np.dtype(order + _PLY_TYPES[prop[2]]), np.dtype(order + _PLY_TYPES[prop[3]])
    first = int(np.frombuffer(body, n_type, 1, offset)[0]) if count else 3
    row = np.dtype([("n", n_type), ("i", i_type, (first,))])
    table = np.frombuffer(body, row, count, offset) if len(body) >= offset + count * row.itemsize else None
    if table is not None and bool((table["n"] == first).all()):  # every face the same size: one view
        return _fans_of(table["i"].astype(np.int64)), offset + count * row.itemsize
    polygons = []
    for _ in range(count):
        k = int(np.frombuffer(body, n_type, 1, offset)[0])
        offset += n_type.itemsize
        polygons.append(np.frombuffer(body, i_type, k, offset).tolist())
        offset += k * i_type.itemsize
    return _fans(polygons), offset


def _fans_of(idx: np.ndarray) -> np.ndarray:
    """Fans of equal-sized polygons ``(F, k)`` -> ``(F (k - 2), 3)``."""
    return idx if idx.shape[1] == 3 else _fans(idx.tolist())


def _ply_ascii(body: bytes, elements: list) -> tuple[np.ndarray, np.ndarray]:
    lines = iter(body.decode("ascii").splitlines())
    vertices = faces = None
    for name, count, props in elements:
        rows = [next(lines).split() for _ in range(count)]
        if name == "vertex":
            cols = [i for i, p in enumerate(props) if p[0] in ("x", "y", "z")]
            vertices = np.array([[float(r[c]) for c in cols] for r in rows], dtype=np.float64).reshape(-1, 3)
        elif name == "face":
            faces = _fans([[int(t) for t in r[1 : 1 + int(r[0])]] for r in rows])
    if vertices is None or faces is None:
        raise ValueError("no vertex or face element")
    return vertices, _checked(faces, len(vertices))


def _checked(faces: np.ndarray, n: int) -> np.ndarray:
    if faces.size and (faces.min() < 0 or faces.max() >= n):
        raise ValueError(f"a face index outside the {n} vertices")
    return faces


def mesh_root() -> Path:
    """The folder that scene files' ``mesh:`` entries are relative to: ``$TORCHGI_MESHES`` when
    set (and not empty), else the package's own ``torchgi/meshes``, which ships the Cornell
    box and the Stanford models the scene configs use (each folder's ``SOURCE.txt`` and the
    folder's ``README.md`` give their sources and terms). A folder named by ``TORCHGI_MESHES`` is
    not checked here: a scene that names a mesh missing from it says where it looked.

    Example:
        >>> (mesh_root() / "stanford_bunny" / "stanford-bunny.ply").is_file()
        True
    """
    env = os.environ.get("TORCHGI_MESHES")
    if env:
        return Path(env)
    return PACKAGE_MESHES
