"""What the joint EKF does after a diverged step (issue #14: after a divergence the filter re-initialises itself).

A step that leaves a non-finite state, output or covariance, or a variance beyond MAX_VARIANCE
(:mod:`.kernels`, step 7), is rolled back: the epoch changes nothing (status DIVERGED). Rolling
back is not enough when the divergence lasts, e.g. after a run-time Q of 1e300: the covariance
that a re-initialising path kept can itself be beyond bounds, and then every later step diverges,
even once Q is restored. So the filter re-initialises (status RESTARTED) when

* the rolled-back state is itself beyond bounds, or
* MAX_DIVERGED steps in a row diverged;

then the motion states come from the measurement (as after a gap), and when it is the parameter
states [theta_f, theta_r, b, h] that diverged (in the failed step, or already before it), their
covariance goes back to P0 (``S_P0_THETA_F``, ``S_P0_THETA_R``, ``S_P0_OFFSET``, ``S_P0_STEERING_GAIN``, ``S_P0_HEADING_OFFSET``).
Their values are kept: they are finite and within the stiffness bounds after a rollback (a non-finite
one would restart from the middle of the bounds, or a zero offset).
"""

from __future__ import annotations

import math

from transplanter_ident.ekf.layout import (
    M_CUSUM,
    M_DIVERGED,
    M_SHIFT,
    N_MODEL,
    N_SHIFT,
    S_HIGH,
    S_LOW,
    S_P0_HEADING_OFFSET,
    S_P0_OFFSET,
    S_P0_STEERING_GAIN,
    S_P0_THETA_F,
    S_P0_THETA_R,
    V_BACKUP_CHANGE,
    V_BACKUP_MODEL,
    V_BACKUP_X,
    W_BACKUP_P,
    W_VEC,
    X_R,
    X_VY,
    StepStatus,
)
from transplanter_ident.jit import called_kernel, inline_kernel

#: consecutive diverged steps after which the filter re-initialises
MAX_DIVERGED = 5


def make_recovery(n, nd, max_variance, write_outputs, restart_motion):  # noqa: ANN001, ANN201
    """(``bounded``, ``recover``): the step's health test and its divergence branch, for n states, nd of them motion.

    ``write_outputs`` and ``restart_motion`` are the step's own helpers (:func:`.kernels.make_kernels`).
    """
    nf, nr, nb, ng = nd, nd + 1, nd + 2, nd + 3

    @inline_kernel
    def bounded(x, p, first):
        """States first..n-1 finite, their covariance rows finite and their variances at most max_variance."""
        for i in range(first, n):
            if not math.isfinite(x[i]) or not p[i, i] <= max_variance:
                return False
            for j in range(n):
                if not math.isfinite(p[i, j]):
                    return False
        return True

    @inline_kernel
    def reset_parameters(x, p, settings):
        """The parameter states' covariance back to P0 (uncorrelated); a non-finite value to a neutral one."""
        for i in range(nf, n):
            for j in range(n):
                p[i, j] = 0.0
                p[j, i] = 0.0
        p[nf, nf] = settings[S_P0_THETA_F]
        p[nr, nr] = settings[S_P0_THETA_R]
        p[nb, nb] = settings[S_P0_OFFSET]
        p[ng, ng] = settings[S_P0_STEERING_GAIN]
        p[n - 1, n - 1] = settings[S_P0_HEADING_OFFSET]
        for k in (nf, nr):
            if not math.isfinite(x[k]):
                x[k] = 0.5 * (settings[S_LOW] + settings[S_HIGH])
        for k in (nb, ng, n - 1):
            if not math.isfinite(x[k]):
                x[k] = 0.0

    @called_kernel
    def recover(x, p, model, memo, settings, t, vy_antenna, psi, yaw_rate, ws, out):
        """Roll the step back (DIVERGED), or re-initialise when the divergence lasts (RESTARTED)."""
        parameters_diverged = not bounded(x, p, nf)
        for i in range(n):
            x[i] = ws[W_VEC, V_BACKUP_X, i]
            for j in range(n):
                p[i, j] = ws[W_BACKUP_P, i, j]
        for i in range(N_MODEL):
            model[i] = ws[W_VEC, V_BACKUP_MODEL, i]
        memo[M_CUSUM] = ws[W_VEC, V_BACKUP_CHANGE, 0]
        for i in range(N_SHIFT):
            memo[M_SHIFT + i] = ws[W_VEC, V_BACKUP_CHANGE, 1 + i]
        memo[M_DIVERGED] += 1.0
        out[:] = 0.0
        if memo[M_DIVERGED] < MAX_DIVERGED and bounded(x, p, 0):
            write_outputs(x, p, memo, settings, StepStatus.DIVERGED, model[X_R], model[X_VY], out)
            return StepStatus.DIVERGED
        if parameters_diverged or not bounded(x, p, nf):
            reset_parameters(x, p, settings)
        return restart_motion(x, p, model, memo, settings, StepStatus.RESTARTED, t, vy_antenna, psi, yaw_rate, out)

    return bounded, recover
