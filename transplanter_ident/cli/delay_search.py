"""``tuner --estimate-delay`` and ``--estimate-steering-scale``: calibration constants found on the bags before Q/R.

``--estimate-delay`` finds ``gnss.delay`` (issue #13 item 4):

Each bag is decoded once into its input samples (:func:`transplanter_ident.bags.inputs.read_bag_inputs`);
:func:`transplanter_ident.tuning.delay.search_delay` then scores each candidate delay by
re-assembling every bag's epochs with it and running the filter at the starting Q/R (the
(bag, delay) pairs of a grid run in parallel on the tuner's local backend). The bags' epochs at
the estimated delay are what the Q/R search uses, and they go into the epoch cache under the
parameters with that delay, so a later ``tuner --params-file OUT.yaml`` run skips decoding. With
the objective ``nll`` the estimate has a std (:func:`transplanter_ident.tuning.delay.profile_std`
over all the bags' epochs), which goes into ``ekf.delay_uncertainty`` (:meth:`DelayRun.calibration`):
the timing error it may leave is then in the reported Cf, Cr std.

``--estimate-steering-play`` then finds ``vehicle.steering_play`` the same way: each candidate play
re-assembles the decoded samples (:mod:`transplanter_ident.tuning.steering_play`). With ``--estimate-delay``
too, both are searched jointly (:func:`estimate_bag_delay_and_play`): a play looks like a delay.

``--estimate-yaw-inertia`` last finds ``vehicle.iz`` (:mod:`transplanter_ident.tuning.yaw_inertia`; with
``--estimate-steering-scale`` jointly, :mod:`transplanter_ident.tuning.scale_and_inertia`) on the same
epochs; with ``nll`` its std goes into ``ekf.yaw_inertia_uncertainty`` (:func:`inertia_calibration`).

``--estimate-steering-scale`` then finds ``vehicle.steering_scale`` on those epochs
(:mod:`transplanter_ident.tuning.steering_scale`; the (bag, scale) pairs of a grid in parallel) and
hands on the epochs at the estimated scale, cached under the parameters with it; with ``nll`` its
std goes into ``ekf.steering_scale_uncertainty`` (:func:`scale_calibration`).

``--estimate-relaxation-length`` last finds ``vehicle.relaxation_length`` from the filter's own measure of
it (:mod:`transplanter_ident.tuning.relaxation`), with the constants found before.
"""

from __future__ import annotations

import functools
import math
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from transplanter_ident.cli.util import CliError
from transplanter_ident.config.params_file import EstimatorParams
from transplanter_ident.config.schema import PARAMS
from transplanter_ident.tuning.delay import (
    DELAY_RANGE,
    DelayEstimate,
    assemble_epochs,
    delay_objective,
    estimate_delay,
    with_delay,
)
from transplanter_ident.tuning.factor_search import FactorEstimate
from transplanter_ident.tuning.heading_offset import estimate_heading_offset, with_heading_offset
from transplanter_ident.tuning.parallel import Backend
from transplanter_ident.tuning.relaxation import estimate_relaxation_length, with_relaxation_length
from transplanter_ident.tuning.scale_and_inertia import (
    LOCATING_OBJECTIVE,
    pooled_pair_objective,
    search_scale_and_inertia,
)
from transplanter_ident.tuning.steering_play import (
    PlayEstimate,
    estimate_delay_and_play,
    estimate_steering_play,
    pair_objective,
    play_objective,
    with_steering_play,
)
from transplanter_ident.tuning.steering_scale import (
    pooled_scale_objective,
    scaled_epochs,
    search_steering_scale,
    with_std,
    with_steering_scale,
)
from transplanter_ident.tuning.yaw_inertia import (
    pooled_inertia_objective,
    search_yaw_inertia,
    with_yaw_inertia,
)
from transplanter_ident.tuning.yaw_inertia import with_std as with_inertia_std


