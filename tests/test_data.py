"""Data generation: resumable, byte-identical shards (local, killed, Dask), the Dataset, bad input."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

pytest.importorskip("embreex", reason="the render extra is not installed")
pytest.importorskip("OpenEXR", reason="the exr extra is not installed")

from torchgi.core import ConfigError
from torchgi.data import FilterFeatures, ShardDataset, config_from_dict, load_config, run_job

TINY = Path(__file__).resolve().parents[1] / "configs" / "data_gen" / "tiny.yaml"
# Slow enough (about 1 s per task on 2 cores) to be killed in the middle.
SLOW = {"scenes": ["cornell", "sky"], "resolution": [48, 48], "views": 2, "spp": [1, 4],
        "reference_spp": 256, "bounces": 2, "seeds": [0, 1]}


def files(root: Path) -> dict[str, bytes]:
    """Every file of a job's output (shards, manifests, index), by relative path."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def quiet(msg: str) -> None:
    pass


@pytest.fixture(scope="module")
def reference_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("uninterrupted")
    run_job(config_from_dict(SLOW), out, workers=2, log=quiet)
    return out


def test_second_run_of_a_finished_job_writes_nothing(reference_run):
    before = {p: (p.stat().st_mtime_ns, p.stat().st_ino) for p in reference_run.rglob("*")}
    summary = run_job(config_from_dict(SLOW), reference_run, log=quiet)
    assert summary["rendered"] == [] and not summary["index_written"] and len(summary["skipped"]) == 8
    assert before == {p: (p.stat().st_mtime_ns, p.stat().st_ino) for p in reference_run.rglob("*")}


def test_killed_job_resumes_to_the_same_bytes(tmp_path, reference_run):
    cfg = tmp_path / "slow.yaml"
    cfg.write_text(json.dumps(SLOW))  # JSON is YAML
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "torchgi.cli", "datagen", str(cfg), "--out", str(out), "--workers", "2",
           "--no-progress"]
    proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while time.time() < deadline and not list(out.glob("*_ref.exr")):
        time.sleep(0.02)
    os.killpg(proc.pid, signal.SIGKILL)  # the job and its workers, mid-run
    proc.wait()
    shards_at_kill = len(list(out.glob("*.exr")))
    assert 0 < shards_at_kill < 24 and not (out / "index.json").exists()
    summary = run_job(load_config(cfg), out, workers=2, log=quiet)
    assert summary["rendered"] and summary["index_written"]
    assert files(out) == files(reference_run)


