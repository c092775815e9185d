"""The stick-node data model of Meeds et al. (section 2.1) and its densities.

Conventions
-----------
Positions are complex numbers ``x = u + i v`` (2D only), so a rotation by an
angle ``theta`` is a multiplication by ``exp(i theta)``. A node (stick) ``k`` has

* ``theta[k, f]``  its angle in frame ``f``,
* ``T[k, f]``      its translation point (the proximal end, the joint with its parent),
* ``s_x[k]``       precision of a point about its rigid position in every frame,
* ``s_yh[k]``      precision of the time-invariant positions along the stick,
* ``s_yv[k]``      precision of the time-invariant positions across the stick,
* ``s_T[k]``       precision of its children's translation points about its distal end.

Its length is ``L_k = 6 / sqrt(s_yh[k])`` along the local x axis (Fig. 3 of the
paper) and a point of the stick is generated as (eqs. 1-2)::

    y_i  ~ N((L_k / 2, 0), diag(1 / s_yh, 1 / s_yv))
    x_if ~ N(exp(i theta_kf) y_i + T_kf, I / s_x)

The node prior given its parent ``p`` (eqs. 3-5) is::

    T_kf       ~ N(J_pf, I / s_pT),      J_pf = T_pf + exp(i theta_pf) L_p  (the parent's distal end)
    theta_k1   ~ vonMises(theta_p1, kappa_rho)
    theta_kf   ~ vonMises(theta_k,f-1, kappa_nd) vonMises(theta_pf, kappa_rho), normalised per frame
    s_*        ~ Gamma(a_*, b_*)

The root of the tree is a virtual node with angle 0, distal end at the origin
and a (weak) precision ``root_precision`` for its children's translations.

Eq. 5 multiplies two von Mises densities; we read it as a directed chain in
which each frame's conditional is normalised, i.e. ``theta_kf`` given
``theta_k,f-1`` and ``theta_pf`` is von Mises with mean direction and
concentration given by ``A exp(i mu) = kappa_nd exp(i theta_k,f-1) + kappa_rho exp(i theta_pf)``.
This makes the prior proper, samplable frame by frame, and gives it the
normaliser ``-log(2 pi I0(A))`` per frame, which the paper's rotation update
(eqs. 19-21) omits; :mod:`.kernels` corrects for it with a Metropolis step.

Marginal likelihood (eq. 13) with the matrix inversion and determinant lemmas
----------------------------------------------------------------------------
Stacking the frames, ``x_i ~ N(R L/2 + T, C)`` with ``C = R Sigma_y R^T + I / s_x``
where ``R`` (2F x 2) stacks the rotations. Because every block is a rotation,
``R^T R = F I_2``, so with ``D = (Sigma_y^-1 + s_x F I)^-1 = diag(d_h, d_v)``::

    C^-1   = s_x I - s_x^2 R D R^T                      (Woodbury)
    det C  = s_x^(-2F) (1 + s_x F / s_yh) (1 + s_x F / s_yv)   (determinant lemma)

and with local residuals ``r_f = exp(-i theta_f) (x_f - T_f) - L/2`` the quadratic form is
``s_x (sum_f |r_f|^2 - a_h Re(u)^2 - a_v Im(u)^2)`` with ``u = sum_f r_f`` and
``a_j = 1 / (F + s_yj / s_x)``. Only 2x2 algebra; a missing frame simply drops out
of the sums (F becomes the number of observed frames), which is how the observed-data
log-likelihood is computed.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.special import gammaln, i0e

__all__ = [
    "Hyper",
    "stick_length",
    "marginal_loglik",
    "gamma_logpdf",
    "log_i0",
    "rotation_prior_logpdf",
    "sample_rotation_prior",
    "translation_prior_logpdf",
    "distal_end",
    "translation_conditional",
    "translation_conditional_logpdf",
    "translation_sample",
    "y_posterior",
]

LOG2PI = float(np.log(2.0 * np.pi))


@dataclass(frozen=True)
class Hyper:
    """Hyper-parameters Theta of the model (the paper's section 4 defaults) and of lambda.

    Attributes
    ----------
    a_sx, b_sx, a_syh, b_syh, a_syv, b_syv, a_sT, b_sT : float
        Shape and inverse scale of the Gamma priors of the precisions.
    kappa_rho, kappa_nd : float
        Concentrations tying a stick's angle to its parent's and to its previous frame.
    root_precision : float
        Precision of the translation points of the root's children about the origin.
    lam : float
        Initial (or fixed) growth parameter lambda.
    update_lambda : bool
        Sample lambda (Escobar & West) under a Gamma(lambda_a, lambda_b) prior.
    lambda_a, lambda_b : float
    update_kappa_nd : bool
        Sample kappa_nd (the tie of an angle to its previous frame) under a
        Gamma(kappa_nd_a, kappa_nd_b) prior; ``kappa_nd`` is then its current value.
    kappa_nd_a, kappa_nd_b : float
    """

    a_sx: float = 10.0
    b_sx: float = 1.0
    a_syh: float = 100.0
    b_syh: float = 1.0
    a_syv: float = 400.0
    b_syv: float = 1.0
    a_sT: float = 100.0
    b_sT: float = 1.0
    kappa_rho: float = 1.0
    kappa_nd: float = 1.0
    root_precision: float = 0.1
    lam: float = 1.0
    update_lambda: bool = True
    lambda_a: float = 1.0
    lambda_b: float = 1.0
    update_kappa_nd: bool = False
    kappa_nd_a: float = 1.0
    kappa_nd_b: float = 0.01

    def as_dict(self) -> dict[str, float]:
        return asdict(self)

    @property
    def gamma_ab(self) -> np.ndarray:
        """(4, 2) array of (shape, rate) for s_x, s_yh, s_yv, s_T."""
        return np.array([[self.a_sx, self.b_sx], [self.a_syh, self.b_syh],
                         [self.a_syv, self.b_syv], [self.a_sT, self.b_sT]], dtype=float)


def stick_length(s_yh: np.ndarray) -> np.ndarray:
    """L = 6 / sqrt(s_yh) (the paper's Fig. 3)."""
    return 6.0 / np.sqrt(s_yh)


def log_i0(a: np.ndarray) -> np.ndarray:
    """log I0(a) without overflow."""
    a = np.asarray(a, dtype=float)
    return np.log(i0e(a)) + np.abs(a)


def gamma_logpdf(s: np.ndarray, a: float, b: float) -> np.ndarray:
    """log Gamma(s | shape a, rate b)."""
    s = np.asarray(s, dtype=float)
    return a * np.log(b) - gammaln(a) + (a - 1.0) * np.log(s) - b * s


def marginal_loglik(x: np.ndarray, theta: np.ndarray, T: np.ndarray, s_x: np.ndarray, s_yh: np.ndarray,
                    s_yv: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Log-likelihood of whole trajectories with the local positions y integrated out (eq. 13).

    All arguments broadcast against each other over their leading dimensions.

    Parameters
    ----------
    x : complex ndarray, shape (..., F)
        Trajectories.
    theta : ndarray, shape (..., F)
    T : complex ndarray, shape (..., F)
    s_x, s_yh, s_yv : ndarray, shape (...)
    w : ndarray of {0, 1}, shape (..., F), optional
        Which frames count (observed); all of them when omitted.

    Returns
    -------
    ndarray, shape (...)
    """
    s_x = np.asarray(s_x, float)
    s_yh = np.asarray(s_yh, float)
    s_yv = np.asarray(s_yv, float)
    half = 3.0 / np.sqrt(s_yh)  # L/2
    r = np.exp(-1j * theta) * (x - T) - half[..., None]
    if w is None:
        n_f = float(r.shape[-1])
        S = (r.real ** 2 + r.imag ** 2).sum(-1)
        u = r.sum(-1)
    else:
        n_f = w.sum(-1)
        S = ((r.real ** 2 + r.imag ** 2) * w).sum(-1)
        u = (r * w).sum(-1)
    a_h = 1.0 / (n_f + s_yh / s_x)
    a_v = 1.0 / (n_f + s_yv / s_x)
    quad = s_x * (S - a_h * u.real ** 2 - a_v * u.imag ** 2)
    logdet = -2.0 * n_f * np.log(s_x) + np.log1p(s_x * n_f / s_yh) + np.log1p(s_x * n_f / s_yv)
    return -n_f * LOG2PI - 0.5 * logdet - 0.5 * quad


def y_posterior(x: np.ndarray, theta: np.ndarray, T: np.ndarray, s_x: np.ndarray, s_yh: np.ndarray,
                s_yv: np.ndarray, w: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gaussian posterior of the local positions y_i given a node's parameters.

    Parameters
    ----------
    x : complex ndarray, shape (..., F)
    theta : ndarray, shape (..., F)
    T : complex ndarray, shape (..., F)
    s_x, s_yh, s_yv : ndarray, shape (...)
    w : ndarray of {0, 1}, shape (..., F), optional
        Which frames count (observed); all of them when omitted.

    Returns
    -------
    mean : complex ndarray, shape (...)
    var_h, var_v : ndarray, shape (...)
        Variances along and across the stick (the posterior is axis-aligned since R^T R = F I).
    """
    if w is None:
        F = x.shape[-1]
        z = (np.exp(-1j * theta) * (x - T)).sum(-1)  # sum_f R_f^T (x_f - T_f)
    else:
        F = w.sum(-1)
        z = (w * np.exp(-1j * theta) * (x - T)).sum(-1)
    prec_h = s_yh + F * s_x
    prec_v = s_yv + F * s_x
    half = 3.0 / np.sqrt(s_yh)
    mean = (s_yh * half + s_x * z.real) / prec_h + 1j * (s_x * z.imag) / prec_v
    return mean, 1.0 / prec_h, 1.0 / prec_v


def distal_end(theta: np.ndarray, T: np.ndarray, s_yh: np.ndarray) -> np.ndarray:
    """J_f = T_f + exp(i theta_f) L, shape (..., F)."""
    return T + np.exp(1j * theta) * stick_length(np.asarray(s_yh, float))[..., None]


def rotation_prior_logpdf(theta: np.ndarray, theta_parent: np.ndarray, kappa_rho: float,
                          kappa_nd: float) -> np.ndarray:
    """log G(theta_k | theta_parent) of the directed von Mises chain (eqs. 4-5), shape (...)."""
    lp0 = kappa_rho * np.cos(theta[..., 0] - theta_parent[..., 0]) - LOG2PI - log_i0(kappa_rho)
    if theta.shape[-1] == 1:
        return lp0
    prev = theta[..., :-1]
    par = theta_parent[..., 1:]
    A = np.abs(kappa_nd * np.exp(1j * prev) + kappa_rho * np.exp(1j * par))
    cur = theta[..., 1:]
    rest = kappa_nd * np.cos(cur - prev) + kappa_rho * np.cos(cur - par) - LOG2PI - log_i0(A)
    return lp0 + rest.sum(-1)


def sample_rotation_prior(theta_parent: np.ndarray, kappa_rho: float, kappa_nd: float,
                          rng: np.random.Generator) -> np.ndarray:
    """Draw theta_k ~ G(. | theta_parent), shape of ``theta_parent`` (..., F)."""
    out = np.empty(theta_parent.shape)
    out[..., 0] = rng.vonmises(theta_parent[..., 0], kappa_rho)
    for f in range(1, theta_parent.shape[-1]):  # a Markov chain: sequential in frames by nature
        m = kappa_nd * np.exp(1j * out[..., f - 1]) + kappa_rho * np.exp(1j * theta_parent[..., f])
        out[..., f] = rng.vonmises(np.angle(m), np.abs(m))
    return out


def translation_prior_logpdf(T: np.ndarray, J: np.ndarray, s_par: np.ndarray) -> np.ndarray:
    """sum_f log N(T_f | J_f, I / s_par), shape (...)."""
    s_par = np.asarray(s_par, float)
    d = T - J
    F = T.shape[-1]
    return F * (np.log(s_par) - LOG2PI) - 0.5 * s_par * (d.real ** 2 + d.imag ** 2).sum(-1)


def translation_conditional(theta: np.ndarray, s_x: float, s_yh: float, s_yv: float, n: int, xsum: np.ndarray,
                            J: np.ndarray, s_par: float, h: int, csum: np.ndarray,
                            s_T: float) -> tuple[np.ndarray, float, np.ndarray]:
    """Exact Gaussian conditional of a node's translations with the y_i integrated out.

    Derivation (replaces the paper's eqs. 15-17, which condition on y_i but then use
    its prior mean L/2). With ``Q = R / sqrt(F)`` (orthonormal columns), the
    precision of the stacked translations is::

        Lambda = n C^-1 + (h s_T + s_par) I = c (I - Q Q^T) + Q diag(e_h, e_v) Q^T
        c   = n s_x + h s_T + s_par
        e_j = c - n s_x^2 F / (s_yj + F s_x) = h s_T + s_par + n s_x s_yj / (s_yj + F s_x)

    and the linear term is ``b = C^-1 sum_i (x_i - R L/2) + s_T sum_c (T_c - R L) + s_par J``.
    (The parent term is centred on ``J = T_parent + R_parent L_parent``: the printed
    ``Delta T_rho = T_rho + R_rho L_rho`` is right, its "Delta" notwithstanding.) The
    directions ``Q`` -- sliding the stick along and across its own axis -- are the ones
    the data leave loose, which is why we integrate y out here instead of
    conditioning on it.

    Parameters
    ----------
    theta : ndarray, shape (F,)
    s_x, s_yh, s_yv : float
        The node's precisions.
    n : int
        Number of points at the node; ``xsum`` (complex, (F,)) their sum.
    J : complex ndarray, shape (F,)
        Parent's distal end; ``s_par`` the parent's child precision.
    h : int
        Number of children; ``csum`` (complex, (F,)) the sum of their translations; ``s_T`` the node's.

    Returns
    -------
    mean : complex ndarray, shape (F,)
    c : float
    e : ndarray, shape (2,)
        The precision's eigenvalues (c on the complement of Q, e on Q).
    """
    F = theta.shape[-1]
    rot = np.exp(1j * theta)
    L = 6.0 / np.sqrt(s_yh)
    c = n * s_x + h * s_T + s_par
    b = s_par * J + 0j
    if n:
        v = xsum - n * rot * (0.5 * L)
        Rtv = (np.conj(rot) * v).sum()
        a_h = s_x * s_x / (s_yh + F * s_x)
        a_v = s_x * s_x / (s_yv + F * s_x)
        b = b + s_x * v - rot * (a_h * Rtv.real + 1j * a_v * Rtv.imag)
    if h:
        b = b + s_T * (csum - h * rot * L)
    e = np.array([h * s_T + s_par + n * s_x * s_yh / (s_yh + F * s_x),
                  h * s_T + s_par + n * s_x * s_yv / (s_yv + F * s_x)])
    Qtb = (np.conj(rot) * b).sum() / np.sqrt(F)
    corr = (1.0 / e[0] - 1.0 / c) * Qtb.real + 1j * (1.0 / e[1] - 1.0 / c) * Qtb.imag
    mean = b / c + rot * corr / np.sqrt(F)
    return mean, c, e


def translation_sample(mean: np.ndarray, theta: np.ndarray, c: float, e: np.ndarray,
                       rng: np.random.Generator) -> np.ndarray:
    """Draw from the Gaussian of :func:`translation_conditional`."""
    F = theta.shape[-1]
    rot = np.exp(1j * theta)
    z = rng.standard_normal(F) + 1j * rng.standard_normal(F)
    Qtz = (np.conj(rot) * z).sum() / np.sqrt(F)
    ic = 1.0 / np.sqrt(c)
    corr = (1.0 / np.sqrt(e[0]) - ic) * Qtz.real + 1j * (1.0 / np.sqrt(e[1]) - ic) * Qtz.imag
    return mean + z * ic + rot * corr / np.sqrt(F)


def translation_conditional_logpdf(T: np.ndarray, mean: np.ndarray, theta: np.ndarray, c: float,
                                   e: np.ndarray) -> float:
    """log density of T under the Gaussian of :func:`translation_conditional`."""
    F = theta.shape[-1]
    d = T - mean
    Qtd = (np.conj(np.exp(1j * theta)) * d).sum() / np.sqrt(F)
    quad = c * float((d.real ** 2 + d.imag ** 2).sum()) + (e[0] - c) * Qtd.real ** 2 + (e[1] - c) * Qtd.imag ** 2
    logdet = (2 * F - 2) * np.log(c) + np.log(e[0]) + np.log(e[1])
    return float(-F * LOG2PI + 0.5 * logdet - 0.5 * quad)
