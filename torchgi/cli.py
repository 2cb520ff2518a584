"""The ``torchgi`` command line: ``info``, ``metrics``, ``render``, ``denoise``, ``export``, ``datagen``, ``demo``."""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import platform
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import torch

import torchgi
from torchgi import methods
from torchgi.core.errors import TorchGIError
from torchgi.io.motion import MOTION_CONVENTIONS

__all__ = ["main"]

# extra -> modules it provides (what ``torchgi info`` reports).
EXTRAS: dict[str, tuple[str, ...]] = {
    "render": ("embreex", "trimesh"),
    "exr": ("OpenEXR",),
    "image": ("imageio", "PIL"),
    "flip": ("flip_evaluator",),
    "gpu": ("triton",),
    "onnx": ("onnx", "onnxruntime", "onnxscript"),
    "ref": ("mitsuba",),
    "dist": ("dask", "distributed"),
    "bench": ("skimage", "matplotlib", "pyoidn"),
}


def _module_version(name: str) -> str | None:
    try:
        mod = importlib.import_module(name)
    except Exception:  # noqa: BLE001 - any import failure means "not usable"
        return None
    return str(getattr(mod, "__version__", "installed"))


def cmd_info(args: argparse.Namespace) -> int:
    """Print versions, devices, which extras import, and the back ends: what each can do here,
    the C compiler and kernel cache, and per op family and device which one runs an eager
    float32 call and why the others decline (:func:`torchgi.backends.status`)."""
    from torchgi import backends

    status = backends.status()
    info = {
        "torchgi": torchgi.__version__,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "devices": ["cpu"] + [f"cuda:{i} {torch.cuda.get_device_name(i)}" for i in range(torch.cuda.device_count())],
        "threads": torch.get_num_threads(),
        "extras": {
            extra: {m: _module_version(m) for m in mods} for extra, mods in EXTRAS.items()
        },
        "backends": {k: v for k, v in status.items() if k != "last"},
    }
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    for key in ("torchgi", "python", "torch", "threads"):
        print(f"{key:8s} {info[key]}")
    print(f"devices  {', '.join(info['devices'])}")
    for extra, mods in info["extras"].items():
        status_line = ", ".join(f"{m} {v}" if v else f"{m} missing" for m, v in mods.items())
        print(f"[{extra}] {status_line}")
    for name in backends.NAMES:
        print(f"backend {name:6s} {status[name]}")
    print(f"compiler {status['compiler'] or 'none found ($CC, cc, gcc): the C kernels cannot be built'}")
    print(f"cache    {status['cache']} (compiled kernels; $TORCHGI_CACHE)")
    for device, ops in status["ops"].items():
        for name in backends.ORDER:
            runs = [op for op, how in ops.items() if how["runs"] == name]
            if not runs:
                continue
            print(f"ops on {device} run by {name}: {', '.join(runs)}")
            reasons: dict[str, list[str]] = {}
            for op in runs:
                for other, why in ops[op]["declined"].items():
                    reasons.setdefault(f"{other}: {why.replace(f' for {op}', '')}", []).append(op)
            for why, which in reasons.items():
                print(f"  declined by {why}" + ("" if which == runs else f" ({', '.join(which)})"))
    return 0


