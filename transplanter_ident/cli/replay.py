"""The `replay` command: run the estimator offline over a bag and report the paper's Table 2 metrics.

The bag is streamed once (:func:`transplanter_ident.bag_io.read_bag`): the input topics go
through the node's :class:`~transplanter_ident.measurements.EpochAssembler` into epochs, and the
filter core (:func:`transplanter_ident.ekf.run_sequence`) runs over them. Then replay

* prints the Table 2 row (max and mean |model output - measurement| of vy and r), the final
  identified stiffness with its 1-sigma, and the GNSS delay, tire relaxation and steering gain left
  out of the configuration as the filter's innovations show them;
* on a simulated bag (``/sim/cornering_stiffness``), prints the final and mean relative
  stiffness error against the truth sampled at the epoch times;
* prints the rejected samples, counted by reason;
* writes the CSV (``--csv``, columns pinned in DESIGN.md section 3) and an MCAP bag with the
  node's output topics (``-o``), both atomically and together: after a failure neither exists.

A bag whose message counts differ from its own metadata (a corrupt chunk that rosbags skipped) is
an error unless ``--allow-partial``; epoch stamps that a bag cannot hold (header.stamp.sec beyond
int32, a negative log time) are an error before anything is written.

Example: ``replay bags/sine --params-file config/estimator.yaml --csv sine.csv``.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import sys
from pathlib import Path

from transplanter_ident.cli.util import CliError, cli_main
from transplanter_ident.files import atomic_output_file


def build_parser() -> argparse.ArgumentParser:
    """Command line pinned in DESIGN.md section 3."""
    parser = argparse.ArgumentParser(
        prog="replay",
        description="Run the estimator offline over a bag; print the paper's Table 2 metrics.",
        epilog="example: replay bags/sine --params-file config/estimator.yaml --csv sine.csv -o sine_out",
    )
    parser.add_argument("bag", metavar="BAG", help="rosbag2 directory (with metadata.yaml) or a .mcap file")
    parser.add_argument(
        "--params-file",
        metavar="P.yaml",
        action="append",
        default=[],
        help="parameters (repeatable, layered: later files override earlier ones key by key); "
             "without it the built-in defaults apply (the values of config/estimator.yaml)",
    )
    parser.add_argument(
        "-o", "--output", metavar="OUT_BAG_DIR", help="write the estimator's output topics to an MCAP bag"
    )
    parser.add_argument("--csv", metavar="OUT.csv", help="write one CSV row per processed epoch")
    parser.add_argument("--force", action="store_true", help="replace OUT_BAG_DIR if it exists")
    parser.add_argument("--allow-partial", action="store_true",
                        help="go on when fewer messages can be read than the bag's metadata counts (a corrupt chunk)")
    parser.add_argument("--quiet", action="store_true", help="no progress output")
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    return parser


def _load_params(paths: list[str]):  # noqa: ANN202 - EstimatorParams, imported lazily
    from transplanter_ident.config.params_file import EstimatorParams, load_params

    return load_params(paths) if paths else EstimatorParams()


def write_csv(path: str | Path, epochs, outputs, valid) -> int:  # noqa: ANN001 - EpochArrays, ndarrays
    """Write the replay CSV (header + one row per epoch) atomically; returns the number of rows."""
    with atomic_output_file(path, "w", newline="") as handle:
        return _write_csv_rows(handle, epochs, outputs, valid)


def _write_csv_rows(handle, epochs, outputs, valid) -> int:  # noqa: ANN001 - text file, EpochArrays, ndarrays
    import numpy as np

    from transplanter_ident.evaluation.metrics import CSV_COLUMNS, csv_rows

    rows = csv_rows(epochs, outputs, valid)
    fmt = ["%.6f"] + ["%.10g"] * (rows.shape[1] - 2) + ["%d"]  # t: us (float64 epoch seconds hold ~0.2 us)
    np.savetxt(handle, rows, fmt=fmt, delimiter=",", header=",".join(CSV_COLUMNS), comments="")
    return rows.shape[0]


#: the epoch times (s) an output bag can hold: header.stamp.sec is an int32, an MCAP log time a uint64 of ns
BAG_TIME_RANGE = (0.0, 2.0**31 - 1.0)


def check_bag_times(times) -> None:  # noqa: ANN001 - ndarray of epoch times, s
    """CliError naming the first epoch time that an output bag cannot hold."""
    import numpy as np

    low, high = BAG_TIME_RANGE
    bad = np.flatnonzero(~((times >= low) & (times < high)))
    if bad.size:
        raise CliError(f"epoch time {float(times[bad[0]])!r} s (and {bad.size - 1} more) cannot be written to a bag: "
                       f"stamps must lie in [{low:g}, {high:.0f}) s (header.stamp.sec is an int32, log times are "
                       "not negative); check the input stamps and gnss.delay. Nothing was written")


def write_outputs(args: argparse.Namespace, epochs, outputs, valid, frame_id: str) -> None:  # noqa: ANN001
    """The CSV and the output bag, all or nothing: the CSV is complete (synced) before the bag, renamed after it."""
    from transplanter_ident.bags import write_output_bag

    if args.output:
        check_bag_times(epochs.t)
    with contextlib.ExitStack() as stack:
        if args.csv:
            handle = stack.enter_context(atomic_output_file(args.csv, "w", newline=""))
            _write_csv_rows(handle, epochs, outputs, valid)
            handle.flush()
            os.fsync(handle.fileno())
        if args.output:
            write_output_bag(args.output, epochs, outputs, overwrite=args.force, frame_id=frame_id)


def _run(args: argparse.Namespace) -> int:
    import numpy as np

    from transplanter_ident.bags import read_bag, summarize_rejections
    from transplanter_ident.config.params_file import parameter_value
    from transplanter_ident.ekf.joint_ekf import Estimate, run_sequence
    from transplanter_ident.ekf.layout import O_CF, O_CF_STD, O_CR, O_CR_STD, O_OFFSET
    from transplanter_ident.evaluation.convergence_report import model_errors_line
    from transplanter_ident.evaluation.cramer_rao import final_bound_line
    from transplanter_ident.evaluation.metrics import format_table2, propagated, stiffness_error, table2_row
    from transplanter_ident.evaluation.validity import decide_sequence

    if args.output and Path(args.output).exists() and not args.force:
        raise CliError(f"{args.output}: already exists (choose another path, or pass --force)")
    if args.csv and Path(args.csv).is_dir():
        raise CliError(f"{args.csv}: is a directory")
    params = _load_params(args.params_file)
    data = read_bag(args.bag, params, truth=True, progress=not args.quiet, allow_partial=args.allow_partial)
    epochs = data.epochs
    outputs = run_sequence(params.config, epochs)
    valid = decide_sequence(params.config, params.validity, epochs, outputs, data.rejected)
    write_outputs(args, epochs, outputs, valid, parameter_value(params, "output.frame_id"))

    counts = data.counts
    span = float(epochs.t[-1] - epochs.t[0]) if len(epochs) else 0.0
    print(f"replay: {args.bag}: {counts['velocity']} velocity, {counts['heading']} heading, "
          f"{counts['steering']} steering messages -> {len(epochs)} epochs over {span:.1f} s "
          f"({int(propagated(outputs).sum())} propagated)")
    print(format_table2([table2_row("EKF", epochs, outputs)], title="Table 2 (model output vs measurement):"))
    last = outputs[-1]
    print(f"Identified stiffness (final): Cf = {last[O_CF]:.1f} +- {last[O_CF_STD]:.1f} N/rad, "
          f"Cr = {last[O_CR]:.1f} +- {last[O_CR_STD]:.1f} N/rad, steering offset "
          f"{math.degrees(last[O_OFFSET]):+.3f} deg; {'valid' if len(valid) and valid[-1] else 'NOT valid'} "
          f"(valid in {100 * float(np.mean(valid)) if len(valid) else 0.0:.0f} % of epochs)")
    print(final_bound_line(params.config, epochs, last))
    print(model_errors_line(Estimate.from_row(float(epochs.t[-1]), last), params.config.vehicle.relaxation_length))
    if data.truth is not None:
        true_f, true_r = data.truth.at(epochs.t)
        err = stiffness_error(outputs, true_f, true_r)
        print(f"Stiffness error vs ground truth (Cf = {true_f[-1]:.1f}, Cr = {true_r[-1]:.1f} N/rad at the end): "
              f"final Cf {100 * err.final_front:+.2f} %, Cr {100 * err.final_rear:+.2f} %; "
              f"mean |error| Cf {100 * err.mean_front:.2f} %, Cr {100 * err.mean_rear:.2f} %")
    summary = summarize_rejections(data.rejections)
    if summary:
        print(f"Rejected samples: {sum(n for _, _, n in summary)}")
        for topic, reason, n in summary:
            print(f"  {n:>7}  {topic}: {reason}")
    else:
        print("Rejected samples: none")
    for note in data.notes:
        print(f"Note: {note}")
    if args.csv:
        print(f"replay: wrote {args.csv} ({len(epochs)} rows)")
    if args.output:
        print(f"replay: wrote {args.output}")
    if not np.all(np.isfinite(outputs[:, [O_CF, O_CR]])):
        print("replay: warning: non-finite stiffness estimates in the output", file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `replay` console script."""
    return cli_main(build_parser(), _run, argv)


if __name__ == "__main__":
    sys.exit(main())
