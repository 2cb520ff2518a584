"""PNG previews: what Pillow decodes is what was written; files are never overwritten unasked."""

import numpy as np
import pytest
import torch
from PIL import Image

from torchgi.io import to_srgb8, write_png


@pytest.mark.parametrize("shape", [(5, 7, 3), (5, 7), (1, 1, 3)])
def test_pillow_reads_back_the_pixels(tmp_path, shape):
    pixels = np.random.default_rng(0).integers(0, 256, shape, dtype=np.uint8)
    path = write_png(tmp_path / "a.png", pixels)
    with Image.open(path) as im:
        assert im.format == "PNG" and im.mode == ("RGB" if len(shape) == 3 else "L")
        np.testing.assert_array_equal(np.asarray(im), pixels)


def test_no_overwrite_unless_asked(tmp_path):
    path = write_png(tmp_path / "a.png", np.zeros((2, 2, 3), np.uint8))
    with pytest.raises(FileExistsError, match="overwrite=True"):
        write_png(path, np.ones((2, 2, 3), np.uint8))
    write_png(path, np.full((2, 2, 3), 9, np.uint8), overwrite=True)
    with Image.open(path) as im:
        assert np.asarray(im).max() == 9
    assert [p.name for p in tmp_path.iterdir()] == ["a.png"]  # no temporary left


def test_bad_pixels_are_named(tmp_path):
    with pytest.raises(ValueError, match="pixels: expected uint8"):
        write_png(tmp_path / "a.png", np.zeros((2, 2, 3), np.float32))
    with pytest.raises(ValueError, match="pixels"):
        write_png(tmp_path / "a.png", np.zeros((2, 2, 4), np.uint8))


def test_srgb_encoding_against_the_formula():
    """0.5 linear is 0.7354 in sRGB (IEC 61966-2-1): 188 of 255; 0.002 is on the linear toe."""
    out = to_srgb8(torch.tensor([0.5, 0.002, 2.0]).view(3, 1, 1))
    assert out[0, 0].tolist() == [188, round(0.002 * 12.92 * 255), 255]


@pytest.mark.parametrize("mask", [0o022, 0o077])
def test_written_files_have_the_umasks_permissions(tmp_path, mask):
    """Issue 69: EXR files were written ``-rw-------`` whatever the umask (renamed from a
    ``mkstemp`` file); every file torchgi writes atomically has ``0o666`` less the umask, as one
    ``open()`` creates."""
    import os
    import stat

    from torchgi.io import write_exr

    old = os.umask(mask)
    try:
        paths = [write_exr(tmp_path / "a.exr", {"color": torch.rand(3, 4, 5)}),
                 write_png(tmp_path / "a.png", np.zeros((4, 5, 3), np.uint8))]
    finally:
        os.umask(old)
    for path in paths:
        assert stat.S_IMODE(os.stat(path).st_mode) == 0o666 & ~mask, path
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.exr", "a.png"]  # no temporary left