def cmd_metrics(args: argparse.Namespace) -> int:
    """Compare the colour layer of each IMG with that of ``--ref``. relMSE (and FLIP, SSIM) are not
    symmetric, so the reference is a flag and the output names it."""
    from torchgi import metrics
    from torchgi.io import read_aovs

    if args.picture is not None:
        if os.path.splitext(args.picture)[1].lower() != ".png":
            raise ValueError(f"--picture: expected a name ending in .png, got {args.picture!r}")
        if os.path.exists(args.picture) and not args.overwrite:
            raise FileExistsError(f"--picture: {args.picture} exists; pass --overwrite")
    ref = read_aovs(args.ref)["color"].float()[None]
    rows, images = {}, []
    for path in args.img:
        img = read_aovs(path)["color"].float()[None]
        if img.shape != ref.shape:
            raise TorchGIError(f"{path}: size {tuple(img.shape[-2:])} differs from --ref's {tuple(ref.shape[-2:])}")
        rows[path] = metrics.summary(img, ref)
        images.append(img[0])
    if args.picture is not None:
        from torchgi.demo import contact_sheet
        from torchgi.io.png import write_png

        labels = [f"{Path(p).name}\nrelMSE {r['relmse']:.4g} PSNR {r['psnr_db']:.1f}" for p, r in rows.items()]
        sheet = contact_sheet([i * args.exposure for i in images] + [ref[0] * args.exposure],
                              labels + [f"{Path(args.ref).name}\nreference"], columns=len(images) + 1)
        write_png(args.picture, sheet, overwrite=args.overwrite)
    if args.json:
        print(json.dumps({"reference": args.ref, "images": rows}))
        return 0
    print(f"reference (--ref): {args.ref}")
    for path, table in rows.items():
        print(path)
        for key, value in table.items():
            print(f"  {key:8s} {value:.6g}")
    if args.picture is not None:
        print(f"wrote {args.picture} (each image beside the reference, labelled with its relMSE and PSNR; sRGB, "
              f"exposure {args.exposure:g}, clipped to [0, 1])")
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    """Path-trace a scene (YAML or built-in name) into a multi-layer EXR."""
    scene = torchgi.load_scene(args.scene)
    if args.resolution:
        scene = scene.with_resolution(*args.resolution)
    if args.frames is not None and args.mirror_guides is not None:
        raise ValueError("--mirror-guides: not with --frames (a still render's guides only)")
    kwargs = {"workers": args.workers, "progress": None if args.progress else False}
    duration = scene.duration
    if args.frames is not None and (duration is None or duration[0] == duration[1]):
        raise ValueError(f"--frames: scene {scene.name!r} has no camera, mesh or light path over time, so every "
                         "frame would be the same still view; render it without --frames, or give it a "
                         "camera.path (see configs/scenes/sequences)")
    budget = {k: v for k, v in (("seconds", args.seconds), ("target", args.target)) if v is not None}
    if budget and (args.frames is not None or args.mirror_guides is not None or args.spp is not None):
        raise ValueError(f"--{next(iter(budget))}: not with --spp, --frames or --mirror-guides (it decides the samples "
                         "of a still render itself)")
    if len(budget) > 1:
        raise ValueError("--seconds, --target: give one of them")
    if args.frames is None or os.path.splitext(args.out)[1]:  # (frames without an extension are EXRs)
        _image_format(args.out)  # (an output it cannot write refused before the render)
    if args.frames is None and not args.overwrite and os.path.exists(args.out):  # (before the render, not after)
        raise FileExistsError(f"--out: {args.out} exists; pass --overwrite")
    t0 = time.perf_counter()
    if budget:
        gb = torchgi.render_to(scene, bounces=args.bounces, seed=args.seed, workers=args.workers, progress=args.progress,
                       **budget)
        written = _write_render(gb, args.out, args)
    elif args.frames is None:
        gb = torchgi.render(scene, spp=args.spp or 16, bounces=args.bounces, seed=args.seed,
                            mirror_guides=args.mirror_guides, **kwargs)
        written = _write_render(gb, args.out, args)
    else:  # <out>_<frame:04d>.exr, each with a motion layer; every name is checked before any render
        root, ext = os.path.splitext(args.out)
        paths = [f"{root}_{k:04d}{ext or '.exr'}" for k in range(args.frames)]
        existing = [p for p in paths if os.path.exists(p)]
        if existing and not args.overwrite:
            raise FileExistsError(f"--out: {existing[0]} exists (and {len(existing) - 1} more); pass --overwrite")
        frames = torchgi.render_sequence(scene, args.frames, spp=args.spp or 16, bounces=args.bounces,
                                         seed=args.seed, **kwargs)
        written = [w for gb, path in zip(frames, paths) for w in _write_render(gb, path, args)]
    seconds = time.perf_counter() - t0
    width, height = scene.camera.resolution
    samples = width * height * (args.spp or 16) * (args.frames or 1) if not budget else int(gb.spp.sum())
    print(f"rendered {scene.name} {width}x{height} at {samples / (width * height * (args.frames or 1)):.4g} spp"
          f"{' (mean; per-pixel counts in the spp layer)' if budget else ''}, {args.bounces} bounce{'' if args.bounces == 1 else 's'} in "
          f"{seconds:.2f} s ({samples / seconds / 1e6:.2f} M samples/s); wrote {', '.join(written)}")
    return 0


