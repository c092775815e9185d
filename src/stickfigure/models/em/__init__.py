"""Method "em": Ross, Tarlow & Zemel, *Unsupervised learning of skeletons from motion* (ECCV 2008).

A probabilistic stick-figure model (section 3) fitted by variational EM
(section 4.1), with the structure (point-to-stick assignments and joints)
learned by resampling assignments and greedily merging stick endpoints
(section 4.2, Fig. 3). Modules:

* :mod:`.model`: the variables, the data normalisation, the objective (eq. 4).
* :mod:`.updates`: the EM updates (vectorised over sticks, vertices and frames).
* :mod:`.initialise`: Affinity-Propagation groups -> per-stick SfM -> endpoints.
* :mod:`.assign`: resampling of the assignments R.
* :mod:`.structure`: the merge search, stages and model selection.
* :mod:`.refine`: moves of points and sticks around the merge search.
* :mod:`.impute`: imputation with a learned structure, and the held-out check.

docs/em.md derives every update and documents the defaults.
"""

from __future__ import annotations

import contextlib
from dataclasses import asdict, replace
from typing import Any

import numpy as np

from ..._threads import available_cpus
from ..._validation import check_labels, check_positive
from ...geometry import fill_gaps, smooth_low_rank_complete
from ...skeleton import Skeleton
from ...trajectories import Trajectories
from ..base import StickEstimator, register
from .forked import Speculative
from .impute import centroid_concentration, frame_scales, refit_motions, rotation_concentration, start_state
from .initialise import initial_state
from .model import Observations, Priors, StickState, hub_endpoints, normalise
from .refine import local_noise_variance, misfit_ratios
from .structure import (EMSettings, Stage, child_rng, extend_frames, learn_structure, run_em,
                        joint_support, search_frames, settings_bic, stick_edges)
from .updates import mirror_alignment, stick_centroids

__all__ = ["EMSkeleton", "fit_stages", "mid_air"]


