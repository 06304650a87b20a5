"""Output-error Fisher information of (ln Cf, ln Cr, b, g) from a drive (issue #11: the Cramér-Rao bound).

The bicycle model (paper eq. 4, discretised as the filter does, :mod:`.model`) is driven by the
measured steering and speed and started from the measured state [vy, r, psi]; it is restarted
every ``segment`` seconds (multiple shooting), after a gap and below ``min_speed``, so that an
open-loop heading never runs away. Its output sensitivities to theta = (ln Cf, ln Cr), to the
steering offset b and to the steering gain's error g (wheel = (1 + g) sensor - b) are carried forward
exactly with dE/dtheta of :func:`.model.discretize`:

    S_{k+1} = E S_k + [dE/dtheta_f u_k, dE/dtheta_r u_k, -E[:, delta], E[:, (delta, rate)] s_k]
    (u_k = [x_k; delta; rate], s_k = the sensor's ramp [start; rate])

and the information of the measurements z = [vy + antenna_x r, psi], whose noise is the
filter's full R of each epoch (:mod:`.kernels`: the body-frame vy error holds -vx e_psi; with
``ekf.measurement_noise_from_covariance``, from the variances the GNSS reports), is summed:

    I = sum_k H S_k^T R_k^-1 H S_k      (4 x 4, over ln Cf, ln Cr, b, g)

With a single antenna (``ekf.measurement: course``, the vehicle array's VEH_COURSE) psi is the antenna's
course and z that course alone, of variance R_vy / vx^2.

Its inverse is the Cramér-Rao bound of an unbiased estimate from these data at that theta.
"""

from __future__ import annotations

import math

import numpy as np

from transplanter_ident.ekf.layout import (
    E_PSI,
    E_SPEED,
    E_STEERING,
    E_STEERING_RATE,
    E_T,
    E_VAR_PSI,
    E_VAR_VY,
    E_VY,
    E_YAW_RATE,
    I_GAIN,
    I_LN_CF,
    I_LN_CR,
    I_OFFSET,
    N_INFORMATION,
    N_MOTION_HEADING,
    VEH_COURSE,
    W_DE_F,
    W_DE_R,
    W_E,
    X_PSI,
    X_R,
    X_VY,
    Z_SECOND,
    Z_VY,
)
from transplanter_ident.ekf.measurement_row import course_variance
from transplanter_ident.ekf.model import discretize_heading
from transplanter_ident.ekf.sequence import epoch_measurement_noise, innovation_covariance
from transplanter_ident.jit import entry_kernel

#: the parameters of the information matrix, in its order (layout.I_*)
STIFFNESS_PARAMETERS = ("ln_cf", "ln_cr")
INFORMATION_PARAMETERS = (*STIFFNESS_PARAMETERS, "steering_offset", "steering_gain")


