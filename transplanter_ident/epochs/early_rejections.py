"""Samples the assembler rejects on their own values, before it looks at any state (the batch path's first cut).

:class:`~.assembler.EpochAssembler` rejects a sample with a non-finite stamp or value, a velocity with
a driver's invalid marker or beyond ``vehicle.max_speed``, a quaternion that is no orientation, and a
steering angle beyond ``vehicle.max_steering`` before any check that reads or changes its state. So
such samples can be taken out of a sequence first: the rest behaves as it would with them in it. The
rejections themselves are made by the assembler's own methods on a fresh assembler (the same
texts), and a sample that a fresh assembler does not reject that way makes the cut fail (None).
"""

from __future__ import annotations

import math

import numpy as np

from transplanter_ident.epochs import checks
from transplanter_ident.epochs.assembler import INPUTS, AssemblerSettings, EpochAssembler
from transplanter_ident.epochs.epoch import Rejection

#: sample kinds (the assembler inputs the bag reader produces), by code
KIND_NAMES = ("velocity", "velocity_body", "heading_quaternion", "steering")
KINDS = {name: code for code, name in enumerate(KIND_NAMES)}
#: the values each input's add_* method takes after the stamp
ARITY = {"velocity": 4, "velocity_body": 4, "heading_quaternion": 5, "steering": 1}


def stateless_bad(settings: AssemblerSettings, kind: np.ndarray, stamp: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Which samples the assembler rejects on their own values (values: n x 5, as epochs.batch merges them)."""
    with np.errstate(invalid="ignore", over="ignore"):
        bad = ~np.isfinite(stamp)
        vel, head, steer = kind <= 1, kind == 2, kind == 3
        v = values
        raw = v[:, :2]
        bad |= vel & ~np.isfinite(raw).all(axis=1)
        bad |= vel & (np.isnan(v[:, 2:4]) | (v[:, 2:4] < 0.0)).any(axis=1)
        at = np.flatnonzero(vel & ~bad)
        speed = np.array(list(map(math.hypot, raw[at, 0].tolist(), raw[at, 1].tolist())))
        bad[at[speed > settings.max_speed]] = True
        q = v[:, :4]
        norm_sq = q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1] + q[:, 2] * q[:, 2] + q[:, 3] * q[:, 3]
        odd = ~np.isfinite(q).all(axis=1) | (norm_sq < 1e-12) | \
            (np.abs(np.sqrt(norm_sq) - 1.0) > checks.QUATERNION_NORM_TOLERANCE)
        bad |= head & odd
        bad |= steer & ~(np.abs(v[:, 0]) <= settings.max_steering)  # NaN included
    return bad


def early_rejections(settings: AssemblerSettings, kind: np.ndarray, stamp: np.ndarray, values: np.ndarray,
                     bad: np.ndarray) -> list[tuple[int, Rejection]] | None:
    """(arrival position, rejection) of every ``bad`` sample, made by the assembler; None if one is not rejected."""
    out = []
    for i in np.flatnonzero(bad).tolist():
        name = KIND_NAMES[int(kind[i])]
        probe = EpochAssembler(settings)
        epochs = getattr(probe, INPUTS[name])(float(stamp[i]), *values[i, :ARITY[name]].tolist())
        made = probe.drain_rejections()
        if epochs or len(made) != 1:
            return None
        out.append((i, made[0]))
    return out