@register("em")
class EMSkeleton(StickEstimator):
    """Articulated skeleton by variational EM and greedy joint merging (Ross, Tarlow & Zemel).

    Parameters
    ----------
    n_iter : int
        EM iterations after initialisation and after every merge (paper: 200).
    n_iter_merge : int
        EM iterations used to score each candidate merge (paper: 20); with
        ``merge_rank="residual"`` they run only for the merge taken, whose start
        they polish.
    resample_every : int
        Resample the point-to-stick assignments every this many iterations (paper: 10; 0 = never).
    resample : {"sample", "map"}
        Draw assignments from their posterior (paper) or take the most probable stick.
    selection : {"bic", "objective"}
        Pick the stage with the highest ``objective - k/2 log N`` (k free
        parameters of the rigid-joint model; the default, right for one
        articulated figure) or with the highest objective (the paper; right when
        the scene holds several independent objects). docs/em.md section 7.
    n_ends : int
        Endpoints per stick. The paper's sticks have 2, so a stick can take part in
        at most two distinct joints; a part with a third joint away from its ends
        (a pelvis with two hips and a spine, a limb hanging from the middle of
        another) then gets a loose joint or none. The default 3 allows that; 2 is
        the paper's model.
    hub_end : bool
        One endpoint more for the sticks with the most points, which alone may use
        it (``StickState.joint_capacity``): a torso on four joints (neck, shoulders,
        lumbar) or a body with four limbs, while every other stick keeps
        ``n_ends``: for a figure whose largest part holds more joints than
        ``n_ends`` (:func:`stickfigure.synthetic.star`) and for human motion capture
        (a thorax on four joints). Default True since session 32: on CMU 85_02
        cameras held out from development it gave 31 body trees of 36 against 21
        with False, fitted on one machine; it gave fewer (26 against 34) on the
        development cameras that chose the other rules, and lost the body tree of
        the take's isometric view (docs/em.md sections 6 and 11). False gives every
        stick ``n_ends`` joints at most (the rules as they were before).
    bic_free_ends : bool
        Whether BIC counts the objective's terms of the endpoints on no joint (True,
        the objective as it is) or leaves them out (False,
        :func:`.model.free_endpoint_terms`). Such an endpoint explains no
        observation, yet its vertex's chain adds about ``D/2 log(tau_t / 2pi)`` a
        frame, so with True a model with more sticks or more endpoints per stick
        gains by them alone. Default True: with False, random figures, the placed
        CMU walk and two hard cameras of the recorded take came out better, but
        four other cameras of that take and its isometric view at 120 Hz lost their
        body tree (docs/em.md sections 7 and 11). Compare fits with different
        ``n_ends`` or ``hub_end`` by their BIC only with False.
    bic_rotations : {"all", "identified"}
        Which rotation angles BIC counts as parameters: 3 a frame for every stick
        ("all"), or those the stick's anchors (its points and its endpoints in
        joints) fix ("identified": 2 for a stick of two anchors, such as a 1-point
        stick on one joint, which turns freely about the line through them; 0 for
        one anchor). :func:`.structure.n_parameters`, docs/em.md section 7.
    endpoint_init : {"axis", "centroid"}
        Start a stick's endpoints along its principal axis (the first two at its
        ends), or all at its centroid (the paper).
    merge_init : {"joint", "mean"}
        Start a merged vertex at the least-squares joint of its sticks, or at the mean
        of the two vertices (the paper).
    merge_scope : {"local", "full"}
        Score a merge by EM on the sticks it touches (batched), or on a copy of the
        whole model (the paper; slow).
    max_candidates : int, optional
        Score only this many candidate merges per stage (those with the smallest
        least-squares joint residual); all when None (the paper). The default 40
        only bites on large figures.
    max_merges : int, optional
        Stop merging after this many merges; all valid merges when None.
    merge_baseline : bool
        Compare a candidate with the model run for the same ``n_iter_merge``
        iterations without the merge (True), or with the model before them (the
        paper); see docs/em.md. Only used with ``merge_rank="objective"``.
    n_polish : int
        Rounds of joint/rotation re-fitting that start a ``"joint"`` merge (0: none).
    reuse_scores : bool
        Keep candidates' scores across stages while their sticks are untouched
        (the winner is always re-scored before it is taken).
    tol : float
        Early stop of an EM run (relative objective change over ``resample_every``
        iterations with unchanged assignments); 0 runs every iteration.
    min_stick_points : int
        A stick without joints that keeps fewer points after resampling is dissolved.
    max_sticks : int, optional
        Upper bound of the number of initial clusters (default ``min(20, P // 3)``).
    labels : array_like of int, shape (P,), optional
        Initial groups of the points instead of Affinity Propagation. The search may
        still change them: resampling, the stick check and articulated splits, the
        pair re-split, the dissolutions (and the held-out check), ``unpair``, the
        bridges and ``split_hubs`` each can. To keep them as the sticks, pass
        ``refine_sticks=False, resample_every=0, resplit=False, dissolve_points=0,
        unpair=False, bridge_points=0, split_hubs=False`` (only the joints are then
        searched).
    refine_sticks : bool
        After the first EM run, split sticks that are not rigid and join sticks that
        move as one, by BIC (an extension: the paper keeps the clustering's count).
    articulated_rounds : int
        Rounds of articulated splits after that (a stick that is two parts joined
        at a joint becomes two sticks sharing a vertex, by BIC; docs/em.md
        section 6); 0 turns them off.
    split_axes : int
        The cuts those splits (and the pair re-split below) try: planes normal to
        the major axis of the stick's shape only (1), to its two largest axes (2),
        or to any of its principal axes (3, the behaviour before). A joint
        divides a limb across its length; in 2D a cut along it pairs markers from
        both ends of a limb (thigh and ankle against knee and toe) into two pieces
        the orthographic model fits as well as the anatomical ones (docs/em.md
        section 6).
    dissolve_points : int
        After the merge search, every stick of the selected stage with at most this
        many points is tried without it (its points moved to the sticks that explain
        them best, its joints contracted into one, EM re-run); kept when the
        selection criterion improves (Hartigan-style moves; docs/em.md section 6).
        0 turns it off (the paper).
    resplit : bool
        Before that, every pair of jointed sticks of the selected stage is re-split:
        their points fitted as one body and cut into the two pieces sharing a joint
        that fit best; a different cut is kept when the selection criterion
        improves after EM (moves groups of points that the resampling, with each
        stick's motion fitted to its wrong points too, cannot). False: off.
    holdout : float or None
        Last, each small stick (``holdout_points``) is tried without it once more,
        now judged by prediction: this fraction of the observed entries is
        hidden as occlusions hide them (half by a sweeping bar, half at random) and
        predicted from the rest with the structure fixed (as in imputation), and a
        dissolution is kept when it predicts them better. A
        2-point stick fits any two 2D trajectories exactly, so the likelihood (and
        BIC) cannot reject one that pairs markers across a body; hiding one of its
        points shows it (docs/em.md section 6). None: off.
    holdout_masks : int
        Independent occlusion masks the held-out check sums its errors over. With
        one, which small sticks it dissolves depends on where the mask's bar falls,
        so on motion capture the seed can decide between skeletons; on one camera of
        the CMU take three gave two seeds that had differed the same skeleton, at about
        20-25 % more time on human-sized problems (docs/em.md section 11).
    holdout_points : int
        Sticks of at most this many points are always offered to the held-out
        check; larger ones (up to ``dissolve_points``) only while their fit is
        suspect (residual variance over 1.25 times the noise's, corrected for the
        fit's degrees of freedom, as the pair re-split judges). Two points in 2D
        fit any two trajectories whose distance stays below the stick's 3D length,
        so only prediction can reject a 2-point stick; three give 6 coordinates a
        frame for 5 pose parameters, and one that fits them at the noise level is
        left to the likelihood. The check is biased against exactly those: a true
        shin or foot of three markers, all hidden by the bar, is predicted better
        as part of a larger neighbour (docs/em.md sections 6 and 11).
    dissolve_scope : {"all", "leaves"}
        Which small sticks the dissolutions (``dissolve_points`` and the held-out
        check) try. "leaves": only sticks with at most one joint; a stick between
        two joints (a thigh between the pelvis and the shin, 2 markers in the CMU
        set) is kept. Once such a stick is dissolved no link of the part below it
        is right. Measured on six CMU
        cameras: mean edge F1 0.379 against 0.303 with "all", and one body tree
        against none. Not the default: a stick pairing markers across the body
        that the search joined at both ends is then never tried, and on the 120 Hz
        takes trained on clean data em's imputation became 3.8 (CMU) and 11
        (HDM05) times worse than multibody SfM (docs/em.md section 11).
    remerge : bool
        After the held-out check dissolves sticks, the merge search goes on from
        the new state and the stage with the best selection criterion among the
        dissolved one and those merges is kept. A dissolved stick takes its joints
        with it, and the trees it linked stay apart unless the search looks at them
        again (on the whole CMU take: 7 trees left on one camera, 3 on another).
        Where the dissolution removed a body segment's stick, the link it adds is
        wrong: on ten random cameras of the CMU take 5 of its 10 links were not
        anatomical (docs/em.md section 11). False: the dissolved state as it is.
    split_dissolved : int
        Before that search, one round of articulated splits (as above) on the
        sticks of at least this many points, when the held-out check dissolved
        any. A dissolved segment's points go to the sticks beside it, and a thigh
        (two CMU markers) put on the pelvis leaves the shin nothing to hinge on, so
        the search re-attaches the leg wherever it scores best (an arm, a foot).
        Smaller sticks are not split: that re-creates what the check removed.
        On 13 cameras of the CMU take body trees rose from 7 to 8, none lost, and
        on 7 of HDM05 from 0 to 1; em's imputation beat multibody SfM on 10 of 12
        motion-capture rows instead of 11. Not judged by the held-out check's
        prediction, which rejected every split that gave a body tree (docs/em.md
        section 11). 0: off.
    unpair : bool
        Then every stick of two points on three or more joints (a hub of three
        sticks) is tried as two 1-point sticks, each keeping the joints nearer its
        point, the two parts of the tree joined again by their best merge; kept
        when the selection criterion improves after EM. Two markers alone on a
        hub are one-marker segments of two limbs lumped together (CMU's LTHI+RTHI,
        joined to the pelvis and both shins), which a 2-point stick fits exactly
        (:func:`.bridge.unpair_hubs`, docs/em.md section 6). False: off.
    bridge_points : int
        Then, up to this many *bridges*: a point whose removal lets the rest of its
        stick fit far better (excess above half the BIC charge of a new stick) is
        made a stick of its own, inserted at one of the two joints nearest to it
        between the sticks that joint held, and kept when the selection criterion
        improves after EM. A segment with one marker off its joints (CMU's thigh
        marker, the knee marker going with the shin) otherwise bends whatever
        stick it lands on, as a free 1-point stick cannot survive
        (:mod:`.bridge`, docs/em.md section 6). 0: off.
    split_hubs : bool
        Then the articulated split test on sticks whose endpoints are all on joints
        (which the rounds above leave out), with both pieces of at least
        ``min_stick_points`` points; a passing split is put in with each joint on
        the piece nearer to it, and kept when the selection criterion improves
        after EM. A torso stick of pelvis and thorax markers twists in a walk, and
        a shoulder joint in its frame fits worse than one in the head's, which
        then takes the arm (:func:`.refine.split_hubs`, docs/em.md section 6).
        False: off.
    reattach : bool
        Finally, sub-tree moves: a joint is cut where a part of the tree has a
        clearly better least-squares joint with a stick on the other side (residual
        below 0.8 times the current one), the merges linking the two parts are scored
        as in the search, and the best one is kept when it is not the old link and
        the selection criterion improves after EM (the greedy search never undoes a
        merge; docs/em.md section 6). False: off.
    spare_end : bool
        The sub-tree moves run with one more endpoint per stick, so that a stick on
        a joint at every endpoint (a thorax holding the lumbar link and both
        shoulders) can still take a part the search hung elsewhere (the head on the
        pelvis). Where no stick ends on more joints than it had endpoints, the spare
        endpoints are removed again (docs/em.md section 6). Default False: the moves
        use the search's endpoints.
    max_trees : int, "auto" or None
        The most separate figures (trees) the skeleton may have. The search selects
        a forest where no joint between its trees pays by the criterion, which is
        right for independent objects; on a figure known to be one piece a forest
        means a segment the sticks do not resolve (a thigh marker on the pelvis
        stick), and the part left apart is still jointed to the body. With a
        number, a forest of more trees is joined by the best-scoring merges
        between its trees, before the sub-tree moves (docs/em.md section 6).
        "auto" (default): the number the data's format records
        (``traj.meta["n_figures"]``: 1 for a motion-capture take of one subject,
        the tracks of a SLEAP file; :mod:`stickfigure.io`), else None. None: the
        forest as selected.
    retry_mid_air : float or None
        When the selected skeleton has a joint in mid-air, farther than this many
        figure radii from the points of both sticks it joins (the smaller
        ``reach`` of ``info["joint_support"]``), the whole search runs again with
        one more endpoint per stick, and of the two skeletons the one whose
        farthest joint is nearer its sticks is kept (``info["retry"]``). Such a
        joint is a part hung where it has no place: on CMU takes a leg whose thigh
        marker went to another part hangs on the other leg. With one more endpoint
        the search takes another path (docs/em.md section 6). A search costs
        twice as much when it retries. Default None (off): on CMU at 0.5 it
        gained two body trees and lost one on the 11 cameras it was run on, and
        anatomical joints can be beyond 0.5 radii (two CMU body trees at 0.52
        and 0.59, the synthetic chain of the tests at 0.55).
    merge_rank : {"residual", "objective"}
        How the merge search (and the forced join of trees) ranks the candidate
        joints. "residual" (default): by the least-squares joint's residual, how far
        the two sticks' predictions of one point fixed in both frames stay apart
        (only the chosen merge runs the ``n_iter_merge`` sweeps, and starts from
        them). "objective" (the
        paper): by the objective's change after ``n_iter_merge`` sweeps, which ranks
        a joint by how tight EM can make it; a stick whose motion its points barely
        fix (two markers, a flat band of four) can be made to meet almost anything.
        On 24 random cameras of the CMU take (with ``align_mirrors``) the body's
        tree came out on 20 (12 by the objective); with the body's segments given
        as ``labels`` (every group move off), on 5 of 6 cameras of CMU 131_01 with
        the 41 markers placed (1 of 6) and 3 of 6 of the recorded take (0 of 6)
        (docs/em.md sections 6 and 11).
    align_mirrors : bool
        Keep each flat stick's mirror image continuous over frames where the two
        images fit equally well (:func:`.updates.align_mirrors`; default True): a
        pelvis or head band of four coplanar markers otherwise flips between its
        two mirror poses from frame to frame, and no joint off its plane (the hips,
        the neck) can be found on it. Each flipped frame may lower the objective by
        half a log-likelihood unit at most.
    max_frames : int, optional
        Run the structure search (EM, stick checks, merges) on at most this many
        evenly spaced frames, then re-fit the selected structure on all frames
        (docs/em.md section 6). None searches on every frame (the paper).
    oversegment : float, optional
        When the search leaves a stick that is not rigid (residual variance above
        1.35 times the noise level, or split by ``split_hubs``) or sticks of more
        than 10 points on average, run it again from a finer initial clustering
        with ``ceil(P / oversegment)`` groups (at most ``max_sticks``; only when that
        is more than the estimated count and than the sticks the first search
        ended with, not counting those ``split_hubs`` added) and keep the start
        whose selected stage has the higher BIC (docs/em.md section 6). The
        eigengap count of the affine rigidity affinity merges body segments of 1-3
        markers (an affine body fits any four trajectories), which no later move
        splits apart again. None: one start (the paper).
    n_jobs : int, optional
        Processes for the search. With more than one (Linux, forked processes):
        the finer start's search runs beside the first one, at a lower priority, and
        is stopped as soon as the first shows it is not needed; the trial that
        follows a rejected refinement trial runs beside it; and half of the merge
        and split candidates' block fits run in a child. The result does not depend
        on it. None: the CPUs this process may use.
    tau_p, alpha0, beta0, max_precision : float
        Priors (normalised units: the data are centred and scaled to unit RMS
        spread): precision of the Gaussian prior on local coordinates; Gamma prior
        of the vertex precisions; upper bound on tau_w and tau_t and on the
        inverse noise variance of the stick checks (default 1e6: noise is taken to be
        at least 1e-3 of the spread, so noiseless data are not over-segmented).
    impute_iter : int
        EM iterations used to re-fit motions on new frames in :meth:`impute`.
    impute_joint_ends : bool
        In :meth:`impute`, update each stick's motion and its endpoint posteriors as
        one block (default True; docs/em.md section 8): the same objective, but an
        endpoint no longer anchors the stick to its previous pose, so a partly
        hidden stick reaches the pose its visible points give. False: the paper's
        order (endpoints, then motions against them).
    impute_rotation_prior : bool
        In :meth:`impute`, a von Mises-Fisher chain prior on each stick's rotations
        from frame to frame, its concentration matched to the trained motions
        (default True; docs/em.md section 8): where a few visible points leave a
        stick's pose loosely determined, it stays near its neighbours' rotations.
        False: no prior on motions (the paper's model).
    impute_centroid_prior : bool
        In :meth:`impute`, a Gaussian random-walk prior on the image path of each
        stick's centroid, its precision matched to the trained motions (default True;
        docs/em.md section 8): a stick hidden for a run of frames follows its own path
        as well as its joints, which alone can place it far off where a joint is loose
        or a 2-point stick's turn about its line is free. False: no such prior.
    impute_scale : bool
        In :meth:`impute`, first estimate the figure's image scale in every new frame
        against the learned stick shapes (:func:`.impute.frame_scales`, relative to the
        training frames' own), divide it out, and multiply the predictions back
        (default False; docs/em.md section 8). For a pinhole camera whose subject comes
        nearer or goes farther than in training: the model's cameras are orthographic.
        It costs some accuracy on data from an orthographic camera.
    random_state : None, int or Generator
    progress : bool
        Show a tqdm progress bar over the merge stages (stage k of n, objective).
    """

    min_points = 4
    min_frames = 3

    def __init__(self, n_iter: int = 200, n_iter_merge: int = 20, resample_every: int = 10,
                 resample: str = "sample", selection: str = "bic", n_ends: int = 3,
                 endpoint_init: str = "axis",
                 merge_init: str = "joint", merge_scope: str = "local", max_candidates: int | None = 40,
                 max_merges: int | None = None, merge_baseline: bool = True, n_polish: int = 3,
                 reuse_scores: bool = True, tol: float = 1e-4, min_stick_points: int = 3,
                 max_sticks: int | None = None, labels: Any = None, refine_sticks: bool = True,
                 articulated_rounds: int = 4, split_axes: int = 1, dissolve_points: int = 3, resplit: bool = True,
                 holdout: float | None = 0.15, holdout_masks: int = 1, holdout_points: int = 2,
                 dissolve_scope: str = "all",
                 remerge: bool = True, split_dissolved: int = 4,
                 unpair: bool = True, bridge_points: int = 2, split_hubs: bool = True, reattach: bool = True,
                 spare_end: bool = False, hub_end: bool = True, bic_free_ends: bool = True, bic_rotations: str = "all",
                 max_trees: int | str | None = "auto", retry_mid_air: float | None = None,
                 merge_rank: str = "residual", align_mirrors: bool = True,
                 max_frames: int | None = 400, oversegment: float | None = 3.5, n_jobs: int | None = None,
                 tau_p: float = 25.0,
                 alpha0: float = 1.0, beta0: float = 1e-3, max_precision: float = 1e6, impute_iter: int = 100,
                 impute_joint_ends: bool = True, impute_rotation_prior: bool = True,
                 impute_centroid_prior: bool = True, impute_scale: bool = False, random_state: Any = None,
                 progress: bool = False) -> None:
        self.n_iter = n_iter
        self.n_iter_merge = n_iter_merge
        self.resample_every = resample_every
        self.resample = resample
        self.selection = selection
        self.n_ends = n_ends
        self.endpoint_init = endpoint_init
        self.merge_init = merge_init
        self.merge_scope = merge_scope
        self.max_candidates = max_candidates
        self.max_merges = max_merges
        self.merge_baseline = merge_baseline
        self.n_polish = n_polish
        self.reuse_scores = reuse_scores
        self.tol = tol
        self.min_stick_points = min_stick_points
        self.max_sticks = max_sticks
        self.labels = labels
        self.refine_sticks = refine_sticks
        self.articulated_rounds = articulated_rounds
        self.split_axes = split_axes
        self.dissolve_points = dissolve_points
        self.resplit = resplit
        self.holdout = holdout
        self.holdout_masks = holdout_masks
        self.holdout_points = holdout_points
        self.dissolve_scope = dissolve_scope
        self.remerge = remerge
        self.split_dissolved = split_dissolved
        self.unpair = unpair
        self.bridge_points = bridge_points
        self.split_hubs = split_hubs
        self.reattach = reattach
        self.spare_end = spare_end
        self.hub_end = hub_end
        self.bic_free_ends = bic_free_ends
        self.bic_rotations = bic_rotations
        self.max_trees = max_trees
        self.retry_mid_air = retry_mid_air
        self.merge_rank = merge_rank
        self.align_mirrors = align_mirrors
        self.max_frames = max_frames
        self.oversegment = oversegment
        self.n_jobs = n_jobs
        self.tau_p = tau_p
        self.alpha0 = alpha0
        self.beta0 = beta0
        self.max_precision = max_precision
        self.impute_iter = impute_iter
        self.impute_joint_ends = impute_joint_ends
        self.impute_rotation_prior = impute_rotation_prior
        self.impute_centroid_prior = impute_centroid_prior
        self.impute_scale = impute_scale
        self.random_state = random_state
        self.progress = progress

    # ----------------------------------------------------------------- checks
    def _settings(self) -> tuple[EMSettings, Priors]:
        for name in ("n_iter", "n_iter_merge", "min_stick_points", "impute_iter", "n_ends"):
            check_positive(getattr(self, name), name, integer=True)
        if self.n_ends < 2:
            raise ValueError(f"n_ends must be >= 2 (a stick has two ends), got {self.n_ends!r}")
        check_positive(self.resample_every, "resample_every", integer=True, allow_zero=True)
        check_positive(self.n_polish, "n_polish", integer=True, allow_zero=True)
        check_positive(self.holdout_masks, "holdout_masks", integer=True)
        check_positive(self.holdout_points, "holdout_points", integer=True)
        if self.dissolve_scope not in ("all", "leaves"):
            raise ValueError(f"dissolve_scope must be 'all' or 'leaves', got {self.dissolve_scope!r}")
        check_positive(self.articulated_rounds, "articulated_rounds", integer=True, allow_zero=True)
        if self.split_axes not in (1, 2, 3) or isinstance(self.split_axes, bool):
            raise ValueError(f"split_axes must be 1, 2 or 3 (principal axes of a 3D shape), got {self.split_axes!r}")
        check_positive(self.dissolve_points, "dissolve_points", integer=True, allow_zero=True)
        check_positive(self.split_dissolved, "split_dissolved", integer=True, allow_zero=True)
        check_positive(self.bridge_points, "bridge_points", integer=True, allow_zero=True)
        check_positive(self.tol, "tol", allow_zero=True)
        for name in ("tau_p", "alpha0", "beta0", "max_precision"):
            check_positive(getattr(self, name), name)
        choices = {"resample": ("sample", "map"), "selection": ("objective", "bic"),
                   "endpoint_init": ("axis", "centroid"), "merge_init": ("joint", "mean"),
                   "merge_scope": ("local", "full")}
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {', '.join(map(repr, allowed))}, got {getattr(self, name)!r}")
        for name in ("impute_joint_ends", "impute_rotation_prior", "impute_centroid_prior", "impute_scale", "unpair",
                     "split_hubs"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"{name} must be True or False, got {getattr(self, name)!r}")
        if isinstance(self.max_trees, (str, bool)) and self.max_trees != "auto":
            raise ValueError(f"max_trees must be a positive integer, 'auto' or None, got {self.max_trees!r}")
        if self.max_trees is not None and self.max_trees != "auto":
            check_positive(self.max_trees, "max_trees", integer=True)
        if self.retry_mid_air is not None and not (isinstance(self.retry_mid_air, (int, float, np.number))
                                                   and not isinstance(self.retry_mid_air, bool)
                                                   and np.isfinite(self.retry_mid_air) and self.retry_mid_air > 0):
            raise ValueError(f"retry_mid_air must be None or a positive number of figure radii, "
                             f"got {self.retry_mid_air!r}")
        if self.bic_rotations not in ("all", "identified"):
            raise ValueError(f"bic_rotations must be 'all' or 'identified', got {self.bic_rotations!r}")
        if self.merge_rank not in ("objective", "residual"):
            raise ValueError(f"merge_rank must be 'objective' or 'residual', got {self.merge_rank!r}")
        for name in ("align_mirrors", "spare_end", "hub_end", "bic_free_ends"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"{name} must be True or False, got {getattr(self, name)!r}")
        for name in ("max_candidates", "max_merges", "max_sticks", "max_frames", "n_jobs"):
            v = getattr(self, name)
            if v is not None:
                check_positive(v, name, integer=True, allow_zero=name == "max_merges")
        if self.holdout is not None and not (isinstance(self.holdout, (int, float)) and 0 < self.holdout < 1):
            raise ValueError(f"holdout must be None or a fraction in (0, 1), got {self.holdout!r}")
        if self.oversegment is not None and not (np.isfinite(self.oversegment) and self.oversegment >= 1):
            raise ValueError(f"oversegment must be None or a number >= 1, got {self.oversegment!r}")
        if self.max_frames is not None and self.max_frames < 10:
            raise ValueError(f"max_frames must be None or >= 10, got {self.max_frames!r}")
        settings = EMSettings(n_iter=int(self.n_iter), n_iter_merge=int(self.n_iter_merge),
                              resample_every=int(self.resample_every), resample=self.resample,
                              min_stick_points=int(self.min_stick_points), merge_scope=self.merge_scope,
                              merge_init=self.merge_init,
                              max_candidates=None if self.max_candidates is None else int(self.max_candidates),
                              max_merges=None if self.max_merges is None else int(self.max_merges),
                              tol=float(self.tol), refine_sticks=bool(self.refine_sticks),
                              merge_baseline=bool(self.merge_baseline), n_polish=int(self.n_polish),
                              reuse_scores=bool(self.reuse_scores),
                              articulated_rounds=int(self.articulated_rounds), split_axes=int(self.split_axes),
                              dissolve_points=int(self.dissolve_points), resplit=bool(self.resplit),
                              holdout=None if self.holdout is None else float(self.holdout),
                              holdout_masks=int(self.holdout_masks), holdout_points=int(self.holdout_points),
                              dissolve_scope=str(self.dissolve_scope),
                              remerge=bool(self.remerge), split_dissolved=int(self.split_dissolved),
                              unpair=bool(self.unpair),
                              bridge_points=int(self.bridge_points), split_hubs=bool(self.split_hubs),
                              reattach=bool(self.reattach), spare_end=bool(self.spare_end),
                              hub_end=bool(self.hub_end), bic_free_ends=bool(self.bic_free_ends),
                              bic_rotations=str(self.bic_rotations),
                              max_trees=None if self.max_trees in (None, "auto") else int(self.max_trees),
                              endpoint_init=self.endpoint_init, n_ends=int(self.n_ends),
                              merge_rank=str(self.merge_rank), align_mirrors=bool(self.align_mirrors))
        priors = Priors(tau_p=float(self.tau_p), alpha0=float(self.alpha0), beta0=float(self.beta0),
                        max_precision=float(self.max_precision))
        return settings, priors

    # -------------------------------------------------------------------- fit
    def _fit(self, traj: Trajectories, rng: np.random.Generator) -> Skeleton:
        if traj.n_dims != 2:
            raise ValueError(f"em models 2D observations, got {traj.n_dims}D data; project 3D data first "
                             "(traj.project())")
        settings, priors = self._settings()
        if isinstance(self.max_trees, str):  # "auto": the figures the data's format names, if any
            n = traj.meta.get("n_figures")
            if isinstance(n, (int, np.integer)) and not isinstance(n, bool) and n >= 1:
                settings = replace(settings, max_trees=int(n))
        skeleton = self._search(traj, settings, priors, rng)
        if self.retry_mid_air is None:
            return skeleton
        first = mid_air(skeleton)
        if first <= self.retry_mid_air:
            return skeleton
        more = replace(settings, n_ends=settings.n_ends + 1)
        # Spawned after the first search, whose generators are then the same as without the retry.
        second = self._search(traj, more, priors, child_rng(rng))
        reach = mid_air(second)
        kept = second if reach < first else skeleton
        kept.info["retry"] = {"mid_air": [first, reach], "n_ends": [settings.n_ends, more.n_ends],
                              "kept": "second" if kept is second else "first"}
        return kept

    def _search(self, traj: Trajectories, settings: EMSettings, priors: Priors,
                rng: np.random.Generator) -> Skeleton:
        with mirror_alignment(settings.align_mirrors), hub_endpoints(settings.hub_end):
            return self._search_stages(traj, settings, priors, rng)

    def _search_stages(self, traj: Trajectories, settings: EMSettings, priors: Priors,
                       rng: np.random.Generator) -> Skeleton:
        stages, selected, norm, info0 = fit_stages(traj, settings, priors, rng, labels=self.labels,
                                                   max_sticks=self.max_sticks, selection=self.selection,
                                                   endpoint_init=self.endpoint_init,
                                                   n_ends=settings.state_ends,
                                                   progress=self.progress, max_frames=self.max_frames,
                                                   oversegment=self.oversegment, n_jobs=self.n_jobs)
        return _skeleton(stages, selected, norm, info0, self.selection, traj)

    # ----------------------------------------------------------------- impute
    @classmethod
    def impute_skeleton(cls, skeleton: Skeleton, traj: Trajectories) -> np.ndarray:
        """Re-fit motions, endpoints and vertices to ``traj`` with L, K, G and R fixed; predict every point.

        The new frames are normalised with the training centre and scale so the
        learned precisions apply. Motions start from a per-frame Procrustes fit of
        the fixed local shapes to the visible points where a stick shows at least
        4 points and 60% of them; in the other frames (where a handful of points
        leaves the depth-mirror ambiguity of orthographic projection open) the
        rotation is interpolated (slerp) between those frames and the translation
        taken from the visible points, or interpolated where none is visible.
        Then ``impute_iter`` EM iterations (local updates only, so each frame stays
        in the branch it starts in) update endpoints, vertices, vertex precisions
        and motions; in frames where a stick's visible points and its joints
        (endpoints on a vertex shared with another stick) number fewer than 3 its
        rotation keeps the interpolated value (such a frame cannot pin it down)
        while its translation is updated. With ``impute_joint_ends`` each stick's
        motion and endpoints are updated as one block, and with
        ``impute_rotation_prior`` each rotation is also drawn toward its
        neighbouring frames' by a prior matched to the trained motions, and with
        ``impute_centroid_prior`` each stick's centroid toward its neighbouring
        frames' (docs/em.md section 8). With ``impute_scale`` every frame is first brought
        to the learned shapes' size (:func:`.impute.frame_scales`) and the
        predictions are scaled back.
        """
        if skeleton.params.get("impute_scale", False):
            return _impute_scaled(skeleton, traj)
        return _impute_plain(skeleton, traj)


