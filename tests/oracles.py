"""Slow, obviously correct float64 references, independent of the code under test."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def box_oracle(x: torch.Tensor, r: int) -> torch.Tensor:
    """Count-normalised (2r+1)² mean via avg_pool (float64, separable: rows then columns)."""
    x = x.double()
    k = 2 * r + 1
    x = F.avg_pool2d(x, (1, k), stride=1, padding=(0, r), count_include_pad=False)
    return F.avg_pool2d(x, (k, 1), stride=1, padding=(r, 0), count_include_pad=False)


def guided_oracle(p: torch.Tensor, I: torch.Tensor, r: int, eps) -> torch.Tensor:
    """He et al.'s guided filter in float64 with torch.linalg.solve, no centring tricks."""
    p, I = p.double(), I.double()
    B, C, H, W = p.shape
    n = I.shape[1]
    mI, mp = box_oracle(I, r), box_oracle(p, r)
    II = torch.stack([box_oracle(I[:, i : i + 1] * I, r) for i in range(n)], 1)  # (B, n, n, H, W)
    Ip = torch.stack([box_oracle(I[:, i : i + 1] * p, r) for i in range(n)], 1)  # (B, n, C, H, W)
    sigma = II - mI[:, :, None] * mI[:, None]
    cov = Ip - mI[:, :, None] * mp[:, None]
    e = torch.as_tensor(eps, dtype=torch.float64).expand(n) if not torch.is_tensor(eps) or eps.dim() < 2 else eps
    A = sigma.permute(0, 3, 4, 1, 2) + torch.diag_embed(e.double().reshape(-1, n)[:, None, None].expand(B, 1, 1, n))
    a = torch.linalg.solve(A, cov.permute(0, 3, 4, 1, 2))  # (B, H, W, n, C)
    a = a.permute(0, 3, 4, 1, 2)  # (B, n, C, H, W)
    b = mp - (a * mI[:, :, None]).sum(1)
    ma = box_oracle(a.reshape(B, n * C, H, W), r).reshape(B, n, C, H, W)
    return (ma * I[:, :, None]).sum(1) + box_oracle(b, r)


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
