"""Build and load the C back end's library: the sources of this folder compiled on first use with
the system C compiler into ``$TORCHGI_CACHE`` (default ``~/.cache/torchgi``), loaded with ctypes,
the entry points' signatures set; :func:`library` returns it, or None with :func:`describe`
saying why."""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

_SOURCE = Path(__file__).with_name("native.c")  # its family files and common.h are #included there
_SOURCES = (_SOURCE, Path(__file__).with_name("tracer.c"))  # the library's two translation units
_FLAGS = ["-O3", "-march=native", "-fno-math-errno", "-fPIC", "-shared"]
# OpenMP first (threads shared with torch's libgomp, see native.c), else the bands run serially
_THREADING = (["-fopenmp"], [])
_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_status = "not built yet"
_tried = False

# pixels per band below which a call runs on fewer threads (a thread hand-off costs more than
# the band's work; docs/calibration.md)
_P = ctypes.c_void_p
_I = ctypes.c_int
_F = ctypes.c_float
_L = ctypes.c_longlong
_BANDS = [_I, _P, _L]  # every entry point ends with: threads, scratch, scratch bytes per thread
_SIGNATURES = {
    "torchgi_native_version": ([], _I),
    "torchgi_openmp": ([], _I),
    "torchgi_exp_neg": ([_F], _F),
    "torchgi_atrous_level": ([_P, _I, _P, _I, _P, _P, _P, _P, _I, _I, _I, _I, _L, _I, _P, _P, _I, _L, _P, _P, *_BANDS],
                             None),
    "torchgi_guided_coefficients": ([_P, _P, _I, _P, _P, _I, _I, _I, _I, _P, _F, _P, *_BANDS], None),
    "torchgi_guided_apply": ([_P, _I, _I, _P, _P, _P, _I, _I, _I, _P, *_BANDS], None),
    "torchgi_guided_grad": ([_P, _P, _P, _I, _I, _I, _I, _I, _P, _F, _P, _P, *_BANDS], None),
    "torchgi_importance": ([_P, _P, _F, _F, _P, _I, _I, _I, _I, _P, *_BANDS], None),
    "torchgi_allocate": ([_P, _I, _P, _L, _L, _L, _I, _P, _P, _P, _I], _I),
    "torchgi_guide_stats": ([_P, _P, _P, _I, _I, *_BANDS], None),
    "torchgi_guide_edges": ([_I, _P, _P, _P, _P, _P, _I, _I, _F, *_BANDS], None),
    "torchgi_guide_pool": ([_I, _P, _P, _P, _P, _P, _P, _I, _I, _I, _P, *_BANDS], None),
    "torchgi_lights": ([_P, _P, _P, _P, _P, _F, _F, _I, _I, _F, _I, _P, *_BANDS], None),
    "torchgi_prepare": ([_P, _P, _P, _P, _P, _F, _F, _I, _I, _P, _F, _F, _P, _P, *_BANDS], None),
    "torchgi_clamp": ([_P, _P, _F, _I, _I, _I, _P, *_BANDS], None),
    "torchgi_finish": ([_P, _P, _P, _P, _P, _P, _F, _F, _I, _I, _P, *_BANDS], None),
    "torchgi_model_residual": ([_P, _P, _P, _P, _P, _I, _P, _P, _I, _I, _I, _P, _P, *_BANDS], None),
    "torchgi_fine_band": ([_P, _P, _P, _P, _P, _I, _I, _I, _P, *_BANDS], None),
    "torchgi_mix_half": ([_P, _P, _P, _P, _P, _P, _I, _I, _I, _I, _I, _I, _P, *_BANDS], None),
    "torchgi_applied_means": ([_P, _P, _I, _I, _I, _I, _I, _P, *_BANDS], None),
    "torchgi_block_mean": ([_P, _I, _I, _I, _I, _P, *_BANDS], None),
    "torchgi_restore_coefficients": ([_I, _P, _P, _P, _P, _P, _P, _P, _P, _P, _I, _I, _I, _I, _P, _F, _P, *_BANDS],
                                     None),
    "torchgi_accumulate": ([_P] * 13 + [_I, _I, _F, _F, _F, _F, _P, *_BANDS], None),
    "torchgi_change": ([_P] * 9 + [_I, _I, _I, _I, _F, _F, _F, _F, _F, _P, *_BANDS], None),
    "torchgi_history": ([_P] * 8 + [_I, _I, _F, _F, _F, _F, _P, _P, *_BANDS], None),
    "torchgi_backoff_planes": ([_P, _P, _P, _I, _P, _I, _I, _P, *_BANDS], None),
    "torchgi_backoff_apply": ([_P, _P, _P, _I, _P, _P, _I, _I, _F, _F, _F, _P, *_BANDS], None),
    "torchgi_choose_planes": ([_P, _P, _P, _P, _I, _P, _I, _P, _I, _I, _P, *_BANDS], None),
    "torchgi_choose_apply": ([_P, _P, _P, _P, _I, _P, _P, _F, _F, _I, _I, _P, *_BANDS], None),
    "torchgi_embree_init": ([_P], None),
    "torchgi_scene_new": ([_P, _L], _P),
    "torchgi_scene_free": ([_P], None),
    "torchgi_render_pixels": ([_P, _P, _L, _P, _L, _L, _P, _P, _I], None),
    "torchgi_render_guides": ([_P, _P, _L, _P, _I], None),
    "torchgi_upsample_apply": ([_P, _I, _I, _P, _P, _P, _P, _I, _I, _P, *_BANDS], None),
    "torchgi_atrous_level_grad": ([_P, _I, _L, _I, _P, _I, _L, _P, _I, _L, _I, _P, _P, _I, _P, _I, _L, _P, _I, _I, _I, _P,
                                   _P, _P, _P, *_BANDS], None),
    "torchgi_apply_kernels": ([_P, _P, _I, _I, _I, _I, _I, _P, _P, *_BANDS], None),
    "torchgi_apply_kernels_grad": ([_P, _P, _P, _P, _I, _I, _I, _I, _I, _I, _P, _P, *_BANDS], None),
    "torchgi_guided_finish": ([_P, _I, _I, _P, _P, _P, _P, _P, _P, _P, _P, _I, _I, _I, _I, _P, _P, _P, _P, _P, _P, _F,
                               _F, _P, *_BANDS], None),
}
# the library's interface version, written once: in the C source
_VERSION = int(re.search(r"torchgi_native_version\(void\) \{ return (\d+); \}", _SOURCE.read_text()).group(1))


