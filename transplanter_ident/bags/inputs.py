"""A bag decoded once into its input samples (and ground truth), for re-assembling epochs many times.

``tuner --estimate-delay`` searches ``gnss.delay`` (DESIGN.md section 7): every candidate delay
gives its own epochs (the epoch times and steering intervals move), but the decoded messages
do not change. :func:`read_bag_inputs` keeps the ``(input, stamp, values)`` samples of one
streaming pass (:func:`.reader.read_samples`'s stream) and the ``/sim/*`` truth, so the epochs
for any delay are :func:`transplanter_ident.tuning.delay.assemble_epochs` of the samples,
without reading the bag again.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from transplanter_ident.bags.errors import BagError
from transplanter_ident.bags.reader import Truth, _build_truth, _Scan

Sample = tuple[str, float, tuple[float, ...]]


@dataclass(frozen=True)
class BagInputs:
    """A bag's input samples in log-time order and its ground truth (None for a recorded bag)."""

    bag: str
    samples: tuple[Sample, ...]
    truth: Truth | None
    note: str = ""  # a partial bag (``allow_partial``): what could not be read


def read_bag_inputs(bag: str, params: Any, allow_partial: bool = False) -> BagInputs:
    """One pass over ``bag``: its input samples and ground truth (BagError as :func:`.reader.read_bag`)."""
    scan = _Scan(bag, params, truth=True, progress=False)
    samples = tuple(scan.samples())
    missing = scan.shortfall()
    if missing and not allow_partial:
        raise BagError(f"{bag}: messages read differ from the bag's own counts ({'; '.join(missing)}): a corrupt "
                       "or truncated chunk was skipped (use --allow-partial to go on with what could be read)")
    note = f"partial bag: messages read of the bag's own counts: {'; '.join(missing)}" if missing else ""
    return BagInputs(bag, samples, _build_truth(scan.truth_rows), note)