def _impute_plain(skeleton: Skeleton, traj: Trajectories) -> np.ndarray:
    """:meth:`EMSkeleton.impute_skeleton` without ``impute_scale``."""
    state, obs, norm = _impute_state(skeleton, traj)
    n_iter = int(skeleton.params.get("impute_iter", 100))
    priors = Priors(**skeleton.info["priors"])
    settings = EMSettings(**{**skeleton.info["settings"], "tol": 0.0})
    # A model saved before these options imputes with their defaults.
    kappa = None
    if skeleton.params.get("impute_rotation_prior", True):
        kappa = rotation_concentration(np.asarray(skeleton.motions, float)[..., :3])
    centre, scale = norm
    lam = None
    if skeleton.params.get("impute_centroid_prior", True):
        motions = np.asarray(skeleton.motions, float)
        lam = centroid_concentration(motions[..., :3], motions[..., 3] / scale, stick_centroids(state))
    refit_motions(state, obs, priors, settings, n_iter,
                  collapse=bool(skeleton.params.get("impute_joint_ends", True)), kappa=kappa, lam=lam)
    return state.point_predictions() * scale + centre


# --------------------------------------------------------------------------- helpers
# A stick whose residual variance (corrected for its fit's degrees of freedom) exceeds the
# robust noise variance by this factor holds points of more than one part (refine.misfit_ratios;
# measured: right sticks of random figures 0.95-1.34, wrong ones 1.39-3.4, CMU 85_02 7.4).
OVERSEGMENT_MISFIT = 1.35
# ... or exceeds the data's local noise variance (geometry.noise_level, squared) by this factor:
# measured on 36 random figures at 1 % noise, right sticks 1.12-1.40 (the local estimate is
# biased low: it takes the most rigid small sets); at 3 % noise, where most of a first search's
# sticks can hold two parts and the factor above stays near 1, right figures up to 1.54 and
# sticks holding two parts 1.36-3.2 (docs/em.md section 11).
OVERSEGMENT_LOCAL_MISFIT = 1.5
# ... or when its sticks hold more than this many points on average (HDM05's 41 markers in 4
# sticks fit at 1.28: the lower quartile of 4 bad sticks is no noise level).
OVERSEGMENT_SIZE = 10.0
# The speculative second search runs at this lower priority (os.nice): on the human-sized
# random figures it is thrown away on 3 of 4 seeds, while the first search's speculative
# trials (trials.py), forked beside it, are needed whenever the trial before them loses.
SECOND_START_NICE = 19


