"""Slow, obviously correct float64 references, independent of the code under test."""

from __future__ import annotations

import math

import torch

from torchgi.render.camera import camera_rays


def box_oracle(x: torch.Tensor, r: int) -> torch.Tensor:
    """Count-normalised (2r+1)² mean in float64 by prefix sums, one axis at a time, each window's
    sum the difference of two prefix sums over its clipped extent, divided by that extent (a
    different algorithm from the torch code's average pools and the C kernels' running sums)."""
    x = x.double()
    for axis in (-1, -2):
        n = x.shape[axis]
        S = torch.cat([torch.zeros_like(x.narrow(axis, 0, 1)), x.cumsum(axis)], axis)
        j = torch.arange(n, device=x.device)
        lo, hi = (j - r).clamp(0, n), (j + r + 1).clamp(0, n)
        count = (hi - lo).to(x.dtype)
        x = (S.index_select(axis, hi) - S.index_select(axis, lo)) / (count if axis == -1 else count[:, None])
    return x


def guided_oracle(p: torch.Tensor, I: torch.Tensor, r: int, eps, coefficients: bool = False) -> torch.Tensor:
    """He et al.'s guided filter in float64 with torch.linalg.solve, no centring tricks (or its
    box-filtered coefficients ``(B, n + 1, C, H, W)``: a_0 .. a_{n-1}, b)."""
    p, I = p.double(), I.double()
    B, C, H, W = p.shape
    n = I.shape[1]
    mI, mp = box_oracle(I, r), box_oracle(p, r)
    II = torch.stack([box_oracle(I[:, i : i + 1] * I, r) for i in range(n)], 1)  # (B, n, n, H, W)
    Ip = torch.stack([box_oracle(I[:, i : i + 1] * p, r) for i in range(n)], 1)  # (B, n, C, H, W)
    sigma = II - mI[:, :, None] * mI[:, None]
    cov = Ip - mI[:, :, None] * mp[:, None]
    e = torch.as_tensor(eps, dtype=torch.float64).expand(n) if not torch.is_tensor(eps) or eps.dim() < 2 else eps
    if e.dim() == 4:  # a per-pixel map (B, 1 | n, H, W)
        diag = e.double().expand(B, n, H, W).permute(0, 2, 3, 1)
    else:
        diag = e.double().reshape(-1, n)[:, None, None].expand(B, 1, 1, n)
    A = sigma.permute(0, 3, 4, 1, 2) + torch.diag_embed(diag)
    a = torch.linalg.solve(A, cov.permute(0, 3, 4, 1, 2))  # (B, H, W, n, C)
    a = a.permute(0, 3, 4, 1, 2)  # (B, n, C, H, W)
    b = mp - (a * mI[:, :, None]).sum(1)
    ma = box_oracle(a.reshape(B, n * C, H, W), r).reshape(B, n, C, H, W)
    if coefficients:
        return torch.cat([ma, box_oracle(b, r)[:, None]], 1)
    return (ma * I[:, :, None]).sum(1) + box_oracle(b, r)