def test_corrupt_shard_is_detected_regenerated_and_reported(tmp_path, reference_run):
    out = tmp_path / "out"
    out.mkdir()
    for name, data in files(reference_run).items():
        (out / name).parent.mkdir(exist_ok=True)
        (out / name).write_bytes(data)
    shard = out / "sky_v01s1_0004spp.exr"
    blob = bytearray(shard.read_bytes())
    blob[len(blob) // 2] ^= 0xFF
    shard.write_bytes(bytes(blob))
    (out / ".cornell_v00s0_ref.exr.abc.tmp").write_bytes(b"partial")  # left by a killed writer
    messages = []
    summary = run_job(config_from_dict(SLOW), out, log=messages.append)
    assert summary["regenerated"] == ["sky_v01s1"] and summary["rendered"] == ["sky_v01s1"]
    assert any("sky_v01s1_0004spp.exr" in m and "regenerating" in m for m in messages)
    assert summary["removed_temporary"] == 1
    assert files(out) == files(reference_run)


@pytest.mark.slow
def test_dask_local_cluster_gives_the_same_bytes(tmp_path):
    distributed = pytest.importorskip("distributed")
    local = tmp_path / "local"
    run_job(TINY, local, log=quiet)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as c:
        summary = run_job(TINY, tmp_path / "dask", scheduler=c.scheduler_address, log=quiet)
    assert len(summary["rendered"]) == 4
    assert files(tmp_path / "dask") == files(local)


def test_index_and_names_follow_the_oidn_convention(reference_run):
    index = json.loads((reference_run / "index.json").read_text())
    assert index["config"]["spp"] == [1, 4] and index["config"]["reference_spp"] == 256
    names = sorted(s["file"] for s in index["shards"])
    assert "cornell_v00s0_0001spp.exr" in names and "cornell_v00s0_ref.exr" in names
    assert len(names) == 2 * 2 * 2 * 3  # scenes x views x seeds x (ladder + reference)
    views = {s["file"]: s for s in index["shards"]}
    # view 1 is a jittered camera: a different image from view 0
    a = ShardDataset(reference_run, features=("color",), spp=[4])
    imgs = {a.items[i]["file"]: a[i]["color"] for i in range(len(a))}
    assert not torch.equal(imgs["cornell_v00s0_0004spp.exr"], imgs["cornell_v01s0_0004spp.exr"])
    assert views["cornell_v00s0_0004spp.exr"]["reference_file"] == "cornell_v00s0_ref.exr"


def test_dataset_crops_features_and_filter_transform(reference_run):
    ds = ShardDataset(reference_run, crop=16, features=("color", "albedo", "normal", "depth"), seed=3)
    item = ds[5]
    assert item["color"].shape == (3, 16, 16) and item["depth"].shape == (1, 16, 16)
    assert item["target"].shape == (3, 16, 16)
    assert torch.equal(ds[5]["color"], item["color"])  # same epoch, same crop
    ds.set_epoch(1)
    assert ShardDataset.stack(item, ("color", "albedo", "normal")).shape == (9, 16, 16)
    loader = torch.utils.data.DataLoader(ds, batch_size=4)
    batch = FilterFeatures(("atrous", "guided"))(next(iter(loader)))
    assert batch["atrous"].shape == (4, 3, 16, 16) and batch["guided"].shape == (4, 3, 16, 16)
    single = FilterFeatures(("atrous", "guided"))(item)
    torch.testing.assert_close(single["guided"], FilterFeatures(("guided",))({k: v[None] if isinstance(
        v, torch.Tensor) else v for k, v in item.items()})["guided"][0])
    with pytest.raises(ValueError, match="features"):
        ShardDataset(reference_run, features=("colour",))


@pytest.mark.parametrize(
    "change, words",
    [
        ({"scenes": ["cornel"]}, "unknown scene 'cornel'"),
        ({"spp": [4, 2]}, "strictly increasing"),
        ({"spp": [0, 1]}, "spp: expected an int >= 1"),
        ({"spp": "1,2"}, "spp: expected a list"),
        ({"reference_spp": 4}, "reference_spp: expected more than"),
        ({"views": 0}, "views"),
        ({"colour": 1}, "unknown key(s) colour"),
        ({"procedural": [0]}, "procedural: expected [first, count]"),
        ({"procedural": [0, 0]}, "procedural: expected an int >= 1"),
        ({"renderer": "cycles"}, "renderer: expected one of"),
    ],
)
def test_bad_config(change, words):
    with pytest.raises(ConfigError) as info:
        config_from_dict({**SLOW, **change})
    assert words in str(info.value)


def test_unwritable_output_directory(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(PermissionError, match="cannot write"):
        run_job(TINY, blocker / "out", log=quiet)


PROCEDURAL = {"procedural": [40, 2], "resolution": [24, 24], "spp": [1, 4], "reference_spp": 8, "bounces": 1}


@pytest.mark.parametrize("renderer", ["torchgi", "mitsuba"])
def test_procedural_seeds_regenerate_bit_for_bit(tmp_path, renderer):
    """A range of procedural seeds is a job like any other: named by seed, and the same bytes on a
    second machine (here: a second folder); Mitsuba renders the scenes without their textures."""
    if renderer == "mitsuba":
        pytest.importorskip("mitsuba")
    cfg = config_from_dict({**PROCEDURAL, "renderer": renderer})
    assert cfg.scenes == ("procedural:40", "procedural:41")
    run_job(cfg, tmp_path / "a", log=quiet)
    run_job(cfg, tmp_path / "b", workers=2, log=quiet)
    a, b = files(tmp_path / "a"), files(tmp_path / "b")
    assert a == b and "procedural_41_v00s0_ref.exr" in a
    shards = json.loads(a["index.json"])["shards"]
    assert {s.get("renderer", "torchgi") for s in shards} == {renderer}
