"""Keyframe features and direct registration of two keyframes (SIFT, ratio test, MAGSAC).

Used to re-find the flight after the estimator loses it, to link consecutive keyframes
directly (more accurate than chaining dozens of small pairwise estimates) and to close loops
between keyframes that see the same ground minutes apart.  Points are kept in full-resolution
source pixels, descriptors as uint8, so a keyframe's features cost ~150 KB.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mosaic_cli.geometry import frame_corners, is_valid, project, resize_matrix
from mosaic_cli.mask import work_mask
from mosaic_cli.video.decode import gray_at

MASK_MARGIN = 4  # px at the feature width: keypoints this close to an overlay are not kept


@dataclass
class FeatureOptions:
    width: int = 640  # keyframes are described at this width (the source's if narrower)
    photo_width: int = 2000  # ... and photos (an image folder), which only features place (12 MP: 2 px needs 2000; CHANGELOG)
    photo_features: int = 4000  # ... with more points: 1500 leave a wide photo's pairs with ~40 inliers
    n_features: int = 1500
    # Lower than OpenCV's 0.04: aerial ground is often low in contrast (grass, fields, water);
    # n_features still keeps only the strongest points on rich ground.
    contrast_threshold: float = 0.01
    ratio: float = 0.8  # Lowe's ratio test
    # Matching guided by the GPS (match_guided): the ratio among the few points near where the
    # prior puts a point, and the inliers that suffice once the prior agrees.
    guided_ratio: float = 0.9
    guided_min_inliers: int = 12
    reproj_threshold: float = 1.5  # pixels at the feature width
    # ... and at most this many pixels of the source itself (None: no cap; photos: photo_threshold).
    # A 12 MP still described at 2000 px would get 3 px: where its ground is not one plane (trees,
    # relief) a band that wide mixes planes (docs/measurements/stitch.md, photo folders).
    max_source_threshold: float | None = None
    photo_threshold: float = 2.0
    min_inliers: int = 20
    min_inlier_ratio: float = 0.15
    # A registered pair may change a frame's area by at most this factor (keyframes of one flight).
    max_area_ratio: float = 4.0
    # Inliers covering less than this fraction of frame a (their convex hull) do not fix a
    # homography's two perspective terms: fitted to a strip at the edge of a photo they swung
    # its far side 8-100 px off on tiles of a real orthophoto whose exact offsets were known
    # (issue 40); such a pair is registered as an affine map where one explains its inliers.
    min_homography_spread: float = 0.25
    # ... and below this, a pair matched by the GPS's guidance is a similarity (match_guided).
    min_affine_spread: float = 0.05

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """No flag sets these: a bad value is a bug (ValueError), not the user's input."""
        if min(self.width, self.photo_width) < 32 or min(self.n_features, self.photo_features) < 4:
            raise ValueError(f"feature widths must be at least 32 px and counts at least 4: {self}")
        if not 0 < self.ratio <= 1 or not 0 <= self.min_inlier_ratio <= 1 or not 0 <= self.min_homography_spread <= 1:
            raise ValueError(f"ratio, min_inlier_ratio and min_homography_spread must be fractions: {self}")
        cap = self.max_source_threshold
        thresholds = [self.reproj_threshold, self.photo_threshold] + ([] if cap is None else [cap])
        if self.min_inliers < 4 or min(thresholds) <= 0 or self.max_area_ratio < 1:
            raise ValueError(f"min_inliers >= 4, thresholds > 0, max_area_ratio >= 1 expected: {self}")


@dataclass
class Features:
    points: np.ndarray  # (n, 2) float32, source pixels
    descriptors: np.ndarray  # (n, 128) uint8

    def __len__(self) -> int:
        return len(self.points)


@dataclass
class PairMatch:
    """A direct registration: ``H`` maps source pixels of frame a to frame b; the inlier
    correspondences ``points_a[k] <-> points_b[k]`` are what the joint refinement uses."""

    H: np.ndarray
    points_a: np.ndarray
    points_b: np.ndarray
    inlier_ratio: float

    @property
    def inliers(self) -> int:
        return len(self.points_a)


