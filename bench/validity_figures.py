"""Figures of the trust issue (#11): how often each scenario is valid, and the +-2 sigma coverage when it is.

Not a test (test/test_validity.py asserts the thresholds on the same scenarios, seeds 0-9).
Run: ``.venv/bin/python bench/validity_figures.py``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))

from test_validity import SCENARIOS, scenario_runs  # noqa: E402


def main() -> int:
    for name in SCENARIOS:
        valid_share, front, rear = [], [], []
        for run, valid in scenario_runs(name):
            after = run.t >= 30.0
            valid_share.append(float(np.mean(valid[after])))
            cf, cr = run.covered()
            front.extend(cf[valid & after])
            rear.extend(cr[valid & after])
        cover = f"{np.mean(front):.3f} / {np.mean(rear):.3f}" if front else "-"
        print(f"{name}: valid in {100 * np.mean(valid_share):.0f} % of epochs after 30 s; when valid, +-2 sigma "
              f"covers Cf / Cr in {cover}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
