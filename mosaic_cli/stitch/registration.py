"""Stage 2, drift control: register keyframes directly and place them all jointly.

Chaining accumulates error: a long flight bends.  Consecutive keyframes were registered
directly during the scan (one SIFT match instead of dozens of chained estimates); here the
keyframes that see the same ground again (loops, neighbouring survey lines) are registered as
well, and one robust least-squares problem (soft-L1 loss over each registration's homography
at its inlier locations, measured in the keyframes' own pixels, each pair weighted by its
inlier count; Levenberg-Marquardt with exact sparse steps, run to convergence) places every
keyframe in the reference keyframe's frame at once.  A loop closure that disagrees with the
rest is dropped and the problem solved again, so one bad match cannot bend the panorama.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from collections.abc import Set as AbstractSet
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # scipy is imported where it is used: a live stitch listens sooner (python -m benchmarks live listen --cold)
    import scipy.sparse

from mosaic_cli.errors import BadInput
from mosaic_cli.geometry import frame_corners, normalize, project
from mosaic_cli.stitch.features import FeatureMatcher, Features, PairMatch
from mosaic_cli.stitch.keyframes import overlap_fraction

DEFAULT_LOOP_PAIRS = 300


@dataclass
class RegistrationOptions:
    enabled: bool = True  # off: keyframes are placed by chaining the neighbours' registrations
    # Bounds the cost: at most this many non-consecutive registrations; None: 300, or for a photo
    # folder loops_per_photo for each photo, at least 300 (a survey photo overlaps photos of the
    # lines beside its own: 504 photos within 300 loops placed pairs 45 px apart).
    max_loop_pairs: int | None = None
    loops_per_photo: int = 3
    max_loops_per_keyframe: int = 6
    min_loop_overlap: float = 0.25  # predicted overlap (fraction of a frame) worth a try
    min_loop_gap: int = 2  # keyframes between the two of a loop pair, at least
    # A loop registration must agree with the predicted placement this well (fraction of the
    # frame diagonal at the corners): a wrong loop closure costs more than a missing one.
    loop_tolerance: float = 0.5
    # Inlier correspondences kept per pair (bounds the cost); a pair still counts as all of its
    # inliers: each kept point stands for inliers / kept of them.
    points_per_pair: int = 60
    chain_weight: float = 0.3  # weight of a point of a chained (estimator-only) link against a registered one
    loss_scale: float = 1.5  # pixels: soft-L1 turns from quadratic to linear here
    outlier_residual: float = 5.0  # pixels: median residual above which a loop pair is dropped
    max_steps: int = 200  # Levenberg-Marquardt steps at most (each accepted step; rejected tries are not counted)
    tolerance: float = 1e-10  # relative fall of the cost below which the refinement has converged
    loop_rounds: int = 2  # look for loops again once the placements are refined

    def __post_init__(self) -> None:
        self.validate()

    def loop_budget(self, keyframes: int, photos: bool) -> int:
        """The loop registrations allowed for ``keyframes`` keyframes (photos, with ``photos``)."""
        if self.max_loop_pairs is not None:
            return self.max_loop_pairs
        return max(DEFAULT_LOOP_PAIRS, self.loops_per_photo * keyframes) if photos else DEFAULT_LOOP_PAIRS

    def validate(self) -> None:
        if self.max_loop_pairs is not None and self.max_loop_pairs < 0:
            raise BadInput(f"--max-loop-pairs must be 0 or more, got {self.max_loop_pairs}")


@dataclass
class Link:
    """A constraint between keyframes a and b: ``points_a[k]`` in a is ``points_b[k]`` in b."""

    a: int
    b: int
    points_a: np.ndarray
    points_b: np.ndarray
    kind: str  # "sequential" (registered), "chain" (estimator only), "loop", "relocalised"
    weight: float = 1.0  # of each point: the correspondences it stands for, times the trust in them
    residual: float = 0.0  # median after refinement, pixels


@dataclass
class RegistrationReport:
    sequential: int = 0
    chained: int = 0
    loop_candidates: int = 0
    loops: int = 0
    loops_dropped: int = 0
    residual_before: float = 0.0
    residual_after: float = 0.0
    links: list[Link] = field(default_factory=list)


def relative(placements: list[np.ndarray], a: int, b: int) -> np.ndarray:
    """Keyframe a -> keyframe b, from placements into a common frame."""
    return normalize(np.linalg.inv(placements[b]) @ placements[a])


# A progress task: ``(description, total)`` -> a context manager yielding ``advance(n)``.
ProgressFactory = Callable[[str, int], AbstractContextManager[Callable[..., None]]]


@contextlib.contextmanager
def no_progress(description: str, total: int):
    yield lambda *a, **k: None


# (a, b, match): keyframe a was linked to keyframe b during the scan, ``match`` its direct
# registration (a -> b), None where that failed (the estimator's chain links them then).
Sequence = list[tuple[int, int, PairMatch | None]]


def register_keyframes(
    features: list[Features],
    placements: list[np.ndarray],
    sequence: Sequence,
    reference: int,
    matcher: FeatureMatcher,
    options: RegistrationOptions,
    progress: ProgressFactory = no_progress,
    extra_links: list[Link] | tuple[Link, ...] = (),
) -> tuple[list[np.ndarray], RegistrationReport]:
    """Keyframe -> reference placements refined against direct registrations: the scan's
    ``sequence`` links, ``extra_links`` (segments relocalised on each other) and loops.

    Loops are looked for twice: with the scan's placements, then again with the refined
    ones, which can reveal overlaps that drift had hidden (within ``max_loop_pairs``)."""
    size = matcher.source_size
    report = RegistrationReport()
    report.links = link_sequence(sequence, placements, size, options, report) + list(extra_links)
    tried: set[tuple[int, int]] = set()
    linked = {(min(l.a, l.b), max(l.a, l.b)) for l in report.links}
    for round_ in range(options.loop_rounds):
        candidates = [c for c in loop_candidates(placements, size, options, tried) if c not in linked]
        if tried and not candidates:
            break
        tried |= set(candidates)
        report.loop_candidates += len(candidates)
        name = "register loops" if round_ == 0 else f"register loops (round {round_ + 1})"
        with (progress if candidates else no_progress)(name, len(candidates)) as advance:  # an empty stage shows nothing
            report.links += link_loops(features, placements, candidates, matcher, options, report, advance)
            advance(0, status="refining")
            placements = refine_placements(placements, report, reference, size, options)
            advance(0, status=f"{report.loops - report.loops_dropped} loops, residual {report.residual_after:.2f} px")
    return placements, report


def chain_sequence(sequence: Sequence, placements: list[np.ndarray], reference: int) -> list[np.ndarray]:
    """Keyframe -> reference by chaining the scan's registrations (full homographies; the
    scan's placement where a registration failed): plain chaining, no drift control.  A
    keyframe linked to none (a segment's first) keeps the scan's placement."""
    chain = [np.asarray(P, float) for P in placements]
    for a, b, match in sorted(sequence):  # a > b: the linked-to keyframe is placed first
        step = match.H if match is not None else relative(placements, a, b)
        chain[a] = normalize(chain[b] @ step)
    to_reference = np.linalg.inv(chain[reference])
    return [normalize(to_reference @ H) for H in chain]


def link_sequence(sequence: Sequence, placements, size, options: RegistrationOptions, report) -> list[Link]:
    """The scan's links: direct registrations, or the estimator's chain (a weaker link) where
    that failed or disagreed with the chain."""
    links = []
    for a, b, match in sequence:
        if match is not None:
            links.append(link_from_match(a, b, match, "sequential", options))
            report.sequential += 1
        else:
            links.append(_from_homography(a, b, relative(placements, a, b), size, "chain", options.chain_weight))
            report.chained += 1
    return links


def link_loops(features, placements, candidates, matcher: FeatureMatcher, options: RegistrationOptions, report, advance) -> list[Link]:
    tolerance = options.loop_tolerance * float(np.hypot(*matcher.source_size))
    links = []
    for a, b in candidates:
        match = matcher.match(features[a], features[b], relative(placements, a, b), tolerance)
        if match is not None:
            links.append(link_from_match(a, b, match, "loop", options))
            report.loops += 1
        advance(1)
    return links


def loop_candidates(
    placements: list[np.ndarray],
    size: tuple[int, int],
    options: RegistrationOptions,
    tried: AbstractSet[tuple[int, int]] = frozenset(),
) -> list[tuple[int, int]]:
    """Non-neighbouring keyframe pairs predicted to overlap and not ``tried`` yet, most
    overlap first (the most reliable registrations), spread over the keyframes, within what
    is left of ``max_loop_pairs``."""
    from scipy.spatial import cKDTree
    budget = options.loop_budget(len(placements), photos=False) - len(tried)
    if budget <= 0 or len(placements) < options.min_loop_gap + 1:
        return []
    corners = [project(P, frame_corners(*size)) for P in placements]
    centres = np.array([c.mean(axis=0) for c in corners])
    radius = float(max(np.hypot(*np.ptp(c, axis=0)) for c in corners))
    scored = []
    for a, b in cKDTree(centres).query_pairs(radius):
        a, b = min(a, b), max(a, b)
        if b - a < options.min_loop_gap or (a, b) in tried:
            continue
        overlap = overlap_fraction(relative(placements, a, b), size)
        if overlap >= options.min_loop_overlap:
            scored.append((overlap, a, b))
    scored.sort(key=lambda s: (-s[0], s[1], s[2]))
    count = np.zeros(len(placements), int)
    for a, b in tried:
        count[a] += 1
        count[b] += 1
    chosen = []
    for _, a, b in scored:
        if count[a] >= options.max_loops_per_keyframe or count[b] >= options.max_loops_per_keyframe:
            continue
        chosen.append((a, b))
        count[a] += 1
        count[b] += 1
        if len(chosen) >= budget:
            break
    return chosen


def link_from_match(a: int, b: int, match: PairMatch, kind: str, options: RegistrationOptions) -> Link:
    """A registered pair as the refinement takes it: its homography ``match.H`` at up to
    ``points_per_pair`` of its inlier locations (a repeatable random pick), weighted so that
    the link counts as all of its inliers: a pair registered on 1000 inliers (two photos that
    overlap by 80%) outweighs one registered on 100 (a loop over a corner), as the evidence does.

    The points in b are where ``H`` puts the points of a, not the matched points: the
    registration (MAGSAC over all of its inliers) is the measurement, and the picked points
    say where in the frames it holds.  With the matched points themselves, a pair over ground
    that is not one plane (relief, trees: the inliers scatter a pixel or two about any
    homography) was fitted again from 60 of its points, to a homography up to a pixel from its
    own registration, and drift control moved consecutive photos that far off even where no
    loop pulled them."""
    n = match.inliers
    weight, points = 1.0, match.points_a
    if n > options.points_per_pair:
        pick = np.random.default_rng(a * 100003 + b).choice(n, options.points_per_pair, replace=False)
        weight, points = n / options.points_per_pair, match.points_a[pick]
    return Link(a, b, points, project(match.H, points), kind, weight)


def _from_homography(a: int, b: int, H: np.ndarray, size: tuple[int, int], kind: str, weight: float) -> Link:
    """A link known only as a homography: a 3x3 grid over frame a and its image in b."""
    xs = np.linspace(0, size[0] - 1, 3)
    ys = np.linspace(0, size[1] - 1, 3)
    grid = np.array([(x, y) for y in ys for x in xs], dtype=np.float64)
    return Link(a, b, grid, project(H, grid), kind, weight)


# -- joint refinement ---------------------------------------------------------------------


class _Problem:
    """Each non-reference keyframe k is placed by G_k = G0_k N^-1 (I + D_k) N, where G0_k is
    its initial placement, N normalises its pixels to about [-1, 1] and D_k (8 numbers, the
    last entry fixed at 0) is the unknown: well scaled, and 0 at the start.

    A link's residuals are transfer errors measured in the keyframes' own pixels, both ways:
    point a carried into keyframe b (G_b^-1 G_a) against its match there, and b into a.  Not in
    the reference keyframe's pixels: there, shrinking the keyframes far from the reference
    shrinks every residual with them, and a flight that revisits its ground (many links far
    from the reference) was squashed toward it.  In each keyframe's own pixels a residual does
    not change when the whole flight is scaled, so the only pull on the scale is the data."""

    def __init__(self, initial: list[np.ndarray], links: list[Link], reference: int, size: tuple[int, int]):
        self.K = len(initial)
        self.reference = reference
        self.f = max(size) / 2.0
        f = self.f
        self.N = np.array([[1 / f, 0, -(size[0] / 2 - 0.5) / f], [0, 1 / f, -(size[1] / 2 - 0.5) / f], [0, 0, 1.0]])
        self.M = np.array([G @ np.linalg.inv(self.N) for G in initial])
        self.M_inv = np.linalg.inv(self.M)
        self.column = np.full(self.K, -1)
        free = [k for k in range(self.K) if k != reference]
        self.column[free] = np.arange(len(free)) * 8
        self.n_params = 8 * len(free)
        self.set_links(links)

    def set_links(self, links: list[Link]) -> None:
        self.links = links
        counts = [len(l.points_a) for l in links]
        self.owner = np.repeat(np.arange(len(links)), counts)
        ia = np.repeat([l.a for l in links], counts)
        ib = np.repeat([l.b for l in links], counts)
        w = np.repeat([l.weight for l in links], counts)
        pa = self._normalised(np.concatenate([l.points_a for l in links]))
        pb = self._normalised(np.concatenate([l.points_b for l in links]))
        # Both directions: "source" points are carried into the "target" keyframe.
        self.n_points = len(ia)
        self.src = np.concatenate([ia, ib])
        self.dst = np.concatenate([ib, ia])
        self.p_src = np.concatenate([pa, pb])
        self.p_dst = np.concatenate([pb, pa])[:, :2]
        # Per residual (x and y of each point, both directions, each direction half).
        self.weight = np.repeat(np.concatenate([w, w]) * 0.5, 2)
        n = len(self.src)
        rows = np.arange(2 * n).reshape(n, 2)
        self._jac_rows, self._jac_cols, self._jac_keep = [], [], []
        for idx in (self.src, self.dst):
            col = self.column[idx]
            keep = np.repeat(col >= 0, 16)
            r = np.repeat(rows, 8, axis=1)  # (n, 16): row 2i for 8 params, then 2i+1
            c = np.tile(col[:, None] + np.arange(8)[None, :], (1, 2))
            self._jac_rows.append(r.ravel())
            self._jac_cols.append(c.ravel())
            self._jac_keep.append(keep)

    def _normalised(self, points: np.ndarray) -> np.ndarray:
        return np.concatenate([points, np.ones((len(points), 1))], axis=1) @ self.N.T

    def _D(self, x: np.ndarray) -> np.ndarray:
        D = np.zeros((self.K, 9))
        free = self.column >= 0
        D[free, :8] = x.reshape(-1, 8)
        return D.reshape(self.K, 3, 3)

    def placements(self, x: np.ndarray) -> np.ndarray:
        G = self.M @ (np.eye(3) + self._D(x)) @ self.N
        return G / G[:, 2:3, 2:3]

    def _transfer(self, x: np.ndarray):
        """Source points carried into their target keyframe (normalised coordinates):
        u = (I + D_t)^-1 M_t^-1 M_s (I + D_s) p."""
        A = np.eye(3) + self._D(x)
        B = np.linalg.inv(A)
        v = np.einsum("nij,nj->ni", A[self.src], self.p_src)
        v = np.einsum("nij,nj->ni", self.M[self.src], v)
        v = np.einsum("nij,nj->ni", self.M_inv[self.dst], v)  # in the target's initial frame
        u = np.einsum("nij,nj->ni", B[self.dst], v)
        return u, B

    def _differences(self, x: np.ndarray) -> np.ndarray:
        u, _ = self._transfer(x)
        return (u[:, :2] / u[:, 2:3] - self.p_dst) * self.f  # pixels

    def residuals(self, x: np.ndarray) -> np.ndarray:
        return self._differences(x).ravel()

    def loss(self, z: np.ndarray, scale: float) -> np.ndarray:
        """Weighted soft-L1 of the squared residuals ``z`` (pixels^2): sum of w s^2 rho(z / s^2)
        with rho(t) = 2 (sqrt(1 + t) - 1), and its first two derivatives (scipy's callable-loss
        form).  Weighting the loss, not the residuals, keeps the quadratic-to-linear turn at
        ``scale`` pixels for every link, however many correspondences a point stands for."""
        t = z / scale**2
        root = np.sqrt(1 + t)
        rho = np.empty((3, len(z)))
        rho[0] = self.weight * scale**2 * 2 * (root - 1)
        rho[1] = self.weight / root
        rho[2] = -0.5 * self.weight / (root * (1 + t)) / scale**2
        return rho

    def cost(self, residuals: np.ndarray, scale: float) -> float:
        return 0.5 * float(self.loss(residuals**2, scale)[0].sum())

    def jacobian(self, x: np.ndarray) -> scipy.sparse.csr_matrix:
        import scipy.sparse
        u, B = self._transfer(x)
        w = u[:, 2]
        xy = u[:, :2] / w[:, None]
        n = len(u)
        # d(xy)/du, (n, 2, 3)
        P = np.zeros((n, 2, 3))
        P[:, 0, 0] = P[:, 1, 1] = 1 / w
        P[:, :, 2] = -xy / w[:, None]
        # Source side: u = C (I + D_s) p with C = B_t M_t^-1 M_s: du/dD_s[r, c] = C[:, r] p[c].
        C = np.einsum("nij,njk->nik", B[self.dst], np.einsum("nij,njk->nik", self.M_inv[self.dst], self.M[self.src]))
        J_src = np.einsum("nkr,nc->nkrc", np.einsum("nki,nir->nkr", P, C), self.p_src).reshape(n, 2, 9)[:, :, :8]
        # Target side: d(I + D_t)^-1 = -B dD B, so du/dD_t[r, c] = -B_t[:, r] u[c].
        J_dst = -np.einsum("nkr,nc->nkrc", np.einsum("nki,nir->nkr", P, B[self.dst]), u).reshape(n, 2, 9)[:, :, :8]
        scale = self.f
        values = [(scale * J_src).reshape(n, 16).ravel(), (scale * J_dst).reshape(n, 16).ravel()]
        keep = np.concatenate(self._jac_keep)
        data = np.concatenate(values)[keep]
        rows = np.concatenate(self._jac_rows)[keep]
        cols = np.concatenate(self._jac_cols)[keep]
        return scipy.sparse.csr_matrix((data, (rows, cols)), shape=(2 * n, self.n_params))

    def link_residuals(self, x: np.ndarray) -> np.ndarray:
        """Median transfer distance (pixels, unweighted, both ways) per link."""
        d = np.linalg.norm(self._differences(x), axis=1)
        owner = np.concatenate([self.owner, self.owner])
        order = np.argsort(owner, kind="stable")
        bounds = np.searchsorted(owner[order], np.arange(len(self.links) + 1))
        d = d[order]
        return np.array([np.median(d[bounds[k] : bounds[k + 1]]) for k in range(len(self.links))])


def refine_placements(
    initial: list[np.ndarray],
    report: RegistrationReport,
    reference: int,
    size: tuple[int, int],
    options: RegistrationOptions,
) -> list[np.ndarray]:
    """Keyframe -> reference placements that agree best with all links (robustly)."""
    if len(initial) < 2 or not report.links:
        return initial
    links = list(report.links)
    problem = _Problem(initial, links, reference, size)
    x = np.zeros(problem.n_params)
    if not report.residual_before:  # before the first refinement
        report.residual_before = float(np.median(problem.link_residuals(x)))
    for _ in range(3):
        x = _solve(problem, x, options)
        residual = problem.link_residuals(x)
        bad = [l for l, r in zip(links, residual) if l.kind == "loop" and r > options.outlier_residual]
        if not bad:
            break
        report.loops_dropped += len(bad)
        links = [l for l in links if not (l.kind == "loop" and any(l is b for b in bad))]
        problem.set_links(links)
    for link, r in zip(links, problem.link_residuals(x)):
        link.residual = float(r)
    report.links = links
    report.residual_after = float(np.median([l.residual for l in links]))
    return list(problem.placements(x))


# Not scipy's least_squares (trf, sparse Jacobian): the same placements 2-62x slower, 27x on a mapping flight (stitch.md, Solver).
def _solve(problem: _Problem, x0: np.ndarray, options: RegistrationOptions) -> np.ndarray:
    """Levenberg-Marquardt on the robust cost, each step an exact sparse solve of the
    reweighted normal equations (soft-L1 as iteratively reweighted least squares), run until
    the cost stops falling.  The cost has directions it barely changes along (a flight's
    keyframes growing a few hundredths of a percent each, seen by the links as hundredths of a
    pixel): an inexact inner solver (LSMR in scipy's trust region) leaves them where the
    starting placements had them, and stops at its evaluation budget."""
    import scipy.sparse
    import scipy.sparse.linalg
    x = np.array(x0, dtype=np.float64)
    f = problem.residuals(x)
    cost = problem.cost(f, options.loss_scale)
    damping = 1e-3
    for _ in range(options.max_steps):
        J = problem.jacobian(x)
        weighted = (J.T @ scipy.sparse.diags(problem.loss(f**2, options.loss_scale)[1])).tocsr()
        normal = (weighted @ J).tocsc()
        gradient = weighted @ f
        diagonal = np.maximum(normal.diagonal(), 1e-12 * max(1.0, float(normal.diagonal().max(initial=0.0))))
        while True:
            step = scipy.sparse.linalg.spsolve(normal + scipy.sparse.diags(damping * diagonal), -gradient)
            f_new = problem.residuals(x + step)
            cost_new = problem.cost(f_new, options.loss_scale)
            if np.isfinite(cost_new) and cost_new < cost:
                damping = max(damping / 3.0, 1e-12)
                break
            damping *= 4.0
            if damping > 1e8:
                return x
        x, f, gained, cost = x + step, f_new, cost - cost_new, cost_new
        if gained <= options.tolerance * cost:
            break
    return x
