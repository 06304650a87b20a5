"""Online identifiability: the Fisher information of (ln Cf, ln Cr) over the last window (issue #11, item 2).

:class:`InformationWindow` keeps the epochs of the last ``diagnostics.information_window``
seconds (data time). When the node publishes /diagnostics it sums their output-error Fisher
information at the filter's current estimate (:mod:`transplanter_ident.ekf.information`: the
bicycle model of eq. 4 with the filter's own discretisation and its dE/dtheta, restarted every
10 s) and inverts it (:func:`~transplanter_ident.evaluation.cramer_rao.cramer_rao_bound`): the
Cramér-Rao bound of what these recent data alone can tell, its weak direction in (ln Cf, ln Cr)
and that direction's 1-sigma. The report is WARN when the weak direction's bound exceeds
``diagnostics.converged_rel_std``: the recent drive does not pin the stiffness in that direction,
whatever the filter's own sigma claims.
"""

from __future__ import annotations

from collections import deque

from transplanter_ident.config.parameters import EstimatorConfig
from transplanter_ident.ekf.joint_ekf import Estimate
from transplanter_ident.epochs.epoch import Epoch, EpochArrays
from transplanter_ident.evaluation.cramer_rao import CramerRaoBound, cramer_rao_bound
from transplanter_ident.evaluation.health import OK, WARN, HealthReport


class InformationWindow:
    """The epochs of the last ``span`` seconds, and the bound they give at an estimate."""

    def __init__(self, config: EstimatorConfig, span: float) -> None:
        self._config = config
        self._span = span
        self._epochs: deque[Epoch] = deque()
        self._estimate: Estimate | None = None

    def set_config(self, config: EstimatorConfig, span: float) -> None:
        """New parameters (R, the vehicle, the window) apply from the next bound on."""
        self._config, self._span = config, span
        self._trim()

    def add(self, epoch: Epoch, estimate: Estimate) -> None:
        """Keep an epoch the filter processed and its estimate; epochs older than ``span`` drop out."""
        if self._epochs and epoch.t < self._epochs[-1].t:  # time went back (bag loop, reset): start again
            self._epochs.clear()
        self._epochs.append(epoch)
        self._estimate = estimate
        self._trim()

    def clear(self) -> None:
        self._epochs.clear()
        self._estimate = None

    def __len__(self) -> int:
        return len(self._epochs)

    def bound(self, estimate: Estimate) -> CramerRaoBound | None:
        """The Cramér-Rao bound of (ln Cf, ln Cr) from the window's epochs at ``estimate``; None if none."""
        stiffness = (estimate.cornering_stiffness_front, estimate.cornering_stiffness_rear)
        return cramer_rao_bound(self._config, EpochArrays(list(self._epochs)), stiffness, estimate.steering_offset)

    def report(self, name: str, converged_rel_std: float) -> HealthReport:
        """The ``<name>: identifiability`` status at the latest estimate: the window's bound and weak direction."""
        title = f"{name}: identifiability"
        values: tuple[tuple[str, str], ...] = (("window_s", f"{self._span:g}"), ("window_epochs", str(len(self))))
        estimate = self._estimate
        bound = self.bound(estimate) if estimate is not None else None
        if bound is None:
            why = ("not computed in yaw_rate mode" if self._config.options.measurement != "heading"
                   else "no informative epoch in the window yet")
            return HealthReport(title, OK, f"Fisher information of the last {self._span:g} s: {why}", values)
        front, rear = bound.relative_std
        known = bound.identifiability
        filter_std = (estimate.cornering_stiffness_front_std / estimate.cornering_stiffness_front,
                      estimate.cornering_stiffness_rear_std / estimate.cornering_stiffness_rear)
        values += (("crb_cf_rel_std", f"{front:.4g}"), ("crb_cr_rel_std", f"{rear:.4g}"),
                   ("crb_weak_direction", f"{known.weak_direction[0]:+.3f} {known.weak_direction[1]:+.3f}"),
                   ("crb_weak_rel_std", f"{known.weak_std:.4g}"), ("crb_condition", f"{known.condition:.4g}"),
                   ("filter_to_crb_cf", _ratio(filter_std[0], front)), ("filter_to_crb_cr", _ratio(filter_std[1], rear)))
        text = (f"Cramér-Rao bound from the last {self._span:g} s ({bound.epochs} epochs): Cf +- {100 * front:.2g} %, "
                f"Cr +- {100 * rear:.2g} %; {known.describe()}")
        if known.weak_std > converged_rel_std:
            return HealthReport(title, WARN, f"weakly identifiable: {text}", values)
        return HealthReport(title, OK, text, values)

    def _trim(self) -> None:
        while self._epochs and self._epochs[0].t < self._epochs[-1].t - self._span:
            self._epochs.popleft()


def _ratio(value: float, reference: float) -> str:
    return f"{value / reference:.3g}" if reference > 0.0 else "inf"
