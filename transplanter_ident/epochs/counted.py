"""Epochs with the input samples rejected before each (issue #14: the estimate is invalid while the input is suspect).

The node counts, for every epoch, the samples that were rejected since the previous epoch (by its
own message conversion and by the assembler, drained after every message; not the kinds in
:data:`.checks.NOT_SUSPECT`, such as a faster GNSS stream's surplus), and hands the count to
the validity decision (:attr:`transplanter_ident.evaluation.validity.Sample.rejected`).
:func:`assemble_counting` counts the same way offline, in the order the samples are processed, so
that the decision agrees online and offline.
"""

from __future__ import annotations

from collections.abc import Iterable

from transplanter_ident.epochs.assembler import INPUTS, EpochAssembler
from transplanter_ident.epochs.checks import NOT_SUSPECT
from transplanter_ident.epochs.epoch import Epoch, Rejection


def assemble_counting(assembler: EpochAssembler, samples: Iterable[tuple[str, float, tuple[float, ...]]],
                      source_rejections: list[Rejection]) -> tuple[list[Epoch], list[int], list[Rejection]]:
    """Feed (input, stamp, values) samples in order, as :func:`.assembler.assemble` does.

    ``source_rejections`` is the list that ``samples`` appends the messages it could not use to
    while it is iterated (undecodable bytes, a JointState without the steering joint).

    Returns the epochs, per epoch the rejections (of the source and the assembler) since the
    previous epoch, and the assembler's rejections.
    """
    adders = {name: getattr(assembler, method) for name, method in INPUTS.items()}
    epochs: list[Epoch] = []
    counts: list[int] = []
    drained: list[Rejection] = []
    pending, seen = 0, len(source_rejections)
    for name, stamp, values in samples:
        new = adders[name](stamp, *values)
        now = assembler.drain_rejections()
        drained.extend(now)
        pending += sum(r.kind not in NOT_SUSPECT for r in now) + len(source_rejections) - seen
        seen = len(source_rejections)
        for epoch in new:
            epochs.append(epoch)
            counts.append(pending)
            pending = 0
    return epochs, counts, drained
