"""Shared benchmark plumbing: timing with torch.utils.benchmark, metadata, CSV/JSON/Markdown."""

from __future__ import annotations

import csv
import json
import platform
import subprocess
from collections.abc import Callable
from pathlib import Path

import torch
import torch.utils.benchmark as tb

# Named sizes used across benchmarks: (H, W).
SIZES = {"512²": (512, 512), "1024x768": (768, 1024), "720p": (720, 1280), "1080p": (1080, 1920), "4K": (2160, 3840)}


def cpu_model() -> str:
    """The CPU's model name and its widest vector units (OIDN's oneDNN and our -march=native
    kernels gain differently from AVX-512 and AMX: ratios to OIDN differ between machines)."""
    try:
        info = Path("/proc/cpuinfo").read_text()
    except OSError:
        return platform.processor() or platform.machine()
    name = next((ln.split(":", 1)[1].strip() for ln in info.splitlines() if ln.startswith("model name")), "unknown")
    flags = set(next((ln.split(":", 1)[1].split() for ln in info.splitlines() if ln.startswith("flags")), []))
    units = [u for u in ("avx2", "avx512f", "amx_tile") if u in flags]
    return f"{name} ({', '.join(units) or 'no AVX2'})"


def metadata(threads: int) -> dict:
    """Commit, versions and device, written beside every result."""
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                check=True).stdout.strip()
        dirty = bool(subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                                    text=True, check=False).stdout.strip())
    except (OSError, subprocess.CalledProcessError):
        commit, dirty = "unknown", False
    import torchgi

    return {
        "commit": commit + ("+dirty" if dirty else ""),
        "torchgi": torchgi.__version__,
        "torch": torch.__version__,
        "python": platform.python_version(),
        "cpu": cpu_model(),
        "threads": threads,
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
    }


def time_ms(fn: Callable[[], object], *, min_run_time: float = 1.0, device: str = "cpu") -> dict:
    """Median and IQR in ms of ``fn()`` (blocked_autorange; CUDA synchronised by the Timer)."""
    fn()  # warm up (allocations, first-call work)
    m = tb.Timer(stmt="fn()", globals={"fn": fn}, num_threads=torch.get_num_threads()).blocked_autorange(
        min_run_time=min_run_time)
    return {"median_ms": m.median * 1e3, "iqr_ms": m.iqr * 1e3, "runs": len(m.times)}


def triton_knob(name: str):
    """The module of :mod:`torchgi.backends.triton_kernels` that holds the tile knob ``name``
    (``_BH``, ``_COL_BW``, ``_PIX``, ...), for ``getattr`` / ``setattr``; KeyError if none does."""
    from torchgi.backends.triton_kernels import filter_atrous, filter_guided

    for mod in (filter_atrous, filter_guided):
        if hasattr(mod, name):
            return mod
    raise KeyError(f"torchgi.backends.triton_kernels has no knob {name}")


def write_results(rows: list[dict], meta: dict, out: Path, stem: str) -> None:
    """``stem.csv`` (rows), ``stem.json`` (metadata + rows)."""
    out.mkdir(parents=True, exist_ok=True)
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with open(out / f"{stem}.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=keys)
        writer.writeheader()
        writer.writerows(rows)
    (out / f"{stem}.json").write_text(json.dumps({"metadata": meta, "rows": rows}, indent=2))


def markdown_table(rows: list[dict], columns: list[str]) -> str:
    def fmt(v: object) -> str:
        if isinstance(v, float):
            return f"{v:.3g}" if abs(v) < 1e4 else f"{v:.0f}"
        return "" if v is None else str(v)

    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(fmt(r.get(c)) for c in columns) + " |" for r in rows]
    return "\n".join(lines)


def oidn(gb, quality: str, split_emission: bool):
    """Intel Open Image Denoise (pyoidn): colour + albedo + normal, HDR; with ``split_emission``
    it denoises colour minus emission and adds the emission back (the issue's second protocol)."""
    import pyoidn

    hwc = lambda t: t[0].permute(1, 2, 0).contiguous()
    color = gb.color - gb.emission if split_emission else gb.color
    y = pyoidn.denoise(hwc(color), hwc(gb.albedo), hwc(gb.normal), hdr=True, quality=quality)
    y = y.permute(2, 0, 1)[None]
    return y + gb.emission if split_emission else y


CONFIG_SCENES = Path(__file__).resolve().parents[1] / "configs" / "scenes"


def load_scene(name: str, size: int):
    """A built-in scene or ``configs/scenes/<name>.yaml`` at ``size`` x ``size`` pixels."""
    import torchgi

    if name in torchgi.scenes.BUILTINS:
        return torchgi.scenes.BUILTINS[name](size)
    return torchgi.load_scene(CONFIG_SCENES / f"{name}.yaml").with_resolution(size, size)


SCENE_SETS = CONFIG_SCENES / "sets.yaml"


def scene_sets() -> dict[str, list[str]]:
    """``{"tuning": [...], "training": [...], "judged": [...]}``: the entries of
    ``configs/scenes/sets.yaml`` (its header says what each set may be used for)."""
    import yaml

    return yaml.safe_load(SCENE_SETS.read_text())


def available_scenes(names: list[str], size: int):
    """``(name, scene)`` for each name that loads; a scene whose mesh files are absent (a
    ``TORCHGI_MESHES`` folder without them) is reported and skipped."""
    for name in names:
        try:
            yield name, load_scene(name, size)
        except FileNotFoundError as exc:
            print(f"skipping {name}: {exc}", flush=True)


def without_back_off(gb, method: str = "guided") -> torch.Tensor:
    """``Denoiser(method)(gb)`` without its back-off toward the input (:func:`torchgi.light.back_off`)
    nor the guided filter's choice among radii from 4 spp (:func:`torchgi.light.choose`): the
    filter's output (``settings.pipeline.back_off=False``)."""
    from torchgi.denoise import Denoiser
    from torchgi.settings import DEFAULTS

    return Denoiser(method, settings=DEFAULTS.replace(pipeline={"back_off": False}))(gb)