@dataclass(frozen=True)
class DelayRun:
    """The estimate, the parameters with it, and each bag's ``bags.cache.DecodedBag`` at that delay."""

    estimate: DelayEstimate
    params: EstimatorParams
    decoded: list[Any]

    def calibration(self, objective: str) -> dict[str, tuple[float, str]]:
        """The keys to write (key -> (value, the line that says where it comes from)).

        ``gnss.delay``, and ``ekf.delay_uncertainty`` when the estimate has a std: that std combined
        with the configured uncertainty (a latency's spread, say; none when it is not stated), capped
        at the schema's 1 s (a delay the objective does not pin: the std then holds a bias no band
        would narrow).
        """
        return {"gnss.delay": (self.estimate.delay, self.estimate.format(objective)),
                **held_uncertainty("ekf.delay_uncertainty", self.estimate.std,
                                   max(self.params.config.options.delay_uncertainty, 0.0), 1.0, "the estimated gnss.delay",
                                   lambda v: f"{1e3 * v:.1f} ms")}


def checked_delay_range(bounds: Sequence[float]) -> tuple[float, float]:
    """``--delay-range LOW HIGH`` (s): finite, LOW < HIGH, within the range of ``gnss.delay`` (config/schema.py)."""
    low, high = (float(b) for b in bounds)
    floor, ceiling = PARAMS["gnss.delay"].low, PARAMS["gnss.delay"].high
    if not (math.isfinite(low) and math.isfinite(high) and floor <= low < high <= ceiling):
        raise CliError(f"--delay-range: need {floor:g} <= LOW < HIGH <= {ceiling:g} s (gnss.delay's range), "
                       f"got {low:g} {high:g}")
    return low, high


def decode_inputs(bags: Sequence[str], params: EstimatorParams, backend: Backend, allow_partial: bool, what: str,
                  out: Any) -> list[Any]:
    """Each bag's input samples (``bags.inputs.BagInputs``), decoded once for a search that re-assembles them."""
    from transplanter_ident.bags.inputs import read_bag_inputs  # rosbags only where bags are read

    inputs = backend.map(read_bag_inputs, [(bag, params, allow_partial) for bag in bags])
    for item in inputs:
        print(f"tuner: {item.bag}: {len(item.samples)} input samples decoded for the {what} search"
              f"{f'; note: {item.note}' if item.note else ''}", file=out, flush=True)
    return inputs


def sample_scores(inputs: Sequence[Any], params: EstimatorParams, backend: Backend, score: Callable[..., tuple[float, int]],
                  objective: str, tune_stiffness_noise: bool) -> Callable[[Sequence[float]], list[list[tuple[float, int]]]]:
    """Per candidate value, every bag's (objective, epochs) by ``score(samples, params, value, ...)``, in parallel."""
    def scores(values: Sequence[float]) -> list[list[tuple[float, int]]]:
        tasks = [(item.samples, params, v, objective, tune_stiffness_noise) for v in values for item in inputs]
        results = backend.map(score, tasks)
        return [results[i * len(inputs):(i + 1) * len(inputs)] for i in range(len(values))]

    return scores


def estimate_bag_delay(bags: Sequence[str], params: EstimatorParams, backend: Backend, *, objective: str,
                       tune_stiffness_noise: bool = False, cache: Path | None = None, allow_partial: bool = False,
                       delay_range: tuple[float, float] = DELAY_RANGE, stream: Any = None) -> DelayRun:
    """Decode the bags once, search the delay, and return the bags' epochs at the estimate."""
    from transplanter_ident.bags.cache import store_bag_epochs  # rosbags only where bags are read

    out = stream if stream is not None else sys.stderr
    inputs = decode_inputs(bags, params, backend, allow_partial, "delay", out)
    scores = sample_scores(inputs, params, backend, delay_objective, objective, tune_stiffness_noise)
    estimate = estimate_delay(scores, objective, *delay_range)
    print(f"tuner: {estimate.format(objective)}", file=out, flush=True)
    chosen = with_delay(params, estimate.delay)
    decoded = [store_bag_epochs(item.bag, chosen, assemble_epochs(item.samples, params, estimate.delay),
                                item.truth, cache) for item in inputs]
    return DelayRun(estimate, chosen, decoded)


