"""The ground adjustment (geo/adjust.py) against exact synthetic truth: keyframes of a
lawnmower flight seen by a tilted pinhole camera, a mosaic bent by a known homography (what
chained registrations leave), GPS with 3 m correlated error and bad fixes, gimbal attitudes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mosaic_cli.geo.adjust import AttitudeViews, adjust_to_ground, attitude_sigma, level_mosaic
from mosaic_cli.geo.camera import focal_pixels, intrinsics, nadir_pixel, tilt_rotation, untilt
from mosaic_cli.geo.fit import SimilarityPrior, fit_similarity, refine_homography
from mosaic_cli.geometry import frame_corners, project
from mosaic_cli.simulate.telemetry import gauss_markov

SIZE = (640, 360)
FOCAL = focal_pixels(SIZE[0], 53.13)  # focal = width: 5 cm per pixel from 32 m
HEIGHT = 32.0


def ground_to_frame(centre, heading, pitch, roll):
    """The camera model of geo/camera.py: ground (x, y metres, y down like the frame) -> pixels."""
    c, s = math.cos(heading), math.sin(heading)
    R = np.array([[c, s], [-s, c]])
    S = np.eye(3)
    S[:2, :2], S[:2, 2], S[2, 2] = R, -R @ centre, HEIGHT
    return intrinsics(SIZE, FOCAL) @ tilt_rotation(pitch, roll) @ S


def flight(seed=0):
    """60 keyframes over 4 lines of 180 m, 9 m apart; the truth and the bent mosaic."""
    rng = np.random.default_rng(seed)
    centres, headings = [], []
    for line in range(4):
        xs = np.linspace(0.0, 180.0, 15)
        centres += [(x, 9.0 * line) for x in (xs if line % 2 == 0 else xs[::-1])]
        headings += [math.pi / 2 if line % 2 == 0 else -math.pi / 2] * 15
    centres = np.array(centres)
    pitch = -90.0 + rng.uniform(-1.5, 1.5, len(centres))
    roll = rng.uniform(-1.5, 1.5, len(centres))
    frame_to_ground = [np.linalg.inv(ground_to_frame(c, h, p, r)) for c, h, p, r in zip(centres, headings, pitch, roll)]
    # the mosaic: the ground through a homography with tilt and shear (40 px per metre, turned)
    bend = np.array([[40.0, 3.0, 100.0], [-2.0, 41.0, -50.0], [4e-4, -6e-4, 1.0]])
    placements = [bend @ T for T in frame_to_ground]
    nadirs = np.array([project(P, nadir_pixel(SIZE, FOCAL, p, r)[None])[0] for P, p, r in zip(placements, pitch, roll)])
    times = np.arange(len(centres)) * 2.0
    return centres, pitch, roll, frame_to_ground, placements, nadirs, times, rng


def views_of(placements, pitch, roll):
    corners = frame_corners(*SIZE)
    unt = [untilt(SIZE, FOCAL, p, r) for p, r in zip(pitch, roll)]
    return AttitudeViews(np.stack([P @ np.linalg.inv(U) for P, U in zip(placements, unt)]),
                         np.stack([project(U, corners) for U in unt]), attitude_sigma(SIZE, FOCAL, 1.0))


def ground_errors(G, placements, frame_to_ground):
    """Metres between where G lays each keyframe's corners and centre and where they are."""
    pts = np.vstack([frame_corners(*SIZE), [[(SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2]]])
    return np.concatenate([np.linalg.norm(project(G @ P, pts) - project(T, pts), axis=1)
                           for P, T in zip(placements, frame_to_ground)])


def noisy_gps(centres, times, rng, rms=3.0):
    sigma = rms / math.sqrt(2)
    return centres + np.stack([gauss_markov(rng, times, sigma, 2.0), gauss_markov(rng, times, sigma, 2.0)], 1)


def test_attitude_sigma_is_the_non_similarity_of_a_tilt():
    """Against a plain least-squares similarity of the tilted frame's corners (numpy lstsq)."""
    corners = frame_corners(*SIZE)
    for degrees in (0.5, 2.0):
        rms = []  # the length of the corners' residuals
        for pitch, roll in ((degrees, 0.0), (0.0, degrees)):
            tilted = project(untilt(SIZE, FOCAL, -90.0 + pitch, roll), corners)
            A = np.zeros((8, 4))
            A[0::2] = np.c_[corners[:, 0], -corners[:, 1], np.ones(4), np.zeros(4)]
            A[1::2] = np.c_[corners[:, 1], corners[:, 0], np.zeros(4), np.ones(4)]
            p = np.linalg.lstsq(A, tilted.ravel(), rcond=None)[0]
            left = (A @ p - tilted.ravel()) / math.hypot(p[0], p[1])
            rms.append(np.linalg.norm(left))
        assert attitude_sigma(SIZE, FOCAL, degrees) == pytest.approx(np.mean(rms), rel=1e-6)
    assert attitude_sigma(SIZE, FOCAL, 2.0) == pytest.approx(4 * attitude_sigma(SIZE, FOCAL, 0.5), rel=0.02)  # linear


def test_levelling_undoes_the_bend_exactly_and_refuses_a_gimbal_that_disagrees():
    centres, pitch, roll, truth, placements, nadirs, times, rng = flight(4)
    bend = placements[0] @ np.linalg.inv(truth[0])
    level = level_mosaic(views_of(placements, pitch, roll))
    assert level.agrees() and level.residual < 1e-6
    L = level.matrix @ bend  # ground metres -> levelled mosaic: a similarity again
    L = L / L[2, 2]
    scale = math.hypot(L[0, 0], L[1, 0])
    assert np.abs(L[2, :2]).max() < 1e-9
    assert abs(L[0, 0] - L[1, 1]) < 1e-6 * scale and abs(L[0, 1] + L[1, 0]) < 1e-6 * scale
    # one keyframe misread by 10 degrees: Huber keeps it from bending the levelling
    misread = level_mosaic(views_of(placements, np.where(np.arange(len(pitch)) == 17, pitch + 10.0, pitch), roll))
    moved = ground_errors(misread.matrix, placements, [level.matrix @ P for P in placements])  # levelled pixels
    assert moved.max() < 1e-4 * scale * 180, moved.max() / scale  # under a ten-thousandth of the flight's length
    # angles 20 degrees off at random: they and the images tell no one story
    n = len(pitch)
    assert not level_mosaic(views_of(placements, pitch + rng.normal(0, 20, n), roll + rng.normal(0, 20, n))).agrees()


def test_adjustment_takes_the_tilt_from_the_gimbal_and_the_place_from_gps():
    centres, pitch, roll, truth, placements, nadirs, times, rng = flight()
    gps = noisy_gps(centres, times, rng)
    start = fit_similarity(nadirs, gps, min_sigma=1.0)
    fit = adjust_to_ground(nadirs, gps, times, start.matrix, views_of(placements, pitch, roll))
    err = ground_errors(fit.matrix, placements, truth)
    assert np.median(err) < 0.8 and err.max() < 1.5, (np.median(err), err.max())  # GPS: 3 m RMS
    assert fit.attitude_residual < 0.1  # every keyframe untilted is a similarity on the ground again
    # GPS alone cannot see the tilt over a 27 m wide strip: the homography from the fixes is far worse
    gps_only = refine_homography(project(start.matrix, nadirs), gps, min_sigma=1.0).matrix @ start.matrix
    assert ground_errors(gps_only, placements, truth).max() > 2 * err.max()


def test_bad_fixes_and_a_bad_gimbal_reading_do_not_bend_the_adjustment():
    centres, pitch, roll, truth, placements, nadirs, times, rng = flight(1)
    gps = noisy_gps(centres, times, rng)
    views = views_of(placements, pitch, roll)
    wrong = [5, 22, 40, 51]
    good = np.setdiff1d(np.arange(len(gps)), wrong)
    clean = adjust_to_ground(nadirs[good], gps[good], times[good], fit_similarity(nadirs, gps, min_sigma=1.0).matrix, views)
    bad = gps.copy()
    angles = rng.uniform(0, 2 * np.pi, len(wrong))
    bad[wrong] += 50.0 * np.stack([np.cos(angles), np.sin(angles)], 1)
    misread = views_of(placements, np.where(np.arange(len(pitch)) == 30, pitch + 10.0, pitch), roll)  # one gimbal 10 deg off
    fit = adjust_to_ground(nadirs, bad, times, fit_similarity(nadirs, bad, min_sigma=1.0).matrix, misread)
    assert set(np.nonzero(~fit.inliers)[0]) == set(wrong)
    moved = ground_errors(fit.matrix, placements, [clean.matrix @ P for P in placements])
    assert moved.max() < 0.05, moved.max()  # as if the bad fixes were not there: 50 m off, they move it by centimetres


def test_adjustment_prior_decides_scale_and_heading_of_a_short_hover():
    """A few metres of GPS track say nothing of scale and heading: the prior (altitude x field
    of view, compass) does, through the prior view's untilted similarity."""
    centres, pitch, roll, truth, placements, nadirs, times, rng = flight(2)
    keep = np.arange(3)  # 3 keyframes along 26 m: GPS noise of 3 m is 10% of it
    gps = noisy_gps(centres[keep], times[keep], rng)
    views = views_of([placements[k] for k in keep], pitch[keep], roll[keep])
    # the true scale and heading of view 0: metres per untilted pixel, and its rotation
    true_ratio = HEIGHT / FOCAL
    heading = math.pi / 2
    prior = SimilarityPrior(true_ratio * 1.01, -heading + math.radians(0.5), 0.05)
    fit = adjust_to_ground(nadirs[keep], gps, times[keep], fit_similarity(nadirs[keep], gps, min_sigma=1.0).matrix, views, prior, 0)
    assert fit.scale == pytest.approx(prior.scale, rel=0.02)
    assert math.degrees(fit.rotation) == pytest.approx(math.degrees(prior.rotation), abs=1.0)


@pytest.mark.slow
def test_georeference_levels_a_bent_mosaic_by_the_gimbal():
    """georeference() end to end on a synthetic track: a mosaic whose chained registrations left
    a slight projective drift (invisible within a frame, metres at the flight's ends) lands on
    the true ground; the old similarity from the reference's own tilt does not."""
    from mosaic_cli.geo.camera import hfov_degrees
    from mosaic_cli.geo.crs import Projection
    from mosaic_cli.geo.georef import GeorefOptions, georeference
    from mosaic_cli.telemetry.flight_log import FlightLog

    centres, pitch, roll, truth, _, _, times, rng = flight(3)
    ref = 30
    centre = np.array([[1, 0, -(SIZE[0] - 1) / 2], [0, 1, -(SIZE[1] - 1) / 2], [0, 0, 1.0]])
    drift = np.linalg.inv(centre) @ np.array([[1.0, 0.003, 0], [0, 1.0, 0], [1.2e-5, -1.5e-5, 1.0]]) @ centre
    placements = [drift @ np.linalg.inv(truth[ref]) @ T for T in truth]
    projection = Projection.utm_for(47.3977, 8.5456)
    origin = projection.to_map([47.3977], [8.5456])[0]
    gps = noisy_gps(centres, times, rng)
    lonlat = projection.to_wgs84(origin[0] + gps[:, 0], origin[1] - gps[:, 1])  # y runs south
    n = len(times)
    headings = np.where((np.arange(n) // 15) % 2 == 0, 90.0, -90.0)
    track = FlightLog("synthetic", times, lonlat[:, 1], lonlat[:, 0], np.full(n, 500.0), np.full(n, HEIGHT), headings,
                      pitch, roll, np.full(n, hfov_degrees(SIZE[0], FOCAL)))
    frame_rate = 10.0
    g = georeference(placements, ref, [int(round(t * frame_rate)) for t in times], SIZE, frame_rate, track, GeorefOptions())
    assert g.model == "homography levelled by the gimbal"
    to_ground = np.array([[1.0, 0, origin[0]], [0, -1.0, origin[1]], [0, 0, 1.0]])  # synthetic (x, y south) -> east, north
    err = ground_errors(np.eye(3), [g.frame_to_ground(k, P) for k, P in enumerate(placements)], [to_ground @ T for T in truth])
    assert np.median(err) < 0.8 and err.max() < 1.5, (np.median(err), err.max())
    # the gimbal not used: the tilt from the GPS alone
    gps_only = georeference(placements, ref, [int(round(t * frame_rate)) for t in times], SIZE, frame_rate, track,
                            GeorefOptions(attitude_accuracy=None))
    assert gps_only.model in ("similarity", "homography")
    # a gimbal whose angles are 20 degrees off: said, and not used
    wild = FlightLog("synthetic", times, lonlat[:, 1], lonlat[:, 0], np.full(n, 500.0), np.full(n, HEIGHT), headings,
                     pitch + rng.normal(0, 20, n), roll + rng.normal(0, 20, n), np.full(n, hfov_degrees(SIZE[0], FOCAL)))
    unused = georeference(placements, ref, [int(round(t * frame_rate)) for t in times], SIZE, frame_rate, wild, GeorefOptions())
    assert unused.model in ("similarity", "homography") and "gimbal's angles disagree with the images" in unused.summary()
    # the reference's tilt alone, then a similarity to the GPS: the drift shows at the ends
    flat = untilt(SIZE, FOCAL, pitch[ref], roll[ref])
    nadirs = np.array([project(flat @ P, nadir_pixel(SIZE, FOCAL, p, r)[None])[0] for P, p, r in zip(placements, pitch, roll)])
    similarity = fit_similarity(nadirs, gps, min_sigma=1.0).matrix @ flat
    assert ground_errors(similarity, placements, truth).max() > 2 * err.max()


def conformal_drift(centres, a):
    """Per keyframe, the ground similarity of the conformal warp with derivative exp(a (z - z0)^2)
    (z: a ground point as a complex number, z0 the flight's centre): keyframes shrink toward both
    ends of the lines by exp(a x^2) and turn slightly, and overlapping keyframes stay consistent,
    as chained registrations' scale drift leaves a mosaic."""
    z0 = complex(*centres.mean(0))
    t = np.linspace(0.0, 1.0, 401)
    out = []
    for c in centres:
        z = complex(*c) - z0
        fz = z0 + z * np.trapezoid(np.exp(a * (t * z) ** 2), t)
        d = np.exp(a * z * z)
        R = abs(d) * np.array([[math.cos(np.angle(d)), -math.sin(np.angle(d))], [math.sin(np.angle(d)), math.cos(np.angle(d))]])
        W = np.eye(3)
        W[:2, :2], W[:2, 2] = R, np.array([fz.real, fz.imag]) - R @ c
        out.append(W)
    return out


def test_over_level_ground_the_heights_undo_the_mosaics_scale_drift():
    """A mosaic whose keyframes shrink by up to 3% toward the ends of the lines (scale drift the
    loops between lines cannot see) and heights with 0.3 m noise: with ``level_ground`` each
    keyframe's size comes closer to the truth; without it no keyframe is scaled."""
    from mosaic_cli.geo.camera import hfov_degrees
    from mosaic_cli.geo.georef import GeorefOptions, _jacobian, georeference

    centres, pitch, roll, truth, _, _, times, rng = flight(5)
    ref = 30
    W = conformal_drift(centres, -0.03 / 90.0**2)
    placements = [np.linalg.inv(W[ref] @ truth[ref]) @ Wk @ T for Wk, T in zip(W, truth)]
    heights = HEIGHT + 0.3 * rng.standard_normal(len(times))
    track, to_ground = synthetic_track(centres, times, pitch, roll, noisy_gps(centres, times, rng), heights, hfov_degrees(SIZE[0], FOCAL))
    indices = [int(round(t * 10.0)) for t in times]
    centre = np.array([(SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2])

    def size_and_ground_errors(level_ground):
        g = georeference(placements, ref, indices, SIZE, 10.0, track, GeorefOptions(level_ground=level_ground))
        maps = [g.frame_to_ground(k, P) for k, P in enumerate(placements)]
        size = np.array([0.5 * math.log(abs(np.linalg.det(_jacobian(M, centre)) / np.linalg.det(_jacobian(to_ground @ T, centre))))
                         for M, T in zip(maps, truth)])
        return g, float(np.sqrt(np.mean((size - size.mean()) ** 2))), ground_errors(np.eye(3), maps, [to_ground @ T for T in truth])

    plain, plain_size, plain_err = size_and_ground_errors(False)
    level, level_size, level_err = size_and_ground_errors(True)
    assert np.all(plain.scales == 1.0) and np.ptp(level.scales) > 0.01
    assert plain_size > 0.009 and level_size < 0.8 * plain_size, (plain_size, level_size)
    # where the keyframes lie is the GPS's to say (3 m noise) either way: no worse than a decimetre
    assert level_err.max() < plain_err.max() + 0.1 and np.median(level_err) < np.median(plain_err) + 0.1


# --- the height x field of view scale (geo/prior.py), weighed against the GPS --------------


def test_height_scale_averages_the_noise_not_the_offset_and_screens_a_misread_height():
    """Each keyframe's height over the focal length against how many mosaic pixels its pixel
    covers: the per-sample noise averages out, the flight's offset stays (and is in sigma)."""
    from mosaic_cli.geo.prior import height_scale

    rng = np.random.default_rng(7)
    n, metres_per_mosaic_pixel = 120, 0.025
    true_heights = HEIGHT * (1 + 0.03 * np.sin(np.linspace(0, 6, n)))  # the drone climbs and sinks
    per_pixel = true_heights / FOCAL / metres_per_mosaic_pixel  # what the images say of each keyframe
    offset = 0.4
    logged = true_heights + offset + rng.normal(0, 0.3, n)
    logged[17] = 3.0  # one misread sample
    logged[40] = np.nan  # one without a height
    hs = height_scale(logged, FOCAL, per_pixel, height_accuracy=0.5, fov_accuracy=0.01)
    assert hs.used == n - 2 and np.isnan(hs.per_keyframe[[17, 40]]).all()
    # the offset shifts the scale by offset / height; the noise of 0.3 m leaves 0.3 / 32 / sqrt(n)
    expected = metres_per_mosaic_pixel * np.exp(np.mean(np.log((true_heights + offset) / true_heights)[np.isfinite(hs.per_keyframe)]))
    assert hs.mosaic_scale == pytest.approx(expected, rel=3 * 0.3 / HEIGHT / math.sqrt(n))
    assert hs.sigma == pytest.approx(math.hypot(0.5 / HEIGHT, 0.01), rel=0.02)
    np.testing.assert_allclose(hs.per_keyframe[0], logged[0] / FOCAL)
    assert height_scale(np.full(n, np.nan), FOCAL, per_pixel, 0.5, 0.01) is None


def synthetic_track(centres, times, pitch, roll, gps, heights, hfov):
    """A FlightLog of the synthetic flight (y of ``gps`` runs south) at the Zurich test origin."""
    from mosaic_cli.geo.crs import Projection
    from mosaic_cli.telemetry.flight_log import FlightLog

    projection = Projection.utm_for(47.3977, 8.5456)
    origin = projection.to_map([47.3977], [8.5456])[0]
    lonlat = projection.to_wgs84(origin[0] + gps[:, 0], origin[1] - gps[:, 1])
    n = len(times)
    headings = np.where((np.arange(n) // 15) % 2 == 0, 90.0, -90.0)
    track = FlightLog("synthetic", times, lonlat[:, 1], lonlat[:, 0], np.full(n, 500.0), heights, headings, pitch, roll, np.full(n, hfov))
    return track, np.array([[1.0, 0, origin[0]], [0, -1.0, origin[1]], [0, 0, 1.0]])


def gps_scale_error(centres, gps):
    """(scale of the GPS track / the true one's) - 1: what the GPS alone says of scale."""
    zt, zg = centres[:, 0] + 1j * centres[:, 1], gps[:, 0] + 1j * gps[:, 1]
    zt, zg = zt - zt.mean(), zg - zg.mean()
    return float(abs(np.vdot(zt, zg) / np.vdot(zt, zt)) - 1.0)


def map_scale_error(g, placements, truth, to_ground):
    """(scale of the map / the truth's) - 1, over every keyframe's corners and centre."""
    pts = np.vstack([frame_corners(*SIZE), [[(SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2]]])
    got = np.concatenate([project(g.frame_to_ground(k, P), pts) for k, P in enumerate(placements)])
    true = np.concatenate([project(to_ground @ T, pts) for T in truth])
    zg, zt = got[:, 0] + 1j * got[:, 1], true[:, 0] + 1j * true[:, 1]
    zg, zt = zg - zg.mean(), zt - zt.mean()
    return float(1.0 / abs(np.vdot(zg, zt) / np.vdot(zg, zg)) - 1.0)


@pytest.mark.parametrize("gimbal", [True, False])
def test_georeference_weighs_the_height_scale_against_the_gps_by_their_errors(gimbal):
    """A GPS track 1% too large (a flight whose GPS errors happen to stretch it) and exact heights:
    the map follows the heights when they are stated to be exact, the GPS when they are stated
    to be poor, and lies between by their weights; in the adjustment and in the similarity alike."""
    from mosaic_cli.geo.camera import hfov_degrees
    from mosaic_cli.geo.georef import GeorefOptions, georeference

    centres, pitch, roll, truth, _, _, times, rng = flight(3)
    ref = 30
    placements = [np.linalg.inv(truth[ref]) @ T for T in truth]
    stretched = centres.mean(0) + 1.01 * (centres - centres.mean(0)) + rng.normal(0, 0.05, centres.shape)
    track, to_ground = synthetic_track(centres, times, pitch, roll, stretched, np.full(len(times), HEIGHT), hfov_degrees(SIZE[0], FOCAL))
    indices = [int(round(t * 10.0)) for t in times]

    def scale_error(height_accuracy):
        # (1% apart, exact heights and a GPS of 0.2% are many sigmas apart: the check is off here; see the next test)
        options = GeorefOptions(height_accuracy=height_accuracy, fov_accuracy=0.0, attitude_accuracy=1.0 if gimbal else None,
                                max_scale_disagreement=1e9)
        g = georeference(placements, ref, indices, SIZE, 10.0, track, options)
        return map_scale_error(g, placements, truth, to_ground)

    exact, half, poor = scale_error(0.005), scale_error(0.06), scale_error(20.0)
    # the heights: exact; the adjustment lets the GPS pull a little of the mosaic's aspect (its non-similar
    # part, held by the gimbal to 1 degree per keyframe), which shows in the along-track scale
    assert abs(exact) < 0.002, exact
    assert poor == pytest.approx(0.01, abs=0.001), poor  # the GPS's 1%
    assert exact < half < poor and 0.002 < half < 0.008, half  # between, by their weights


def test_a_wrong_field_of_view_is_said_and_the_gps_scale_used():
    """--hfov 15% off on a long flight: the height x field of view scale disagrees with the GPS
    track's by many sigmas: one warning, and the map at the GPS's scale, not dragged by it."""
    from mosaic_cli.geo.camera import hfov_degrees
    from mosaic_cli.geo.georef import GeorefOptions, georeference

    centres, pitch, roll, truth, _, _, times, rng = flight(5)
    ref = 30
    placements = [np.linalg.inv(truth[ref]) @ T for T in truth]
    gps = noisy_gps(centres, times, rng)
    hfov = hfov_degrees(SIZE[0], FOCAL)
    track, to_ground = synthetic_track(centres, times, pitch, roll, gps, np.full(len(times), HEIGHT), hfov)
    indices = [int(round(t * 10.0)) for t in times]
    right = georeference(placements, ref, indices, SIZE, 10.0, track, GeorefOptions())
    assert not right.warnings and right.prior.sigma is not None
    wide = 2 * math.degrees(math.atan(1.15 * math.tan(math.radians(hfov) / 2)))  # 15% more ground per pixel
    wrong = georeference(placements, ref, indices, SIZE, 10.0, track, GeorefOptions(hfov=wide))
    assert len(wrong.warnings) == 1 and "check --hfov" in wrong.warnings[0], wrong.warnings
    assert wrong.prior.sigma is None
    own = gps_scale_error(centres, gps)
    # the GPS's own scale (the wrong field of view still undoes the gimbal's tilts a little wrongly)
    assert map_scale_error(wrong, placements, truth, to_ground) == pytest.approx(own, abs=0.005)
    # the same field of view trusted at its stated accuracy would have pulled the map percents larger
    trusted = georeference(placements, ref, indices, SIZE, 10.0, track, GeorefOptions(hfov=wide, max_scale_disagreement=1e9))
    assert map_scale_error(trusted, placements, truth, to_ground) > own + 0.015


def test_a_short_tracks_gps_does_not_overrule_the_height():
    """Five keyframes over 10 s whose GPS happens to stretch the track by 25% (fixes 2 s apart
    whose errors agree): so few fixes cannot tell their own scatter, so their scale is not
    many sigmas from the (exact) height's, and the map keeps the height's scale.  Taken at
    their own agreement they would call the height wrong and make the map 25% too large."""
    from mosaic_cli.geo.camera import hfov_degrees
    from mosaic_cli.geo.georef import GeorefOptions, georeference

    centres, pitch, roll, truth, _, _, times, rng = flight(3)
    keep = slice(0, 5)
    centres, pitch, roll, truth, times = centres[keep], pitch[keep], roll[keep], truth[keep], times[keep]
    ref = 2
    placements = [np.linalg.inv(truth[ref]) @ T for T in truth]
    stretched = centres.mean(0) + 1.25 * (centres - centres.mean(0))
    track, to_ground = synthetic_track(centres, times, pitch, roll, stretched, np.full(len(times), HEIGHT), hfov_degrees(SIZE[0], FOCAL))
    g = georeference(placements, ref, [int(round(t * 10.0)) for t in times], SIZE, 10.0, track, GeorefOptions(fov_accuracy=0.0))
    assert not g.warnings, g.warnings
    assert abs(map_scale_error(g, placements, truth, to_ground)) < 0.03


@pytest.mark.slow
def test_without_height_or_field_of_view_the_gps_alone_places_the_map():
    """A log without heights, or without a field of view (and no --hfov): no scale prior, the
    map as the GPS and the images make it, as before the prior existed."""
    from mosaic_cli.geo.camera import hfov_degrees
    from mosaic_cli.geo.georef import GeorefOptions, georeference

    centres, pitch, roll, truth, _, _, times, rng = flight(6)
    ref = 30
    placements = [np.linalg.inv(truth[ref]) @ T for T in truth]
    gps = noisy_gps(centres, times, rng)
    n = len(times)
    indices = [int(round(t * 10.0)) for t in times]
    own = gps_scale_error(centres, gps)
    for heights, hfov in ((np.full(n, np.nan), hfov_degrees(SIZE[0], FOCAL)), (np.full(n, HEIGHT), np.nan)):
        track, to_ground = synthetic_track(centres, times, pitch, roll, gps, heights, hfov)
        g = georeference(placements, ref, indices, SIZE, 10.0, track, GeorefOptions())
        assert g.prior is None and not g.warnings
        # the GPS's own scale; without a field of view the reference's tilt is not undone either (0.5% here)
        assert map_scale_error(g, placements, truth, to_ground) == pytest.approx(own, abs=0.002 if np.isfinite(hfov) else 0.008)


@pytest.mark.slow
@pytest.mark.parametrize("spacing", [0.1, 1.0, 2.1, 6.0])
def test_fix_weights_give_what_correlated_fixes_tell_of_a_mean_and_a_trend(spacing):
    """Against generalised least squares with the exact covariance of exponentially correlated
    errors (rho^|i - j|): the information of n fixes about their mean and about a slope (a
    scale) is what the weights add up to (over a flight of 100 correlation times, where a slope is
    told by the positions, not by the errors' own changes)."""
    from mosaic_cli.geo.fit import fix_weights

    tau = 2.0
    n = int(round(100 * tau / spacing))
    times = np.arange(n) * spacing
    w = fix_weights(times, np.ones(n, bool), tau)
    cov = np.exp(-np.abs(times[:, None] - times[None, :]) / tau)
    inv = np.linalg.inv(cov)
    ones = np.ones(n)
    x = times - times.mean()
    assert w.sum() == pytest.approx(ones @ inv @ ones, rel=0.03)
    assert (w * (x - (w * x).sum() / w.sum()) ** 2).sum() == pytest.approx(x @ inv @ x, rel=0.05)
    assert fix_weights(times, np.arange(n) % 2 == 0, tau)[1] == 0.0  # a fix not in use is worth nothing
