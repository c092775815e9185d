"""The EM updates of method "em": each one must not decrease the objective, and the
closed forms derived in docs/em.md must match brute-force answers."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from sklearn.metrics import adjusted_rand_score

import stickfigure as sf
from stickfigure import geometry as G
from stickfigure.models.em import structure as S
from stickfigure.models.em import updates as U
from stickfigure.models.em.assign import candidate_fits, resample_assignments
from stickfigure.models.em.initialise import end_positions, initial_state
from stickfigure.models.em.model import Priors, normalise, objective, objective_terms, structure_log_prior


@pytest.fixture(scope="module")
def scene():
    traj = sf.synthetic.random_figure(n_sticks=4, frames=50, noise=0.01, seed=3)
    xy = traj.xy.copy()
    rng = np.random.default_rng(0)
    xy[rng.random(xy.shape[:2]) < 0.1] = np.nan  # missing data everywhere
    obs, _, _ = normalise(xy)
    return traj, obs


def _state(scene, n_ends=3, endpoint_init="axis"):
    traj, obs = scene
    pri = Priors()
    st = initial_state(obs, traj.labels_true, traj.n_parts_true, pri, np.random.default_rng(0),
                       endpoint_init=endpoint_init, n_ends=n_ends)
    return st, obs, pri


STEPS = [
    ("endpoints", lambda st, obs, pri: U.update_endpoints(st)),
    ("vertices", lambda st, obs, pri: U.update_vertices(st)),
    ("phi", lambda st, obs, pri: U.update_phi(st, pri)),
    ("motions", lambda st, obs, pri: U.update_motions(st, obs)),
    ("motions-global", lambda st, obs, pri: U.update_motions(st, obs, global_search=True)),
    ("motions-joint", lambda st, obs, pri: U.update_motions(st, obs, collapse=True)),
    ("local", lambda st, obs, pri: U.update_local(st, obs, pri)),
    ("ends", lambda st, obs, pri: U.update_ends(st, pri)),
    ("precisions", lambda st, obs, pri: U.update_precisions(st, obs, pri)),
]


def _assert_sweeps_monotone(st, obs, pri, n_sweeps: int = 6) -> None:
    """Every update in STEPS, in turn, never lowers the objective (up to round-off)."""
    prev = objective(st, obs, pri)
    for sweep in range(n_sweeps):
        for name, step in STEPS:
            step(st, obs, pri)
            cur = objective(st, obs, pri)
            assert cur >= prev - 1e-9 * abs(prev), f"{name} decreased the objective in sweep {sweep}"
            prev = cur


@pytest.mark.parametrize("n_ends,endpoint_init", [(2, "centroid"), (3, "axis")])
def test_every_update_is_monotone(scene, n_ends, endpoint_init):
    st, obs, pri = _state(scene, n_ends, endpoint_init)
    _assert_sweeps_monotone(st, obs, pri)


def test_monotone_after_merges_with_ghost_endpoints(scene):
    st, obs, pri = _state(scene)
    settings = S.EMSettings(n_iter=20, resample_every=0)
    st, _, _ = S.run_em(st, obs, pri, settings, 20, np.random.default_rng(0), resample=False)
    cand = S.merge_candidates(st, settings)[0]
    st = S.merge_vertices(st, cand, pri, "joint")
    sub, sobs, _ = S._block(st, obs, np.unique(cand.ends // st.ends_per_stick))
    prev = sum(x.sum() for x in objective_terms(sub, sobs, pri))
    for _ in range(5):
        for name, step in STEPS[:-1]:  # blocks keep the global precisions fixed
            step(sub, sobs, pri)
            ps, pv = objective_terms(sub, sobs, pri)
            cur = ps.sum() + pv.sum()
            assert cur >= prev - 1e-9 * abs(prev), f"{name} decreased a block objective"
            prev = cur


def test_translation_update_is_the_derived_closed_form(scene):
    # t = [tau_w sum_p o (w - R l) + tau_m sum_i (mu(e_i) - R k_i)] / (tau_w n_sf + E tau_m)
    st, obs, pri = _state(scene)
    U.update_motions(st, obs)
    E = st.ends_per_stick
    for s in range(st.n_sticks):
        pts = np.flatnonzero(st.labels == s)
        m = obs.mask[pts]  # (n, F)
        Rl = np.einsum("fdk,pk->pfd", st.rot[s], st.local[pts])
        num = st.tau_w * np.einsum("pf,pfd->fd", m, obs.w[pts] - Rl)
        ends = np.arange(E * s, E * (s + 1))
        Rk = np.einsum("fdk,ik->ifd", st.rot[s], st.ends[ends])
        num += st.tau_m * np.sum(st.mu_e[ends] - Rk, axis=0)
        den = st.tau_w * m.sum(axis=0) + E * st.tau_m
        np.testing.assert_allclose(st.trans[s], num / den[:, None], rtol=1e-9, atol=1e-12)


def test_joint_motion_and_endpoint_step_is_the_derived_closed_form(scene):
    # collapse=True: for fixed vertices, motion and endpoint means are optimised together. The
    # endpoints' terms become tau_m a / (tau_m + a) |M k - mu(v)|^2, so t is the weighted
    # centroid formula with those weights and vertex targets, and mu(e) is then its own optimum.
    st, obs, pri = _state(scene)
    U.update_vertices(st)
    U.update_motions(st, obs, collapse=True)
    E = st.ends_per_stick
    a = (st.alpha / st.beta)[st.vertex_of]
    wm = st.tau_m * a / (st.tau_m + a)
    for s in range(st.n_sticks):
        pts = np.flatnonzero(st.labels == s)
        m = obs.mask[pts]
        Rl = np.einsum("fdk,pk->pfd", st.rot[s], st.local[pts])
        num = st.tau_w * np.einsum("pf,pfd->fd", m, obs.w[pts] - Rl)
        ends = np.arange(E * s, E * (s + 1))
        Rk = np.einsum("fdk,ik->ifd", st.rot[s], st.ends[ends])
        num += np.einsum("i,ifd->fd", wm[ends], st.mu_v[st.vertex_of[ends]] - Rk)
        den = st.tau_w * m.sum(axis=0) + wm[ends].sum()
        np.testing.assert_allclose(st.trans[s], num / den[:, None], rtol=1e-9, atol=1e-12)
    mu_e = st.mu_e.copy()
    U.update_endpoints(st)
    np.testing.assert_allclose(st.mu_e, mu_e, rtol=1e-12, atol=1e-12)


def test_joint_step_reaches_the_data_where_endpoints_anchor_the_paper_order(scene):
    # One stick turned away from its fitted pose, its endpoints pushed far from its points
    # (a loose endpoint can drift metres away in training): the paper's order moves the
    # rotation a small part of the way per sweep, the joint step gets there.
    _, obs = scene
    st, _, pri = _state(scene)
    settings = S.EMSettings(n_iter=60, resample_every=0)
    st, _, _ = S.run_em(st, obs, pri, settings, 60, np.random.default_rng(0), resample=False)
    E = st.ends_per_stick
    lone = st.vertex_counts()[st.vertex_of] == 1
    s = int(np.argmax(lone.reshape(-1, E).sum(axis=1)))
    ends = np.arange(E * s, E * (s + 1))
    far = ends[lone[ends]]
    assert far.size  # the premise: a stick with an endpoint on no joint
    st.ends[far] *= 8.0
    # A loose endpoint far out moves jerkily, and its vertex's precision phi falls far below
    # tau_m (HDM05: phi 2 and 31 against tau_m 1.1e6 on a chest stick; docs/em.md section 8).
    v = st.vertex_of[far]
    st.beta[v] = st.alpha[v] / (1e-3 * st.tau_w)
    U.update_endpoints(st)
    U.update_vertices(st)
    U.update_endpoints(st)
    truth = st.rot[s].copy()
    turn = Rotation.from_rotvec([0.0, 0.0, 0.6]).as_matrix()
    results = {}
    for collapse in (False, True):
        u = st.copy()
        u.rot[s] = u.rot[s] @ turn
        U.update_endpoints(u)
        for _ in range(10):
            U.update_endpoints(u)
            U.update_vertices(u)
            U.update_motions(u, obs, collapse=collapse, hold=None, newton=True)
        results[collapse] = float(np.max(np.abs(u.rot[s] - truth)))
    assert results[True] < 0.05 < results[False]


def test_rotation_concentration_matches_a_steady_turn():
    # R_f turns by theta per frame about the viewing axis: D - tr(R_f R_f-1^T) = 2 - 2 cos theta.
    from stickfigure.models.em.impute import rotation_concentration

    theta = 0.05
    R = Rotation.from_rotvec(np.outer(np.arange(30) * theta, [0.0, 0.0, 1.0])).as_matrix()[:, :2, :]
    kappa = rotation_concentration(np.stack([R, R[:1].repeat(30, axis=0)]))
    assert kappa[0] == pytest.approx(1.0 / (2.0 - 2.0 * np.cos(theta)))
    assert kappa[1] > 1e10  # a still stick: a stiff prior
    assert rotation_concentration(R[None, :1]).tolist() == [0.0]
    with pytest.raises(ValueError, match=r"\(S, F, D, 3\)"):
        rotation_concentration(R)


def test_rotation_prior_is_the_map_given_the_neighbours(scene):
    # With kappa, the motion step's energy gains -2 kappa tr(R (R_f-1 + R_f+1)^T): a frame
    # whose data are weighted down to nothing takes the mean of its neighbours' rotations.
    st, obs, pri = _state(scene)
    U.update_endpoints(st)
    f = 20
    weak = obs.mask.copy()
    weak[:, f] = 0.0  # no point seen in frame f
    w_obs = type(obs)(obs.w * weak[..., None], weak)
    u = st.copy()
    u.ends[:] = 0.0  # endpoints at the sticks' origins carry no rotation either
    u.tau_m = 1e-9
    U.update_endpoints(u)
    kappa = np.full(u.n_sticks, 5.0)
    mean = u.rot[:, f - 1] + u.rot[:, f + 1]
    U.update_motions(u, w_obs, hold=None, kappa=kappa, global_search=True)
    # The maximiser of tr(R M^T) over orthonormal rows is the polar factor of M.
    Uu, _, Vt = np.linalg.svd(mean, full_matrices=False)
    np.testing.assert_allclose(u.rot[:, f], Uu @ Vt, atol=1e-6)


def test_centroid_concentration_matches_a_random_walk_whatever_the_turns():
    # c_f = R_f lbar + t_f takes Gaussian steps of s.d. sigma per coordinate; the sticks turn at
    # random about their centroids (a flat stick's mirror flips too): lam = D / mean |step|^2.
    from stickfigure.models.em.impute import centroid_concentration

    rng = np.random.default_rng(4)
    S, F, sigma = 3, 4000, 0.02
    R = Rotation.random(S * F, random_state=5).as_matrix()[:, :2, :].reshape(S, F, 2, 3)
    lbar = rng.normal(size=(S, 3))
    c = np.cumsum(rng.normal(scale=sigma, size=(S, F, 2)), axis=1)
    t = c - np.einsum("sfdj,sj->sfd", R, lbar)
    lam = centroid_concentration(R, t, lbar)
    steps = np.mean(np.sum(np.diff(c, axis=1) ** 2, axis=-1), axis=1)
    np.testing.assert_allclose(lam, 2.0 / steps, rtol=1e-9)
    np.testing.assert_allclose(lam, 1.0 / sigma ** 2, rtol=0.05)
    assert centroid_concentration(R[:, :1], t[:, :1], lbar).tolist() == [0.0] * S
    with pytest.raises(ValueError, match="centroids"):
        centroid_concentration(R, t, lbar[:, :2])


def _pooled_moments(weights, targets, sources):
    """Brute-force weighted centroids and centred moments of one Procrustes problem."""
    w, a, b = (np.asarray(x, float) for x in (weights, targets, sources))
    W = w.sum()
    a_bar, b_bar = w @ a / W, w @ b / W
    return a_bar, b_bar, (w[:, None] * (a - a_bar)).T @ (b - b_bar), (w[:, None] * (b - b_bar)).T @ (b - b_bar)


def test_centroid_prior_is_one_more_source_point(scene):
    # With lam, each (stick, frame) problem pools its visible points (tau_w), its endpoints (the
    # series weight, vertex targets) and the stick's centroid lbar, weight lam times the number
    # of neighbouring frames, target the neighbours' mean centroid: checked against the moments
    # of that pooled set computed from scratch, and the translation against its closed form.
    st, obs, pri = _state(scene)
    U.update_vertices(st)
    lam = np.linspace(50.0, 5e4, st.n_sticks)
    a_bar, b_bar, C_ab, C_bb = U._motion_statistics(st, obs, collapse=True, lam=lam)
    E, F = st.ends_per_stick, st.trans.shape[1]
    a = (st.alpha / st.beta)[st.vertex_of]
    wm = st.tau_m * a / (st.tau_m + a)
    lbar = U.stick_centroids(st)
    cen = np.einsum("sfdj,sj->sfd", st.rot, lbar) + st.trans
    for s in range(st.n_sticks):
        pts = np.flatnonzero(st.labels == s)
        np.testing.assert_allclose(lbar[s], st.local[pts].mean(axis=0))
        ends = np.arange(E * s, E * (s + 1))
        for f in (0, 17, F - 1):
            nb = [g for g in (f - 1, f + 1) if 0 <= g < F]
            seen = pts[obs.mask[pts, f] > 0]
            w = np.r_[np.full(seen.size, st.tau_w), wm[ends], lam[s] * len(nb)]
            tgt = np.r_[obs.w[seen, f], st.mu_v[st.vertex_of[ends], f], [cen[s, nb].mean(axis=0)]]
            src = np.r_[st.local[seen], st.ends[ends], [lbar[s]]]
            want = _pooled_moments(w, tgt, src)
            for got, ref in zip((a_bar[s, f], b_bar[s, f], C_ab[s, f], C_bb[s, f]), want):
                np.testing.assert_allclose(got, ref, rtol=1e-8, atol=1e-10)
    u = st.copy()
    U.update_motions(u, obs, collapse=True, lam=lam, hold=None)
    t = a_bar - np.einsum("sfdj,sfj->sfd", u.rot, b_bar)  # the closed form for the new rotations
    np.testing.assert_allclose(u.trans, t, rtol=1e-9, atol=1e-12)


def test_centroid_prior_carries_a_hidden_stick_along_its_path(scene):
    # A stick that shows no point for a run of frames, and whose endpoints pull with almost no
    # weight, keeps its centroid on the straight line between the frames either side.
    st, obs, pri = _state(scene)
    s, run = 1, np.arange(20, 27)
    pts = np.flatnonzero(st.labels == s)
    mask = obs.mask.copy()
    mask[np.ix_(pts, run)] = 0.0
    sub = type(obs)(obs.w * mask[..., None], mask)
    u = st.copy()
    u.beta[:] = u.alpha / 1e-9  # vertex precisions ~0: joints hold nothing
    lam = np.full(u.n_sticks, 1e3)
    for _ in range(400):  # Jacobi sweeps: the run's centroids relax to the interpolation
        U.update_endpoints(u)
        U.update_vertices(u)
        U.update_motions(u, sub, collapse=True, lam=lam, hold=None)
    c = np.einsum("fdj,j->fd", u.rot[s], U.stick_centroids(u)[s]) + u.trans[s]
    lo, hi = run[0] - 1, run[-1] + 1
    x = (run - lo) / (hi - lo)
    np.testing.assert_allclose(c[run], (1 - x)[:, None] * c[lo] + x[:, None] * c[hi], atol=1e-3)


def test_rotation_prior_releases_held_sticks_of_three_points(scene, monkeypatch):
    # refit_motions holds a stick's rotation where its visible points and joints number fewer
    # than 3. With the rotation prior (kappa) only sticks of 1 or 2 points stay held: a larger
    # one is placed by its neighbours' rotations, its joints and its path (docs/em.md section 8).
    from stickfigure.models.em import impute as I

    traj, obs = scene
    labels = traj.labels_true.copy()
    pair = np.flatnonzero(labels == 0)[:2]
    labels[pair] = labels.max() + 1  # a 2-point stick
    st = initial_state(obs, labels, int(labels.max()) + 1, Priors(), np.random.default_rng(0))
    mask = obs.mask.copy()
    mask[:, 10:14] = 0.0  # nothing seen in four frames: every stick under-determined there
    sub = type(obs)(obs.w * mask[..., None], mask)
    seen = []
    real = I.em_sweep

    def recording_sweep(*args, **kwargs):  # the hold that refit_motions passes to each sweep
        seen.append(kwargs["hold"])
        return real(*args, **kwargs)

    monkeypatch.setattr(I, "em_sweep", recording_sweep)
    settings = S.EMSettings(resample_every=0)
    size = np.bincount(st.labels)
    for kappa in (None, np.full(st.n_sticks, 5.0)):
        seen.clear()
        I.refit_motions(st.copy(), sub, Priors(), settings, 1, collapse=True, kappa=kappa)
        old_rule = st.design(sub).n + st.joints_per_stick()[:, None] < 3
        assert old_rule[:, 10:14].all()
        want = old_rule if kappa is None else old_rule & (size < 3)[:, None]
        np.testing.assert_array_equal(seen[0], want)
    assert seen[0][size < 3][:, 10:14].all() and not seen[0][size >= 3].any()


def test_vertex_update_solves_the_chain_exactly(scene):
    st, obs, pri = _state(scene)
    U.update_endpoints(st)
    U.update_vertices(st)
    exact = st.mu_v.copy()
    # The paper's coordinate-wise update applied to the exact solution leaves it unchanged.
    a = st.alpha / st.beta
    n = st.vertex_counts()
    s = np.zeros_like(st.mu_v)
    np.add.at(s, st.vertex_of, st.mu_e)
    F = st.n_frames
    nb = np.zeros_like(exact)
    nb[:, 1:] += st.tau_t * exact[:, :-1]
    nb[:, :-1] += st.tau_t * exact[:, 1:]
    deg = np.full(F, 2.0)
    deg[[0, -1]] = 1.0
    paper = (a[:, None, None] * s + nb) / (a[:, None] * n[:, None] + st.tau_t * deg)[..., None]
    np.testing.assert_allclose(paper, exact, atol=1e-10)
    np.testing.assert_allclose(st.tau_v, (a * n)[:, None] + st.tau_t * deg[None, :])


def test_rotation_steps_never_increase_the_energy():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(200, 2, 7))
    B = rng.normal(size=(200, 3, 7))
    B[:50, 2] *= 1e-3  # nearly planar sources: several local minima
    C_ab, C_bb = A @ np.swapaxes(B, 1, 2), B @ np.swapaxes(B, 1, 2)
    R = Rotation.random(200, random_state=2).as_matrix()[:, :2]
    e = U._rotation_energy(R, C_ab, C_bb)
    for _ in range(5):
        R, _ = U.procrustes_step(R, C_ab, C_bb)
        e2 = U._rotation_energy(R, C_ab, C_bb)
        assert np.all(e2 <= e + 1e-9)
        e = e2
        R = U.newton_step(R, C_ab, C_bb)
        e2 = U._rotation_energy(R, C_ab, C_bb)
        assert np.all(e2 <= e + 1e-9)
        e = e2
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(2), (200, 2, 2)), atol=1e-10)
    Rb = U.best_rotations(R, C_ab, C_bb, np.broadcast_to(np.eye(3), (200, 3, 3)), np.ones(200, bool))
    assert np.all(U._rotation_energy(Rb, C_ab, C_bb) <= e + 1e-9)


def test_newton_derivatives_match_finite_differences():
    rng = np.random.default_rng(4)
    B = rng.normal(size=(3, 3, 6))
    C_bb = B @ np.swapaxes(B, 1, 2)
    C_ab = rng.normal(size=(3, 2, 6)) @ np.swapaxes(B, 1, 2)
    R0 = Rotation.random(3, random_state=5).as_matrix()[:, :2]

    def f(w):
        return U._rotation_energy(R0 @ Rotation.from_rotvec(w).as_matrix(), C_ab, C_bb)

    # The Newton step from R0 lands where the quadratic model (g, H) predicts: check g, H
    # through a finite-difference model of f at R0.
    eps = 1e-5
    g = np.stack([(f(eps * np.eye(3)[k][None].repeat(3, 0)) - f(-eps * np.eye(3)[k][None].repeat(3, 0))) / (2 * eps)
                  for k in range(3)], -1)
    g_an, H_an = G.rotation_newton_model(R0, C_ab, C_bb)
    np.testing.assert_allclose(g_an, g, rtol=1e-5, atol=1e-6)
    # The Hessian (closed form of T = tr(P K_a C K_b)) against second differences.
    eps = 1e-4
    E = np.eye(3)
    H = np.empty((3, 3, 3))
    for a in range(3):
        for b in range(3):
            def at(sa, sb):
                return f(np.repeat((sa * E[a] + sb * E[b])[None] * eps, 3, 0))
            H[:, a, b] = (at(1, 1) - at(1, -1) - at(-1, 1) + at(-1, -1)) / (4 * eps ** 2)
    H = 0.5 * (H + np.swapaxes(H, 1, 2))
    np.testing.assert_allclose(H_an, H, rtol=1e-4, atol=1e-4 * np.abs(H).max())
    for D in (2, 3):  # the step lowers f for both the projected (2 rows) and full rotations
        R = Rotation.random(3, random_state=6).as_matrix()[:, :D]
        Ca = rng.normal(size=(3, D, 6)) @ np.swapaxes(B, 1, 2)
        assert np.all(U._rotation_energy(U.newton_step(R, Ca, C_bb), Ca, C_bb)
                      <= U._rotation_energy(R, Ca, C_bb) + 1e-12)


def test_quaternions_round_trip():
    R = Rotation.random(50, random_state=0).as_matrix()
    q = U.rot_to_quat(R)
    np.testing.assert_allclose(U.quat_to_rot(q), R, atol=1e-12)


def test_frame_and_point_subsets_of_the_observations_are_c_ordered():
    # The compiled loops take C-ordered arrays and copy anything else on every call; indexing
    # the frame axis with an index array leaves a strided result unless it is made C-ordered.
    rng = np.random.default_rng(2)
    obs, _, _ = normalise(rng.normal(size=(6, 30, 2)))
    for sub in (obs.take_frames(np.arange(0, 30, 3)), obs.take(np.array([0, 2, 5]))):
        assert sub.w.flags.c_contiguous and sub.mask.flags.c_contiguous
    np.testing.assert_array_equal(obs.take_frames(np.array([1, 4])).w, obs.w[:, [1, 4]])


def test_vertex_sums_add_in_the_order_of_np_add_at():
    # updates._vertex_sums sums endpoint means per vertex in a compiled loop; the same additions
    # in the same order as np.add.at, so the same bits (the EM's results do not move).
    from stickfigure.models.em import _point_kernels as PK

    rng = np.random.default_rng(5)
    index = rng.integers(0, 7, size=40)
    x = rng.normal(size=(40, 9)) * 10.0 ** rng.integers(-8, 8, size=(40, 1))
    want = np.zeros((8, 9))
    np.add.at(want, index, x)
    got = np.full((8, 9), np.nan)
    PK.row_sums(index.astype(np.int64), x, got)
    np.testing.assert_array_equal(got, want)


def _horn(C):
    """Horn's 4x4 matrix N with q^T N q = tr(R(q)^T C) (reference for the compiled loop)."""
    c = C
    tr = c[..., 0, 0] + c[..., 1, 1] + c[..., 2, 2]
    rows = [[tr, c[..., 2, 1] - c[..., 1, 2], c[..., 0, 2] - c[..., 2, 0], c[..., 1, 0] - c[..., 0, 1]],
            [None, 2 * c[..., 0, 0] - tr, c[..., 0, 1] + c[..., 1, 0], c[..., 0, 2] + c[..., 2, 0]],
            [None, None, 2 * c[..., 1, 1] - tr, c[..., 1, 2] + c[..., 2, 1]],
            [None, None, None, 2 * c[..., 2, 2] - tr]]
    N = np.empty(C.shape[:-2] + (4, 4))
    for a in range(4):
        for b in range(a, 4):
            N[..., a, b] = N[..., b, a] = rows[a][b]
    return N


