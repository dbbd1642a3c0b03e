"""Telemetry readers (DJI SRT variants, GPX, CSV, MISB ST 0601 KLV), frame alignment, and
the simulator's logs scored against its exact camera poses."""

from __future__ import annotations

import math
import struct
import subprocess

import numpy as np
import pytest

from mosaic_cli.cli import main
from mosaic_cli.errors import BadInput
from mosaic_cli.geo.camera import focal_pixels, nadir_pixel
from mosaic_cli.geo.crs import Projection
from mosaic_cli.geometry import project
from mosaic_cli.simulate import load_ground_truth
from mosaic_cli.simulate.telemetry import GpsErrors, MapGeo, camera_poses, klv_bytes, simulate_log
from mosaic_cli.telemetry import align_to_frames, find_telemetry, read_telemetry
from mosaic_cli.telemetry.klv import checksum, decode_stream, encode_packet
from tests.conftest import FFMPEG

SRT_BRACKETS = """1
00:00:00,000 --> 00:00:00,033
<font size="28">FrameCnt: 1, DiffTime: 33ms
2023-03-17 15:41:35.367
[iso: 100] [shutter: 1/1000.0] [fnum: 2.8] [ev: 0] [ct: 5500] [color_md: default] [focal_len: 24.00] [dzoom_ratio: 1.00, delta:0] [latitude: 41.403130] [longitude: 2.174480] [rel_alt: 51.300 abs_alt: 175.800] [gb_yaw: -12.3 gb_pitch: -88.5 gb_roll: 0.4] </font>

2
00:00:00,033 --> 00:00:00,067
<font size="28">FrameCnt: 2, DiffTime: 34ms
2023-03-17 15:41:35.401
[iso: 100] [shutter: 1/1000.0] [fnum: 2.8] [ev: 0] [ct: 5500] [color_md: default] [focal_len: 280] [latitude: 41.403140] [longitude: 2.174490] [rel_alt: 51.400 abs_alt: 175.900] [gb_yaw: -12.1 gb_pitch: -88.4 gb_roll: 0.3] </font>
"""

SRT_LONGTITUDE = """1
00:00:00,000 --> 00:00:00,033
<font size="36">SrtCnt : 1, DiffTime : 33ms
2020-06-10 12:00:00,000,000
[iso : 110] [shutter : 1/200.0] [fnum : 280] [ev : 0] [ct : 5064] [color_md : default] [focal_len : 240] [latitude : 0.000000] [longtitude : 0.000000] [altitude: 0.000000] </font>

2
00:00:00,033 --> 00:00:00,066
<font size="36">SrtCnt : 2, DiffTime : 33ms
2020-06-10 12:00:00,033,000
[iso : 110] [shutter : 1/200.0] [fnum : 280] [ev : 0] [ct : 5064] [color_md : default] [focal_len : 240] [latitude : 22.543096] [longtitude : 113.958494] [altitude: 27.600000] </font>
"""

SRT_GPS_BAROMETER = """1
00:00:00,000 --> 00:00:01,000
HOME(149.0251,-20.2532) 2017.08.05 14:11:51
GPS(149.0251,-20.2533,16) BAROMETER:1.9
ISO:100 Shutter:60 EV:0 Fnum:2.2

2
00:00:01,000 --> 00:00:02,000
HOME(149.0251,-20.2532) 2017.08.05 14:11:52
GPS(149.0252,-20.2534,17) BAROMETER:2.4
ISO:100 Shutter:60 EV:0 Fnum:2.2
"""

SRT_PHANTOM = """1
00:00:00,000 --> 00:00:01,000
F/2.8, SS 1000, ISO 100, EV 0, GPS (8.6625, 47.2031, 17), D 45.49m, H 30.50m, HS 0.00m/s, VS 0.00m/s

2
00:00:01,000 --> 00:00:02,000
F/2.8, SS 1000, ISO 100, EV 0, GPS (0.0, 0.0, 0), D 0.00m, H 31.20m, HS 0.00m/s, VS 0.00m/s

3
00:00:02,000 --> 00:00:03,000
F/2.8, SS 1000, ISO 100, EV 0, GPS (8.6627, 47.2033, 18), D 46.90m, H 32.00m, HS 1.00m/s, VS 0.00m/s
"""


