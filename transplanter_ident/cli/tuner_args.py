"""The `tuner` command line (pinned in DESIGN.md section 3): its flags, their types and help.

The flags select what :mod:`.tuner` runs: the optimiser of paper eqs. 15-20 (``--algorithm``), the
objective (eq. 21 or the NLL, ``--objective``), the search box of eq. 22 (``--q-span``), and the
calibration searches run ahead of Q/R (:data:`CALIBRATIONS`).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import NoReturn

from transplanter_ident.tuning.delay import DELAY_RANGE
from transplanter_ident.tuning.parallel import default_jobs
from transplanter_ident.tuning.problem import OBJECTIVES, Q_SPAN, check_q_span
from transplanter_ident.tuning.tune import ALGORITHMS

CALIBRATIONS = ("estimate_heading_offset", "estimate_delay", "estimate_steering_play", "estimate_steering_scale",
                "estimate_yaw_inertia", "estimate_relaxation_length")  # the calibration searches' argparse names


class _Parser(argparse.ArgumentParser):
    """argparse, but a usage error is one line (``tuner: error: ...``) and exit code 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())} (see {self.prog} -h)\n")


def _int_at_least(minimum: int) -> Callable[[str], int]:
    """An argparse type: an integer >= ``minimum``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < minimum:
            raise argparse.ArgumentTypeError(f"must be an integer >= {minimum}, got {text!r}")
        return value

    return parse


_count = _int_at_least(1)
_seed = _int_at_least(0)


def _span(text: str) -> float:
    """An argparse type: decades, a positive number or inf (``tuning.problem.check_q_span``)."""
    try:
        return check_q_span(float(text))
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive number of decades or inf, got {text!r}") from None


def build_parser() -> argparse.ArgumentParser:
    """Command line pinned in DESIGN.md section 3."""
    parser = _Parser(prog="tuner", description="Tune the EKF's Q and R on recorded bags (IPSO, PSO or CMA-ES); "
                                                "several bags get one Q/R for all of them.")
    parser.add_argument("bags", metavar="BAG", nargs="+",
                        help="rosbag2 directory (with metadata.yaml) or a .mcap file; several: one Q/R for all")
    parser.add_argument("-o", "--output", metavar="OUT.yaml", required=True, help="params YAML to write")
    parser.add_argument("--params-file", metavar="P.yaml", action="append", default=[],
                        help="base parameters (repeatable, layered; default: built-in = config/estimator.yaml)")
    parser.add_argument("--algorithm", choices=ALGORITHMS, default="ipso",
                        help="optimiser: ipso (the paper's, default), pso, cmaes (CMA-ES, the cma package)")
    parser.add_argument("--objective", choices=tuple(OBJECTIVES), default="nll",
                        help="nll: innovation negative log-likelihood (default; more robust, see README); "
                             "mae: the paper's eq. 21 mean |innovation|")
    parser.add_argument("--particles", metavar="N", type=_count, default=20, help="swarm size F (default 20)")
    parser.add_argument("--iterations", metavar="N", type=_count, default=40, help="iterations k_max (default 40)")
    parser.add_argument("--seed", metavar="N", type=_seed, help="random seed (default: drawn, and recorded in OUT)")
    parser.add_argument("--report", metavar="DIR", help="write plots (Figs. 4-7) and the metrics to DIR")
    parser.add_argument("--jobs", metavar="N", type=_count, default=None,
                        help=f"worker processes for decoding bags and evaluating candidates (default: the number "
                             f"of cores, {default_jobs()} here); the result is the same for any N")
    parser.add_argument("--dask", metavar="ADDRESS",
                        help="evaluate candidates on a dask.distributed cluster (scheduler address, e.g. "
                             "tcp://10.0.0.5:8786); bags are decoded here and sent to the workers")
    parser.add_argument("--epoch-cache", metavar="DIR", default=None,
                        help="where decoded epochs are kept (default $XDG_CACHE_HOME/transplanter_ident/epochs)")
    parser.add_argument("--no-epoch-cache", action="store_true", help="decode every bag, keep nothing")
    parser.add_argument("--allow-partial", action="store_true",
                        help="go on when fewer messages can be read than the bag's metadata counts (a corrupt chunk)")
    parser.add_argument("--estimate-delay", action="store_true",
                        help="first search gnss.delay (--delay-range) on the bags at the starting Q/R, then tune Q/R "
                             "at it; writes it (with nll, and its std as ekf.delay_uncertainty) into OUT.yaml")
    parser.add_argument("--delay-range", metavar=("LOW", "HIGH"), nargs=2, type=float, default=DELAY_RANGE, help=f"s "
                        f"(default {DELAY_RANGE[0]:g} {DELAY_RANGE[1]:g}; < 0: the steering is stamped after the GNSS)")
    parser.add_argument("--estimate-steering-play", action="store_true", help="then search vehicle.steering_play "
                        "(the steering linkage's free travel, -1.15 to 1.15 deg, signed) on the bags at the starting "
                        "Q/R, each candidate re-assembling them; writes it into OUT.yaml, and Q/R are tuned at it")
    parser.add_argument("--estimate-steering-scale", action="store_true", help="then search vehicle.steering_scale "
                        "(0.95-1.05 x the configured) likewise, tune Q/R at it; writes it (with nll, and its std as "
                        "ekf.steering_scale_uncertainty) into OUT.yaml")
    parser.add_argument("--estimate-yaw-inertia", action="store_true", help="then search vehicle.iz (0.6-1.6 x the "
                        "configured, m lf lr if 0) likewise; writes it (with nll, its std as ekf.yaw_inertia_uncertainty)")
    parser.add_argument("--estimate-heading-offset", action="store_true", help="first find vehicle.heading_offset "
                        "(a dual-antenna baseline's yaw) from the filter's measure of a misaligned heading, pooled over "
                        "the bags; writes it into OUT.yaml, and everything after runs at it")
    parser.add_argument("--estimate-relaxation-length", action="store_true", help="then find "
                        "vehicle.relaxation_length from the filter's own measure of the tire force's lag, pooled "
                        "over the bags; writes it into OUT.yaml (Q/R are tuned with it)")
    parser.add_argument("--tune-stiffness-noise", action="store_true",
                        help="also tune the stiffness random walk (q_Cf, q_Cr of ekf.process_noise); by default "
                             "only the physical noises (vy, r, psi and R) are tuned and the stiffness and offset "
                             "random walks and the change mechanism keep their designed values")
    parser.add_argument("--q-span", metavar="DECADES", type=_span, default=Q_SPAN,
                        help=f"search each process noise within this many decades of its configured value "
                             f"(default {Q_SPAN:g}; inf: the whole box). Wider lets drives the linear model does "
                             f"not fit buy motion noise that starves the stiffness (README)")
    parser.add_argument("--no-leave-one-out", action="store_true",
                        help="with several bags, skip the leave-one-bag-out check (2 tuning runs per bag)")
    parser.add_argument("--debug", action="store_true", help="print tracebacks on errors")
    return parser