def estimate_bag_play(bags: Sequence[str], params: EstimatorParams, backend: Backend, *, objective: str,
                      tune_stiffness_noise: bool = False, cache: Path | None = None, allow_partial: bool = False,
                      stream: Any = None) -> tuple[PlayEstimate, EstimatorParams, list[Any]]:
    """``--estimate-steering-play``: decode the bags once, search the play (at the configured or found delay).

    Returns the estimate, the parameters with it, and the bags' epochs at it (cached under those parameters).
    """
    from transplanter_ident.bags.cache import store_bag_epochs  # rosbags only where bags are read

    out = stream if stream is not None else sys.stderr
    inputs = decode_inputs(bags, params, backend, allow_partial, "steering play", out)
    estimate = estimate_steering_play(sample_scores(inputs, params, backend, play_objective, objective,
                                                    tune_stiffness_noise), objective)
    print(f"tuner: {estimate.format(objective)}", file=out, flush=True)
    chosen = with_steering_play(params, estimate.play)
    decoded = [store_bag_epochs(item.bag, chosen, assemble_epochs(item.samples, chosen, chosen.gnss.delay),
                                item.truth, cache) for item in inputs]
    return estimate, chosen, decoded


def estimate_bag_delay_and_play(bags: Sequence[str], params: EstimatorParams, backend: Backend, *, objective: str,
                                tune_stiffness_noise: bool = False, cache: Path | None = None,
                                allow_partial: bool = False, delay_range: tuple[float, float] = DELAY_RANGE,
                                stream: Any = None) -> tuple[DelayRun, PlayEstimate]:
    """``--estimate-delay`` with ``--estimate-steering-play``: both searched jointly (they look alike).

    Returns the delay's run (the parameters with both, the bags' epochs at them, cached) and the play.
    """
    from transplanter_ident.bags.cache import store_bag_epochs  # rosbags only where bags are read

    out = stream if stream is not None else sys.stderr
    inputs = decode_inputs(bags, params, backend, allow_partial, "joint delay and steering play", out)
    scores = sample_scores(inputs, params, backend, pair_objective, objective, tune_stiffness_noise)
    start = (min(max(params.gnss.delay, delay_range[0]), delay_range[1]), params.config.vehicle.steering_play)
    delay, play = estimate_delay_and_play(scores, objective, start, delay_range)
    for found in (delay, play):
        print(f"tuner: {found.format(objective)} (jointly)", file=out, flush=True)
    chosen = with_steering_play(with_delay(params, delay.delay), play.play)
    decoded = [store_bag_epochs(item.bag, chosen, assemble_epochs(item.samples, chosen, delay.delay), item.truth,
                                cache) for item in inputs]
    return DelayRun(delay, chosen, decoded), play


def calibrate_timing(bags: Sequence[str], params: EstimatorParams, backend: Backend,
                     estimated: dict[str, tuple[float, str]], *, delay: bool, play: bool,
                     delay_range: tuple[float, float] = DELAY_RANGE, **search: Any) -> tuple[EstimatorParams, list[Any]]:
    """``--estimate-delay`` (issue #13 item 4) and ``--estimate-steering-play``, jointly when both are asked.

    ``search``: objective, tune_stiffness_noise, cache, allow_partial. Adds the keys to write to ``estimated``;
    returns the parameters and the bags' epochs at the estimates.
    """
    found_play = None
    if delay:
        if play:
            found, found_play = estimate_bag_delay_and_play(bags, params, backend, delay_range=delay_range, **search)
        else:
            found = estimate_bag_delay(bags, params, backend, delay_range=delay_range, **search)
        params, decoded = found.params, found.decoded
        estimated.update(found.calibration(search["objective"]))
    else:
        found_play, params, decoded = estimate_bag_play(bags, params, backend, **search)
    if found_play is not None:
        estimated["vehicle.steering_play"] = (found_play.play, found_play.format(search["objective"]))
        estimated.update(held_uncertainty("ekf.steering_play_uncertainty", found_play.std,
                                          params.config.options.steering_play_uncertainty, 0.05, "the estimated play",
                                          lambda v: f"{math.degrees(v):.3f} deg"))
    return params, decoded


def scale_calibration(estimate: FactorEstimate, params: EstimatorParams, objective: str) -> dict[str, tuple[float, str]]:
    """The keys to write: ``vehicle.steering_scale``, and ``ekf.steering_scale_uncertainty`` when it has a std.

    The std relative to the scale, combined with the configured uncertainty, capped at the schema's 0.2.
    """
    return {"vehicle.steering_scale": (estimate.value, estimate.format(objective)),
            **held_uncertainty("ekf.steering_scale_uncertainty", estimate.std / estimate.value,
                               params.config.options.steering_scale_uncertainty, 0.2, "the estimated scale",
                               lambda v: f"{100 * v:.2f} %")}