def write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_srt_brackets_per_frame_with_gimbal_and_focal_length(tmp_path):
    t = read_telemetry(write(tmp_path, "DJI_0001.SRT", SRT_BRACKETS))
    assert "per-frame" in t.source
    np.testing.assert_allclose(t.time, [0.0, 0.033])
    np.testing.assert_allclose(t.lat, [41.403130, 41.403140])
    np.testing.assert_allclose(t.lon, [2.174480, 2.174490])
    np.testing.assert_allclose(t.height, [51.3, 51.4])
    np.testing.assert_allclose(t.alt, [175.8, 175.9])
    np.testing.assert_allclose(t.yaw, [-12.3, -12.1])
    np.testing.assert_allclose(t.pitch, [-88.5, -88.4])
    np.testing.assert_allclose(t.roll, [0.4, 0.3])
    # 24 mm and "280" (28 mm written times ten) across a 36 mm frame
    np.testing.assert_allclose(t.hfov, [2 * math.degrees(math.atan(18 / 24)), 2 * math.degrees(math.atan(18 / 28))])


def test_srt_longtitude_misspelling_and_zero_coordinates_without_fix(tmp_path):
    t = read_telemetry(write(tmp_path, "a.srt", SRT_LONGTITUDE))
    assert t.has_fix.tolist() == [False, True]
    assert t.lat[1] == pytest.approx(22.543096) and t.lon[1] == pytest.approx(113.958494)
    assert t.alt[1] == pytest.approx(27.6)


def test_srt_gps_lon_lat_alt_with_barometer_per_second(tmp_path):
    t = read_telemetry(write(tmp_path, "b.SRT", SRT_GPS_BAROMETER))
    assert "per-second" in t.source
    np.testing.assert_allclose(t.lon, [149.0251, 149.0252])  # GPS(lon, lat, alt), HOME ignored
    np.testing.assert_allclose(t.lat, [-20.2533, -20.2534])
    np.testing.assert_allclose(t.alt, [16, 17])
    np.testing.assert_allclose(t.height, [1.9, 2.4])


def test_srt_phantom_comma_style_height_and_dropout(tmp_path):
    t = read_telemetry(write(tmp_path, "c.SRT", SRT_PHANTOM))
    assert t.has_fix.tolist() == [True, False, True]
    np.testing.assert_allclose(t.height, [30.5, 31.2, 32.0])
    a = align_to_frames(t, np.array([0.0, 1.0, 2.0]))
    assert a.without_fix == 1 and a.fix.all()  # a one-second hole is bridged by interpolation
    np.testing.assert_allclose(a.lat, [47.2031, 47.2032, 47.2033])


def test_srt_without_telemetry_and_not_srt(tmp_path):
    with pytest.raises(BadInput, match="no GPS telemetry"):
        read_telemetry(write(tmp_path, "captions.srt", "1\n00:00:00,000 --> 00:00:01,000\nHello there\n"))
    with pytest.raises(BadInput, match="not an SRT"):
        read_telemetry(write(tmp_path, "x.srt", "nothing here\n"))


