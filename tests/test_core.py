import sys

import pytest
import torch

from torchgi.core import (
    ConfigError,
    DeviceError,
    DTypeError,
    ExtraNotInstalledError,
    NonFiniteError,
    OptionError,
    RangeError,
    Registry,
    ShapeError,
    check_finite,
    check_option,
    check_range,
    check_same_device,
    check_shape,
    finite_or_sanitized_all,
    finite_or_sanitized_later,
    require,
)
from torchgi.filters import guided


def test_check_shape_binds_and_reuses_sizes():
    sizes = check_shape(torch.zeros(2, 3, 4, 5), "B C H W", "color")
    assert sizes == {"B": 2, "C": 3, "H": 4, "W": 5}
    check_shape(torch.zeros(2, 1, 4, 5), "B 1 H W", "depth", sizes)
    with pytest.raises(ShapeError, match=r"normal: dimension H is 6 but other inputs have H=4"):
        check_shape(torch.zeros(2, 3, 6, 5), "B 3 H W", "normal", sizes)


@pytest.mark.parametrize(
    "shape, spec, pattern",
    [((3, 4, 5), "B C H W", r"x: expected shape \(B, C, H, W\), got \(3, 4, 5\)"),
     ((1, 2, 4, 4), "B 3 H W", r"x: expected shape \(B, 3, H, W\), got \(1, 2, 4, 4\)")],
)
def test_check_shape_errors(shape, spec, pattern):
    with pytest.raises(ShapeError, match=pattern):
        check_shape(torch.zeros(shape), spec, "x")


def test_check_shape_rejects_non_tensor():
    with pytest.raises(DTypeError, match="color: expected a torch.Tensor, got list"):
        check_shape([1, 2], "B", "color")


def test_check_same_device_names_both():
    a = torch.zeros(1)
    b = torch.zeros(1, device="meta")
    with pytest.raises(DeviceError, match="normal is on meta but color is on cpu"):
        check_same_device({"color": a, "normal": b})


def test_check_finite_counts():
    x = torch.tensor([1.0, float("nan"), float("inf"), -float("inf"), float("nan")])
    with pytest.raises(NonFiniteError, match="color: expected finite values, found 2 NaN and 2 "):
        check_finite(x, "color")
    check_finite(torch.arange(3), "ints")  # integers are always finite


def test_finite_or_sanitized_all_names_the_bad_tensor():
    ok = torch.ones(2, 3)
    bad = torch.tensor([[1.0, float("inf")], [float("nan"), 0.0]])
    with pytest.raises(NonFiniteError, match="normal: expected finite values, found 1 NaN and 1 "):
        finite_or_sanitized_all({"color": ok, "normal": bad, "position": None}, False)
    # sums that overflow are no false alarm: float32 3e38 + 3e38 is inf, every term finite
    big = torch.full((2,), 3e38)
    half = torch.full((4,), 6e4, dtype=torch.float16)  # 2.4e5 > float16's 65504
    a, none, b = finite_or_sanitized_all({"big": big, "none": None, "half": half}, False)
    assert a is big and none is None and b is half
    with pytest.warns(UserWarning, match="normal: replaced 2 non-finite values by 0"):
        c, n = finite_or_sanitized_all({"color": ok, "normal": bad}, True)
    assert c is ok and torch.equal(n, torch.tensor([[1.0, 0.0], [0.0, 0.0]]))


def test_finite_or_sanitized_later_raises_only_when_checked():
    """The reductions are launched at once, the read back and the error wait for ``check()``
    (what a filter calls just before it returns)."""
    ok = torch.ones(2, 3)
    bad = torch.tensor([[1.0, float("inf")], [float("nan"), 0.0]])
    (c, n, x), check = finite_or_sanitized_later({"color": ok, "normal": bad, "position": None}, False)
    assert c is ok and n is bad and x is None  # nothing raised, nothing copied yet
    with pytest.raises(NonFiniteError, match="normal: expected finite values, found 1 NaN and 1 "):
        check()
    _, check = finite_or_sanitized_later({"big": torch.full((2,), 3e38)}, False)
    check()  # an overflowing sum of finite terms: no error
    with pytest.warns(UserWarning, match="normal: replaced 2 non-finite values by 0") as record:
        (c, n), check = finite_or_sanitized_later({"color": ok, "normal": bad}, True)
    check()  # sanitized: nothing left to check
    assert torch.equal(n, torch.tensor([[1.0, 0.0], [0.0, 0.0]]))
    assert record[0].filename == __file__  # the warning points at the caller's line


def test_sanitize_warning_points_at_the_users_line():
    """However deep inside torchgi the check runs (guided -> _guided -> ...), the warning names
    the line that called the filter."""
    src = torch.rand(1, 3, 8, 8)
    src[0, 0, 0, 0] = float("nan")
    line = sys._getframe().f_lineno + 2
    with pytest.warns(UserWarning, match="src: replaced 1 non-finite values by 0") as record:
        guided(src, torch.rand(1, 2, 8, 8), radius=2, sanitize=True)
    assert (record[0].filename, record[0].lineno) == (__file__, line)


def test_check_range_and_option():
    with pytest.raises(RangeError, match=r"albedo: expected values <= 1.0, found max 1.5"):
        check_range(torch.tensor([0.0, 1.5]), "albedo", 0.0, 1.0)
    with pytest.raises(OptionError, match=r"reduction: expected one of 'mean', 'none'; got 'sum'"):
        check_option("sum", "reduction", ("mean", "none"))


def test_require_names_extra():
    with pytest.raises(ExtraNotInstalledError, match=r"pip install 'torchgi\[render\]'"):
        require("definitely_not_a_module_xyz", "render")


def test_registry_build_and_unknown():
    reg = Registry("filter")

    @reg.register("affine")
    def affine(scale: float = 1.0, shift: float = 0.0):
        return lambda x: x * scale + shift

    assert reg.build({"type": "affine", "scale": 2.0}, shift=1.0)(3.0) == 7.0
    with pytest.raises(ConfigError, match=r"unknown filter type 'nope'; known: affine"):
        reg.build({"type": "nope"})
    with pytest.raises(ConfigError, match="'affine'.*unexpected keyword"):
        reg.build({"type": "affine", "sigma": 1})
    with pytest.raises(ConfigError, match="'type' key"):
        reg.build({"scale": 1})
    with pytest.raises(ValueError, match="already registered"):
        reg.register("affine")(affine)
