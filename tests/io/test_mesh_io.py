"""``torchgi.io.read_mesh``: OBJ and PLY read with numpy, against hand-written files and against
trimesh (the reader scenes used before) on every mesh the project and its benchmarks load."""

from __future__ import annotations

import glob
import os
import struct

import numpy as np
import pytest

from torchgi.core import ConfigError
from torchgi.io.mesh import read_mesh

CONFIG_MESHES = os.path.join(os.path.dirname(__file__), "..", "..", "configs", "scenes", "meshes")


def test_obj_index_forms_negative_indices_and_polygons(tmp_path):
    path = tmp_path / "m.obj"
    path.write_text(
        "# a comment\nv 0 0 0\nv 1 0 0 1.0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\n"
        "f 1/1/1 2/1/1 3/1/1\n"  # v/vt/vn
        "f 1//1 3//1 4//1\n"  # v//vn
        "f -4 -3 -2 -1\n"  # negative = from the end; a quad
        "f 1 2 3 4 1\n"  # a pentagon (degenerate, but legal): a fan
        "o name\ng group\ns off\n"
    )
    v, f = read_mesh(path)
    assert v.tolist() == [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]  # the w coordinate dropped
    # trimesh's order: triangles, then the quads' (0, 1, 2), their (2, 3, 0), then fans
    assert f.tolist() == [[0, 1, 2], [0, 2, 3], [0, 1, 2], [2, 3, 0], [0, 1, 2], [0, 2, 3], [0, 3, 0]]


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_ascii_and_binary_with_extra_properties(tmp_path, fmt):
    verts = [(0.0, 0.0, 0.0, 7), (2.0, 0.0, 0.0, 7), (2.0, 3.0, 0.0, 7), (0.0, 3.0, 1.5, 7)]
    faces = [(0, 1, 2), (0, 2, 3, 1)]
    header = (f"ply\nformat {fmt} 1.0\ncomment hand-made\nelement vertex 4\nproperty float x\n"
              "property double y\nproperty float z\nproperty uchar red\nelement face 2\n"
              "property list uchar int vertex_indices\nend_header\n")
    if fmt == "ascii":
        body = "".join(f"{x} {y} {z} {r}\n" for x, y, z, r in verts) + \
            "".join(f"{len(p)} {' '.join(map(str, p))}\n" for p in faces)
        data = header.encode() + body.encode()
    else:
        e = "<" if fmt == "binary_little_endian" else ">"
        data = header.encode() + b"".join(struct.pack(e + "fdfB", *v) for v in verts) + \
            b"".join(struct.pack(e + "B" + "i" * len(p), len(p), *p) for p in faces)
    path = tmp_path / "m.ply"
    path.write_bytes(data)
    v, f = read_mesh(path)
    assert v.tolist() == [list(p[:3]) for p in verts]
    assert f.tolist() == [[0, 1, 2], [0, 2, 3], [3, 1, 0]]


def test_bad_and_missing_files_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.obj"):
        read_mesh(tmp_path / "nope.obj")
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")
    with pytest.raises(ConfigError, match="bad.obj.*outside the 3 vertices"):
        read_mesh(bad)
    ply = tmp_path / "bad.ply"
    ply.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nend_header\n")
    with pytest.raises(ConfigError, match="bad.ply"):
        read_mesh(ply)


def test_same_triangles_as_trimesh_on_every_mesh_scenes_load(meshes_dir):
    trimesh = pytest.importorskip("trimesh")
    files = sorted(glob.glob(os.path.join(CONFIG_MESHES, "*.obj")) + glob.glob(os.path.join(meshes_dir, "*", "*.obj"))
                   + glob.glob(os.path.join(meshes_dir, "*", "*.ply")))
    assert len(files) >= 10
    for path in files:
        v, f = read_mesh(path)
        ref = trimesh.load(path, force="mesh", process=False)
        # the same triangles, corner for corner and in the same order (so renders are unchanged)
        assert np.array_equal(v[f], np.asarray(ref.vertices, dtype=np.float64)[np.asarray(ref.faces)]), path