def test_compiled_rotation_loops_match_numpy_references():
    # geometry.rotation_energy / rotation_newton_step and updates.procrustes_step run one matrix at
    # a time in compiled loops (stickfigure._rotation_kernels); each against the closed forms in numpy.
    rng = np.random.default_rng(11)
    n = 40
    B = rng.normal(size=(n, 3, 7))
    C_bb = B @ np.swapaxes(B, 1, 2)
    Q = Rotation.random(n, random_state=3).as_matrix()
    for D in (2, 3):
        R = Q[:, :D]
        C_ab = rng.normal(size=(n, D, 7)) @ np.swapaxes(B, 1, 2)
        e = U._rotation_energy(R, C_ab, C_bb)
        np.testing.assert_allclose(e, np.sum((R @ C_bb - 2.0 * C_ab) * R, axis=(1, 2)), rtol=1e-12, atol=1e-9)
        # broadcasting over batch axes, as numpy would
        assert U._rotation_energy(R.reshape(4, 10, D, 3), C_ab.reshape(4, 10, D, 3), C_bb[0]).shape == (4, 10)
        # Newton: w = -(H + mu I)^-1 g, capped at 0.5 rad, kept where the energy drops
        g, H = G.rotation_newton_model(R, C_ab, C_bb)
        lam = np.linalg.eigvalsh(H)[:, 0]
        mu = np.maximum(0.0, -lam) + 1e-6 * np.abs(H).max(axis=(1, 2)) + 1e-300
        w = -np.linalg.solve(H + mu[:, None, None] * np.eye(3), g[..., None])[..., 0]
        w *= np.minimum(1.0, 0.5 / np.linalg.norm(w, axis=1))[:, None]
        R_ref = R @ Rotation.from_rotvec(w).as_matrix()
        e_ref = np.sum((R_ref @ C_bb - 2.0 * C_ab) * R_ref, axis=(1, 2))
        keep = e_ref < e
        R_ref = np.where(keep[:, None, None], R_ref, R)
        R_new, e_new = U.newton_step(R, C_ab, C_bb, return_energy=True)
        assert keep.sum() > n // 2  # the comparison covers taken steps
        np.testing.assert_allclose(R_new, R_ref, atol=1e-9)
        np.testing.assert_allclose(e_new, np.minimum(e, e_ref), rtol=1e-10, atol=1e-9)
        # Near the minimum H is positive definite and the loop skips the eigenvalue (the shift
        # is then 1e-6 |H|max): the same step as the reference there too.
        Rc = R_new
        for _ in range(12):
            Rc = U.newton_step(Rc, C_ab, C_bb)
        g, H = G.rotation_newton_model(Rc, C_ab, C_bb)
        lam = np.linalg.eigvalsh(H)[:, 0]
        assert np.sum(lam > 1e-6 * np.trace(H, axis1=1, axis2=2)) > n // 2  # most are definite
        mu = np.maximum(0.0, -lam) + 1e-6 * np.abs(H).max(axis=(1, 2)) + 1e-300
        w = -np.linalg.solve(H + mu[:, None, None] * np.eye(3), g[..., None])[..., 0]
        w *= np.minimum(1.0, 0.5 / np.maximum(np.linalg.norm(w, axis=1), 1e-300))[:, None]
        R_ref = Rc @ Rotation.from_rotvec(w).as_matrix()
        e_c = U._rotation_energy(Rc, C_ab, C_bb)
        e_ref = np.sum((R_ref @ C_bb - 2.0 * C_ab) * R_ref, axis=(1, 2))
        R_ref = np.where((e_ref < e_c)[:, None, None], R_ref, Rc)
        np.testing.assert_allclose(U.newton_step(Rc, C_ab, C_bb), R_ref, atol=1e-9)
        # Procrustes: the power iteration on Horn's N(C) + sigma I from the current quaternion
        q = U.rot_to_quat(Q)
        C = C_ab if D == 3 else np.concatenate([C_ab, Q[:, 2:3] @ C_bb], axis=1)
        sigma = np.sqrt(3.0 * np.sum(C * C, axis=(1, 2)))
        Mk = np.linalg.matrix_power(_horn(C) + sigma[:, None, None] * np.eye(4), 8)
        q_ref = (Mk @ q[..., None])[..., 0]
        q_ref /= np.linalg.norm(q_ref, axis=1, keepdims=True)
        R_p, q_p = U.procrustes_step(R, C_ab, C_bb, quat=q)
        np.testing.assert_allclose(q_p, q_ref, atol=1e-9)
        np.testing.assert_allclose(R_p, U.quat_to_rot(q_ref)[:, :D], atol=1e-9)
        assert np.all(U._rotation_energy(R_p, C_ab, C_bb) <= e + 1e-9)
    # D = 3 with many squarings: the proper rotation maximising tr(R^T C_ab) (Kabsch)
    C3 = rng.normal(size=(n, 3, 3))
    U_, _, Vt = np.linalg.svd(C3)
    d = np.sign(np.linalg.det(U_ @ Vt))
    kabsch = U_ @ (np.eye(3) * np.stack([np.ones(n), np.ones(n), d], 1)[:, None, :]) @ Vt
    R_k, _ = U.procrustes_step(Q, C3, np.zeros((n, 3, 3)), n_square=8)
    np.testing.assert_allclose(R_k, kabsch, atol=1e-6)
    # the closed-form polar factor of 2x3 matrices (rank-1 ones fall back to the SVD's)
    C2 = rng.normal(size=(n, 2, 3))
    C2[0, 1] = 2.0 * C2[0, 0]
    U_, _, Vt = np.linalg.svd(C2, full_matrices=False)
    np.testing.assert_allclose(U._polar_rows(C2), U_ @ Vt, atol=1e-10)
    with pytest.raises(ValueError, match=r"\(\.\.\., D, 3\)"):
        U._rotation_energy(Q[:, :2], C3, C_bb)


