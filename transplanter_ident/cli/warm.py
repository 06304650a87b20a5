"""`warm`: compile the kernels the tools run into numba's disk cache, once per install (`make venv`).

Without it the first run of a tool on a machine compiles the filter step (paper eqs. 9-14) and
the tuner's objective (eqs. 21-22) as it goes: the tuner's first run on a 10-minute bag takes
~38 s instead of ~11 s (``bench/tuner_bench.py``), and the node compiles before it subscribes. This
runs what a user runs, on a short simulated drive, so every kernel those runs need is compiled here:

1. ``tuner`` with the defaults (a tiny IPSO swarm, eqs. 15-20, with its report: Table 2, the
   Cramér-Rao bound, the validity), on all cores as a user's run;
2. ``replay`` (the decoding kernels, the run over epochs, the validity);
3. the node's warm-up (the compiled step, the information sum, the validity's window checks);
4. the paper's configuration (Euler eq. 10, linear stiffness, z = [vy, r]) as ``make demo``
   tunes and replays it.

The cache folder is keyed by the package's sources (``transplanter_ident/__init__.py``): after an
edit the tools compile again as they go, or ``python -m transplanter_ident.cli.warm`` does it
once. It writes nothing else that stays.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from transplanter_ident.cli import replay, tuner

WARM_DRIVE_SECONDS = 30.0  # long enough for every branch a run takes (the re-linearised start, the bound)


def _drive(folder: Path) -> Path:
    """A short simulated sine drive as a bag in ``folder``."""
    from transplanter_ident.bags import write_sim_bag
    from transplanter_ident.sim.scenarios import build_config
    from transplanter_ident.sim.simulator import simulate

    path = folder / "drive"
    write_sim_bag(simulate(build_config("sine", duration=WARM_DRIVE_SECONDS, seed=0)), path)
    return path


def _paper_configuration(bag: Path) -> None:
    """Tune and filter in the paper's configuration, as ``make demo`` does."""
    from transplanter_ident.bags import read_bag
    from transplanter_ident.config.paper import PAPER_NOISE, PAPER_OPTIONS
    from transplanter_ident.config.params_file import EstimatorParams
    from transplanter_ident.ekf.joint_ekf import run_sequence
    from transplanter_ident.tuning.tune import tune

    params = EstimatorParams()
    paper = replace(params.config, options=PAPER_OPTIONS, noise=PAPER_NOISE)
    epochs = read_bag(bag, params).epochs
    tune(paper, epochs, algorithm="ipso", objective="mae", particles=2, iterations=1, seed=0)
    run_sequence(paper, epochs)


def _node_warm_up() -> None:
    """What the node runs before it subscribes (the default parameters)."""
    from transplanter_ident.config.params_file import EstimatorParams
    from transplanter_ident.ekf.joint_ekf import warm_up
    from transplanter_ident.evaluation import validity

    params = EstimatorParams()
    warm_up(params.config)
    validity.warm_up(params.config, params.validity)


def main(argv: list[str] | None = None) -> int:
    """Run every step; prints one line per step (unless --quiet). Returns 0, or 1 if a step failed."""
    parser = argparse.ArgumentParser(prog="warm", description=__doc__.split("\n\n")[0])
    parser.add_argument("--quiet", action="store_true", help="print nothing but errors")
    args = parser.parse_args(argv)
    say = (lambda _text: None) if args.quiet else (lambda text: print(text, flush=True))
    begin = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="transplanter_warm_") as tmp:
        folder = Path(tmp)
        bag = _drive(folder)
        steps = (
            ("tuner", lambda: tuner.main([str(bag), "-o", str(folder / "tuned.yaml"), "--particles", "2",
                                          "--iterations", "1", "--seed", "0", "--no-epoch-cache",
                                          "--report", str(folder / "report")])),
            ("replay", lambda: replay.main([str(bag), "--csv", str(folder / "replay.csv"), "--quiet"])),
            ("node", _node_warm_up),
            ("paper configuration", lambda: _paper_configuration(bag)),
        )
        for name, step in steps:
            start = time.perf_counter()
            with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()) as errors:
                code = step()
            if code:
                print(f"warm: {name} failed ({code}): {errors.getvalue()[-2000:]}", file=sys.stderr)
                return 1
            say(f"warm: {name} compiled or loaded in {time.perf_counter() - start:.1f} s")
    say(f"warm: numba's cache is filled ({time.perf_counter() - begin:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
