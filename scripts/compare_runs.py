"""Before/after ratios of two or more runs of a benchmark that writes a CSV (e.g. bench_filters.py):

    python scripts/compare_runs.py --before out/ab/before1 out/ab/before2 --after out/ab/after1 out/ab/after2 \
        --csv filters.csv --out out/ab

Rows are matched on their key columns (every column that is not a timing); for each timing column
(``*_ms``) the script reports the median over the runs of each side and the ratio after / before.
Writes ``compare.csv`` and ``compare.md`` and prints the median ratio per timing column. Interleave the
runs (before, after, before, after) on one machine: the ratio is then measured side by side.
"""

from __future__ import annotations

import argparse
import csv
import statistics
from pathlib import Path

_KEYS = ("filter", "impl", "size", "guide_dim", "radius", "offset", "iterations", "weights")


def _rows(folder: Path, name: str) -> dict[tuple, dict[str, float]]:
    out: dict[tuple, dict[str, float]] = {}
    with open(folder / name, newline="") as fh:
        for row in csv.DictReader(fh):
            key = tuple(row.get(k, "") for k in _KEYS)
            out[key] = {k: float(v) for k, v in row.items() if k.endswith("_ms") and not k.endswith("iqr_ms") and v}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", nargs="+", type=Path, required=True)
    ap.add_argument("--after", nargs="+", type=Path, required=True)
    ap.add_argument("--csv", default="filters.csv")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    before = [_rows(f, args.csv) for f in args.before]
    after = [_rows(f, args.csv) for f in args.after]
    table, ratios = [], {}
    for key in before[0]:
        for col in before[0][key]:
            b = [r[key][col] for r in before if col in r.get(key, {})]
            a = [r[key][col] for r in after if col in r.get(key, {})]
            if not a or not b:
                continue
            mb, ma = statistics.median(b), statistics.median(a)
            table.append({**dict(zip(_KEYS, key)), "timing": col, "before_ms": mb, "after_ms": ma, "ratio": ma / mb})
            ratios.setdefault(col, []).append(ma / mb)
    args.out.mkdir(parents=True, exist_ok=True)
    cols = [*_KEYS, "timing", "before_ms", "after_ms", "ratio"]
    with open(args.out / "compare.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, cols)
        w.writeheader()
        w.writerows(table)
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(f"{r[c]:.3g}" if isinstance(r[c], float) else str(r[c]) for c in cols) + " |"
              for r in table]
    (args.out / "compare.md").write_text("\n".join(lines) + "\n")
    for col, rs in ratios.items():
        print(f"{col}: median after/before {statistics.median(rs):.3f} over {len(rs)} cases "
              f"(min {min(rs):.3f}, max {max(rs):.3f})")


if __name__ == "__main__":
    main()