def test_compiled_conversions_give_the_bits_of_the_array_forms():
    # rot_to_quat and _plane_normal run in compiled loops whose arithmetic is that of scipy's
    # Rotation.from_matrix and of the numpy form below: the same bits for the quaternions, so the
    # EM's path is unchanged; the normals to the last place (see below).
    rng = np.random.default_rng(12)
    n = 3000
    Q = np.concatenate([Rotation.random(n, random_state=4).as_matrix(),
                        Rotation.from_rotvec(rng.normal(size=(n, 3)) * 1e-3).as_matrix(),  # the trace branch
                        U.complete_rotation(Rotation.random(n, random_state=5).as_matrix()[:, :2])])
    np.testing.assert_array_equal(U.rot_to_quat(Q), Rotation.from_matrix(Q).as_quat()[:, [3, 0, 1, 2]])
    assert U.rot_to_quat(Q.reshape(3, n, 3, 3)).shape == (3, n, 4)
    # not orthonormal to scipy's tolerance: scipy orthogonalises it first, and so do we (through it)
    bent = Q[:5] * np.array([1.0, 1.0 + 1e-6, 1.0])[:, None]
    np.testing.assert_array_equal(U.rot_to_quat(bent), Rotation.from_matrix(bent).as_quat()[:, [3, 0, 1, 2]])
    sheared = Q[:5].copy()
    sheared[:, 0, 1] += 1e-9  # within scipy's relative tolerance on the diagonal, beyond its 1e-12 off it
    np.testing.assert_array_equal(U.rot_to_quat(sheared), Rotation.from_matrix(sheared).as_quat()[:, [3, 0, 1, 2]])
    with pytest.raises(ValueError, match="determinant"):
        U.rot_to_quat(-Q[:2])
    B = rng.normal(size=(n, 3, 3)) * rng.uniform(0.01, 10.0, size=(n, 1, 1))
    B[: n // 3, 2] *= 1e-3  # nearly planar sources, where the normal matters
    C = B @ np.swapaxes(B, 1, 2)
    lam_min = G.min_eig_sym3(C)
    lam_max = -G.min_eig_sym3(-C)
    M = C - lam_min[:, None, None] * np.eye(3)
    cands = np.stack([np.cross(M[:, 0], M[:, 1]), np.cross(M[:, 0], M[:, 2]), np.cross(M[:, 1], M[:, 2])], axis=1)
    norms = np.linalg.norm(cands, axis=-1)
    k = np.argmax(norms, axis=-1)
    want = cands[np.arange(n), k] / np.maximum(norms[np.arange(n), k], 1e-300)[:, None]
    normal, ratio = U._plane_normal(C.reshape(3, n // 3, 3, 3))
    # The same arithmetic, but not always the same bits: where the CPU fuses multiply-adds the
    # compiled loop rounds differently in the last place (measured: 56 of 9000 normal components, by at
    # most 6e-16, and 11 of 3000 eigenvalue ratios by 3e-16, on an AMD EPYC with AVX-512; none
    # on the machines before).
    np.testing.assert_allclose(normal.reshape(n, 3), want, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(ratio.reshape(n), lam_min / np.maximum(lam_max, 1e-300), rtol=1e-13, atol=1e-15)
    # the normal is the smallest eigenvector: C n = lambda_min n
    np.testing.assert_allclose((C @ want[..., None])[..., 0], lam_min[:, None] * want, atol=1e-8 * np.abs(C).max())


def test_block_score_is_the_change_of_the_full_objective(scene):
    st, obs, pri = _state(scene)
    settings = S.EMSettings(n_iter_merge=5, merge_baseline=False, reuse_scores=False, merge_rank="objective")
    st, _, _ = S.run_em(st, obs, pri, settings, 30, np.random.default_rng(0), resample=False)
    cands = S.merge_candidates(st, settings)
    blocks = S.score_candidates(st, obs, pri, settings, cands, np.random.default_rng(0))
    base = objective(st, obs, pri)
    for c, b in list(zip(cands, blocks))[:4]:
        merged = S.apply_merge(st, c, pri, settings, b)
        full = objective(merged, obs, pri)
        assert full - base == pytest.approx(c.score, rel=1e-6, abs=1e-6)


def test_candidate_fits_match_the_local_update(scene):
    st, obs, pri = _state(scene)
    U.update_local(st, obs, pri)
    loc, sq = candidate_fits(st, obs, pri)
    own = loc[np.arange(obs.n_points), st.labels]
    np.testing.assert_allclose(own, st.local, atol=1e-8)
    pred = st.point_predictions()
    res = np.sum(((obs.w - pred) * obs.mask[..., None]) ** 2, axis=(1, 2))
    np.testing.assert_allclose(sq[np.arange(obs.n_points), st.labels], res, rtol=1e-6, atol=1e-9)


def test_resampling_moves_a_mislabelled_point_back(scene):
    traj, obs = scene
    pri = Priors()
    st = initial_state(obs, traj.labels_true, traj.n_parts_true, pri, np.random.default_rng(0))
    st, _, _ = S.run_em(st, obs, pri, S.EMSettings(), 30, np.random.default_rng(0), resample=False)
    wrong = st.copy()
    p = int(np.flatnonzero(st.labels == 0)[0])
    wrong.labels = st.labels.copy()
    wrong.labels[p] = 1
    out, changed = resample_assignments(wrong, obs, pri, np.random.default_rng(0), mode="map")
    assert changed and out.labels[p] == 0


def test_objective_parts_and_structure_prior(scene):
    st, obs, pri = _state(scene)
    ps, pv = objective_terms(st, obs, pri)
    assert ps.shape == (st.n_sticks,) and pv.shape == (st.n_vertices,)
    total = ps.sum() + pv.sum() + structure_log_prior(st.labels, st.n_sticks, st.vertex_of, st.n_vertices)
    assert objective(st, obs, pri) == pytest.approx(total)
    # Uniform structures: log P = N log(1/K).
    assert structure_log_prior(np.repeat(np.arange(3), 2), 3, np.arange(6), 6) == pytest.approx(
        6 * np.log(1 / 3) + 6 * np.log(1 / 6))


def test_endpoint_initialisations():
    local = np.array([[0.0, 0.1, 0.0], [1.0, -0.1, 0.0], [2.0, 0.1, 0.05], [3.0, 0.0, -0.05]])
    ends = end_positions(local, np.zeros(4, int), 1, 3)
    assert ends[0, 0] == pytest.approx(0.0, abs=0.1) or ends[0, 0] == pytest.approx(3.0, abs=0.1)
    assert abs(ends[0, 0] - ends[1, 0]) == pytest.approx(3.0, abs=0.1)  # the two ends of the stick
    assert ends[2, 0] == pytest.approx(1.5, abs=0.1)  # the third endpoint in the middle


def test_centroid_initialisation_is_the_papers(scene):
    st, obs, _ = _state(scene, n_ends=2, endpoint_init="centroid")
    E = st.ends_per_stick
    for s in range(st.n_sticks):
        np.testing.assert_allclose(st.ends[E * s], st.ends[E * s + 1])  # both endpoints at the centroid
        np.testing.assert_allclose(st.mu_v[E * s], st.mu_e[E * s])


def test_major_axis_cuts_divide_a_stick_across_its_length():
    """n_axes=1: the n-1 threshold cuts along the major axis, each piece on one side of a plane."""
    from stickfigure.models.em.refine import _axis_bipartitions

    rng = np.random.default_rng(3)
    local = rng.normal(size=(7, 3)) * [5.0, 1.0, 0.5]  # long along x
    local = local @ np.linalg.qr(rng.normal(size=(3, 3)))[0]  # in a random orientation
    c = local - local.mean(axis=0)
    major = np.linalg.svd(c, full_matrices=False)[2][0]
    x = c @ major
    cuts = _axis_bipartitions(local, n_axes=1)
    assert len(cuts) == 6
    for second in cuts:
        assert 0 < second.sum() < 7
        assert x[second].min() > x[~second].max() or x[second].max() < x[~second].min()
    # All three axes: the major axis's cuts and others besides, each split once.
    every = _axis_bipartitions(local, n_axes=3, max_candidates=100)
    keys = {tuple(np.flatnonzero(m if m[0] else ~m)) for m in every}
    assert len(keys) == len(every) > 6
    assert {tuple(np.flatnonzero(m if m[0] else ~m)) for m in cuts} <= keys


def test_articulated_split_detects_a_joint_inside_a_stick_and_leaves_rigid_sticks_alone():
    """A stick holding a part and its 2-point child is split (the pieces joined); true sticks are not."""
    from stickfigure.models.em.refine import apply_articulated_splits, articulated_split_candidates

    traj = sf.synthetic.random_figure(n_sticks=5, frames=80, noise=0.01, seed=11, points_per_stick=6)
    a, b = traj.edges_true[0]
    keep = np.ones(traj.n_points, bool)
    keep[np.flatnonzero(traj.labels_true == b)[2:]] = False  # the child keeps two points
    traj = traj.slice(points=keep)
    truth = traj.labels_true
    pri, rng = Priors(), np.random.default_rng(0)
    obs, _, _ = normalise(traj.xy)
    settings = S.EMSettings(resample_every=0)
    # True groups: nothing to split.
    st = initial_state(obs, truth, traj.n_parts_true, pri, rng, n_ends=3)
    st, _, _ = S.run_em(st, obs, pri, settings, 100, rng)
    assert articulated_split_candidates(st, obs, pri) == []
    # The part and its child in one stick: that stick, and only it, is split.
    merged = np.where(truth == b, a, truth)
    _, merged = np.unique(merged, return_inverse=True)
    st = initial_state(obs, merged, 4, pri, rng, n_ends=3)
    st, _, _ = S.run_em(st, obs, pri, settings, 100, rng)
    splits = articulated_split_candidates(st, obs, pri)
    assert [s for s, _ in splits] == [int(merged[np.flatnonzero(truth == b)[0]])]
    new = apply_articulated_splits(st, obs, pri, splits)
    assert new.n_sticks == 5 and len(S.stick_edges(new)[0]) == 1  # the pieces share their joint
    assert objective(new, obs, pri) > objective(st, obs, pri)


@pytest.fixture(scope="module")
def sparse_scene():
    """75% of the observations withheld: most (stick, frame) pairs show fewer than 3 points."""
    traj = sf.synthetic.random_figure(n_sticks=3, frames=40, noise=0.01, seed=5, points_per_stick=(6, 8))
    xy = traj.xy.copy()
    rng = np.random.default_rng(1)
    xy[rng.random(xy.shape[:2]) < 0.75] = np.nan
    obs, _, _ = normalise(xy)
    return traj, obs


def test_updates_are_monotone_with_held_rotations(sparse_scene):
    st, obs, pri = _state(sparse_scene)
    hold = U.underdetermined_frames(st, obs)
    assert hold is not None and hold.mean() > 0.3
    _assert_sweeps_monotone(st, obs, pri)


def test_held_rotations_are_interpolated_or_kept(sparse_scene):
    """A frame showing < 3 of a stick's points never gets a rotation solved from them.

    Its rotation is either the previous one or the slerp of the stick's rotations in the
    nearest determined frames (two points let any turn about their line fit, and left free
    such turns blew the sticks' depth up).
    """
    st, obs, pri = _state(sparse_scene)
    hold = U.underdetermined_frames(st, obs)
    for _ in range(3):
        before = st.rot.copy()
        U.update_endpoints(st)
        U.update_motions(st, obs, global_search=True)
        q = U.rot_to_quat(U.complete_rotation(st.rot))
        R_int = U.quat_to_rot(U.slerp_fill(q, ~hold))[..., :2, :]
        kept = np.all(np.isclose(st.rot, before, atol=1e-12), axis=(-1, -2))
        interp = np.all(np.isclose(st.rot, R_int, atol=1e-8), axis=(-1, -2))
        assert np.all((kept | interp)[hold])
        assert not np.all(kept[~hold])  # the determined frames do move


def test_slerp_fill_matches_the_single_stick_interpolation():
    from stickfigure.models.em.initialise import interpolate_rotations

    R = Rotation.random(12, random_state=0).as_matrix()[:, :2, :]
    good = np.zeros(12, bool)
    good[[1, 4, 5, 9]] = True
    q = U.rot_to_quat(U.complete_rotation(R))
    got = U.quat_to_rot(U.slerp_fill(q[None], good[None]))[0, :, :2, :]
    np.testing.assert_allclose(got, interpolate_rotations(R, good), atol=1e-9)
    np.testing.assert_allclose(got[good], R[good], atol=1e-9)
    np.testing.assert_allclose(got[10:], R[[9, 9]], atol=1e-9)  # after the last: the last, not the one before
    np.testing.assert_allclose(got[0], R[1], atol=1e-9)
    # half-way between frames 5 and 9 (frame 7): the rotation half-way along the geodesic
    rel = Rotation.from_matrix(U.complete_rotation(R[5]).T @ U.complete_rotation(R[9])).as_rotvec()
    mid = U.complete_rotation(R[5]) @ Rotation.from_rotvec(rel / 2).as_matrix()
    np.testing.assert_allclose(got[7], mid[:2], atol=1e-9)


def test_split_round_after_a_dissolution_gives_a_segment_back_and_spares_small_sticks(monkeypatch):
    """A stick that took a dissolved segment's points is split at their joint; smaller ones are not,
    nor one with no free endpoint to hang the piece on."""
    from stickfigure.models.em import refine
    from stickfigure.models.em.refine import articulated_split_round

    traj = sf.synthetic.random_figure(n_sticks=5, frames=80, noise=0.01, seed=11, points_per_stick=6)
    a, b = traj.edges_true[0]
    keep = np.ones(traj.n_points, bool)
    keep[np.flatnonzero(traj.labels_true == b)[2:]] = False  # a 2-point segment, as a CMU thigh
    traj = traj.slice(points=keep)
    truth = traj.labels_true
    pri, rng = Priors(), np.random.default_rng(0)
    obs, _, _ = normalise(traj.xy)
    settings = S.EMSettings(resample_every=0)
    # The segment's points on its parent's stick, as a dissolution leaves them.
    merged = np.where(truth == b, a, truth)
    _, merged = np.unique(merged, return_inverse=True)
    st = initial_state(obs, merged, 4, pri, rng, n_ends=3)
    st, _, _ = S.run_em(st, obs, pri, settings, 100, rng)
    s = int(merged[np.flatnonzero(truth == b)[0]])
    size = int(np.sum(merged == s))
    # Every stick below min_points: nothing is tried, the state comes back as it was.
    same, val, sweeps, split = articulated_split_round(st, obs, pri, settings, rng, size + 1)
    assert same is st and val is None and sweeps == 0 and split == []
    # Its endpoints all on joints (as a torso's): not offered.
    with monkeypatch.context() as m:
        m.setattr(refine, "free_end_sticks", lambda state: np.arange(state.n_sticks) != s)
        same, val, sweeps, split = articulated_split_round(st, obs, pri, settings, rng, size)
    assert same is st and val is None and split == []
    assert refine.free_end_sticks(st)[s]
    new, val, sweeps, split = articulated_split_round(st, obs, pri, settings, rng, size)
    assert split == [s] and sweeps > 0 and val == pytest.approx(objective(new, obs, pri), rel=1e-6)
    # The new stick holds the segment (a cut across the parent's length may take the point
    # nearest the joint with it).
    child = np.unique(new.labels[truth == b])
    assert child.size == 1 and child[0] != s and np.sum(new.labels == child[0]) <= 3
    assert adjusted_rand_score(truth, new.labels) > 0.9
    assert new.n_sticks == 5 and len(S.stick_edges(new)[0]) == 1  # the pieces share their joint


def test_a_stopped_run_ends_at_the_check_where_stop_says_so(scene):
    """``run_em(stop=...)`` asks at every check, with the sweeps done and left."""
    st, obs, pri = _state(scene)
    settings = S.EMSettings(tol=1e-12)  # no convergence stop in 60 sweeps
    _, _, n_full = S.run_em(st.copy(), obs, pri, settings, 60, np.random.default_rng(5))
    seen = []
    _, _, n_stop = S.run_em(st.copy(), obs, pri, settings, 60, np.random.default_rng(5),
                            stop=lambda it, left, s, v: seen.append((it, left)) or it >= 30)
    assert (n_full, n_stop) == (60, 30) and seen == [(10, 50), (20, 40), (30, 30)]


def test_out_of_reach_stops_only_a_trial_that_cannot_catch_up():
    """The rise per block, however slow, is allowed twice over for every block left."""
    crit = lambda st, v: v  # noqa: E731

    def calls(stop, values):  # checks every 10 sweeps of a 200-sweep run
        return [stop(10 * (k + 1), 200 - 10 * (k + 1), None, v) for k, v in enumerate(values)]

    # A rise of 100 a block, 17 blocks left: at most 400 + 2 x 1700 = 3800 at the end.
    assert calls(S.out_of_reach(1000.0, crit), (200.0, 300.0, 400.0)) == [False, False, False]
    assert calls(S.out_of_reach(5000.0, crit), (200.0, 300.0, 400.0)) == [False, False, True]
    # A trial already rising fast enough is left to run; one above best is never stopped.
    assert not any(calls(S.out_of_reach(3000.0, crit), (0.0, 100.0, 200.0, 300.0)))
    assert not any(calls(S.out_of_reach(0.0, crit), (5.0, 5.0, 5.0)))
    # The block is measured between checks: the same rise over 20-sweep blocks is half the rate.
    slow = S.out_of_reach(3000.0, crit)
    assert [slow(d, 200 - d, None, v) for d, v in ((20, 200.0), (40, 300.0), (60, 400.0))] == [False, False, True]


def _flat_stick(F: int = 40, seed: int = 5):
    """One flat stick (5 coplanar points) turning smoothly in 3D, its state and its rotation statistics."""
    rng = np.random.default_rng(seed)
    b = np.c_[rng.normal(size=(5, 2)), np.zeros(5)]
    b -= b.mean(axis=0)
    rotvec = np.array([0.9, 0.3, 0.1]) + np.cumsum(rng.normal(scale=0.03, size=(F, 3)), axis=0)
    R = Rotation.from_rotvec(rotvec).as_matrix()[:, :2]  # (F, 2, 3)
    xy = np.einsum("fdj,pj->pfd", R, b)
    obs, _, _ = normalise(xy)
    st = initial_state(obs, np.zeros(5, np.int64), 1, Priors(), np.random.default_rng(0))
    st.local = b
    a = np.einsum("fdj,pj->fpd", R, b)
    C_ab = np.einsum("fpd,pj->fdj", a, b)[None]  # (1, F, 2, 3)
    C_bb = np.broadcast_to(b.T @ b, (1, F, 3, 3)).copy()
    return st, R[None].copy(), C_ab, C_bb


def _mirror_flips(st, R, s):
    axes, _ = U._principal_axes(st)
    rn = np.einsum("fdj,j->fd", R[s], axes[s, 0, 0])
    return int(np.sum(np.sum(rn[1:] * rn[:-1], axis=-1) < 0))


def test_align_mirrors_undoes_flips_of_a_flat_stick_where_the_energy_ties():
    st, R0, C_ab, C_bb = _flat_stick()
    axes, flat = U._principal_axes(st)
    assert flat.all()
    n = axes[0, 0, 0]
    assert np.linalg.norm(np.einsum("fdj,j->fd", R0[0], n), axis=-1).min() > 0.3  # never face-on
    assert _mirror_flips(st, R0, 0) == 0
    R = R0.copy()
    bad = np.zeros(R.shape[1], bool)
    bad[[5, 6, 7, 20]] = True
    R[0, bad] = R[0, bad] @ (np.eye(3) - 2.0 * np.outer(n, n))
    assert _mirror_flips(st, R, 0) == 4
    e_before = G.rotation_energy(R, C_ab, C_bb)
    np.testing.assert_allclose(e_before, G.rotation_energy(R0, C_ab, C_bb), atol=1e-9)  # mirrors tie
    out, changed = U.align_mirrors(st, R, C_ab, C_bb, tie=U.MIRROR_TIE)
    assert changed is not None and np.array_equal(changed[0], bad)
    np.testing.assert_allclose(out, R0, atol=1e-12)
    assert _mirror_flips(st, out, 0) == 0
    # frames the energy decides (no tie allowed) are left as they are
    same, none = U.align_mirrors(st, R, C_ab, C_bb, tie=-1.0)
    assert none is None and same is R


def _align_mirrors_reference(st, R, C_ab, C_bb, tie):
    """align_mirrors' rules in numpy (its form before the compiled loop), for the test below."""
    lab, X, S = st.labels, st.local, st.n_sticks
    cnt = np.maximum(np.bincount(lab, minlength=S), 1).astype(float)
    mean = np.stack([np.bincount(lab, weights=X[:, k], minlength=S) for k in range(3)], -1) / cnt[:, None]
    Xc = X - mean[lab]
    cov = np.zeros((S, 3, 3))
    np.add.at(cov, lab, Xc[:, :, None] * Xc[:, None, :])
    lam, V = np.linalg.eigh(cov)
    lam = np.maximum(lam, 0.0)
    flat = np.sqrt(lam[:, 0]) < U.FLAT_RATIO * np.sqrt(np.maximum(lam[:, 2], 1e-300))
    idx = np.flatnonzero(flat & (np.bincount(lab, minlength=S) >= 3))
    F = R.shape[1]
    n = V[idx, :, 0]
    Rk = R[idx]
    H = np.eye(3)[None] - 2.0 * n[:, :, None] * n[:, None, :]
    Rm = Rk[..., 0:1] * H[:, None, None, 0] + Rk[..., 1:2] * H[:, None, None, 1] + Rk[..., 2:3] * H[:, None, None, 2]
    e0, e1 = U._rotation_energy(Rk, C_ab[idx], C_bb[idx]), U._rotation_energy(Rm, C_ab[idx], C_bb[idx])
    tied = np.abs(e1 - e0) <= tie
    rn = np.einsum("kfdj,kj->kfd", Rk, n)
    long = np.linalg.norm(rn, axis=-1) >= 0.3
    flip = np.zeros(tied.shape, bool)
    flip[:, 1:] = (np.sum(rn[:, 1:] * rn[:, :-1], axis=-1) < 0) & long[:, 1:] & long[:, :-1]
    count = np.cumsum(flip & tied, axis=1)
    last = np.maximum.accumulate(np.where(~tied, np.arange(F)[None], -1), axis=1)
    base = np.where(last >= 0, np.take_along_axis(count, np.maximum(last, 0), axis=1), 0)
    odd = tied & ((count - base) % 2 == 1)
    run = np.cumsum(~tied, axis=1) + (F + 1) * np.arange(len(idx))[:, None]
    n_runs = (F + 1) * len(idx)
    rid = run[tied]
    keep = np.bincount(rid, weights=np.where(odd, e1, e0)[tied], minlength=n_runs)
    other = np.bincount(rid, weights=np.where(odd, e0, e1)[tied], minlength=n_runs)
    n_odd = np.bincount(rid, weights=odd[tied].astype(float), minlength=n_runs)
    n_tied = np.bincount(rid, minlength=n_runs)
    swap = (other < keep) | ((other == keep) & (n_tied - n_odd < n_odd))
    odd = np.where(swap[run], tied & ~odd, odd)
    out = R.copy()
    out[idx] = np.where(odd[..., None, None], Rm, Rk)
    changed = np.zeros(R.shape[:2], bool)
    changed[idx] = odd
    return flat, out, changed


def test_compiled_mirror_alignment_matches_its_numpy_rules():
    # align_mirrors and _principal_axes run in compiled loops (_rotation_kernels.mirror_runs,
    # _point_kernels.stick_scatter): the same decisions as the rules in numpy on sticks of
    # several shapes, with frames mirrored at random and tie limits from none to all frames.
    rng = np.random.default_rng(21)
    S, F, D = 4, 60, 2
    sizes = np.array([5, 4, 6, 2])  # flat, planar, not flat, too few points to mirror
    lab = np.repeat(np.arange(S), sizes)
    local = rng.normal(size=(lab.size, 3))
    local[lab == 0, 2] *= 0.05  # flat
    local[lab == 1, 2] = 0.0  # exactly planar
    local[lab == 3, 2] = 0.0
    st = initial_state(normalise(rng.normal(size=(lab.size, F, D)))[0], lab, S, Priors(), np.random.default_rng(0))
    st.local = local
    rotvec = rng.normal(size=(S, 1, 3)) + np.cumsum(rng.normal(scale=0.05, size=(S, F, 3)), axis=1)
    R0 = Rotation.from_rotvec(rotvec.reshape(-1, 3)).as_matrix().reshape(S, F, 3, 3)[:, :, :D]
    noise = [0.0, 0.01, 0.3]
    seen = set()
    for trial in range(30):
        b = local
        a = np.einsum("sfdj,pj->spfd", R0, b) + noise[trial % 3] * rng.normal(size=(S, lab.size, F, D))
        m = (lab[None, :] == np.arange(S)[:, None]).astype(float)  # (S, P)
        C_ab = np.einsum("sp,spfd,pj->sfdj", m, a, b)
        C_bb = np.broadcast_to(np.einsum("sp,pi,pj->sij", m, b, b)[:, None], (S, F, 3, 3)).copy()
        want_flat, want, want_changed = _align_mirrors_reference(st, R0, C_ab, C_bb, 0.0)
        R = R0.copy()
        for s in np.flatnonzero(want_flat):
            n = U._principal_axes(st)[0][s, 0, 0]
            bad = rng.random(F) < rng.uniform(0.05, 0.6)
            R[s, bad] = R[s, bad] @ (np.eye(3) - 2.0 * np.outer(n, n))
        tie = float(rng.choice([-1.0, 0.0, 1e-3, 0.1, 1.0, 1e9]))
        flat, want, want_changed = _align_mirrors_reference(st, R, C_ab, C_bb, tie)
        assert np.array_equal(U._principal_axes(st)[1], flat)
        got, changed = U.align_mirrors(st, R, C_ab, C_bb, tie)
        assert np.array_equal(got, want)
        if want_changed.any():
            assert np.array_equal(changed, want_changed) and not changed[2:].any()
            seen.add("changed")
        else:
            assert changed is None and got is R
            seen.add("unchanged")
    assert seen == {"changed", "unchanged"} and flat[:2].all() and not flat[2]


def _best_rotations_reference(R, C_ab, C_bb, axes, flat, use_polar, n_newton, only_mirrors):
    """best_rotations' search in numpy (its form before the compiled loop), for the test below."""
    batch = R.shape[:-2]
    best, best_e = R, U._rotation_energy(R, C_ab, C_bb)
    if not only_mirrors:
        for _ in range(n_newton):
            best, best_e = U.newton_step(best, C_ab, C_bb, best_e, return_energy=True)
    candidates = [(None, U._polar_rows(C_ab))] if use_polar else []
    mask = np.broadcast_to(flat[:, None], batch)
    ax = np.broadcast_to(axes, batch + (3, 3))[mask]
    for k in range(2):
        n = ax[..., k, :]
        candidates.append((mask, R[mask] @ (np.eye(3) - 2.0 * n[..., :, None] * n[..., None, :])))
    n, ratio = U._plane_normal(C_bb)
    mask = ratio < U.FLAT_RATIO ** 2
    n = n[mask]
    candidates.append((mask, R[mask] @ (np.eye(3) - 2.0 * n[..., :, None] * n[..., None, :])))
    for sel, X in candidates:
        Ca, Cb = (C_ab, C_bb) if sel is None else (C_ab[sel], C_bb[sel])
        e = U._rotation_energy(X, Ca, Cb)
        for _ in range(n_newton):
            X, e = U.newton_step(X, Ca, Cb, e, return_energy=True)
        if sel is None:
            take = e < best_e
            best, best_e = np.where(take[..., None, None], X, best), np.where(take, e, best_e)
        else:
            take = e < best_e[sel]
            best, best_e = best.copy(), best_e.copy()
            best[sel] = np.where(take[..., None, None], X, best[sel])
            best_e[sel] = np.where(take, e, best_e[sel])
    return best


def test_compiled_rotation_search_matches_its_numpy_form():
    # best_rotations polishes its starts and keeps the best in a compiled loop
    # (_rotation_kernels.best_rotations); the starts, their order and the rule are the numpy
    # form's, so the rotations are the same bits. Sticks flat and not; frames where the sources
    # are planar (a mirror start of their own) and not; rotations far from and near the minimum.
    rng = np.random.default_rng(8)
    S, F, D = 3, 50, 2
    B = rng.normal(size=(S, F, 3, 6))
    B[0, :, 2] *= 0.05  # a flat stick
    B[1, :20, 2] = 0.0  # planar sources in some frames
    C_bb = B @ np.swapaxes(B, -1, -2)
    R_true = Rotation.random(S * F, random_state=6).as_matrix().reshape(S, F, 3, 3)[:, :, :D]
    C_ab = R_true @ C_bb + 0.05 * rng.normal(size=(S, F, D, 3))
    R = Rotation.random(S * F, random_state=7).as_matrix().reshape(S, F, 3, 3)[:, :, :D]
    near = rng.random((S, F)) < 0.5
    R[near] = R_true[near]
    axes = np.swapaxes(np.linalg.eigh(C_bb[:, 0])[1], -1, -2)[:, None]  # (S, 1, 3, 3), rows by spread
    flat = np.array([True, False, True])
    for use_polar in (False, True):
        for n_newton, only_mirrors in ((2, False), (1, True), (0, False)):
            want = _best_rotations_reference(R, C_ab, C_bb, axes, flat, use_polar, n_newton, only_mirrors)
            got = U.best_rotations(R, C_ab, C_bb, axes, flat, use_polar=use_polar, n_newton=n_newton,
                                   only_mirrors=only_mirrors)
            assert np.array_equal(got, want)
            assert np.all(U._rotation_energy(got, C_ab, C_bb) <= U._rotation_energy(R, C_ab, C_bb))
    # the starts changed something (a test that cannot fail otherwise)
    assert not np.array_equal(want, R)
    # a subset of sticks, as update_motions passes them
    sub = np.array([0, 2])
    got = U.best_rotations(R[sub], C_ab[sub], C_bb[sub], axes[sub], flat[sub], use_polar=False, n_newton=1)
    want = _best_rotations_reference(R[sub], C_ab[sub], C_bb[sub], axes[sub], flat[sub], False, 1, False)
    assert np.array_equal(got, want)


def test_keep_lower_selects_as_numpy_where():
    # update_motions keeps each Procrustes step only where its energy is not above the old one's,
    # in one compiled pass (_keep_lower): numpy's `new <= old` and np.where, NaN keeping the old.
    rng = np.random.default_rng(4)
    S, F, D = 3, 40, 2
    B = rng.normal(size=(S, F, 3, 5))
    C_bb = B @ np.swapaxes(B, -1, -2)
    C_ab = rng.normal(size=(S, F, D, 3))
    R_old = Rotation.random(S * F, random_state=1).as_matrix().reshape(S, F, 3, 3)[:, :, :D]
    R_new = Rotation.random(S * F, random_state=2).as_matrix().reshape(S, F, 3, 3)[:, :, :D]
    R_new[0, :5] = R_old[0, :5]  # equal energies: the new is kept
    R_new[1, 0, 0, 0] = np.nan
    q_old, q_new = rng.normal(size=(S, F, 4)), rng.normal(size=(S, F, 4))
    old, new = U._rotation_energy(R_old, C_ab, C_bb), U._rotation_energy(R_new, C_ab, C_bb)
    keep = new <= old
    assert 0 < keep.sum() < keep.size and not keep[1, 0]
    R, q, e = U._keep_lower(R_old, q_old, R_new, q_new, C_ab, C_bb)
    assert np.array_equal(R, np.where(keep[..., None, None], R_new, R_old), equal_nan=True)
    assert np.array_equal(q, np.where(keep[..., None], q_new, q_old))
    assert np.array_equal(e, old)


def test_mirror_alignment_is_scoped_to_its_block():
    assert U._mirror_tie is None
    with pytest.raises(RuntimeError):
        with U.mirror_alignment(True):
            assert U._mirror_tie == U.MIRROR_TIE
            raise RuntimeError("stop")
    assert U._mirror_tie is None
    with U.mirror_alignment(False):
        assert U._mirror_tie is None
