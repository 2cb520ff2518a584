"""Training data: the data-generation job (noisy/reference EXR shards with AOVs) and a Dataset.

The job (docs/design.md, Training data) reads a YAML config, plans one task per (scene, view, seed), and renders
each task's spp ladder and reference into multi-layer EXR shards named as Intel Open Image
Denoise's training tools expect: ``<scene>_<view>_<spp:04d>spp.exr`` and ``<scene>_<view>_ref.exr``
(``<view>`` = ``v<view:02d>s<seed>``). Every file is written atomically; a task's manifest (the
SHA-256 of each of its shards) is written last, so a task is complete exactly when its manifest
exists and every shard matches it. A re-run skips complete tasks, regenerates tasks whose shards
are missing or corrupt (and says so), and removes temporary files a killed run left behind.
Renders are deterministic, so a resumed job writes the same bytes as an uninterrupted one,
locally or on a Dask cluster. ``index.json`` lists every shard with its metadata and the
resolved config.

:class:`ShardDataset` reads the shards back as ``(C, H, W)`` tensors with random crops;
:class:`FilterFeatures` adds filtered versions of the noisy colour as extra channels, on any
device, before or after collation.
"""

from __future__ import annotations

import dataclasses
import glob
import hashlib
import itertools
import json
import os
import zlib
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchgi.core.check import check_int, check_nonnegative, check_option, require
from torchgi.core.errors import ConfigError, RangeError
from torchgi.core.files import temp_beside

__all__ = ["DataGenConfig", "FilterFeatures", "ShardDataset", "Task", "load_config", "plan", "run_job", "run_task"]

_KEYS = ("scenes", "procedural", "renderer", "resolution", "views", "jitter", "spp", "reference_spp", "bounces",
         "seeds")
RENDERERS = ("torchgi", "mitsuba")  # DataGenConfig.renderer
INDEX = "index.json"
_TASKS = ".tasks"


@dataclasses.dataclass(frozen=True)
class DataGenConfig:
    """A resolved data-generation config (see ``configs/data_gen/*.yaml``).

    Args:
        scenes: built-in names, YAML paths (relative paths resolved against ``root``) or
            ``procedural:<seed>`` names (the config key ``procedural: [first, count]`` adds a range).
        resolution: ``(width, height)`` for every scene, or None for each scene's own.
        views: camera views per scene; view 0 is the scene's camera, the others jitter it.
        jitter: camera position jitter as a fraction of the scene's extent (look-at: half).
        spp: the ladder of noisy sample counts, strictly increasing ints > 0.
        reference_spp: samples of the reference, > max(spp).
        bounces: indirect bounces >= 0.
        seeds: one task per seed per view (independent noise).
        root: folder of the config file.
        renderer: "torchgi" or "mitsuba" (Mitsuba 3 renders the converted scene,
            :func:`torchgi.render.mitsuba.render_gbuffer`; procedural scenes without their
            textures, which Mitsuba has no counterpart for).
    """

    scenes: tuple[str, ...]
    resolution: tuple[int, int] | None
    views: int
    jitter: float
    spp: tuple[int, ...]
    reference_spp: int
    bounces: int
    seeds: tuple[int, ...]
    root: str = "."
    renderer: str = "torchgi"

    def __post_init__(self) -> None:
        """Every number checked, as :func:`config_from_dict` checks a file's (errors name the field)."""
        for key, low in (("views", 1), ("reference_spp", 1), ("bounces", 0)):
            _int(getattr(self, key), key, low)
        for key, values, low in (("spp", self.spp, 1), ("seeds", self.seeds, 0),
                                 ("resolution", self.resolution or (1, 1), 1)):
            if not isinstance(values, (tuple, list)) or not values or (key == "resolution" and len(values) != 2):
                raise ConfigError(f"{key}: expected a non-empty sequence of ints (resolution: two), got {values!r}")
            for value in values:
                _int(value, key, low)
        if isinstance(self.jitter, bool) or not isinstance(self.jitter, (int, float)) or not 0 <= self.jitter < 1:
            raise ConfigError(f"jitter: expected a number in [0, 1), got {self.jitter!r}")
        if any(b <= a for a, b in itertools.pairwise(self.spp)) or self.reference_spp <= self.spp[-1]:
            raise ConfigError(f"spp, reference_spp: expected a strictly increasing ladder and a larger reference, "
                              f"got {list(self.spp)} and {self.reference_spp}")

    def resolved(self) -> dict[str, Any]:
        """The config as plain data (what ``index.json`` records)."""
        out = dataclasses.asdict(self)
        out.pop("root")
        if self.renderer == "torchgi":  # the index of a job made before the key existed stays the same
            out.pop("renderer")
        return {k: list(v) if isinstance(v, tuple) else v for k, v in out.items()}