def held_uncertainty(key: str, std: float, configured: float, cap: float, what: str,
                     shown: Callable[[float], str]) -> dict[str, tuple[float, str]]:
    """{key: (value, line)}: a calibration's ``std`` combined with the ``configured`` one, capped at ``cap``.

    Empty without a std (NaN: objective ``mae``). The estimator's Cf, Cr std then hold the bias it may leave.
    """
    if math.isnan(std):
        return {}
    value = min(math.hypot(std, configured), cap)
    return {key: (value, f"{key}: {shown(value)} ({what}'s std {shown(std)} with the configured {shown(configured)}; "
                         "the Cf, Cr std hold the bias it may leave)")}


def estimate_bag_steering_scale(decoded: Sequence[Any], params: EstimatorParams, backend: Backend, *,
                                objective: str, tune_stiffness_noise: bool = False, cache: Path | None = None,
                                with_inertia: bool = False,
                                stream: Any = None) -> tuple[FactorEstimate, FactorEstimate | None, EstimatorParams,
                                                             list[Any]]:
    """Search the scale (and with ``with_inertia`` Iz jointly) on the decoded bags.

    Returns the scale, Iz (or None), the parameters with them, and the bags' epochs at the scale.
    Only for a sensor on the centre line: one wheel's angle goes through the nonlinear Ackermann map,
    so scaling the epochs (:func:`~transplanter_ident.tuning.steering_scale.scaled_epochs`) would not
    be assembling with that scale.
    """
    from transplanter_ident.bags.cache import store_bag_epochs  # rosbags only where bags are read

    vehicle = params.config.vehicle
    if vehicle.steering_sensor_wheel != "center":
        raise CliError(f"--estimate-steering-scale needs vehicle.steering_sensor_wheel: center, got "
                       f"{vehicle.steering_sensor_wheel!r} (calibrate a sensor on one wheel against that wheel)")
    epochs = [item.epochs for item in decoded]
    count = sum(len(e) for e in epochs) if objective == "nll" else None  # a likelihood: its curvature is the information
    inertia = None
    if with_inertia:
        pairs = functools.partial(pooled_pair_objective, epochs, params.config, tune_stiffness_noise=tune_stiffness_noise,
                                  run=backend.map)
        estimate, inertia = search_scale_and_inertia(pairs(LOCATING_OBJECTIVE), (vehicle.steering_scale, vehicle.yaw_inertia),
                                                     pairs("nll") if count else None, count or 0)
        params = replace(params, config=with_yaw_inertia(params.config, inertia.value))
    else:
        estimate = search_steering_scale(pooled_scale_objective(epochs, params.config, objective, tune_stiffness_noise,
                                                                backend.map), vehicle.steering_scale)
        estimate = with_std(estimate, count) if count else estimate
    shown = LOCATING_OBJECTIVE if with_inertia else objective  # the joint estimate is eq. 21's minimum
    for found in (estimate, inertia):
        if found is not None:
            print(f"tuner: {found.format(shown)}", file=stream if stream is not None else sys.stderr, flush=True)
    chosen = with_steering_scale(params, estimate.value)
    return estimate, inertia, chosen, [store_bag_epochs(item.bag, chosen, scaled_epochs(e, estimate.factor), item.truth,
                                                        cache) for item, e in zip(decoded, epochs, strict=True)]


def calibrate_heading(epochs_at: Callable[[EstimatorParams], Sequence[Any]], params: EstimatorParams,
                      backend: Backend, estimated: dict[str, tuple[float, str]]) -> EstimatorParams:
    """``--estimate-heading-offset``, ahead of the rest (it shapes the epochs): the parameters with the offset found.

    ``epochs_at``: the bags' epochs decoded at given parameters. Adds ``vehicle.heading_offset`` to ``estimated``.
    """
    estimate = estimate_heading_offset(epochs_at, params, backend.map)
    print(f"tuner: {estimate.format()}", file=sys.stderr, flush=True)
    if not estimate.bags:
        return params
    estimated["vehicle.heading_offset"] = (estimate.value, estimate.format())
    return with_heading_offset(params, estimate.value)


