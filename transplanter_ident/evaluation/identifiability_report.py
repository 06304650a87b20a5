"""The /diagnostics "identifiability" status: what the recent data pin (issue #11, item 2).

Every ``ekf.identifiability_period`` the filter sums the Fisher information of (ln Cf, ln Cr, b)
of its recent epochs at its current estimate (:mod:`transplanter_ident.ekf.identifiability`).
Inverted, with the steering offset a nuisance, it is the Cramér-Rao bound of what these data
alone can tell: the status gives it for Cf and Cr, its weak direction in (ln Cf, ln Cr) and that
direction's 1-sigma, and the published 1-sigma as a multiple of the bound. It is WARN "weakly
identifiable" where the weak direction's bound exceeds ``ekf.max_identifiable_rel_std``: there the
published band along it is the prior's.
"""

from __future__ import annotations

import numpy as np

from transplanter_ident.config.parameters import FilterOptions
from transplanter_ident.ekf.identifiability import nuisances
from transplanter_ident.ekf.joint_ekf import Estimate
from transplanter_ident.evaluation.cramer_rao import bound_from_information
from transplanter_ident.evaluation.health_report import OK, WARN, HealthReport


def identifiability_report(name: str, information: np.ndarray, estimate: Estimate | None,
                           options: FilterOptions) -> HealthReport:
    """The ``<name>: identifiability`` status from the filter's recent information and latest estimate."""
    title = f"{name}: identifiability"
    memory = options.identifiability_memory
    values: tuple[tuple[str, str], ...] = (("memory_s", f"{memory:g}"),
                                           ("limit_rel_std", f"{options.max_identifiable_rel_std:g}"))
    if not options.heading_state or not options.identifiability_check:
        why = "yaw_rate mode" if not options.heading_state else "ekf.identifiability_check is false"
        return HealthReport(title, OK, f"not computed ({why})", values)
    bound = bound_from_information(information, nuisances(options), 0)
    if bound is None or estimate is None:
        return HealthReport(title, WARN, "weakly identifiable: no informative epoch yet (the published band is "
                            "the prior's)", values)
    front, rear = bound.relative_std
    known = bound.identifiability
    published = (estimate.cornering_stiffness_front_std / estimate.cornering_stiffness_front,
                 estimate.cornering_stiffness_rear_std / estimate.cornering_stiffness_rear)
    values += (("crb_cf_rel_std", f"{front:.4g}"), ("crb_cr_rel_std", f"{rear:.4g}"),
               ("crb_weak_direction", f"{known.weak_direction[0]:+.3f} {known.weak_direction[1]:+.3f}"),
               ("crb_weak_rel_std", f"{known.weak_std:.4g}"), ("crb_condition", f"{known.condition:.4g}"),
               ("published_to_crb_cf", f"{published[0] / front:.3g}"),
               ("published_to_crb_cr", f"{published[1] / rear:.3g}"))
    text = (f"Cramér-Rao bound from the last {memory:g} s: Cf +- {100 * front:.2g} %, Cr +- {100 * rear:.2g} %; "
            f"{known.describe()}")
    if known.weak_std > options.max_identifiable_rel_std:
        return HealthReport(title, WARN, f"weakly identifiable (the published band is the prior's along the weak "
                            f"direction): {text}", values)
    return HealthReport(title, OK, text, values)
