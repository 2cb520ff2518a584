"""Calibration of ``PIPELINE.albedo_ceiling`` (docs/calibration.md), on tuning scenes only.

The tuning scenes rendered by Mitsuba 3 (whose albedo AOV of a rough conductor exceeds 1), 2
bounces, against 512 spp: the relMSE of every Denoiser method with the demodulator's ceiling at
1 ("on") and at 1e3 ("off", no ceiling in effect), printed as a table.

    python scripts/calibrate_albedo_ceiling.py [--size 256] [--spp 1 4 16]
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile

from bench_quality import available_scenes

import torchgi
import torchgi.backends.c_kernels.pipeline as c_pipeline
from torchgi import light, metrics
from torchgi.render import mitsuba

SCENES = ("cornell_glossy", "sky", "bunny_box", "bunny")
METHODS = ("guided", "pyramid", "blend", "atrous")


def _ceiling(settings) -> None:
    """The pipeline settings the torch code and the C back end read (the experiment's switch)."""
    light.PIPELINE = settings
    c_pipeline.PIPELINE = settings


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--spp", type=int, nargs="+", default=[1, 4, 16])
    args = parser.parse_args()
    on = light.PIPELINE
    off = dataclasses.replace(on, albedo_ceiling=1e3)
    print("scene spp share_albedo>1 max_albedo noisy " + " ".join(f"{m}_off {m}_on" for m in METHODS))
    for entry in SCENES:
        for name, scene in available_scenes([entry], args.size):
            with tempfile.TemporaryDirectory() as tmp:
                d = mitsuba.to_mitsuba(scene, tmp, bounces=2)
                ref = mitsuba.render_gbuffer(d, spp=512, bounces=2, seed=999).color
                for spp in args.spp:
                    gb = mitsuba.render_gbuffer(d, spp=spp, bounces=2, seed=1)
                    a = gb.albedo
                    row = [name, spp, f"{float((a.amax(1) > 1).float().mean()):.4f}", f"{float(a.max()):.1f}",
                           f"{float(metrics.relmse(gb.color, ref)):.4g}"]
                    for method in METHODS:
                        for settings in (off, on):
                            _ceiling(settings)
                            row.append(f"{float(metrics.relmse(torchgi.Denoiser(method)(gb), ref)):.4g}")
                    _ceiling(on)
                    print(*row, flush=True)


if __name__ == "__main__":
    main()