def cmd_denoise(args: argparse.Namespace) -> int:
    """Denoise the colour of a multi-layer EXR (torchgi, Blender/Cycles, Mitsuba or Arnold names),
    or with ``--temporal`` an animation, frame by frame (:func:`_denoise_sequence`)."""
    from torchgi.denoise import Denoiser

    if args.temporal and args.spp is not None:
        raise ValueError("--spp: not with --temporal (the TemporalDenoiser takes each frame's spp layer, else 1)")
    if args.temporal:
        return _denoise_sequence(args)
    if len(args.input) != 1:
        raise ValueError(f"input: one EXR without --temporal, got {len(args.input)}")
    if args.motion_convention is not None:
        raise ValueError("--motion-convention: only with --temporal (a single frame's denoising reads no motion)")
    if not args.short_pass:
        raise ValueError("--no-short-pass: only with --temporal (the TemporalDenoiser's pass over short histories)")
    _image_format(args.out)
    if not args.overwrite and os.path.exists(args.out):  # (before anything is read)
        raise FileExistsError(f"--out: {args.out} exists; pass --overwrite")
    gb, report = torchgi.GBuffer.from_exr(args.input[0], required=("color", "albedo", "normal"),
                                          sanitize=args.sanitize, return_report=True)
    if args.spp is not None and gb.spp is not None and not bool((gb.spp == args.spp).all()):
        raise ValueError(f"--spp: {args.input[0]} records its own sample counts (layer {report.used['spp']!r}, mean "
                         f"{float(gb.spp.float().mean()):.4g}); --spp is for a render that records none")
    print(report)  # which layer each input was read from, and what was left
    method, quality = args.method or "guided", args.quality or "balanced"
    params = {} if args.radius is None else {"radius": args.radius}
    samples = (f"{args.spp:g} spp (--spp)" if args.spp is not None else "spp from the file" if gb.spp is not None
               else "1 spp: the file records none, --spp gives it")
    t0 = time.perf_counter()
    memory = {None: "auto", "none": None}.get(args.max_memory_mb, args.max_memory_mb)  # None: no flag
    out = Denoiser(method, quality, max_memory_mb=memory, **params)(gb.to(args.device), spp=args.spp).cpu()
    seconds = time.perf_counter() - t0  # (.cpu() waits for a CUDA device)
    path = ", ".join(_write_image(args.out, {"color": out[0]}, args.overwrite, args.exposure))
    print(f"denoised {args.input[0]} ({gb.shape[2]}x{gb.shape[1]}, {samples}) with {method} on {args.device} in "
          f"{seconds * 1e3:.1f} ms; wrote {path}")
    return 0


def _device(text: str) -> torch.device:
    """``--device``: ``cpu``, ``cuda`` or ``cuda:N``, refused where this machine has no such device."""
    try:
        device = torch.device(text)
    except (RuntimeError, ValueError):
        device = None
    if device is None or device.type not in ("cpu", "cuda"):
        raise argparse.ArgumentTypeError(f"expected cpu, cuda or cuda:N, got {text!r}")
    count = torch.cuda.device_count() if device.type == "cuda" else 0
    if device.type == "cuda" and count == 0:
        build = "a CPU build of torch" if torch.version.cuda is None else f"torch built for CUDA {torch.version.cuda}"
        raise argparse.ArgumentTypeError(f"{text}: no CUDA device here ({build}, torch {torch.__version__}); "
                                         "`torchgi info` lists the devices")
    if device.type == "cuda" and device.index is not None and device.index >= count:
        raise argparse.ArgumentTypeError(f"{text}: this machine has {count} CUDA device(s), cuda:0 to cuda:{count - 1}")
    return device