def test_csv_and_gpx(tmp_path):
    csv = write(tmp_path, "log.csv", "Time,Latitude,Longitude,Alt,Yaw\n0.0,47.1,8.5,400,10\n0.5,,,401,11\n1.0,47.2,8.6,402,12\n")
    t = read_telemetry(csv)
    assert t.has_fix.tolist() == [True, False, True]
    np.testing.assert_allclose(t.yaw, [10, 11, 12])
    gpx = write(tmp_path, "t.gpx", """<?xml version="1.0"?><gpx version="1.1" creator="x" xmlns="http://www.topografix.com/GPX/1/1">
<trk><trkseg><trkpt lat="47.1" lon="8.5"><ele>400</ele><time>2026-01-01T10:00:05Z</time></trkpt>
<trkpt lat="0" lon="0"><time>2026-01-01T10:00:06Z</time><fix>none</fix></trkpt>
<trkpt lat="47.2" lon="8.6"><ele>402</ele><time>2026-01-01T10:00:07Z</time></trkpt></trkseg></trk></gpx>""")
    g = read_telemetry(gpx)
    np.testing.assert_allclose(g.time, [0, 1, 2])  # clock times, from the first sample
    assert g.has_fix.tolist() == [True, False, True] and g.clock_time
    with pytest.raises(BadInput, match="time, lat and lon"):
        read_telemetry(write(tmp_path, "bad.csv", "a,b\n1,2\n"))


def test_klv_packets_round_trip_and_agree_with_klvdata(tmp_path):
    values = {"lat": 47.123456, "lon": 8.654321, "alt": 512.3, "ground_alt": 412.0, "platform_heading": 123.4,
              "sensor_azimuth": 10.0, "sensor_elevation": -88.0, "sensor_roll": 359.0, "hfov": 60.0}
    packet = encode_packet(1_780_000_000_000_000, values)
    packets, dropped = decode_stream(packet * 3)
    assert dropped == 0 and len(packets) == 3
    got = packets[0].values
    for k, v in values.items():
        step = 0.16 if "alt" in k else 0.01  # altitudes: 19900 m over 16 bits
        assert got[k] == pytest.approx(v, abs=step), k
    klvdata = pytest.importorskip("klvdata")
    import io

    parsed = next(iter(klvdata.StreamParser(io.BytesIO(packet)))).MetadataList()
    assert float(parsed[13][3]) == pytest.approx(values["lat"], abs=1e-6)
    assert float(parsed[14][3]) == pytest.approx(values["lon"], abs=1e-6)
    assert float(parsed[19][3]) == pytest.approx(values["sensor_elevation"], abs=1e-6)
    # checksum: the 16-bit sum of big-endian words from the key through the checksum's tag and length
    words = packet[:-2] + (b"\0" if len(packet[:-2]) % 2 else b"")
    assert checksum(packet[:-2]) == sum(struct.unpack(f">{len(words) // 2}H", words)) & 0xFFFF


def test_klv_corrupt_packet_is_dropped_and_counted(tmp_path):
    good = encode_packet(1_000_000, {"lat": 10.0, "lon": 20.0})
    bad = bytearray(encode_packet(2_000_000, {"lat": 10.5, "lon": 20.5}))
    bad[30] ^= 0xFF
    p = tmp_path / "x.klv"
    p.write_bytes(good + bytes(bad) + encode_packet(3_000_000, {"lat": 11.0, "lon": 21.0}))
    t = read_telemetry(p)
    np.testing.assert_allclose(t.time, [0.0, 2.0])
    np.testing.assert_allclose(t.lat, [10.0, 11.0], atol=1e-6)
    assert any("checksum" in n for n in t.notes)


def test_alignment_reports_outliers_and_gaps():
    n = 200
    times = np.arange(n) / 10.0
    lat = 47.0 + 1e-6 * times * 50  # ~5.6 m/s north
    lon = np.full(n, 8.0)
    lat[50] += 40 / 111_000  # a bad fix 40 m off
    lat[100:150] = np.nan  # 5 s without a fix
    from mosaic_cli.telemetry.flight_log import FlightLog

    nan = np.full(n, np.nan)
    track = FlightLog("t", times, lat, lon, nan, nan, nan, nan, nan, nan)
    a = align_to_frames(track, np.arange(0, 19.9, 1 / 30))
    assert a.outliers == 1 and a.without_fix == 50
    assert a.dropped.shape == (n,) and np.flatnonzero(a.dropped).tolist() == [50]  # which sample, for the maps
    assert len(a.gaps) == 1 and a.gaps[0][1] == pytest.approx(5.1)
    inside_gap = (a.frame_times > 9.9) & (a.frame_times < 15.0)
    assert not a.fix[inside_gap].any() and a.fix[~inside_gap].all()
    expect = 47.0 + 1e-6 * a.frame_times * 50
    assert np.nanmax(np.abs(a.lat - expect)) < 1e-9  # the outlier bent nothing


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    d = tmp_path_factory.mktemp("telemetry_flight")
    out = d / "f.mp4"
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "-o", str(out), "-n", "40", "--size", "320x180", "--preset", "ultrafast", "-q", "--seed", "3",
              "--telemetry", "srt", "--origin", "-33.8568,151.2153", "--gsd", "0.02"])
    assert exc.value.code in (0, None)
    return out


