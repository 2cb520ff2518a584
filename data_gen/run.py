"""Run a data-generation job: ``python data_gen/run.py CONFIG --out DIR [--workers N] [--scheduler ADDR]``.

The same as ``torchgi datagen`` (the code lives in ``torchgi.data``).
"""

import sys

from torchgi.cli import main

if __name__ == "__main__":
    sys.exit(main(["datagen", *sys.argv[1:]]))