def _sample_count(text: str) -> float:
    """``denoise --spp``: the render's samples per pixel, a finite number >= 1."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 1 <= value < math.inf:
        raise argparse.ArgumentTypeError(f"expected the render's samples per pixel, a finite number >= 1, got {text}")
    return value


SUMMARY = "summary.json"  # what `denoise --temporal` writes beside the frames


def _denoise_sequence(args: argparse.Namespace) -> int:
    """``torchgi denoise --temporal FRAMES --out FOLDER``: the TemporalDenoiser over the frames in
    order, one EXR per frame (the input's file name, layer ``color``) and ``summary.json`` in the
    folder. Resumable: a frame already written is kept (never overwritten without --overwrite)
    and still denoised, so that the history of the frames after it is the one an uninterrupted
    run has; the summary's settings must match the run's."""
    from tqdm.auto import tqdm

    from torchgi.io import write_exr
    from torchgi.io.sequence import frame_paths
    from torchgi.temporal import TemporalDenoiser

    for flag, value in (("--quality", args.quality), ("--radius", args.radius), ("--max-memory-mb", args.max_memory_mb)):
        if value is not None:
            raise ValueError(f"{flag}: not with --temporal (the TemporalDenoiser's parameters are fixed)")
    spatial = args.method or "guided"
    if spatial not in methods.names(temporal=True):
        raise ValueError(f"--method: the TemporalDenoiser's spatial filter is one of "
                         f"{', '.join(methods.names(temporal=True))}, "
                         f"not {spatial!r}")
    paths = frame_paths(args.input)
    folder = Path(args.out)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"--out: {folder} is a file; with --temporal it is the folder the frames go to")
    outs = [folder / p.name for p in paths]
    clash = next((p for p, o in zip(paths, outs) if p.resolve() == o.resolve()), None)
    if clash is not None:
        raise ValueError(f"--out: the output of {clash} would replace it; choose another folder")
    settings = {"command": "torchgi denoise --temporal", "torchgi": torchgi.__version__, "spatial": spatial,
                "short_pass": args.short_pass, "sanitize": args.sanitize,
                "motion_convention": args.motion_convention or "from each file's motion layer name"}
    summary_path, written = folder / SUMMARY, {}
    if summary_path.exists() and not args.overwrite:
        try:
            earlier = json.loads(summary_path.read_text())
            written = {Path(r["output"]).name: r["input"] for r in earlier["frames"]}  # output name -> its input
        except (ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"--out: {summary_path} is not a summary this command wrote; pass --overwrite or "
                             "choose another folder") from exc
        if earlier["settings"] != settings:
            raise ValueError(f"--out: {folder} holds frames denoised with other settings ({earlier['settings']}); "
                             "pass --overwrite or choose another folder")
    for path, out_path in zip(paths, outs):
        if out_path.exists() and not args.overwrite:
            if out_path.name not in written:
                raise FileExistsError(f"--out: {out_path} exists and is not a frame this command wrote there; "
                                      "pass --overwrite or choose another folder")
            if written[out_path.name] != str(path.resolve()):
                raise ValueError(f"--out: {out_path} was denoised from {written[out_path.name]}, not {path}; pass "
                                 "--overwrite or choose another folder")
    folder.mkdir(parents=True, exist_ok=True)
    den, rows = TemporalDenoiser(spatial=spatial, short_pass=args.short_pass, sanitize=args.sanitize), []
    with tqdm(total=len(paths), disable=not args.progress, unit="frame", desc="denoise") as bar:
        for path, out_path in zip(paths, outs):
            gb = torchgi.GBuffer.from_exr(path, required=("color", "albedo", "normal", "depth", "motion"),
                                          sanitize=args.sanitize, motion_convention=args.motion_convention)
            t0 = time.perf_counter()
            out = den(gb.to(args.device)).cpu()
            ms = (time.perf_counter() - t0) * 1e3
            kept = out_path.exists() and not args.overwrite
            if not kept:
                write_exr(out_path, {"color": out[0]}, overwrite=args.overwrite)
            rows.append({"input": str(path.resolve()), "output": str(out_path), "ms": round(ms, 3), "kept": kept})
            _write_json(summary_path, {"settings": settings, "frames": rows})
            bar.update()
    kept = sum(r["kept"] for r in rows)
    print(f"denoised {len(rows)} frame(s) with the TemporalDenoiser in {sum(r['ms'] for r in rows) / 1e3:.2f} s; "
          f"wrote {len(rows) - kept} to {folder} (kept {kept} already there); summary {summary_path}")
    return 0


def _write_json(path: Path, data: dict) -> None:
    """``data`` as JSON at ``path``, replaced atomically (a file this command owns)."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)


def cmd_export(args: argparse.Namespace) -> int:
    """Export a Denoiser, fixed for an spp, or with ``--temporal`` one frame of the temporal
    denoiser (its state as inputs and outputs), to ONNX; says what it builds before (an export
    takes from seconds to minutes) and what it built, with its time, after."""
    from torchgi.export import export_denoiser, export_temporal

    if args.temporal:
        given = [f for f, v in (("--method", args.method), ("--spp", args.spp), ("--quality", args.quality),
                                ("--sigma-position", args.sigma_position)) if v is not None]
        given += ["--variance"] if args.variance else []
        if given or not args.emission:
            raise ValueError(f"{(given or ['--no-emission'])[0]}: not with --temporal (its graph is fixed: "
                             "emission in, per-frame guided filter for new pixels)")
        what = "temporal step"
        export = lambda: export_temporal(args.out, overwrite=args.overwrite)
    else:
        method, spp, quality = args.method or "guided", 1.0 if args.spp is None else args.spp, args.quality or "balanced"
        if args.variance and spp < 2:
            raise ValueError(f"--variance: the back-off needs --spp 2 or more, got {spp}")
        what = (f"{method}, fixed for {spp:g} spp (other sample counts refused), {quality}, "
                f"{'with' if args.variance else 'without'} a variance input")
        export = lambda: export_denoiser(method, args.out, spp=spp, quality=quality, sigma_position=args.sigma_position,
                                         emission=args.emission, variance=args.variance, overwrite=args.overwrite)
    if os.path.exists(args.out) and not args.overwrite:
        raise FileExistsError(f"--out: {args.out} exists; pass --overwrite to replace it")
    print(f"exporting {what} to ONNX ...", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    path = export()
    import onnx

    graph = onnx.load(str(path)).graph  # names as written, not restated here
    outputs = "" if not args.temporal else f"; outputs {', '.join(o.name for o in graph.output)}"
    print(f"wrote {path} ({what}) in {time.perf_counter() - t0:.1f} s; inputs {', '.join(i.name for i in graph.input)}"
          f"{outputs} (B, C, H, W) float32, dynamic B/H/W")
    return 0


def cmd_datagen(args: argparse.Namespace) -> int:
    """Run or resume a data-generation job."""
    from torchgi.data import run_job

    t0 = time.perf_counter()
    summary = run_job(args.config, args.out, workers=args.workers, scheduler=args.scheduler,
                      progress=None if args.progress else False)
    print(f"datagen {args.config}: rendered {len(summary['rendered'])} task(s), skipped {len(summary['skipped'])} "
          f"complete, regenerated {len(summary['regenerated'])}, in {time.perf_counter() - t0:.1f} s; "
          f"index {'written' if summary['index_written'] else 'unchanged'}: {Path(args.out) / 'index.json'}")
    return 0


def _positive_int(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected an int > 0, got {text}")
    return value


def _memory_mb(text: str) -> float | str:
    """``--max-memory-mb``: MB > 0, ``auto`` or ``none`` (never in tiles)."""
    if text in ("auto", "none"):
        return text
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0 < value < math.inf:
        raise argparse.ArgumentTypeError(f"expected MB > 0, 'auto' or 'none', got {text}")
    return value


def cmd_demo(args: argparse.Namespace) -> int:
    """Path-trace the Cornell box at low and high spp, round-trip the buffers through multi-layer
    EXR, denoise with every method of the Denoiser and report each one's error and time
    (:func:`torchgi.demo.run_demo`); writes a labelled picture."""
    from torchgi.demo import DEMO_FILES, run_demo

    rows, seconds = run_demo(args.out, size=args.size, spp=args.spp, ref_spp=args.ref_spp, bounces=args.bounces,
                             overwrite=args.overwrite)
    print(f"rendered the Cornell box at {args.size}x{args.size}, {args.spp} and {args.ref_spp} spp, in {seconds:.1f} s")
    print(f"{'method':10s} {'relMSE':>9s} {'SSIM':>9s} {'FLIP':>9s} {'ms':>9s}   (lower relMSE and FLIP, higher SSIM "
          "are better)")
    for name, row in rows.items():
        ms = f"{row['ms']:9.1f}" if "ms" in row else f"{'-':>9s}"
        print(f"{name:10s} {row['relmse']:9.4g} {row['ssim']:9.4f} {row['flip']:9.4f} {ms}")
    print("wrote " + ", ".join(str(Path(args.out) / f) for f in DEMO_FILES))
    return 0


IMAGE_FORMATS = (".exr", ".png")  # what render and denoise write, by --out's extension


def _image_format(path: str, flag: str = "--out") -> str:
    """The format of an image output by its extension (:data:`IMAGE_FORMATS`); other names are
    refused by ``flag``."""
    ext = os.path.splitext(path)[1].lower()
    if ext not in IMAGE_FORMATS:
        raise ValueError(f"{flag}: expected a name ending in .exr (every layer, linear) or .png (the colour, "
                         f"tonemapped to 8-bit sRGB), got {path!r}")
    return ext


def _write_image(path: str, layers: dict, overwrite: bool, exposure: float) -> list[str]:
    """``layers`` (name to ``(C, H, W)``) as a multi-layer EXR, or for a ``.png`` their colour as
    8-bit sRGB (linear x ``exposure``, clipped to [0, 1]); the files written, the PNG's tonemap said."""
    from torchgi.io import write_exr
    from torchgi.io.png import to_srgb8, write_png

    if _image_format(path) == ".exr":
        return [str(write_exr(path, layers, overwrite=overwrite))]
    written = write_png(path, to_srgb8(layers["color"], exposure=exposure), overwrite=overwrite)
    return [f"{written} (colour only: sRGB, exposure {exposure:g}, clipped to [0, 1])"]


def _write_render(gb: torchgi.GBuffer, path: str, args: argparse.Namespace) -> list[str]:
    """A render's GBuffer to ``path``: every layer to an EXR, the colour to a PNG."""
    if _image_format(path) == ".exr":
        return gb.to_exr(path, overwrite=args.overwrite)
    return _write_image(path, {"color": gb.color[0]}, args.overwrite, args.exposure)


def _out_flags(p: argparse.ArgumentParser, what: str) -> None:
    """``--out`` (required; ``what`` it is) and ``--overwrite`` on ``p``."""
    p.add_argument("--out", required=True, help=f"{what}; never overwritten unless --overwrite")
    p.add_argument("--overwrite", action="store_true")


def _denoise_and_export_parsers(sub: argparse._SubParsersAction) -> None:
    """The ``denoise`` and ``export`` sub-commands on ``sub``."""
    p = sub.add_parser("denoise", help="denoise an EXR with AOVs (colour, albedo, normal; uses depth, emission "
                       "when present; pyramid and blend need depth, atrous position); prints the layers it read")
    p.add_argument("input", nargs="+", help="multi-layer EXR: torchgi, Blender/Cycles, Mitsuba 3 or Arnold layer "
                   "names (torchgi.io.AOV_ALIASES; it prints which it read and which it ignored); with --temporal the frames: a folder, a glob, name_####.exr, or the files in order")
    p.add_argument("--method", choices=list(methods.names()), default=None, help="Denoiser method (default guided); with "
                   "--temporal the spatial filter of the accumulated light: guided, pyramid or blend")
    p.add_argument("--quality", choices=["fast", "balanced", "high"], default=None, help="(default balanced)")
    p.add_argument("--radius", type=_positive_int, default=None, help="filter radius (default: from spp)")
    p.add_argument("--spp", type=_sample_count, default=None, help="the render's samples per pixel (a number >= 1; "
                   "the mean of an adaptive render); default: the file's spp layer, else 1. Not with --temporal")
    _out_flags(p, "output .exr (layer 'color') or .png (tonemapped sRGB); with --temporal a folder (one EXR per "
               "frame, summary.json)")
    p.add_argument("--exposure", type=float, default=1.0, help="a .png output's exposure (linear scale before sRGB)")
    p.add_argument("--device", type=_device, default=torch.device("cpu"), help="where to denoise: cpu (default), "
                   "cuda or cuda:N (the result is written from the CPU)")
    p.add_argument("--temporal", action="store_true", help="an animation: the TemporalDenoiser over the frames "
                   "in order (needs depth and motion layers; resumes a folder it wrote)")
    p.add_argument("--motion-convention", choices=list(MOTION_CONVENTIONS), default=None,
                   help="the motion layer's convention (default: from its name: motion torchgi, Vector Cycles, "
                   "motionvector Arnold)")
    p.add_argument("--no-short-pass", dest="short_pass", action="store_false", help="--temporal: skip the guided "
                   "pass over histories shorter than 4 frames (from 256 px; about 1.4x faster, new pixels noisier)")
    p.add_argument("--sanitize", action="store_true", help="replace NaN/Inf in the input by 0 (with a warning)")
    p.add_argument("--max-memory-mb", type=_memory_mb, default=None, help="most MB denoising adds beyond the input "
                   "(tiles; guided and pyramid): a number, 'none' (never tiles) or 'auto' (the default: tiles "
                   "only calls estimated above 2 GB, then within twice the input)")
    p.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar (--temporal)")
    p.set_defaults(func=cmd_denoise)

    p = sub.add_parser("export", help="export a Denoiser to ONNX (needs the onnx extra)")
    p.add_argument("--method", choices=list(methods.names(exportable=True)), default=None, help="Denoiser method (default guided)")
    p.add_argument("--spp", type=float, default=None, help="samples per pixel the parameters are fixed for (default 1)")
    p.add_argument("--quality", choices=["fast", "balanced", "high"], default=None, help="(default balanced)")
    p.add_argument("--temporal", action="store_true", help="one frame of the TemporalDenoiser, its state as graph "
                   "inputs and outputs (torchgi.temporal.DeployedTemporal)")
    p.add_argument("--sigma-position", type=float, default=None, help="À-Trous σ_x, scene units squared")
    p.add_argument("--no-emission", dest="emission", action="store_false", help="a graph without emission input")
    p.add_argument("--variance", action="store_true", help="a graph with a variance input that backs off toward "
                   "the input as the eager Denoiser given one (needs --spp 2 or more)")
    _out_flags(p, "the .onnx file")
    p.set_defaults(func=cmd_export)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="torchgi", description=torchgi.__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"torchgi {torchgi.__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("info", help="versions, devices and which extras import")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("metrics", help="MSE, relMSE, PSNR, SSIM, FLIP of each IMG against --ref (EXR colour layers)")
    p.add_argument("img", nargs="+", help="EXR file(s) to evaluate")
    p.add_argument("--ref", required=True, help="the reference EXR (relMSE is not symmetric: it is named, not guessed)")
    p.add_argument("--json", action="store_true", help='one JSON object: {"reference": REF, "images": {IMG: {...}}}')
    p.add_argument("--picture", default=None, help="also write a .png: each IMG beside the reference, labelled with its "
                   "errors; never overwritten unless --overwrite")
    p.add_argument("--exposure", type=float, default=1.0, help="the picture's exposure (linear scale before sRGB)")
    p.add_argument("--overwrite", action="store_true")
    p.set_defaults(func=cmd_metrics)

    p = sub.add_parser("render", help="path-trace a scene into a multi-layer EXR (needs the render and exr extras)")
    p.add_argument("scene", help="scene YAML, or a built-in: cornell, cornell_glossy, sky, grass")
    p.add_argument("--spp", type=_positive_int, default=None, help="samples per pixel (default 16)")
    p.add_argument("--seconds", type=float, default=None,
                   help="render in rounds for this many seconds (render and denoise), samples placed for the Denoiser")
    p.add_argument("--target", type=float, default=None,
                   help="render in rounds until the Denoiser's estimated relMSE is at most this")
    p.add_argument("--bounces", type=int, default=1, help="indirect bounces, 0 = direct light only (default 1)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--resolution", type=_positive_int, nargs=2, metavar=("W", "H"), help="override the camera's")
    p.add_argument("--workers", type=_positive_int, default=None, help="tracer threads or processes (default: all)")
    p.add_argument("--frames", type=_positive_int, help="N frames of the camera's and meshes' paths: <out>_<frame:04d>.exr, motion layer")
    p.add_argument("--mirror-guides", type=float, default=None, metavar="ROUGHNESS",
                   help="albedo and normal of what mirrors smoother than ROUGHNESS reflect (e.g. 0.05)")
    _out_flags(p, "output .exr (every layer) or .png (the colour, tonemapped sRGB)")
    p.add_argument("--exposure", type=float, default=1.0, help="a .png output's exposure (linear scale before sRGB)")
    p.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar")
    p.set_defaults(func=cmd_render)

    _denoise_and_export_parsers(sub)

    p = sub.add_parser("datagen", help="noisy/reference EXR shards for training (resumable; local or Dask)")
    p.add_argument("config", help="data-generation YAML (configs/data_gen/*.yaml)")
    p.add_argument("--out", required=True, help="output folder (a re-run resumes it)")
    p.add_argument("--workers", type=_positive_int, default=1, help="local processes (default 1)")
    p.add_argument("--scheduler", default=None, help="Dask scheduler address, e.g. tcp://host:8786")
    p.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar")
    p.set_defaults(func=cmd_datagen)

    p = sub.add_parser("demo", help="render the Cornell box, write/read EXR, denoise with every method, measure "
                       "(needs the cpu extra: pip install -e '.[cpu]')")
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo); its files are never "
                   "overwritten unless --overwrite")
    p.add_argument("--overwrite", action="store_true")
    p.add_argument("--size", type=_positive_int, default=128, help="image width and height, px (default 128)")
    p.add_argument("--spp", type=_positive_int, default=1, help="samples per pixel of the noisy render (default 1)")
    p.add_argument("--ref-spp", type=_positive_int, default=256, help="samples per pixel of the reference (default 256)")
    p.add_argument("--bounces", type=int, default=1, help="indirect bounces (default 1)")
    p.set_defaults(func=cmd_demo)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``torchgi`` console script."""
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except FileExistsError as exc:  # the library speaks Python (path, overwrite=True); the shell has flags
        message = str(exc).replace("path: ", "--out: ", 1).replace("overwrite=True", "--overwrite")
        print(f"torchgi {args.command}: error: {message}", file=sys.stderr)
        return 2
    except (TorchGIError, FileNotFoundError, PermissionError, ValueError) as exc:
        message = str(exc)
        if isinstance(exc, FileNotFoundError) and message.startswith("path: folder "):  # a writer's missing folder
            message = message.replace("path: ", "--out: ", 1) + " (create it first)"
        print(f"torchgi {args.command}: error: {message}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