class FeatureExtractor:
    """SIFT on a gray copy of a frame at ``options.width``; frames may arrive at any resolution.
    ``use`` (uint8 at the source size, 255 = use) keeps features off burned-in overlays."""

    def __init__(self, source_size: tuple[int, int], options: FeatureOptions | None = None, use: np.ndarray | None = None):
        self.options = options or FeatureOptions()
        self.source_size = source_size
        width = min(self.options.width, source_size[0])
        self.size = (width, max(1, round(source_size[1] * width / source_size[0])))
        self._sift = cv2.SIFT_create(nfeatures=self.options.n_features, contrastThreshold=self.options.contrast_threshold)
        self._to_source = np.linalg.inv(resize_matrix(source_size, self.size))
        # The matching threshold, re-expressed in source pixels.
        self.threshold = self.options.reproj_threshold * source_size[0] / width
        if self.options.max_source_threshold is not None:
            self.threshold = min(self.threshold, self.options.max_source_threshold)
        self._mask = work_mask(use, self.size, margin=MASK_MARGIN)

    def __call__(self, frame: np.ndarray, use: np.ndarray | None = None) -> Features:
        """The frame's features; ``use``: this frame's own mask in place of the extractor's (a
        photo fitted into a folder's frame: its part of it; ``use`` includes the overlays')."""
        mask = self._mask if use is None else work_mask(use, self.size, margin=MASK_MARGIN)
        keypoints, descriptors = self._sift.detectAndCompute(gray_at(frame, self.size), mask)
        if not keypoints or descriptors is None:
            return Features(np.zeros((0, 2), np.float32), np.zeros((0, 128), np.uint8))
        points = project(self._to_source, np.array([k.pt for k in keypoints], np.float64)).astype(np.float32)
        return Features(points, np.clip(descriptors, 0, 255).astype(np.uint8))