def calibrate_vehicle(decoded: Sequence[Any], params: EstimatorParams, backend: Backend,
                      estimated: dict[str, tuple[float, str]], *, objective: str, steering_scale: bool,
                      yaw_inertia: bool, relaxation: bool = False, tune_stiffness_noise: bool = False,
                      cache: Path | None = None) -> tuple[EstimatorParams, list[Any]]:
    """``--estimate-steering-scale`` and ``--estimate-yaw-inertia`` (both: jointly) on the epochs at the delay.

    Then ``--estimate-relaxation-length`` (``relaxation``) with those constants. Adds the keys to write to
    ``estimated``; returns the parameters and the bags' epochs at the estimates.
    """
    inertia = None
    shown = LOCATING_OBJECTIVE if steering_scale and yaw_inertia else objective  # the joint estimate: eq. 21's minimum
    if steering_scale and not yaw_inertia and params.config.vehicle.iz <= 0.0:
        print("tuner: note: the steering scale is confounded with the yaw inertia, and vehicle.iz is m lf lr (paper "
              "eq. 5, a rule of thumb): add --estimate-yaw-inertia to search both", file=sys.stderr, flush=True)
    if steering_scale:
        scale, inertia, params, decoded = estimate_bag_steering_scale(
            decoded, params, backend, objective=objective, tune_stiffness_noise=tune_stiffness_noise, cache=cache,
            with_inertia=yaw_inertia)
        estimated.update(scale_calibration(scale, params, shown))
    elif yaw_inertia:
        inertia = estimate_bag_yaw_inertia([item.epochs for item in decoded], params, backend, objective=objective,
                                           tune_stiffness_noise=tune_stiffness_noise)
        params = replace(params, config=with_yaw_inertia(params.config, inertia.value))
    if inertia is not None:
        estimated.update(inertia_calibration(inertia, params, shown))
    if relaxation:
        length = estimate_relaxation_length([item.epochs for item in decoded], params.config, backend.map)
        print(f"tuner: {length.format()}", file=sys.stderr, flush=True)
        params = replace(params, config=with_relaxation_length(params.config, length.value))
        estimated["vehicle.relaxation_length"] = (length.value, length.format())
        if math.isfinite(length.std):
            estimated.update(held_uncertainty("ekf.relaxation_uncertainty", length.std,
                                              params.config.options.relaxation_uncertainty, 2.0, "the estimated length",
                                              lambda v: f"{v:.3f} m"))
    return params, list(decoded)


def inertia_calibration(estimate: FactorEstimate, params: EstimatorParams, objective: str) -> dict[str, tuple[float, str]]:
    """The keys to write: ``vehicle.iz``, and ``ekf.yaw_inertia_uncertainty`` when it has a std.

    The std relative to Iz, combined with the configured uncertainty, capped at the schema's 1.
    """
    return {"vehicle.iz": (estimate.value, estimate.format(objective)),
            **held_uncertainty("ekf.yaw_inertia_uncertainty", estimate.std / estimate.value,
                               params.config.options.yaw_inertia_uncertainty, 1.0, "the estimated Iz",
                               lambda v: f"{100 * v:.2f} %")}


def estimate_bag_yaw_inertia(epochs: Sequence[Any], params: EstimatorParams, backend: Backend, *, objective: str,
                             tune_stiffness_noise: bool = False, stream: Any = None) -> FactorEstimate:
    """Search ``vehicle.iz`` on the bags' epochs (the (bag, factor) pairs of a grid in parallel); print it."""
    config = params.config
    estimate = search_yaw_inertia(pooled_inertia_objective(epochs, config, objective, tune_stiffness_noise,
                                                           backend.map), config.vehicle.yaw_inertia)
    if objective == "nll":  # a likelihood: its curvature is the estimate's information
        estimate = with_inertia_std(estimate, sum(len(e) for e in epochs))
    print(f"tuner: {estimate.format(objective)}", file=stream if stream is not None else sys.stderr, flush=True)
    return estimate
