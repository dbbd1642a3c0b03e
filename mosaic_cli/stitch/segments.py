"""Stage 2a: put the segments of a flight back together.

A cut (or a photo that registers with none of the last ones) starts a new segment during the
scan, placed in a world of its own.  Here each segment is relocalised against the keyframes of
the segments before it by direct feature registration, with no prior (as a loop closure, but
anywhere): a match moves the whole segment into the other's world and becomes a link of the
joint refinement.  A join is confirmed by a second keyframe pair where the segment has one,
so one repeated pattern cannot fold two unrelated flights together.  Segments that join
nothing form panoramas of their own: the result is a list of *groups*, each one panorama.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mosaic_cli.stitch.features import FeatureMatcher, Features
from mosaic_cli.stitch.keyframes import closest_affine, overlap_fraction
from mosaic_cli.stitch.registration import Link, ProgressFactory, RegistrationOptions, link_from_match, no_progress


@dataclass
class JoinOptions:
    picks: int = 4  # keyframes of a segment tried against the others (spread along it)
    max_pairs: int = 120  # registrations tried to join one segment to one group, at most
    min_confirm_overlap: float = 0.2  # predicted overlap of the pair that confirms a join
    strong_inliers: int = 40  # a join nothing else can confirm needs this many inliers

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """No flag sets these: a bad value is a bug (ValueError), not the user's input."""
        if self.picks < 1 or self.max_pairs < 1 or self.strong_inliers < 4:
            raise ValueError(f"picks and max_pairs >= 1, strong_inliers >= 4 expected: {self}")
        if not 0 < self.min_confirm_overlap <= 1:
            raise ValueError(f"min_confirm_overlap must be a fraction, got {self.min_confirm_overlap}")


@dataclass
class Joined:
    placements: list[np.ndarray]  # world placements, each group in one world
    groups: list[list[int]]  # keyframe positions of each panorama, in frame order; the first keyframe's group first
    links: list[Link] = field(default_factory=list)  # the joins, for the refinement
    tried: int = 0


def join_segments(
    features: list[Features],
    placements: list[np.ndarray],
    segments: list[int],
    matcher: FeatureMatcher,
    registration: RegistrationOptions,
    options: JoinOptions | None = None,
    progress: ProgressFactory = no_progress,
) -> Joined:
    options = options or JoinOptions()
    placements = [np.asarray(P, float) for P in placements]
    order = list(dict.fromkeys(segments))  # segments in the order they start
    members = {s: [k for k, t in enumerate(segments) if t == s] for s in order}
    group_of = {s: s for s in order}
    links: list[Link] = []
    tried = 0
    plan = [(s, c) for i, s in enumerate(order) for c in order[:i]]
    budget = {(s, c): len(_pairs(members[s], members[c], options)) for s, c in plan}
    with progress("relocalise segments", sum(budget.values())) as advance:
        for s, c in plan:
            if group_of[s] == group_of[c]:
                advance(budget[s, c])
                continue
            join, n = _try_join(features, placements, members[s], members[c], matcher, registration, options, advance)
            tried += n
            advance(budget[s, c] - n)  # the pairs not needed
            if join is None:
                continue
            k, j, match = join
            # Move s's whole group into c's world.
            T = placements[j] @ closest_affine(match.H, matcher.source_size) @ np.linalg.inv(placements[k])
            moving = group_of[s]
            for t in order:
                if group_of[t] == moving:
                    for m in members[t]:
                        placements[m] = T @ placements[m]
                    group_of[t] = group_of[c]
            links.append(link_from_match(k, j, match, "relocalised", registration))
    groups: dict[int, list[int]] = {}
    for k, s in enumerate(segments):
        groups.setdefault(group_of[s], []).append(k)
    return Joined(placements, list(groups.values()), links, tried)


def _pairs(mine: list[int], theirs: list[int], options: JoinOptions) -> list[tuple[int, int]]:
    """Keyframe pairs to try, ``max_pairs`` at most: every pair when there are no more (a few
    photos: a photo that failed with its neighbours in name order is tried against every
    photo of the others, so a set that overlaps comes out whole); else keyframes spread along
    the segment (``picks``, more when the other group is small), each against keyframes spread
    over the other group."""
    if len(mine) * len(theirs) <= options.max_pairs:
        return [(k, j) for k in mine for j in theirs]
    count = min(len(mine), max(options.picks, options.max_pairs // len(theirs)))
    picks = [mine[int(round(p))] for p in np.linspace(0, len(mine) - 1, count)]
    per_pick = max(1, options.max_pairs // len(picks))
    targets = [theirs[int(round(p))] for p in np.linspace(0, len(theirs) - 1, min(per_pick, len(theirs)))]
    return [(k, j) for k in picks for j in targets]


def _try_join(features, placements, mine, theirs, matcher: FeatureMatcher, registration: RegistrationOptions, options: JoinOptions, advance):
    """The first of the pairs that registers and is confirmed; (None, tries) if none."""
    size = matcher.source_size
    tolerance = registration.loop_tolerance * float(np.hypot(*size))
    tries = 0
    for k, j in _pairs(mine, theirs, options):
        tries += 1
        advance(1)
        match = matcher.match(features[k], features[j])
        if match is None:
            continue
        # Confirm with another keyframe of the segment, where the join predicts an overlap.
        k_to_world = placements[j] @ closest_affine(match.H, size) @ np.linalg.inv(placements[k])
        if _confirmed(features, placements, k, j, match, mine, theirs, k_to_world, matcher, tolerance, options):
            return (k, j, match), tries
    return None, tries


def _confirmed(features, placements, k, matched, match, mine, theirs, T, matcher, tolerance, options: JoinOptions) -> bool:
    """A second registration where the join predicts an overlap: another keyframe of the
    segment over their ground, or (a one-photo segment has no other) the same keyframe over
    another of their keyframes.  With none predicted, the single registration must be strong."""
    strong = match.inliers >= options.strong_inliers
    size = matcher.source_size
    moved = {m: T @ placements[m] for m in mine}
    # Another keyframe of the segment is the more independent check (a repeated pattern that
    # fooled k may fool k again beside j); a one-keyframe segment has only k.
    others = [m for m in mine if m != k]
    candidates = [(m, j) for m in others for j in theirs] if others else [(k, j) for j in theirs if j != matched]
    best = max(
        ((overlap_fraction(np.linalg.inv(placements[j]) @ moved[m], size), m, j) for m, j in candidates),
        default=(0.0, None, None),
    )
    if best[0] < options.min_confirm_overlap:
        # Nothing else is predicted over their ground: the segment only touches it; accept
        # the single registration only if it is strong.
        return strong
    _, m, j = best
    prior = np.linalg.inv(placements[j]) @ moved[m]
    return matcher.match(features[m], features[j], prior, tolerance) is not None