@pytest.mark.slow
def test_simulated_camera_poses_match_the_exact_homographies(flight):
    """The decomposed pose and the gimbal convention put the point below the camera exactly
    where the simulator's own matrix projects it."""
    gt = load_ground_truth(flight)
    poses = camera_poses(gt)
    f = focal_pixels(gt.size[0], poses.hfov)
    for t in range(0, gt.frames, 7):
        below = project(gt.smooth_map_to_frame[t], np.array([[poses.x[t], poses.y[t]]]))[0]
        np.testing.assert_allclose(below, nadir_pixel(gt.size, f, poses.pitch[t], poses.roll[t]), atol=1e-6)
        # the frame's scale at the centre: focal / height in map pixels
        assert poses.z[t] > 0
    assert max(np.abs(poses.pitch + 90).max(), np.abs(poses.roll).max()) > 0.3  # tilted: the test has teeth


@pytest.mark.slow
@pytest.mark.parametrize("fmt", ["srt", "gpx", "csv", "klv"])
def test_simulated_logs_read_back_to_the_truth(flight, fmt, tmp_path):
    gt = load_ground_truth(flight)
    geo = MapGeo.from_origin(-33.8568, 151.2153, 0.02, gt.map_size)
    errors = GpsErrors(rms=3.0, dropouts=0.1, bad_fixes=0.0, seed=1)
    log = simulate_log(gt, geo, errors, rate=None)
    path = tmp_path / f"log.{fmt}"
    from mosaic_cli.simulate import telemetry as sim

    if fmt == "klv":
        path.write_bytes(klv_bytes(log))
    else:
        path.write_text({"srt": sim.srt_text, "gpx": sim.gpx_text, "csv": sim.csv_text}[fmt](log))
    t = read_telemetry(path)
    np.testing.assert_allclose(t.time, log.time, atol=1e-3)
    assert t.has_fix.tolist() == np.isfinite(log.lat).tolist()
    proj = Projection(geo.crs)
    got = proj.to_map(t.lat[t.has_fix], t.lon[t.has_fix])
    noisy = proj.to_map(log.lat[t.has_fix], log.lon[t.has_fix])
    assert np.abs(got - noisy).max() < 0.02  # what was written is what is read (format precision)
    assert proj.name == "EPSG:32756"  # Sydney: UTM 56 south
    if fmt != "gpx":
        np.testing.assert_allclose(t.height, log.height, atol=0.31 if fmt == "klv" else 0.01)
        np.testing.assert_allclose(t.pitch, log.pitch, atol=0.01)
        np.testing.assert_allclose(t.hfov, log.hfov, atol=0.02)


def test_gps_error_statistics():
    from mosaic_cli.simulate.telemetry import gauss_markov

    rng = np.random.default_rng(0)
    times = np.arange(0, 3000, 0.1)
    e = gauss_markov(rng, times, 2.0, 2.0)
    assert np.sqrt(np.mean(e**2)) == pytest.approx(2.0, rel=0.1)
    lag = int(2.0 / 0.1)  # correlation e^-1 at one time constant
    assert np.corrcoef(e[:-lag], e[lag:])[0, 1] == pytest.approx(math.exp(-1), abs=0.05)