def _cache_dir() -> Path:
    root = os.environ.get("TORCHGI_CACHE") or os.path.join(os.path.expanduser("~"), ".cache", "torchgi")
    return Path(root)


def _compiler() -> str | None:
    for name in (os.environ.get("CC"), "cc", "gcc"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def _build() -> ctypes.CDLL:
    cc = _compiler()
    if cc is None:
        raise RuntimeError("no C compiler found ($CC, cc, gcc)")
    errors = []
    for threading_flags in _THREADING:
        try:
            return _build_with(cc, [*_FLAGS, *threading_flags])
        except RuntimeError as err:
            errors.append(str(err))
    raise RuntimeError("; ".join(errors))


def _build_with(cc: str, flags: list[str]) -> ctypes.CDLL:
    source = b"\0".join(p.read_bytes() for p in sorted(Path(__file__).parent.glob("*.[ch]")))  # every file of the build
    cpu = ""
    if os.path.exists("/proc/cpuinfo"):  # -march=native: one library per CPU model
        cpu = next((ln for ln in Path("/proc/cpuinfo").read_text().splitlines() if ln.startswith("flags")), "")
    key = hashlib.sha256(b"\0".join([source, " ".join(flags).encode(), cc.encode(), cpu.encode(),
                                     platform.machine().encode(), sys.platform.encode()])).hexdigest()[:16]
    out = _cache_dir() / f"native-{key}.so"
    if not out.exists():
        out.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(suffix=".so", dir=out.parent)
        os.close(fd)
        try:
            proc = subprocess.run([cc, *flags, *map(str, _SOURCES), "-o", tmp, "-lm"], capture_output=True, text=True,
                                  check=False)
            if proc.returncode != 0:
                raise RuntimeError(f"{cc} {' '.join(flags)} failed: {proc.stderr.strip()[-500:]}")
            os.replace(tmp, out)  # atomic: concurrent builders each write their own temporary file
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    try:
        lib = ctypes.CDLL(str(out))
    except OSError as err:  # e.g. an OpenMP runtime that cannot be loaded
        raise RuntimeError(f"{out}: {err}") from err
    for name, (args, res) in _SIGNATURES.items():
        fn = getattr(lib, name)
        fn.argtypes, fn.restype = args, res
    if lib.torchgi_native_version() != _VERSION:
        raise RuntimeError(f"{out}: unexpected version")
    return lib


def library() -> ctypes.CDLL | None:
    """The compiled kernels, built on first use; None when disabled or when no build works.

    Example:
        >>> lib = library()
        >>> lib is None or abs(lib.torchgi_exp_neg(1.0) - 0.36787944) < 1e-7
        True
    """
    global _lib, _status, _tried
    if not _tried:
        with _lock:
            if not _tried:
                try:
                    _lib = _build()
                    threads = "OpenMP threads" if _lib.torchgi_openmp() else "one thread (no OpenMP)"
                    _status = f"compiled kernels in use, {threads} ({_lib._name})"
                except Exception as err:  # noqa: BLE001 - no compiler, a failed build, an unloadable library
                    _lib, _status = None, f"compiled kernels unavailable, torch code in use: {err}"
                _tried = True
    return _lib


def describe() -> str:
    """Whether the compiled kernels are built, and why not (for :func:`torchgi.backends.status`);
    builds them first if no call has yet.

    Example:
        >>> describe().startswith(("compiled kernels in use", "compiled kernels unavailable"))
        True
    """
    library()
    return _status