def _int(value: Any, key: str, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ConfigError(f"{key}: expected an int >= {low}, got {value!r}")
    return value


def _scenes(scenes: Any, root: str) -> list[str]:
    """The ``scenes`` key: a non-empty list of built-in names or YAML paths with distinct names."""
    from torchgi.render.scenes import BUILTINS, PROCEDURAL

    if not isinstance(scenes, list) or not scenes or not all(isinstance(s, str) for s in scenes):
        raise ConfigError(f"scenes: expected a non-empty list of names or YAML paths, got {scenes!r}")
    for name in scenes:
        if name not in BUILTINS and not name.startswith(PROCEDURAL) and not os.path.isfile(os.path.join(root, name)):
            raise ConfigError(
                f"scenes: unknown scene {name!r} (not a built-in: {', '.join(sorted(BUILTINS))}; "
                f"no file {os.path.join(root, name)})"
            )
    if len({_scene_name(s) for s in scenes}) != len(scenes):
        raise ConfigError(f"scenes: two scenes share a name: {scenes}")
    return scenes


def _procedural(value: Any) -> list[str]:
    """The ``procedural`` key: ``[first, count]`` -> the scene names ``procedural:<seed>`` for
    ``count`` seeds from ``first`` (:func:`torchgi.scenes.procedural`)."""
    from torchgi.render.scenes import PROCEDURAL

    if value is None:
        return []
    if not isinstance(value, list) or len(value) != 2:
        raise ConfigError(f"procedural: expected [first, count] (two ints), got {value!r}")
    first, count = _int(value[0], "procedural", 0), _int(value[1], "procedural", 1)
    return [f"{PROCEDURAL}{seed}" for seed in range(first, first + count)]


def config_from_dict(cfg: Mapping[str, Any], root: str = ".") -> DataGenConfig:
    """Validate a parsed config; errors name the key."""
    if not isinstance(cfg, Mapping):
        raise ConfigError("config: expected a mapping")
    unknown = sorted(set(cfg) - set(_KEYS))
    if unknown:
        raise ConfigError(f"config: unknown key(s) {', '.join(unknown)}; known: {', '.join(_KEYS)}")
    for key in ("spp", "reference_spp"):
        if key not in cfg:
            raise ConfigError(f"{key}: required")
    if "scenes" not in cfg and "procedural" not in cfg:
        raise ConfigError("scenes: required (or procedural: [first, count], a range of procedural seeds)")
    scenes = _scenes(cfg.get("scenes", []) + _procedural(cfg.get("procedural")), root)
    spp = cfg["spp"]
    if not isinstance(spp, list) or not spp:
        raise ConfigError(f"spp: expected a list of ints > 0 (the ladder), got {spp!r}")
    ladder = tuple(_int(s, "spp", 1) for s in spp)
    if any(b <= a for a, b in itertools.pairwise(ladder)):
        raise ConfigError(f"spp: the ladder must be strictly increasing, got {list(ladder)}")
    reference = _int(cfg["reference_spp"], "reference_spp", 1)
    if reference <= ladder[-1]:
        raise ConfigError(f"reference_spp: expected more than the ladder's largest ({ladder[-1]}), got {reference}")
    resolution = cfg.get("resolution")
    if resolution is not None:
        if not isinstance(resolution, list) or len(resolution) != 2:
            raise ConfigError(f"resolution: expected [width, height], got {resolution!r}")
        resolution = (_int(resolution[0], "resolution", 1), _int(resolution[1], "resolution", 1))
    jitter = cfg.get("jitter", 0.02)
    if isinstance(jitter, bool) or not isinstance(jitter, (int, float)) or not 0 <= jitter < 1:
        raise ConfigError(f"jitter: expected a number in [0, 1), got {jitter!r}")
    seeds = cfg.get("seeds", [0])
    if not isinstance(seeds, list) or not seeds:
        raise ConfigError(f"seeds: expected a non-empty list of ints, got {seeds!r}")
    seeds = tuple(_int(s, "seeds", 0) for s in seeds)
    if len(set(seeds)) != len(seeds):
        raise ConfigError(f"seeds: repeated seed in {list(seeds)}")
    return DataGenConfig(
        scenes=tuple(scenes),
        resolution=resolution,
        views=_int(cfg.get("views", 1), "views", 1),
        jitter=float(jitter),
        spp=ladder,
        reference_spp=reference,
        bounces=_int(cfg.get("bounces", 1), "bounces", 0),
        seeds=seeds,
        root=root,
        renderer=_renderer(cfg.get("renderer", "torchgi")),
    )


def _renderer(value: Any) -> str:
    if value not in RENDERERS:
        raise ConfigError(f"renderer: expected one of {', '.join(map(repr, RENDERERS))}; got {value!r}")
    return value


def load_config(path: str | os.PathLike[str]) -> DataGenConfig:
    """Read and validate a data-generation YAML config.

    Example:
        >>> load_config("configs/data_gen/tiny.yaml").spp
        (1, 2, 4)
    """
    import yaml

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"config {path!r} does not exist")
    with open(path, encoding="utf-8") as fh:
        try:
            cfg = yaml.safe_load(fh)
        except yaml.YAMLError as exc:
            raise ConfigError(f"{path}: malformed YAML: {exc}") from None
    return config_from_dict(cfg, os.path.dirname(os.path.abspath(path)))


