"""How wide the reported band is against the error, on rows of bench/robustness_sweep.py, over many seeds.

Not a test (``test/test_validity.py`` asserts the clean drive's figures). For each row it filters
``--seeds`` drives with the default parameters (``--option`` changes a FilterOptions field) and, over
the epochs flagged valid from 30 s on, prints the errors over the reported std, z = (estimate -
truth) / std, of Cf and Cr: pooled over the valid epochs (sd), and at each drive's last valid epoch
(mean, sd, root mean square), with the share of valid epochs outside +-2 sigma. A calibrated band
has a root mean square of z about 1; below it the band is padded (wider than the error), above it
overconfident.

Run: ``.venv/bin/python bench/band_width.py [--seeds 20] [--option NAME=VALUE] ROW [ROW ...]``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))

from robustness_sweep import ALL_ROWS, _with, judged_seed  # noqa: E402

from transplanter_ident.config.parameters import FilterOptions  # noqa: E402
from transplanter_ident.ekf.layout import O_CF, O_CF_STD, O_CR, O_CR_STD  # noqa: E402


def row_z(name: str, seeds: int, options: FilterOptions) -> tuple[np.ndarray, np.ndarray, float]:
    """(z of every valid epoch after 30 s, z at each drive's last valid epoch, share of valid epochs), Cf and Cr columns."""
    pooled, last, shares = [], [], []
    for seed in range(seeds):
        run, valid = judged_seed(name, seed, options)
        after = run.t >= 30.0
        kept = valid & after
        o = run.outputs
        z = np.c_[(o[:, O_CF] - run.true_cf) / o[:, O_CF_STD], (o[:, O_CR] - run.true_cr) / o[:, O_CR_STD]]
        shares.append(float(np.mean(kept[after])))
        pooled.append(z[kept])
        if kept.any():
            last.append(z[np.flatnonzero(kept)[-1]])
    return np.vstack(pooled), np.array(last).reshape(-1, 2), float(np.mean(shares))


def row_line(name: str, seeds: int, options: FilterOptions) -> str:
    pooled, last, valid = row_z(name, seeds, options)
    if not len(pooled):
        return f"valid {valid:5.2f}  (never valid)"
    outside = np.mean(np.any(np.abs(pooled) > 2.0, axis=1))
    cells = [f"{np.std(pooled[:, k]):5.2f} {np.mean(last[:, k]):+6.2f} {np.std(last[:, k]):5.2f} "
             f"{np.sqrt(np.mean(last[:, k] ** 2)):5.2f}" for k in (0, 1)]
    return f"valid {valid:5.2f}  outside {outside:6.3f}  Cf {cells[0]}  Cr {cells[1]}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--option", action="append", default=[], metavar="NAME=VALUE",
                        help="a FilterOptions field to set, e.g. min_friction=0 (repeatable)")
    parser.add_argument("rows", nargs="+", help="rows of bench/robustness_sweep.py")
    args = parser.parse_args(argv)
    unknown = [r for r in args.rows if r not in ALL_ROWS]
    if unknown or args.seeds < 1:
        parser.error(f"unknown rows {unknown}" if unknown else "--seeds must be positive")
    try:
        options = _with(FilterOptions(), args.option)
    except (TypeError, ValueError) as error:
        parser.error(f"--option: {error}")
    width = max(len(r) for r in args.rows)
    print(f"seeds 0-{args.seeds - 1}, valid epochs from 30 s on; defaults{''.join(' ' + o for o in args.option)}")
    print(f"{'row':<{width}}  valid share, share outside +-2 sigma; per stiffness: pooled z sd, "
          "then at the last valid epoch z mean, sd, rms")
    for name in args.rows:
        print(f"{name:<{width}}  {row_line(name, args.seeds, options)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