@pytest.mark.slow
def test_srt_subtitle_track_inside_the_video_is_found(flight, tmp_path):
    muxed = tmp_path / "with_srt.mp4"
    subprocess.run([FFMPEG, "-hide_banner", "-loglevel", "error", "-y", "-i", str(flight), "-i", str(flight.with_suffix(".SRT")),
                    "-map", "0:v", "-map", "1:0", "-c:v", "copy", "-c:s", "mov_text", str(muxed)], check=True)
    t = find_telemetry(muxed)
    sidecar = read_telemetry(flight.with_suffix(".SRT"))
    assert t is not None and len(t) == len(sidecar)
    np.testing.assert_allclose(t.lat, sidecar.lat, equal_nan=True)
    np.testing.assert_allclose(t.time, sidecar.time, atol=2e-3)
    assert find_telemetry(flight) is None


def test_geotiff_map_geotransform_follows_the_crop(tmp_path):
    """A GeoTIFF's own geotransform, shifted by the crop load_map makes of its white fill."""
    import rasterio
    from affine import Affine

    from mosaic_cli.simulate import load_map
    from tests.conftest import textured_image

    img = textured_image(240, 160, seed=1)
    img[:, :40] = 255  # fill outside the footprint, cropped away by load_map
    path = tmp_path / "ortho.tif"
    transform = Affine(0.1, 0, 404_000.0, 0, -0.1, 3_285_000.0)
    with rasterio.open(path, "w", driver="GTiff", width=240, height=160, count=3, dtype="uint8", crs="EPSG:32617", transform=transform) as ds:
        ds.write(img.transpose(2, 0, 1))
    geo = MapGeo.from_geotiff(path)
    cropped = load_map(path)
    assert geo.crs == "EPSG:32617" and geo.gsd == pytest.approx(0.1)
    offset = 240 - cropped.shape[1]
    assert offset >= 40
    # map pixel (0, 0) of the cropped map is image pixel (offset, 0): its centre in the CRS
    np.testing.assert_allclose(geo.map_to_crs @ [0, 0, 1], [404_000.0 + 0.1 * (offset + 0.5), 3_285_000.0 - 0.05, 1])
    plain = tmp_path / "plain.tif"
    import cv2

    cv2.imwrite(str(plain), img)
    assert MapGeo.from_geotiff(plain) is None  # no georeference: --origin and --gsd apply


@pytest.mark.slow
def test_simulated_barometric_height_has_one_offset_per_flight(flight):
    """The log's height: the camera's true height above the ground (from the exact pose) plus
    one offset for the whole flight (0.5 m RMS over flights) and white noise; the horizontal
    GPS error of a seed is the same whatever the barometer's error."""
    from mosaic_cli.simulate.telemetry import height_offset

    gt = load_ground_truth(flight)
    geo = MapGeo.from_origin(47.3977, 8.5456, 0.05, gt.map_size)
    true_height = camera_poses(gt).z * geo.gsd  # one log sample per frame
    offsets = []
    for seed in range(40):
        exact = simulate_log(gt, geo, GpsErrors(height_rms=0.0, height_bias=0.0, seed=seed))
        np.testing.assert_allclose(exact.height, true_height, atol=1e-9)
        log = simulate_log(gt, geo, GpsErrors(height_rms=0.0, height_bias=0.5, seed=seed))
        error = log.height - true_height
        assert np.ptp(error) < 1e-9  # one offset, the same for every sample
        assert error[0] == pytest.approx(height_offset(GpsErrors(height_bias=0.5, seed=seed)))
        offsets.append(error[0])
        np.testing.assert_array_equal(np.nan_to_num(log.lat), np.nan_to_num(exact.lat))
    assert np.sqrt(np.mean(np.square(offsets))) == pytest.approx(0.5, rel=0.3)
    noisy = simulate_log(gt, geo, GpsErrors(height_rms=0.3, height_bias=0.0, seed=3))
    assert np.std(noisy.height - true_height) == pytest.approx(0.3, rel=0.2)
