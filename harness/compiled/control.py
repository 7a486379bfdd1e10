"""Compiled paper's law (eq. ``modified density feedback law using estimates``) on the
grid, centre and face values in one pass; :func:`harness.control.paper.paper_law_reference`
is the numpy statement that tests compare against.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def paper_velocity(
    p_hat: np.ndarray,
    q_hat: np.ndarray,
    f_p: np.ndarray,
    f_grad: np.ndarray,
    t_p: np.ndarray,
    t_grad: np.ndarray,
    t_log_p: np.ndarray,
    alpha: float,
    sigma: float,
    dx: float,
    dy: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Centre and face values of the paper's law (eq. ``modified density feedback law
    using estimates``; :func:`harness.control.paper.paper_law` holds the equation and its
    discretisation, :func:`harness.control.paper.paper_law_reference` the numpy statement) in
    one pass,
    each value by the reference's operations in the reference's order (the same bits):

        feedback = (-alpha) (f_p q_hat - p_hat f_grad) / (f_p f_p),
        centres  = feedback + (sigma t_grad) / t_p,
        face_x   = 0.5 (feedback_x[:, 1:] + feedback_x[:, :-1])
                   + (sigma (log p_*[:, 1:] - log p_*[:, :-1])) / dx,   likewise face_y,

    ``f_*`` the feedback target's cell values and gradient, ``t_*`` the target's.
    """
    ny, nx = p_hat.shape
    neg = -alpha
    feedback = np.empty((2, ny, nx))
    centres = np.empty((2, ny, nx))
    for c in range(2):
        for j in range(ny):
            for i in range(nx):
                fp = f_p[j, i]
                fb = neg * (fp * q_hat[c, j, i] - p_hat[j, i] * f_grad[c, j, i]) / (fp * fp)
                feedback[c, j, i] = fb
                centres[c, j, i] = fb + sigma * t_grad[c, j, i] / t_p[j, i]
    face_x = np.empty((ny, nx - 1))
    for j in range(ny):
        for i in range(nx - 1):
            mean = 0.5 * (feedback[0, j, i + 1] + feedback[0, j, i])
            face_x[j, i] = mean + sigma * (t_log_p[j, i + 1] - t_log_p[j, i]) / dx
    face_y = np.empty((ny - 1, nx))
    for j in range(ny - 1):
        for i in range(nx):
            mean = 0.5 * (feedback[1, j + 1, i] + feedback[1, j, i])
            face_y[j, i] = mean + sigma * (t_log_p[j + 1, i] - t_log_p[j, i]) / dy
    return centres, face_x, face_y