def block_means(x: torch.Tensor, s: int) -> torch.Tensor:
    """``s x s`` means of ``x (B, C, H, W)`` in float64 loops (partial blocks at the far edges
    average what exists)."""
    h, w = -(-x.shape[-2] // s), -(-x.shape[-1] // s)
    out = torch.zeros(x.shape[0], x.shape[1], h, w, dtype=torch.float64)
    for i in range(h):
        for j in range(w):
            out[:, :, i, j] = x[:, :, i * s : (i + 1) * s, j * s : (j + 1) * s].double().mean((2, 3))
    return out


def bilinear_rows(n_out: int, n_in: int, s: int) -> torch.Tensor:
    """``(n_out, n_in)`` float64 weights of bilinear upsampling by the factor ``s`` with pixel
    centres aligned (u = (i + 0.5) / s - 0.5, clamped to the image)."""
    rows = []
    for i in range(n_out):
        u = max((i + 0.5) / s - 0.5, 0.0)
        i0 = min(math.floor(u), n_in - 1)
        i1 = min(i0 + 1, n_in - 1)
        row = torch.zeros(n_in, dtype=torch.float64)
        row[i0] += 1 - (u - i0)
        row[i1] += u - i0
        rows.append(row)
    return torch.stack(rows)


def upsample(x: torch.Tensor, s: int, size: tuple[int, int]) -> torch.Tensor:
    """:func:`bilinear_rows` upsampling of ``x (..., h, w)`` to ``size`` by the factor ``s``."""
    return torch.einsum("Hh,...hw,Ww->...HW", bilinear_rows(size[0], x.shape[-2], s), x.double(),
                        bilinear_rows(size[1], x.shape[-1], s))


def fast_guided_oracle(p: torch.Tensor, I: torch.Tensor, r: int, eps, s: int) -> torch.Tensor:
    """He & Sun 2015 in float64 loops: s x s means (partial blocks at the far edges average what
    exists), coefficients at radius round(r / s), bilinear upsampling by the factor s with pixel
    centres aligned (u = (i + 0.5) / s - 0.5, clamped to the image; the same grid whatever the
    size, so tiles agree), applied to the full-resolution guide."""
    p, I = p.double(), I.double()
    co = guided_oracle(block_means(p, s), block_means(I, s), round(r / s), eps, coefficients=True)  # (B, n+1, C, h, w)
    up = upsample(co, s, p.shape[-2:])
    n = I.shape[1]
    return (up[:, :n] * I[:, :, None]).sum(1) + up[:, n]


def scene(B, H, W, n, seed=0, noise=0.5):
    """Piecewise-smooth guides with hard edges (discs over a sloped plane) and a noisy
    source that follows them — a stand-in for normal/depth guides and indirect light."""
    g = torch.Generator().manual_seed(seed)
    y, x = torch.meshgrid(torch.linspace(0, 1, H), torch.linspace(0, 1, W), indexing="ij")
    guides, clean = [], []
    for _ in range(B):
        layer = torch.stack([0.3 + 0.2 * x, 0.5 + 0.1 * y, 0.8 - 0.3 * x * y, 0.2 + 0.6 * y])
        for _ in range(6):
            cx, cy, rad = torch.rand(3, generator=g)
            inside = (x - cx) ** 2 + (y - cy) ** 2 < (0.1 + 0.2 * rad) ** 2
            layer = torch.where(inside, torch.rand(4, 1, 1, generator=g), layer)
        guides.append(layer[:n])
        clean.append(torch.stack([layer[0] * 2, layer[1 % n] + 0.5, layer[-1] * 3]))
    I, p = torch.stack(guides), torch.stack(clean)
    return p + noise * torch.randn(p.shape, generator=g), I


_B3 = (1 / 16, 1 / 4, 3 / 8, 1 / 4, 1 / 16)


def atrous_oracle(  # noqa: C901, PLR0912 - the oracle is one literal loop, to be read against docs/design.md, À-Trous
        color, normal=None, position=None, *, iterations, sigma_color=None, sigma_normal=0.1,
                  sigma_position=0.1, variance=None, color_weight=True, subsample=1, energy=False):
    """docs/design.md, À-Trous, pixel by pixel in float64 numpy (one image ``(C, H, W)``), literally:
    taps outside the image are skipped, σ_rt,i = 2^-i σ_rt, no centring or fusing."""
    import math

    import numpy as np

    def arr(t):
        return None if t is None else (t.detach().cpu().double().numpy() if torch.is_tensor(t) else np.asarray(t, float))

    c = arr(color).copy()
    n, x = arr(normal), arr(position)
    var = None if variance is None else np.broadcast_to(arr(variance), c.shape).copy()
    C, H, W = c.shape
    valid = np.ones((H, W), bool)
    fill = 0
    if subsample > 1:
        valid = (np.arange(H)[:, None] % subsample == 0) & (np.arange(W)[None, :] % subsample == 0)
        c = c * valid
        fill = int(math.log2(subsample))
    if var is None:
        sc = max(c.max(), np.finfo(np.float32).tiny) if sigma_color is None else arr(sigma_color)
    else:
        sc = 4.0 if sigma_color is None else arr(sigma_color)
    sc = sc.reshape(H, W) if np.size(sc) == H * W and H * W > 1 else float(sc)  # a map, or one value
    total_in = c.sum(axis=(1, 2))
    for i in range(iterations):
        s = 2**i
        use_c = color_weight and i >= fill
        if var is not None:
            pad = np.pad(var, ((0, 0), (1, 1), (1, 1)), mode="edge")
            k = np.array([0.25, 0.5, 0.25])
            blur = sum(k[a] * k[b] * pad[:, a : a + H, b : b + W] for a in range(3) for b in range(3)).sum(0)
        out = c.copy()
        var_out = None if var is None else var.copy()
        new_valid = np.zeros((H, W), bool)
        for py in range(H):
            for px in range(W):
                num = np.zeros(C)
                den = 0.0
                vnum = np.zeros(C)
                for ky in range(5):
                    for kx in range(5):
                        qy, qx = py + (ky - 2) * s, px + (kx - 2) * s
                        if not (0 <= qy < H and 0 <= qx < W) or not valid[qy, qx]:
                            continue
                        d = 0.0
                        if use_c:
                            dc = float(((c[:, py, px] - c[:, qy, qx]) ** 2).sum())
                            sp = float(sc[py, px]) if np.ndim(sc) == 2 else sc  # a per-pixel map: this pixel's
                            d += dc / (sp * sp * blur[py, px] + 1e-12) if var is not None else dc / (sp * 2.0**-i)
                        if n is not None and sigma_normal is not None:
                            d += float(((n[:, py, px] - n[:, qy, qx]) ** 2).sum()) / (s * s * sigma_normal)
                        if x is not None and sigma_position is not None:
                            d += float(((x[:, py, px] - x[:, qy, qx]) ** 2).sum()) / sigma_position
                        w = _B3[ky] * _B3[kx] * math.exp(-d)
                        num += w * c[:, qy, qx]
                        den += w
                        if var is not None:
                            vnum += w * w * var[:, qy, qx]
                if den > 0:
                    out[:, py, px] = num / den
                    if var is not None:
                        var_out[:, py, px] = vnum / den**2
                    new_valid[py, px] = True
        c, var = out, var_out
        if subsample > 1:
            valid = new_valid
    if energy:
        total_out = c.sum(axis=(1, 2))
        c = c * np.where(total_out != 0, total_in / np.where(total_out != 0, total_out, 1), 1)[:, None, None]
    return c


# Weight subsets of the kernel tests (c colour, n normal, x position), then variance guidance and
# sub-sampling: a level kernel against atrous_oracle (tests/backends/test_native.py, tests/backends/test_gpu.py).
ATROUS_CASES = ["cnx", "c", "nx", "cn", "", "variance", "subsample"]


def atrous_case(C: int, case: str):
    """12 x 70 buffers (wide enough for the CPU kernel's vector blocks at steps 1, 2, 4) and the
    ``atrous`` arguments of ``case``; distances stay where exp(-d) > 0 in float32."""
    g = torch.Generator().manual_seed(C)
    H, W = 12, 70
    c = torch.rand(1, C, H, W, generator=g) * 2
    n = torch.nn.functional.normalize(torch.randn(1, 3, H, W, generator=g), dim=1)
    x = torch.rand(1, 3, H, W, generator=g)
    kw = {"iterations": 3, "sigma_color": 0.5, "sigma_normal": 0.2 if "n" in case else None,
              "sigma_position": 0.3 if "x" in case else None, "color_weight": "c" in case}
    if case == "variance":
        kw = {"iterations": 3, "variance": torch.rand(1, 1, H, W, generator=g) * 0.1}
    if case == "subsample":
        kw = {"iterations": 3, "sigma_color": 1.0, "subsample": 2}
    return c, n, x, kw


def atrous_error(out: torch.Tensor, c, n, x, kw) -> float:
    """Max error of image 0 of ``out`` against :func:`atrous_oracle`, relative to its maximum."""
    from tests.helpers import rel_error

    want = atrous_oracle(c[0], n[0], x[0], **{k: v[0] if torch.is_tensor(v) else v for k, v in kw.items()})
    return rel_error(out[0], want)


def bilateral_oracle(color, guides, *, radius, sigma_space, sigma_color, sigma_guides):
    """Joint bilateral pixel by pixel in float64 numpy (one image ``(C, H, W)``); a σ may be an
    ``(H, W)`` map (the centre pixel's σ)."""
    import math

    import numpy as np

    c = color.detach().double().numpy()
    gs = [g.detach().double().numpy() for g in guides]
    C, H, W = c.shape

    def at(s, y, x):
        return float(s[y, x]) if torch.is_tensor(s) else s

    out = np.empty_like(c)
    for py in range(H):
        for px in range(W):
            num, den = np.zeros(C), 0.0
            for qy in range(max(py - radius, 0), min(py + radius, H - 1) + 1):
                for qx in range(max(px - radius, 0), min(px + radius, W - 1) + 1):
                    e = ((qy - py) ** 2 + (qx - px) ** 2) / (2 * at(sigma_space, py, px) ** 2)
                    if sigma_color is not None:
                        e += ((c[:, py, px] - c[:, qy, qx]) ** 2).sum() / (2 * at(sigma_color, py, px) ** 2)
                    for g, s in zip(gs, sigma_guides):
                        e += ((g[:, py, px] - g[:, qy, qx]) ** 2).sum() / (2 * at(s, py, px) ** 2)
                    w = math.exp(-e)
                    num += w * c[:, qy, qx]
                    den += w
            out[:, py, px] = num / den
    return out


def z_pass_rate(a, b, threshold=3.0):
    """Per-pixel Z-test of two sets of independent renders ``(K, C, H, W)`` (K seeds each):
    the fraction of pixel channels whose means agree within ``threshold`` standard errors.
    Pixels where both sets are constant (zero variance) pass when equal to 1e-5 relative."""
    ma, mb = a.double().mean(0), b.double().mean(0)
    va, vb = a.double().var(0) / a.shape[0], b.double().var(0) / b.shape[0]
    var = va + vb
    z = (ma - mb).abs() / var.sqrt().clamp(min=1e-300)
    exact = (ma - mb).abs() <= 1e-5 * torch.maximum(ma.abs(), mb.abs()) + 1e-7
    ok = torch.where(var > 0, z < threshold, exact)
    return ok.double().mean().item()


def mean_z(a, b):
    """The Welch z of the image means of two sets of independent renders ``(K, C, H, W)``: each
    render's mean over its pixels and channels is one sample; a global bias (a 2 % scale) shows
    here however well the per-pixel test passes. 0 when both sets are constant and equal."""
    ma, mb = a.double().flatten(1).mean(1), b.double().flatten(1).mean(1)
    se = (ma.var() / len(ma) + mb.var() / len(mb)).sqrt()
    d = (ma.mean() - mb.mean()).abs()
    return float(d / se) if se > 0 else (0.0 if d <= 1e-7 * ma.mean().abs() + 1e-12 else float("inf"))


# ------------------------------------------------------------------------------ motion of moving geometry
def _barycentric(tri: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Barycentric (b1, b2) of points ``p (N, 3)`` in the planes of triangles ``tri (N, 3, 3)``, float64."""
    e1, e2, d = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], p - tri[:, 0]
    g = torch.stack([torch.stack([(e1 * e1).sum(1), (e1 * e2).sum(1)], 1),
                     torch.stack([(e1 * e2).sum(1), (e2 * e2).sum(1)], 1)], 1)
    return torch.linalg.solve(g, torch.stack([(d * e1).sum(1), (d * e2).sum(1)], 1))


def _plane_hit(camera, y: torch.Tensor, tri: torch.Tensor) -> torch.Tensor:
    """Barycentric coordinates where the camera rays through image points ``y (N, 2)`` (pixels,
    x right, y down) meet the planes of ``tri``: the renderer's own ray generation."""
    origin, d = camera_rays(camera, torch.zeros(len(y), dtype=torch.int64), y.T.float())
    o, d = origin.double()[:, 0], d.double().T
    n = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    t = ((tri[:, 0] - o) * n).sum(1) / (d * n).sum(1)
    return _barycentric(tri, o + d * t[:, None])


def where_rendered(camera, tri: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The image point ``(N, 2)`` of ``camera`` whose ray meets triangle ``tri`` at barycentric
    ``target``, by Newton's method on ray casting (finite-difference Jacobian, pseudo-inverse:
    a triangle seen edge on has none), and whether it converged (the last step below 1e-4 px;
    not: edge on, behind the camera)."""
    y = torch.full((len(tri), 2), 0.5, dtype=torch.float64) * torch.tensor(camera.resolution, dtype=torch.float64)
    h = 1e-2
    for _ in range(10):
        b = _plane_hit(camera, y, tri)
        jx = (_plane_hit(camera, y + torch.tensor([h, 0.0]), tri) - b) / h
        jy = (_plane_hit(camera, y + torch.tensor([0.0, h]), tri) - b) / h
        J = torch.nan_to_num(torch.stack([jx, jy], 2), nan=0.0, posinf=0.0, neginf=0.0)
        step = (torch.linalg.pinv(J) @ torch.nan_to_num(target - b)[..., None])[..., 0]
        step = step.clamp(-4 * max(camera.resolution), 4 * max(camera.resolution))
        y = y + step
    return y, (step.abs().amax(1) < 1e-4) & torch.isfinite(y).all(1)


def motion_oracle(now, before) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The backward motion ``(2, H, W)`` float64 of scene ``now`` (posed at its time) into scene
    ``before`` found by ray casting, not by projection: each pixel centre's first-hit triangle and
    barycentric point, then the image point of ``before``'s camera whose ray meets that triangle
    (posed as ``before`` poses it) at that point (:func:`where_rendered`). Also ``visible (H, W)``:
    a hit found (Newton converged) inside ``before``'s image whose ray there meets the same
    triangle first, and
    ``moving (H, W)``: a hit on a mesh with a path."""
    from torchgi.render.accel import Accel

    W, H = now.camera.resolution
    a_now, a_before = now.arrays(), before.arrays()
    origin, d = camera_rays(now.camera, torch.arange(W * H), None)
    t, prim = Accel(a_now.triangles).intersect(origin, d)
    hit = prim >= 0
    p = (origin + d * t).T.double()[hit]
    target = _barycentric(torch.from_numpy(a_now.triangles).double()[prim[hit]], p)
    y, converged = where_rendered(before.camera, torch.from_numpy(a_before.triangles).double()[prim[hit]], target)
    y = torch.where(converged[:, None], y, -1.0)
    inside = converged & (y[:, 0] >= 0) & (y[:, 0] < W) & (y[:, 1] >= 0) & (y[:, 1] < H)
    o2, d2 = camera_rays(before.camera, torch.zeros(len(y), dtype=torch.int64), y.T.float())
    _, prim2 = Accel(a_before.triangles).intersect(o2, d2)
    pix = torch.arange(W * H)[hit]
    centre = torch.stack([pix % W, pix // W], 1).double() + 0.5
    ref = torch.zeros(2, W * H, dtype=torch.float64)
    ref[:, hit] = (y - centre).T
    visible = torch.zeros(W * H, dtype=torch.bool)
    visible[hit] = inside & (prim2 == prim[hit])
    moving = torch.zeros(W * H, dtype=torch.bool)
    moving[hit] = torch.isin(torch.from_numpy(a_now.mesh)[prim[hit]], torch.tensor(now.moving, dtype=torch.int64))
    return ref.reshape(2, H, W), visible.reshape(H, W), moving.reshape(H, W)


def apply_kernels_oracle(x: torch.Tensor, w: torch.Tensor, d: int, normalize: bool) -> torch.Tensor:
    """Per-pixel kernels in float64 by gathering: for each tap, the source coordinates of every
    pixel computed and tested against the image bounds (no padding), out-of-image taps dropped
    from the sum and from the weight sum. Differentiable (autograd through the gathers)."""
    x, w = x.double(), w.double()
    B, C, H, W = x.shape
    k = round(w.shape[1] ** 0.5)
    ys, xs = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    out = torch.zeros(B, C, H, W, dtype=torch.float64)
    den = torch.zeros(B, 1, H, W, dtype=torch.float64)
    for i in range(k):
        for j in range(k):
            sy, sx = ys + (i - k // 2) * d, xs + (j - k // 2) * d
            inside = ((sy >= 0) & (sy < H) & (sx >= 0) & (sx < W)).double()
            src = x[:, :, sy.clamp(0, H - 1), sx.clamp(0, W - 1)] * inside
            wt = w[:, i * k + j : i * k + j + 1] * inside
            out = out + wt * src
            den = den + wt
    return out / den if normalize else out
