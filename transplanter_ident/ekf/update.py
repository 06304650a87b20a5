"""The covariance prediction and the Joseph-form update of the joint EKF (paper eq. 12).

:func:`make_update` compiles both for one state size (n states, nd motion states, the second
measured state h1) so that their loops unroll. F's parameter rows are [0, I] (random walks); H's vy
row is :mod:`.measurement_row`'s. The speed is an input measured with noise: the mean of an interval's two GNSS samples. Its variance
enters P through g = dx_{k+1}/dvx, and so does its first sample's, which the previous interval
used too: without that covariance the filter took the speed's errors as white, and a heading
that integrates many intervals as better known than it is (overconfident at low speed).
"""

from __future__ import annotations

from transplanter_ident.ekf.layout import (
    G_HP0,
    G_HP1,
    G_K0,
    G_K1,
    M_SPEED_CROSS,
    S_CHANGE_OFFSET_Q,
    S_CHANGE_Q,
    S_P0_OFFSET,
    V_SPEED_CROSS,
    V_SPEED_GAIN,
    W_F,
    W_GAIN,
    W_TMP,
    W_VEC,
)
from transplanter_ident.ekf.measurement_row import vy_row_times_column, vy_row_times_motion
from transplanter_ident.jit import inline_kernel


def make_update(n, nd, h1):  # noqa: ANN001, ANN201
    """The covariance kernels for n states, nd of them motion, measuring states 0 and h1.

    Returns (propagate_covariance, add_speed_noise, joseph_update, keep_speed_cross).
    """
    nf, nr, nb, ng = nd, nd + 1, nd + 2, nd + 3  # theta_f, theta_r, steering offset and gain error (then h)

    @inline_kernel
    def propagate_covariance(p, q, dt, adapting, settings, scale, ws):
        """P = F P F^T + Q dt, F = [[F_motion], [0, I]]: the parameter states are random walks, Q a density.

        While ``adapting`` (after a change alarm) the stiffness density is at least the raised one
        (relative: ``scale`` = dC/dtheta of each stiffness, 1 in log mode), and an estimated steering
        offset's at least ``ekf.change_offset_variance`` / ``change_hold``: a knocked sensor alarms too.
        """
        for i in range(nd):
            for j in range(n):
                acc = 0.0
                for k in range(n):
                    acc += ws[W_F, i, k] * p[k, j]
                ws[W_TMP, i, j] = acc
        for i in range(nd):
            for j in range(i, nd):
                acc = 0.0
                for k in range(n):
                    acc += ws[W_TMP, i, k] * ws[W_F, j, k]
                p[i, j] = acc
                p[j, i] = acc
            for j in range(nd, n):
                p[i, j] = ws[W_TMP, i, j]
                p[j, i] = ws[W_TMP, i, j]
        for i in range(n):
            density = q[i]
            if adapting and (i == nf or i == nr):
                density = max(density, settings[S_CHANGE_Q] * scale[i - nf] * scale[i - nf])
            elif adapting and i == nb and settings[S_P0_OFFSET] > 0.0:  # an estimated steering offset may have moved
                density = max(density, settings[S_CHANGE_OFFSET_Q])
            p[i, i] += density * dt

    @inline_kernel
    def add_speed_noise(p, sample_variance, memo, ws):
        """P += (var / 2) g g^T + (u g^T + g u^T) / 2 for the interval's speed error e = (n_prev + n) / 2.

        var: one GNSS speed sample's variance; g = dx_{k+1}/dvx (ws[W_VEC, V_SPEED_GAIN], from predict,
        zero beyond the motion states); c = memo[M_SPEED_CROSS:] = Cov(state error, n_prev) from the
        previous step (:func:`keep_speed_cross`), so Cov(F state error, e) = u / 2 with u = F c.
        """
        for i in range(n):
            acc = memo[M_SPEED_CROSS + i]  # the parameter rows of F are [0, I]
            if i < nd:
                acc = 0.0
                for j in range(n):
                    acc += ws[W_F, i, j] * memo[M_SPEED_CROSS + j]
            ws[W_VEC, V_SPEED_CROSS, i] = acc
        for i in range(n):
            g_i = ws[W_VEC, V_SPEED_GAIN, i] if i < nd else 0.0
            u_i = ws[W_VEC, V_SPEED_CROSS, i]
            for j in range(n):
                g_j = ws[W_VEC, V_SPEED_GAIN, j] if j < nd else 0.0
                p[i, j] += 0.5 * (sample_variance * g_i * g_j + u_i * g_j + g_i * ws[W_VEC, V_SPEED_CROSS, j])

    @inline_kernel
    def keep_speed_cross(memo, sample_variance, updated, ws):
        """memo[M_SPEED_CROSS:] = Cov(state error, n) = (I - K H) g var / 2 after the step (n: the last sample's error).

        Before the update the state's error holds g e, and Cov(e, n) = var / 2; an update (gain K in
        ws[W_GAIN], zero rows where the step held them) takes it to (I - K H) times that. g is zero
        beyond the motion states.
        """
        half = 0.5 * sample_variance
        hc0 = half * vy_row_times_motion(ws, ws[W_VEC, V_SPEED_GAIN])
        hc1 = half * ws[W_VEC, V_SPEED_GAIN, h1]
        for i in range(n):
            c = half * ws[W_VEC, V_SPEED_GAIN, i] if i < nd else 0.0
            if updated:
                c -= ws[W_GAIN, G_K0, i] * hc0 + ws[W_GAIN, G_K1, i] * hc1
            memo[M_SPEED_CROSS + i] = c

    @inline_kernel
    def joseph_update(x, p, e0, e1, s00, s01, s11, det, motion_only, heading_held, gain_held, ws):
        """X += K e; P = (I - K H) P (I - K H)^T + K R K^T with H = [H[0], e_h1] (H[0]: measurement_row.py).

        Evaluated expanded, P - K HP - (K HP)^T + K S K^T with S = H P H^T + R: the same function of
        K (so valid for any gain), in O(n^2). ``motion_only`` zeroes the parameter rows of K (a
        Schmidt update: the stiffness and offset keep their estimate and take the right covariance);
        ``heading_held`` zeroes h's row alone, ``gain_held`` g's.
        """
        i00, i01, i11 = s11 / det, -s01 / det, s00 / det
        for i in range(n):
            hp0, hp1 = vy_row_times_column(ws, n, p, i), p[h1, i]
            k0 = hp0 * i00 + hp1 * i01
            k1 = hp0 * i01 + hp1 * i11
            if (motion_only and i >= nd) or (heading_held and i == n - 1) or (gain_held and i == ng):
                k0, k1 = 0.0, 0.0
            ws[W_GAIN, G_K0, i] = k0
            ws[W_GAIN, G_K1, i] = k1
            ws[W_GAIN, G_HP0, i] = hp0
            ws[W_GAIN, G_HP1, i] = hp1
            x[i] += k0 * e0 + k1 * e1
        for i in range(n):
            k0, k1 = ws[W_GAIN, G_K0, i], ws[W_GAIN, G_K1, i]
            hp0, hp1 = ws[W_GAIN, G_HP0, i], ws[W_GAIN, G_HP1, i]
            ks0 = k0 * s00 + k1 * s01 - hp0
            ks1 = k0 * s01 + k1 * s11 - hp1
            for j in range(i, n):
                acc = (p[i, j] - k0 * ws[W_GAIN, G_HP0, j] - k1 * ws[W_GAIN, G_HP1, j]
                       + ks0 * ws[W_GAIN, G_K0, j] + ks1 * ws[W_GAIN, G_K1, j])
                p[i, j] = acc
                p[j, i] = acc

    return propagate_covariance, add_speed_noise, joseph_update, keep_speed_cross