class FeatureMatcher:
    """Registers two keyframes directly; ``None`` when the evidence is not convincing."""

    def __init__(self, extractor: FeatureExtractor):
        self.options = extractor.options
        self.source_size = extractor.source_size
        self.threshold = extractor.threshold
        # Brute force, not FLANN: FLANN's randomised kd-trees are about twice as fast here but
        # make every run place the frames a little differently; results should be repeatable.
        self._matcher = cv2.BFMatcher(cv2.NORM_L2)

    def match(
        self,
        a: Features,
        b: Features,
        prior: np.ndarray | None = None,
        tolerance: float | None = None,
    ) -> PairMatch | None:
        """H: a -> b.  With a ``prior`` (a -> b) the result must agree with it to ``tolerance``
        pixels at the frame corners: a wrong loop closure costs more than a missing one."""
        o = self.options
        if len(a) < o.min_inliers or len(b) < o.min_inliers:
            return None
        pairs = self._matcher.knnMatch(a.descriptors.astype(np.float32), b.descriptors.astype(np.float32), k=2)
        good = [m[0] for m in pairs if len(m) == 2 and m[0].distance < o.ratio * m[1].distance]
        if len(good) < o.min_inliers:
            return None
        src = a.points[[m.queryIdx for m in good]]
        dst = b.points[[m.trainIdx for m in good]]
        return self._fit(src, dst, o.min_inliers, prior, tolerance)

    def match_guided(self, a: Features, b: Features, prior: np.ndarray, radius: float) -> PairMatch | None:
        """H: a -> b, matched where ``prior`` (a -> b, from the GPS: see stitch/guide.py) says
        each point of a should be in b: a point's candidates are b's points within ``radius``
        pixels of it, and its best must beat the second best among them alone, by the looser
        ``guided_ratio``.  Fewer rivals pass more true matches: a pair whose overlap is a strip
        of flat ground beside canopy (whose parallax spoils its matches) gets enough to place it.
        The result must agree with ``prior`` to ``radius`` at the frame corners; fewer inliers
        (``guided_min_inliers``) suffice, and no share of the matches, the GPS vouching for the rest."""
        o = self.options
        if len(a) < o.guided_min_inliers or len(b) < o.guided_min_inliers:
            return None
        from scipy.spatial import cKDTree

        tree = cKDTree(b.points.astype(np.float64))
        da, db = a.descriptors.astype(np.float32), b.descriptors.astype(np.float32)
        # A point with a single candidate near it is measured against its best rival anywhere:
        # alone in a small circle, any point would pass.  (query -> its nearest point of b, that
        # distance, and the second nearest's, from one search of b.)
        nearest = {m[0].queryIdx: (m[0].trainIdx, m[0].distance, m[1].distance if len(m) == 2 else m[0].distance)
                   for m in self._matcher.knnMatch(da, db, k=2) if m}

        def near(H: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
            src, dst = [], []
            for i, candidates in enumerate(tree.query_ball_point(project(H, a.points.astype(np.float64)), reach)):
                if not candidates:
                    continue
                d = np.linalg.norm(db[candidates] - da[i], axis=1)
                chosen = candidates[int(np.argmin(d))]
                if len(candidates) > 1:
                    first, second = np.partition(d, 1)[:2]
                else:
                    best, best_distance, second_distance = nearest.get(i, (-1, np.inf, np.inf))
                    first, second = d[0], second_distance if best == chosen else best_distance
                if first >= o.guided_ratio * second:
                    continue
                src.append(i)
                dst.append(chosen)
            return a.points[src], b.points[dst]

        src, dst = near(prior, radius)
        if len(src) < o.guided_min_inliers:
            return None
        # Most of these matches are rivals that happened to win (canopy): their share is no test.
        match = self._fit(src, dst, o.guided_min_inliers, prior, radius, min_ratio=0.0)
        if match is not None and spread(match.points_a, self.source_size) < o.min_affine_spread:
            match = self._similarity(match)
        return match

    def _similarity(self, match: PairMatch) -> PairMatch:
        """``match`` as a similarity where one explains its inliers: a strip a few per cent of the
        frame wide fixes no shear, and an affine map fitted to it swung the far corners 2-3 px
        off (a 12-px strip of a 640-px photo; the similarity: 0.04 px).  Two nadir photos of one
        survey differ by a similarity, up to their tilt."""
        S, _ = cv2.estimateAffinePartial2D(match.points_a, match.points_b, method=cv2.LMEDS, refineIters=10)
        if S is None:
            return match
        similarity = np.vstack([S, [0.0, 0.0, 1.0]])
        near = np.linalg.norm(project(similarity, match.points_a) - match.points_b, axis=1) < self.threshold
        if near.sum() < 0.9 * match.inliers:
            return match
        return PairMatch(similarity, match.points_a[near], match.points_b[near], match.inlier_ratio * near.mean())

    def _fit(self, src: np.ndarray, dst: np.ndarray, min_inliers: int, prior: np.ndarray | None,
             tolerance: float | None, min_ratio: float | None = None) -> PairMatch | None:
        """The homography (or affine map) of matches ``src`` -> ``dst`` ((n, 2) source pixels) by
        MAGSAC, if convincing: enough inliers, and ``min_ratio`` of the matches (None: the
        options'), a plausible shape, and near ``prior`` when given."""
        o = self.options
        min_ratio = o.min_inlier_ratio if min_ratio is None else min_ratio
        H, mask = cv2.findHomography(src, dst, cv2.USAC_MAGSAC, self.threshold, maxIters=5000, confidence=0.999)
        if H is None or mask is None:
            return None
        keep = mask.ravel().astype(bool)
        if spread(src[keep], self.source_size) < o.min_homography_spread:
            H, keep = self._affine(src, dst, H, keep)
        inliers = int(keep.sum())
        ratio = inliers / len(src)
        if inliers < min_inliers or ratio < min_ratio:
            return None
        if not is_valid(H, self.source_size, max_area_ratio=o.max_area_ratio):
            return None
        H = H / H[2, 2]
        if prior is not None and tolerance is not None and corner_distance(H, prior, self.source_size) > tolerance:
            return None
        return PairMatch(H, src[keep].astype(np.float64), dst[keep].astype(np.float64), ratio)

    def _affine(self, src: np.ndarray, dst: np.ndarray, H: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(3x3, keep) of an affine map fitted to the inliers of homography ``H`` (``src``, ``dst``:
        (n, 2) matches, ``keep``: (n,) bool): least median of squares, then Levenberg-Marquardt
        on its inliers.  ``H`` stands where the affine map keeps fewer than 9 in 10 of its
        inliers: perspective that even a small region shows is real."""
        A, _ = cv2.estimateAffine2D(src[keep], dst[keep], method=cv2.LMEDS, refineIters=10)
        if A is None:
            return H, keep
        affine = np.vstack([A, [0.0, 0.0, 1.0]])
        near = np.linalg.norm(project(affine, src.astype(np.float64)) - dst, axis=1) < self.threshold
        if (near & keep).sum() < 0.9 * keep.sum():
            return H, keep
        return affine, near & keep


def spread(points: np.ndarray, size: tuple[int, int]) -> float:
    """The area of the convex hull of ``points`` ((n, 2) pixels) as a fraction of a frame of ``size``."""
    if len(points) < 3:
        return 0.0
    return float(cv2.contourArea(cv2.convexHull(np.asarray(points, np.float32)))) / (size[0] * size[1])


def corner_distance(H1: np.ndarray, H2: np.ndarray, size: tuple[int, int]) -> float:
    """The largest distance between the frame corners mapped by two homographies."""
    c = frame_corners(*size)
    return float(np.max(np.linalg.norm(project(H1, c) - project(H2, c), axis=-1)))