def fit_stages(traj: Trajectories, settings: EMSettings, priors: Priors, rng: np.random.Generator, *,
               labels: Any = None, max_sticks: int | None = None, selection: str = "bic",
               endpoint_init: str = "axis", n_ends: int = 2, progress: bool = False,
               max_frames: int | None = None, oversegment: float | None = None, n_jobs: int | None = None
               ) -> tuple[list[Stage], int, tuple[np.ndarray, float], dict[str, Any]]:
    """Initialisation and the whole structure search; returns every stage and the selected one.

    With ``max_frames`` and more frames than that, the search runs on evenly spaced
    frames and the selected stage's model is then re-fitted on all of them
    (``info0["refit"]``); the other stages keep their values on the searched frames.
    With ``oversegment``, when the first search leaves a stick that is not rigid
    (:func:`refine.misfit_ratios` above ``OVERSEGMENT_MISFIT``) or sticks of more
    than ``OVERSEGMENT_SIZE`` points on average, a second search
    starts from ``ceil(P / oversegment)`` groups and the start whose selected stage
    has the higher BIC (on the same frames) is kept (``info0["starts"]``). With
    ``n_jobs`` > 1 (None: the CPUs available) the second search starts at once in
    a forked process and is stopped when the first shows it is not needed, and
    the searches run some of their work in forked children (:mod:`.forked`); the
    result is the same either way.
    """
    n_jobs = available_cpus() if n_jobs is None else n_jobs
    settings = replace(settings, n_jobs=n_jobs)
    obs_all, centre, scale = normalise(traj.xy)
    frames = search_frames(obs_all.mask > 0, max_frames)
    obs = obs_all if frames is None else obs_all.take_frames(frames)
    P = traj.n_points
    info0: dict[str, Any] = {}
    starts = []
    filled = None
    if labels is None:
        ms = max_sticks if max_sticks is not None else int(max(2, min(20, P // 3)))
        labels, ap = _initial_groups(traj, ms, rng)
        filled = ap.get("filled")
        info0["initial_clustering"] = {k: v for k, v in ap.items() if isinstance(v, (int, float, str, type(None)))}
        starts.append(labels)
        fine = min(int(np.ceil(P / oversegment)), ms) if oversegment is not None else 0
        if fine > int(labels.max()) + 1:
            starts.append(_initial_groups(traj, ms, rng, n_segments=fine)[0])
    else:
        labels = check_labels(labels, P, "labels")
        if (labels < 0).any():
            raise ValueError("labels must assign every point to a stick (no -1)")
        starts.append(labels)
    if filled is None and obs_all.mask.mean() < 0.5:
        # Given groups: the same completion the grouping would have used (its own fixed seed,
        # so that rng's stream is the one without it).
        filled = smooth_low_rank_complete(traj.xy, interpolation_fallback=True, random_state=0)
    if filled is not None:
        # Sparse data (fewer than half the entries seen): every stick's SfM start is also made
        # from the scene's completion (low-rank and smooth in time), not only from its own
        # trajectories interpolated in time, whose errors the metric upgrade turned into
        # rotations EM could not undo; the better-fitting start is kept (docs/em.md section 5).
        obs_all.filled = (filled - centre) / scale
        obs = obs_all if frames is None else obs_all.take_frames(frames)

    def search(labels: np.ndarray, r: np.random.Generator, k: int, show: bool = progress
               ) -> tuple[list[Stage], int, int]:
        _, labels = np.unique(labels, return_inverse=True)
        S = int(labels.max()) + 1
        st = initial_state(obs, labels, S, priors, r, endpoint_init=endpoint_init, n_ends=n_ends)
        bar = None
        cb = None
        if show:
            from tqdm.auto import tqdm

            class Bar(tqdm):  # type: ignore[misc, valid-type]
                # No monitor thread: forking is refused while any other thread runs (forked.py: a
                # fork taken while the monitor held tqdm's or stderr's lock leaves it held in the
                # child), so with a monitor the search would run on one core.
                monitor_interval = 0

            bar = Bar(total=max(S - 1, 1), desc=f"em merges (start {k + 1} of {len(starts)})", unit="stage")

            def cb(i: int, n: int, value: float, bar: Any = bar) -> None:
                bar.total = max(n, 1)
                bar.n = i
                bar.set_postfix_str(f"stage {i} of {n}, objective {value:.6g}")
                bar.refresh()

        try:
            stages, selected = learn_structure(st, obs, priors, settings, r, selection=selection, progress=cb)
        finally:
            if bar is not None:
                bar.close()
        return stages, selected, S

    runs = []
    second: Speculative | contextlib.nullcontext = contextlib.nullcontext()
    if len(starts) > 1:
        # The finer start draws from its own generator, so it gives the same result whether it
        # runs beside the first search (a forked process, started before the first search
        # knows whether it is needed) or after it; spawning does not advance rng's stream.
        rng_fine = child_rng(rng)
        second = Speculative(lambda: search(starts[1], rng_fine, 1, show=False), parallel=n_jobs > 1,
                             here=lambda: search(starts[1], rng_fine, 1), name="the second structure search",
                             nice=SECOND_START_NICE)
    with second:
        runs.append(search(starts[0], rng, 0))
        stages, selected, _ = runs[0]
        if len(starts) > 1:
            # The finer start only where the first leaves a stick that is not rigid: every
            # stick fitting at the noise level means the clustering found the parts.
            # With a few large sticks the noise level (lower quartile over sticks) is itself
            # inflated, so more than OVERSEGMENT_SIZE points per stick also qualify.
            # A stick split by split_hubs was not rigid when the search left it: that counts too,
            # and the stick it added is not one the search found.
            worst = float(misfit_ratios(stages[selected].state, obs, priors).max())
            info0["first_start_misfit"] = worst
            # The lower quartile over sticks is no noise level when most sticks hold two parts
            # (a noisy figure whose first groups were all too coarse): the data's local noise
            # level, from the most rigid small sets of neighbouring points, is one that holds then.
            var_local = local_noise_variance(obs, priors)
            local = 0.0 if var_local is None else float(
                misfit_ratios(stages[selected].state, obs, priors, var=var_local).max())
            info0["first_start_local_misfit"] = local
            hubs = sum(len(s.hubs) for s in stages)
            info0["first_start_hub_split"] = hubs > 0
            n_first = int(stages[selected].labels.max()) + 1 - hubs
            # The rules before session 35; the local misfit is the one added then.
            before = worst > OVERSEGMENT_MISFIT or P > OVERSEGMENT_SIZE * n_first or hubs > 0
            # A start is only finer if it has more groups than the first search ended with sticks.
            if (before or local > OVERSEGMENT_LOCAL_MISFIT) and fine > n_first:
                info0["second_start_by_local_misfit"] = not before
                runs.append(second.result())
                info0["second_start_parallel"] = second.forked
    # Starts are compared by BIC whatever the selection: the objective has no charge for the
    # per-frame motions, so it always prefers the start with more sticks.
    # (the BIC each search reached before its held-out check: that check may lower it)
    best = int(np.argmax([r[0][r[1]].search_bic for r in runs]))
    stages, selected, S = runs[best]
    info0["n_initial_sticks"] = S
    if len(runs) > 1:
        info0["starts"] = [{"n_initial_sticks": int(k), "n_sticks": int(stg[sel].labels.max()) + 1,
                            "bic": float(stg[sel].bic), "objective": float(stg[sel].objective),
                            "search_bic": float(stg[sel].search_bic)}
                           for stg, sel, k in runs]
        info0["start"] = best
    if frames is not None:
        sel = stages[selected]
        assert sel.state is not None
        full = extend_frames(sel.state, obs_all, frames, priors)
        full, value, sweeps = run_em(full, obs_all, priors, settings, settings.n_iter, rng)
        info0["refit"] = {"search_frames": int(frames.size), "frames": int(obs_all.n_frames),
                          "objective": float(value),
                          "bic": settings_bic(full, obs_all, value, priors, settings),
                          "n_sweeps": int(sweeps), "labels_changed": int(np.sum(full.labels != sel.labels))}
        sel.state = full
        for s in stages:  # states on the searched frames only would not match the data any more
            if s is not sel:
                s.state = None
    info0["settings"] = asdict(settings)
    info0["priors"] = asdict(priors)
    return stages, selected, (centre, scale), info0


def _rigid_bic_terms(xy: np.ndarray, labels: np.ndarray) -> tuple[float, float, float]:
    """RSS of every group's own affine rank-3 fit to its *observed* entries, its parameter
    count (per frame at most the coordinates the group shows there) and N."""
    from ...geometry import affine_factorization

    obs = ~np.isnan(xy[..., 0])
    D = xy.shape[2]
    rss = k = 0.0
    for c in np.unique(labels):
        idx = np.flatnonzero(labels == c)
        seen = obs[idx].sum(axis=0)
        k += float(np.minimum(D * 4, D * seen).sum()) + 3.0 * idx.size
        if idx.size > 4:
            fac = affine_factorization(xy[idx], rank=3, random_state=0)
            rss += fac.rms ** 2 * fac.n_observed * D
    return rss, k, float(obs.sum() * D)


def _initial_groups(traj: Trajectories, max_segments: int, rng: np.random.Generator, n_segments: int | None = None
                    ) -> tuple[np.ndarray, dict]:
    """Affinity Propagation groups; with missing data also from the gap-interpolated trajectories.

    The rigid-subspace affinity completes gaps by a low-rank fit, which with sparse
    observations (75% withheld) merges the whole scene into one or two groups.
    Where fewer than half of the entries are observed the trajectories are completed
    by a factorisation smooth in time (:func:`geometry.smooth_low_rank_complete`):
    on 16 random 4-stick figures with 75 % withheld the groups' mean ARI was 0.94
    against 0.62 with linear interpolation in time (docs/em.md section 5). Where
    interpolation predicts the completion's held-out entries better (motion capture
    at 120 Hz: short gaps, and more independent markers than the factorisation's
    rank), the interpolated trajectories are grouped instead. Where at
    least half are observed, every point's gaps are filled by linear interpolation
    (held at the nearest observation before the first and after the last,
    :func:`geometry.fill_gaps`); over a long gap (an occluder) interpolation bends
    the trajectory and can mix parts, so both that grouping and the one on the
    data as given are made and the one with the lower BIC of per-group affine fits
    to the observed entries is kept. The EM itself sees the observations only.
    ``n_segments`` fixes the count instead of estimating it.
    """
    from ...segmentation import affinity_propagation_segments

    if traj.observed.all():
        return affinity_propagation_segments(traj.xy, max_segments=max_segments, n_segments=n_segments,
                                             random_state=rng, return_info=True)
    seed = int(rng.integers(2**31 - 1))
    if traj.observed.mean() < 0.5:
        filled, fill_info = smooth_low_rank_complete(traj.xy, interpolation_fallback=True, random_state=seed,
                                                     return_info=True)
        how = ("gaps interpolated (lower held-out error)" if fill_info["method"] == "interpolation"
               else "smooth low-rank completion")
        lab, info = affinity_propagation_segments(filled, max_segments=max_segments, n_segments=n_segments,
                                                  random_state=seed, return_info=True)
        return lab, {**info, "input": how, "completion": fill_info, "filled": filled}
    filled = fill_gaps(traj.xy)
    lab_f, info_f = affinity_propagation_segments(filled, max_segments=max_segments, n_segments=n_segments,
                                                  random_state=seed, return_info=True)
    info_f = {**info_f, "input": "gaps interpolated"}
    lab_r, info_r = affinity_propagation_segments(traj.xy, max_segments=max_segments, n_segments=n_segments,
                                                  random_state=seed, return_info=True)
    if np.array_equal(lab_r, lab_f):
        return lab_f, info_f
    terms = [_rigid_bic_terms(traj.xy, lab) for lab in (lab_f, lab_r)]
    N = terms[0][2]
    sig2 = min(r / max(N - k, 1.0) for r, k, _ in terms)
    cost = [r / (2.0 * max(sig2, 1e-300)) + 0.5 * k * np.log(N) for r, k, _ in terms]
    if cost[1] < cost[0]:
        return lab_r, {**info_r, "input": "gaps as given"}
    return lab_f, info_f


def _skeleton(stages: list[Stage], selected: int, norm: tuple[np.ndarray, float], info0: dict[str, Any],
              selection: str, traj: Trajectories) -> Skeleton:
    centre, scale = norm
    st = stages[selected].state
    assert st is not None
    S, F, D = st.trans.shape
    edges, verts = stick_edges(st)
    counts = st.vertex_counts()
    joint_v = np.flatnonzero(counts >= 2)
    row = {int(v): r for r, v in enumerate(joint_v)}
    joints = st.mu_v[joint_v] * scale + centre
    motions = np.concatenate([st.rot, (st.trans * scale + centre)[..., None]], axis=-1)
    ref = int(np.argmax((~np.isnan(traj.xy[..., 0])).sum(axis=0)))
    info = dict(info0)
    info.update({
        "selection": selection,
        "selected_stage": int(selected),
        "reference_frame": ref,
        "refinements": stages[0].refinements,
        "stages": [{
            "objective": s.objective, "bic": s.bic, "n_sticks": int(s.labels.max()) + 1,
            "labels": s.labels.tolist(), "vertex_of": s.vertex_of.tolist(), "edges": [list(e) for e in s.edges],
            "merged": None if s.merged is None else list(s.merged), "n_sweeps": s.n_sweeps,
            "dissolved": s.dissolved, "moved": s.moved, "heldout": s.heldout, "split": s.split,
            "reattached": s.reattached,
            "joined": s.joined,
            "bridged": s.bridged,
            "unpaired": s.unpaired,
            "hubs": s.hubs,
            "ends_xy": (s.ends_xy * scale + centre).tolist(), "joints_xy": (s.joints_xy * scale + centre).tolist(),
        } for s in stages],
        "objective_stage": int(np.argmax([s.objective for s in stages])),
        "bic_stage": int(np.argmax([s.bic for s in stages])),
        "precisions": {"tau_w": st.tau_w, "tau_m": st.tau_m, "tau_t": st.tau_t},
        "joint_support": _joint_support_info(st, edges, verts, scale, traj.xy),
        "units": "objective in normalised units (data centred, scaled to unit RMS spread)",
    })
    state = {
        "ends": st.ends * scale,
        "vertex_of": st.vertex_of,
        "alpha": st.alpha,
        "beta": st.beta,
        "centre": centre,
        "scale": np.array(scale),
        "precisions": np.array([st.tau_w, st.tau_m, st.tau_t]),
        # The training frames' own image scale against the learned shapes (``impute_scale``
        # measures new frames relative to it: noise and skin motion bias each estimate alike).
        "frame_scale_reference": np.array(np.exp(np.mean(np.log(frame_scales(st.labels, st.local * scale,
                                                                              traj.xy))))),
    }
    return Skeleton(method="em", labels=st.labels, n_sticks=S, edges=edges, joints=joints,
                    edge_joints=np.array([row[v] for v in verts], dtype=np.int64), motions=motions,
                    local=st.local * scale,
                    log_likelihood=info0.get("refit", {}).get("objective", stages[selected].objective), n_dims=D,
                    state=state,
                    info=info)


def _joint_support_info(st: StickState, edges: list[tuple[int, int]], verts: list[int], scale: float,
                        xy: np.ndarray) -> dict[str, Any]:
    """``info["joint_support"]``: :func:`structure.joint_support` in data units, with the figure's size.

    ``figure_radius`` is the median over frames of the RMS distance of the visible
    points from their centroid, a scale to read ``reach`` against.
    """
    reach, gap = joint_support(st, edges, verts)
    seen = ~np.isnan(xy[..., 0])  # (P, F)
    n = seen.sum(axis=0)
    ok = n > 0
    w = np.where(seen[..., None], xy, 0.0)[:, ok]
    centroid = w.sum(axis=0) / n[ok, None]
    sq = np.where(seen[:, ok], np.sum((w - centroid) ** 2, axis=-1), 0.0).sum(axis=0) / n[ok]
    radius = float(np.median(np.sqrt(sq))) if ok.any() else float("nan")
    return {"edges": [list(e) for e in edges], "reach": (reach * scale).tolist(), "gap": (gap * scale).tolist(),
            "figure_radius": radius}


def mid_air(skeleton: Skeleton) -> float:
    """The farthest joint from its sticks: the largest over edges of the smaller ``reach``, in figure radii.

    0 for a skeleton without joints (``info["joint_support"]``, :func:`structure.joint_support`).
    A joint of a stick without points (reach NaN) is left out: such a stick is a segment
    no point shows, and its joints lie wherever that segment ends (CMU 85_02 at camera
    30000/7: a body tree whose one such joint was 1.06 radii from the other stick's points).
    """
    js = skeleton.info["joint_support"]
    reach = np.asarray(js["reach"], float).reshape(-1, 2)
    reach = reach[~np.isnan(reach).any(axis=1)]
    if reach.size == 0 or not np.isfinite(js["figure_radius"]) or js["figure_radius"] <= 0:
        return 0.0
    return float(reach.min(axis=1).max() / js["figure_radius"])


def _impute_scaled(skeleton: Skeleton, traj: Trajectories) -> np.ndarray:
    """``impute_scale``: each frame scaled to the learned shapes' size about its visible points' mean,
    imputed, and scaled back (docs/em.md section 8)."""
    if traj.n_dims != 2:
        raise ValueError(f"impute_scale applies to 2D data, these are {traj.n_dims}D")
    xy = traj.xy
    seen = traj.observed  # (P, F)
    cnt = seen.sum(axis=0)
    f = np.arange(traj.n_frames)
    has = cnt > 0
    if not has.any():
        raise ValueError("no point is observed in any frame given; em cannot impute")
    mean = np.where(seen[..., None], xy, 0.0).sum(axis=0)[has] / cnt[has, None]
    # frames with nothing visible: the mean interpolated in time, so that scaling moves nothing there
    centre = np.stack([np.interp(f, f[has], mean[:, d]) for d in range(2)], axis=1)  # (F, 2)
    reference = float(skeleton.state.get("frame_scale_reference", 1.0))
    c = frame_scales(skeleton.labels, skeleton.local, xy) / reference  # (F,)
    pred = _impute_plain(skeleton, traj.with_xy(centre + (xy - centre) / c[:, None]))
    return centre + c[:, None] * (pred - centre)


def _impute_state(skeleton: Skeleton, traj: Trajectories) -> tuple[StickState, Observations, tuple]:
    """A state for new frames: fixed L, K, G, R; motions by Procrustes; vertices from endpoints
    (:func:`impute.start_state`)."""
    for key in ("ends", "vertex_of", "alpha", "beta", "centre", "scale", "precisions"):
        if key not in skeleton.state:
            raise ValueError(f"the em skeleton lacks state[{key!r}]; it cannot impute (re-fit it)")
    centre = np.asarray(skeleton.state["centre"], float)
    scale = float(skeleton.state["scale"])
    xy = traj.xy
    mask = ~np.isnan(xy[..., 0])
    obs = Observations(np.where(mask[..., None], (xy - centre) / scale, 0.0), mask.astype(float))
    labels = skeleton.labels
    if (labels < 0).any():
        raise ValueError("the em skeleton has unassigned points; it cannot impute")
    for s in range(skeleton.n_sticks):  # a stick's pose in a frame comes from its own points
        pts = np.flatnonzero(labels == s)
        if not mask[pts].any():
            raise ValueError(f"stick {s} (points {pts.tolist()}) is not visible in any frame given; em cannot "
                             "place it (give frames where at least one of its points is seen)")
    st = start_state(labels, skeleton.local / scale, np.asarray(skeleton.state["ends"], float) / scale,
                     np.asarray(skeleton.state["vertex_of"], np.int64), np.asarray(skeleton.state["alpha"], float),
                     np.asarray(skeleton.state["beta"], float),
                     tuple(float(v) for v in skeleton.state["precisions"]),
                     float(skeleton.info.get("priors", {}).get("alpha0", 1.0)), obs)
    return st, obs, (centre, scale)