def _scene_name(spec: str) -> str:
    """A scene's name in file names: the YAML file's stem; ``procedural:12`` -> ``procedural_12``."""
    return os.path.splitext(os.path.basename(spec))[0].replace(":", "_")


@dataclasses.dataclass(frozen=True)
class Task:
    """One unit of work: every spp of the ladder and the reference of one (scene, view, seed)."""

    scene: str
    view: int
    seed: int

    @property
    def name(self) -> str:
        return f"{_scene_name(self.scene)}_v{self.view:02d}s{self.seed}"

    def shard(self, spp: int | None) -> str:
        """File name of the shard with ``spp`` samples (None: the reference)."""
        return f"{self.name}_ref.exr" if spp is None else f"{self.name}_{spp:04d}spp.exr"


def plan(config: DataGenConfig) -> list[Task]:
    """Every task of the job, in a fixed order."""
    return [Task(s, v, seed) for s in config.scenes for v in range(config.views) for seed in config.seeds]


def task_scene(config: DataGenConfig, task: Task):
    """The task's scene with its view's camera (view 0: unchanged; others jittered by a
    generator keyed by the scene's name and the view, so every run sees the same views)."""
    from torchgi.render import load_scene, scenes

    spec = task.scene
    if config.renderer == "mitsuba" and spec.startswith(scenes.PROCEDURAL):
        scene = scenes.procedural(int(spec[len(scenes.PROCEDURAL):]), textures=False)
    else:
        scene = load_scene(spec if not spec.endswith((".yaml", ".yml")) else os.path.join(config.root, spec))
    if config.resolution is not None:
        scene = scene.with_resolution(*config.resolution)
    if task.view == 0 or config.jitter == 0:
        return scene
    cam = scene.camera
    rng = np.random.default_rng([zlib.crc32(_scene_name(spec).encode()), task.view])
    extent = scene.arrays().scale
    position = np.add(cam.position, rng.normal(size=3) * config.jitter * extent)
    look_at = np.add(cam.look_at, rng.normal(size=3) * config.jitter * extent / 2)
    camera = dataclasses.replace(cam, position=tuple(position.tolist()), look_at=tuple(look_at.tolist()))
    return type(scene)(camera, scene.meshes, scene.lights, scene.name)