@entry_kernel
def output_error_information(epochs, theta, vehicle, antenna_x, r_noise, segment, min_speed, max_interval,  # noqa: ANN001, ANN201, PLR0913
                             method, from_covariance, ws, information):
    """Add the Fisher information of ``epochs`` (kernel columns E_*) at ``theta`` to ``information`` (4, 4).

    theta : (4,)  ln Cf, ln Cr, steering offset b (rad), steering gain's relative error g
    vehicle : (N_VEHICLE,)  model.vehicle_array (VEH_COURSE: a course measured)
    r_noise : (2,)  diag R of vy (m/s)^2 and psi rad^2
    from_covariance : bool  R per epoch as the filter takes it with ``ekf.measurement_noise_from_covariance``:
        the variances the epoch reports (E_VAR_VY, E_VAR_PSI) where larger than ``r_noise``
    ws : model.work_buffer()
    Returns the number of epochs that contributed.
    """
    nd = N_MOTION_HEADING
    course = vehicle[VEH_COURSE] > 0.5  # psi is the antenna's course (model.course_row), the one measurement
    cf, cr, offset, gain = math.exp(theta[I_LN_CF]), math.exp(theta[I_LN_CR]), theta[I_OFFSET], 1.0 + theta[I_GAIN]
    x = np.zeros(nd)
    new_x = np.zeros(nd)
    sens = np.zeros((nd, N_INFORMATION))
    new_sens = np.zeros((nd, N_INFORMATION))
    r_epoch = np.empty(2)
    start = -math.inf
    used = 0
    for k in range(epochs.shape[0]):
        t, speed = epochs[k, E_T], epochs[k, E_SPEED]
        dt = t - epochs[k - 1, E_T] if k > 0 else math.inf
        if speed < min_speed or not dt <= max_interval or t - start >= segment:
            x[X_VY] = epochs[k, E_VY] - antenna_x * epochs[k, E_YAW_RATE]
            x[X_R] = epochs[k, E_YAW_RATE]
            x[X_PSI] = epochs[k, E_PSI]
            sens[:, :] = 0.0
            start = t
            continue
        sensor_rate = epochs[k, E_STEERING_RATE]
        sensor = epochs[k, E_STEERING] - 0.5 * sensor_rate * dt  # the ramp's start, as the filter drives it
        delta, rate = gain * sensor - offset, gain * sensor_rate
        discretize_heading(cf, cr, cf, cr, speed, dt, vehicle, method, False, 0.0, ws)
        for i in range(nd):
            acc = ws[W_E, i, nd] * delta + ws[W_E, i, nd + 1] * rate
            d_f = ws[W_DE_F, i, nd] * delta + ws[W_DE_F, i, nd + 1] * rate
            d_r = ws[W_DE_R, i, nd] * delta + ws[W_DE_R, i, nd + 1] * rate
            for j in range(nd):
                acc += ws[W_E, i, j] * x[j]
                d_f += ws[W_DE_F, i, j] * x[j]
                d_r += ws[W_DE_R, i, j] * x[j]
            new_x[i] = acc
            new_sens[i, I_LN_CF] = d_f
            new_sens[i, I_LN_CR] = d_r
            new_sens[i, I_OFFSET] = -ws[W_E, i, nd]
            new_sens[i, I_GAIN] = ws[W_E, i, nd] * sensor + ws[W_E, i, nd + 1] * sensor_rate
            for p in range(N_INFORMATION):
                for j in range(nd):
                    new_sens[i, p] += ws[W_E, i, j] * sens[j, p]
        for i in range(nd):  # element by element: a slice assignment compiles numba's shape-error message (~3 s)
            x[i] = new_x[i]
            for p in range(N_INFORMATION):
                sens[i, p] = new_sens[i, p]
        # R of z = [vy_antenna, psi] as the filter takes it, inverted
        epoch_measurement_noise(r_noise, from_covariance, True, epochs[k, E_VAR_VY], epochs[k, E_VAR_PSI], 0.0,
                                r_epoch)
        second = course_variance(r_epoch[Z_VY], speed) if course else r_epoch[Z_SECOND]
        s00, s01, s11 = innovation_covariance(not course, 0.0, 0.0, 0.0, r_epoch[Z_VY], second, speed)
        det = s00 * s11 - s01 * s01
        i00, i01, i11 = s11 / det, -s01 / det, s00 / det
        vy_weight = 0.0 if course else 1.0  # a course measures no vy (measurement_row.predict_vy)
        for p in range(N_INFORMATION):
            h0p = vy_weight * (sens[X_VY, p] + antenna_x * sens[X_R, p])
            h1p = sens[X_PSI, p]
            for q in range(N_INFORMATION):
                h0q = vy_weight * (sens[X_VY, q] + antenna_x * sens[X_R, q])
                h1q = sens[X_PSI, q]
                information[p, q] += h0p * (i00 * h0q + i01 * h1q) + h1p * (i01 * h0q + i11 * h1q)
        used += 1
    return used
