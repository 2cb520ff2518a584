import numpy as np
import pytest
import torch

from torchgi import GBuffer
from torchgi.core import DeviceError, DTypeError, LayerError, NonFiniteError, ShapeError

pytest.importorskip("OpenEXR")


def make(B=2, H=6, W=5, dtype=torch.float32, device="cpu"):
    g = torch.Generator().manual_seed(0)

    def r(c):
        return torch.rand(B, c, H, W, generator=g, dtype=torch.float64).to(device=device, dtype=dtype)

    hit = torch.rand(B, 1, H, W, generator=g) > 0.3
    return GBuffer(
        direct=r(3), indirect=r(3), emission=r(3), albedo=r(3), normal=r(3) * 2 - 1,
        position=r(3) * 10, depth=r(1), variance=r(1),
        spp=torch.randint(1, 9, (B, 1, H, W), generator=g).to(device), hit=hit.to(device),
    )


def test_color_is_sum_of_parts(device, dtype):
    gb = make(device=device, dtype=dtype)
    torch.testing.assert_close(gb.color, gb.emission + gb.direct + gb.indirect)
    assert gb.dtype == dtype and gb.device.type == device.type


def test_validation_errors():
    with pytest.raises(ShapeError, match=r"normal: expected shape \(B, 3, H, W\), got \(1, 2, 4, 4\)"):
        GBuffer(color=torch.rand(1, 3, 4, 4), normal=torch.rand(1, 2, 4, 4))
    with pytest.raises(ShapeError, match="depth: dimension W is 5 but other inputs have W=4"):
        GBuffer(color=torch.rand(1, 3, 4, 4), depth=torch.rand(1, 1, 4, 5))
    with pytest.raises(DTypeError, match="albedo is torch.float64 but color is torch.float32"):
        GBuffer(color=torch.rand(1, 3, 4, 4), albedo=torch.rand(1, 3, 4, 4, dtype=torch.float64))
    with pytest.raises(DTypeError, match="spp: expected an integer tensor"):
        GBuffer(color=torch.rand(1, 3, 4, 4), spp=torch.ones(1, 1, 4, 4))
    with pytest.raises(DTypeError, match="hit: expected a bool tensor"):
        GBuffer(color=torch.rand(1, 3, 4, 4), hit=torch.ones(1, 1, 4, 4, dtype=torch.int64))
    bad = torch.zeros(1, 3, 4, 4)
    bad[0, 1, 2, 2] = float("nan")
    with pytest.raises(NonFiniteError, match="normal: expected finite values, found 1 NaN"):
        GBuffer(color=torch.rand(1, 3, 4, 4), normal=bad)
    with pytest.raises(DeviceError, match="normal is on meta but color is on cpu"):
        GBuffer(color=torch.rand(1, 3, 4, 4), normal=torch.rand(1, 3, 4, 4, device="meta"))
    with pytest.raises(ShapeError, match="at least one field"):
        GBuffer()


def test_crop_slice_cat_match_indexing():
    gb = make(B=3)
    c = gb.crop(1, 2, 4, 3)
    for name, t in c.items():
        torch.testing.assert_close(t, getattr(gb, name)[:, :, 1:5, 2:5], rtol=0, atol=0)
    one = gb[-1]
    assert one.shape == (1, 6, 5)
    torch.testing.assert_close(one.normal, gb.normal[2:3], rtol=0, atol=0)
    both = GBuffer.cat([gb[0], gb[1:3]])
    for name, t in both.items():
        assert torch.equal(t, getattr(gb, name))
    with pytest.raises(ShapeError, match="does not fit"):
        gb.crop(4, 0, 4, 2)
    with pytest.raises(LayerError, match="buffers\\[1\\] has fields"):
        GBuffer.cat([gb, GBuffer(color=gb.color)])


def test_to_casts_only_float_fields():
    gb = make().to(dtype=torch.float64)
    assert gb.color.dtype == torch.float64 and gb.spp.dtype == torch.int64 and gb.hit.dtype == torch.bool
    with pytest.raises(DTypeError):
        gb.to(dtype=torch.int32)


def test_numpy_round_trip():
    gb = make(B=1)
    arr = gb.numpy("normal")
    assert arr.shape == (6, 5, 3)
    np.testing.assert_array_equal(arr[2, 3], gb.normal[0, :, 2, 3].numpy())
    back = GBuffer.from_numpy(normal=arr, depth=gb.numpy("depth"))
    assert torch.equal(back.normal, gb.normal)
    with pytest.raises(LayerError, match="'albedo' is not present"):
        GBuffer(color=gb.color).numpy("albedo")


def test_exr_round_trip_is_exact(tmp_path):
    gb = make(B=1)
    gb.to_exr(tmp_path / "g.exr")
    back = GBuffer.from_exr(tmp_path / "g.exr")
    assert [n for n, _ in back.items()] == [n for n, _ in gb.items()]
    for name, t in gb.items():
        got = getattr(back, name)
        assert got.dtype == t.dtype, name
        assert torch.equal(got, t), name


def test_exr_batch_writes_numbered_files_and_never_overwrites(tmp_path):
    gb = make(B=2)
    paths = gb.to_exr(tmp_path / "g.exr")
    assert [p.rsplit("/", 1)[1] for p in paths] == ["g_0000.exr", "g_0001.exr"]
    before = (tmp_path / "g_0001.exr").read_bytes()
    with pytest.raises(FileExistsError, match="exists; pass overwrite=True"):
        gb.to_exr(tmp_path / "g.exr")
    assert (tmp_path / "g_0001.exr").read_bytes() == before
    second = GBuffer.from_exr(tmp_path / "g_0001.exr")
    assert torch.equal(second.indirect, gb.indirect[1:2])


def test_from_exr_rejects_or_sanitizes_nonfinite(tmp_path):
    from torchgi.io import write_exr

    color = torch.rand(3, 4, 4)
    color[1, 1, 1] = float("inf")
    write_exr(tmp_path / "c.exr", {"color": color})
    with pytest.raises(NonFiniteError, match="layer color"):
        GBuffer.from_exr(tmp_path / "c.exr")
    with pytest.warns(UserWarning, match="replaced 1 non-finite"):
        gb = GBuffer.from_exr(tmp_path / "c.exr", sanitize=True)
    assert gb.color[0, 1, 1, 1] == 0 and torch.isfinite(gb.color).all()