def _render_seed(task: Task, spp: int | None) -> int:
    key = f"{task.name}/{'ref' if spp is None else spp}".encode()
    return (zlib.crc32(key) ^ (task.seed * 0x9E3779B1)) & 0xFFFFFFFF


def _sha256(path: str | os.PathLike[str]) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _write_atomic(path: Path, text: str) -> None:
    tmp = temp_beside(path)
    Path(tmp).write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def run_task(config: DataGenConfig, task: Task, out: str | os.PathLike[str]) -> dict[str, Any]:
    """Render one task's shards into ``out`` (replacing this task's files), then its manifest.

    Returns the manifest: the task, its shards' metadata and SHA-256.
    """
    from torchgi.render import mitsuba, render

    out = Path(out)
    scene = task_scene(config, task)
    shards = []
    for spp in (*config.spp, None):
        samples = config.reference_spp if spp is None else spp
        if config.renderer == "mitsuba":
            gb = mitsuba.scene_gbuffer(scene, spp=samples, bounces=config.bounces, seed=_render_seed(task, spp))
        else:
            gb = render(scene, spp=samples, bounces=config.bounces, seed=_render_seed(task, spp), workers=1,
                        progress=False)
        path = out / task.shard(spp)
        gb.to_exr(path, overwrite=True)
        shards.append({
            "file": path.name, "scene": _scene_name(task.scene), "view": task.view, "seed": task.seed,
            "spp": config.reference_spp if spp is None else spp, "reference": spp is None,
            "reference_file": task.shard(None), "resolution": list(scene.camera.resolution),
            "bounces": config.bounces, "sha256": _sha256(path),
            **({"renderer": config.renderer} if config.renderer != "torchgi" else {}),
        })
    manifest = {"task": dataclasses.asdict(task), "shards": shards}
    _write_atomic(out / _TASKS / f"{task.name}.json", json.dumps(manifest, indent=1, sort_keys=True) + "\n")
    return manifest


def _complete(task: Task, out: Path) -> tuple[dict[str, Any] | None, list[str]]:
    """The task's manifest if every shard matches it, else None and the bad files."""
    path = out / _TASKS / f"{task.name}.json"
    if not path.is_file():
        return None, []
    try:
        manifest = json.loads(path.read_text())
        bad = [s["file"] for s in manifest["shards"] if not (out / s["file"]).is_file()
               or _sha256(out / s["file"]) != s["sha256"]]
    except (ValueError, KeyError, TypeError):
        return None, [path.name]
    return (None, bad) if bad else (manifest, [])


def _check_writable(out: Path) -> None:
    try:
        out.mkdir(parents=True, exist_ok=True)
        (out / _TASKS).mkdir(exist_ok=True)
    except OSError as exc:
        raise PermissionError(f"out: cannot write to {out} ({exc.strerror or exc})") from None
    for folder in (out, out / _TASKS):
        if not os.access(folder, os.W_OK | os.X_OK):
            raise PermissionError(f"out: cannot write to {folder} (permission denied)")


def _task_entry(args: tuple[DataGenConfig, Task, str]) -> dict[str, Any]:
    torch.set_num_threads(1)
    return run_task(*args)


def run_job(
    config: DataGenConfig | str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    workers: int = 1,
    scheduler: str | None = None,
    progress: bool | None = None,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Run (or resume) a data-generation job.

    Args:
        config: a :class:`DataGenConfig` or the path of its YAML.
        out: output folder (created; must be writable).
        workers: local processes (ignored with ``scheduler``).
        scheduler: a Dask scheduler address (``tcp://host:8786``): one Dask task per job task.
        progress: a progress bar over tasks; None = only on a terminal.
        log: where messages about skipped, regenerated and cleaned files go.

    Returns:
        ``{"rendered": [...], "skipped": [...], "regenerated": [...], "removed_temporary": n,
        "index_written": bool}`` (task names).

    Example:
        >>> import tempfile
        >>> cfg = config_from_dict({"scenes": ["cornell"], "resolution": [8, 8], "spp": [1],
        ...                         "reference_spp": 2, "bounces": 0})
        >>> d = tempfile.mkdtemp()
        >>> run_job(cfg, d, log=lambda m: None)["rendered"], run_job(cfg, d, log=lambda m: None)["skipped"]
        (['cornell_v00s0'], ['cornell_v00s0'])
    """
    import sys

    from tqdm.auto import tqdm

    if not isinstance(config, DataGenConfig):
        config = load_config(config)
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise RangeError(f"workers: expected an int >= 1, got {workers!r}")
    out = Path(out)
    _check_writable(out)
    removed = _remove_temporaries(out, log)
    todo, manifests, skipped, regenerated = _sort_tasks(config, out, log)
    show = sys.stderr.isatty() if progress is None else progress
    with tqdm(total=len(todo), disable=not show, unit="task", desc="datagen") as bar:
        for m in _run_tasks(config, todo, out, workers, scheduler):
            manifests[Task(**m["task"]).name] = m
            bar.update()
    shards = [s for t in plan(config) for s in manifests[t.name]["shards"]]
    index = json.dumps({"config": config.resolved(), "shards": shards}, indent=1, sort_keys=True) + "\n"
    index_path = out / INDEX
    written = not index_path.is_file() or index_path.read_text() != index
    if written:
        _write_atomic(index_path, index)
    return {
        "rendered": [t.name for t in todo], "skipped": skipped, "regenerated": regenerated,
        "removed_temporary": removed, "index_written": written,
    }


def _remove_temporaries(out: Path, log: Callable[[str], None]) -> int:
    """Delete the temporary files a killed run left (writes are atomic: the real files are whole)."""
    removed = 0
    for tmp in glob.glob(str(out / ".*.tmp")) + glob.glob(str(out / _TASKS / ".*.tmp")):
        os.unlink(tmp)
        removed += 1
    if removed:
        log(f"removed {removed} temporary file(s) left by an interrupted run")
    return removed


def _sort_tasks(
    config: DataGenConfig, out: Path, log: Callable[[str], None]
) -> tuple[list[Task], dict[str, dict], list[str], list[str]]:
    """The tasks still to run, the manifests of the complete ones, and the names of the tasks
    skipped (complete) and regenerated (missing or corrupt files)."""
    todo, manifests, skipped, regenerated = [], {}, [], []
    for task in plan(config):
        manifest, bad = _complete(task, out)
        if manifest is not None:
            manifests[task.name] = manifest
            skipped.append(task.name)
        else:
            if bad:
                log(f"{task.name}: missing or corrupt {', '.join(bad)}: regenerating the task")
                regenerated.append(task.name)
            todo.append(task)
    return todo, manifests, skipped, regenerated


def _run_tasks(config: DataGenConfig, todo: list[Task], out: Path, workers: int, scheduler: str | None):
    """Yield each task's manifest as it completes: on a Dask scheduler, local worker processes or here."""
    if scheduler is not None:
        distributed = require("distributed", "dist")
        with distributed.Client(scheduler) as client:
            futures = [client.submit(run_task, config, t, str(out), pure=False, key=f"torchgi-{t.name}")
                       for t in todo]
            for future in distributed.as_completed(futures):
                yield future.result()
    elif workers > 1 and len(todo) > 1:
        from torchgi.render.engine import worker_pool

        with worker_pool(workers) as pool:
            yield from pool.map(_task_entry, [(config, t, str(out)) for t in todo])
    else:
        for t in todo:
            yield run_task(config, t, out)


def _sigma_position(position: torch.Tensor, hit: torch.Tensor | None) -> torch.Tensor:
    """σ_x of each sample of ``position (B, 3, H, W)``, ``(B,)``: the Denoiser's rule on its own
    pixels (all of them without ``hit``)."""
    from torchgi.geometry import sigma_position_rule
    from torchgi.settings import ATROUS

    if hit is None:
        hit = torch.ones_like(position[:, :1], dtype=torch.bool)
    return torch.tensor([sigma_position_rule(position[b : b + 1], hit[b : b + 1].bool(), ATROUS.sigma_position_footprints)
                         for b in range(position.shape[0])], dtype=position.dtype, device=position.device)


# ------------------------------------------------------------------------------ reading
class ShardDataset(torch.utils.data.Dataset):
    """The noisy shards of a data-generation output folder, each with its reference.

    Args:
        root: the job's output folder (with ``index.json``).
        crop: side of a random square crop, or None for whole images.
        features: AOVs of the noisy shard to return (``color``, ``albedo``, ``normal``,
            ``position``, ``depth``, ``direct``, ``indirect``, ``emission``, ``variance``).
        spp: keep only shards with these sample counts (None: all of the ladder).
        seed: crops are drawn from a generator keyed by (seed, epoch, index).

    Items are dicts: each feature ``(C, h, w)`` float32, ``target`` the reference colour
    ``(3, h, w)``, ``spp`` and ``name``. :meth:`stack` concatenates chosen keys into one input.

    Example:
        >>> import tempfile
        >>> d = tempfile.mkdtemp()
        >>> _ = run_job(config_from_dict({"scenes": ["cornell"], "resolution": [16, 16], "spp": [1, 2],
        ...             "reference_spp": 4, "bounces": 0}), d, log=lambda m: None)
        >>> ds = ShardDataset(d, crop=8)
        >>> len(ds), ds[0]["color"].shape, ds[0]["target"].shape
        (2, torch.Size([3, 8, 8]), torch.Size([3, 8, 8]))
    """

    def __init__(
        self,
        root: str | os.PathLike[str],
        *,
        crop: int | None = None,
        features: Sequence[str] = ("color", "albedo", "normal"),
        spp: Sequence[int] | None = None,
        seed: int = 0,
    ) -> None:
        self.root = Path(root)
        index = self.root / INDEX
        if not index.is_file():
            raise FileNotFoundError(f"root: {index} does not exist (run the data-generation job first)")
        shards = json.loads(index.read_text())["shards"]
        self.items = [s for s in shards if not s["reference"] and (spp is None or s["spp"] in spp)]
        if not self.items:
            raise ConfigError(f"spp: no shard with {list(spp or [])} samples in {index}")
        for name in features:
            check_option(name, "features", ("color", "albedo", "normal", "position", "depth", "direct",
                                            "indirect", "emission", "variance"))
        if crop is not None and (isinstance(crop, bool) or not isinstance(crop, int) or crop < 1):
            raise RangeError(f"crop: expected an int >= 1 or None, got {crop!r}")
        check_int(seed, "seed")
        self.crop, self.features, self.seed, self.epoch = crop, tuple(features), seed, 0

    def __len__(self) -> int:
        return len(self.items)

    def set_epoch(self, epoch: int) -> None:
        """New random crops for a new epoch (same epoch, same crops)."""
        self.epoch = epoch

    def __getitem__(self, i: int) -> dict[str, Any]:
        from torchgi.io.exr import read_aovs

        item = self.items[i]
        layers = read_aovs(self.root / item["file"], required=self.features)
        target = read_aovs(self.root / item["reference_file"], required=("color",))["color"]
        out: dict[str, Any] = {k: layers[k].float() for k in self.features}
        out["target"] = target.float()
        H, W = target.shape[-2:]
        if self.crop is not None:
            if self.crop > min(H, W):
                raise RangeError(f"crop: {self.crop} is larger than the image ({W}x{H})")
            g = torch.Generator().manual_seed(hash((self.seed, self.epoch, i)) & 0x7FFFFFFF)
            y = int(torch.randint(0, H - self.crop + 1, (1,), generator=g))
            x = int(torch.randint(0, W - self.crop + 1, (1,), generator=g))
            out = {k: v[..., y : y + self.crop, x : x + self.crop] for k, v in out.items()}
        out["spp"], out["name"] = item["spp"], item["file"]
        return out

    @staticmethod
    def stack(sample: Mapping[str, Any], keys: Sequence[str]) -> torch.Tensor:
        """Concatenate ``keys`` along the channel axis (``(C, H, W)`` or ``(B, C, H, W)``)."""
        return torch.cat([sample[k] for k in keys], dim=-3)


class FilterFeatures(torch.nn.Module):
    """Add filtered versions of the noisy colour to a sample as extra features.

    ``atrous``: edge-avoiding À-Trous of ``color`` guided by ``normal`` (and ``position`` when
    present, σ_x by :func:`~torchgi.geometry.sigma_position_rule` as the Denoiser's, from each
    sample's own positions and ``hit``); ``guided``: the guided filter of ``color`` with the
    Denoiser's guide (:func:`~torchgi.filters.guide_from`: normal, and depth over each sample's
    largest). A sample's features do not depend on the batch it is in. Works on single samples
    ``(C, H, W)`` or collated batches ``(B, C, H, W)`` on any device, so it can run in a
    DataLoader worker or on the GPU after collation.

    Example:
        >>> s = {"color": torch.rand(3, 16, 16), "normal": torch.nn.functional.normalize(torch.randn(3, 16, 16), dim=0)}
        >>> out = FilterFeatures(("atrous", "guided"))(s)
        >>> out["atrous"].shape, out["guided"].shape
        (torch.Size([3, 16, 16]), torch.Size([3, 16, 16]))
    """

    def __init__(self, methods: Sequence[str] = ("atrous", "guided"), *, radius: int = 4, eps: float = 1e-3,
                 iterations: int = 4) -> None:
        super().__init__()
        for m in methods:
            check_option(m, "methods", ("atrous", "guided"))
        check_int(radius, "radius")
        check_int(iterations, "iterations", 1)
        check_nonnegative(eps, "eps")
        self.methods, self.radius, self.eps, self.iterations = tuple(methods), radius, eps, iterations

    def forward(self, sample: Mapping[str, Any]) -> dict[str, Any]:
        from torchgi.filters import atrous, guide_from, guided

        out = dict(sample)
        color = sample["color"]
        single = color.dim() == 3
        batch = {k: v[None] if single else v for k, v in sample.items() if isinstance(v, torch.Tensor)}
        if "atrous" in self.methods:
            position = batch.get("position")
            sigma = None if position is None else _sigma_position(position, batch.get("hit"))
            r = atrous(batch["color"], batch.get("normal"), position, iterations=self.iterations,
                       sigma_position=sigma)
            out["atrous"] = r[0] if single else r
        if "guided" in self.methods:
            guide = guide_from(batch["normal"], batch.get("depth"), depth_scale="image")
            r = guided(batch["color"], guide, radius=self.radius, eps=self.eps)
            out["guided"] = r[0] if single else r
        return out

    def extra_repr(self) -> str:
        return f"methods={self.methods}, radius={self.radius}, eps={self.eps}, iterations={self.iterations}"
