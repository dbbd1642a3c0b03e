"""A ``--mask`` image is drawn in the video's own (distorted) pixels; with ``--lens`` the frames
are undistorted, and so is the mask (issue 41): a mask drawn over a burned-in overlay in the raw
frame covers it in the undistorted frame, offline and live."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from conftest import textured_image, write_clip
from mosaic_cli.geometry.lens import radial_lens, undistort_maps, undistort_mask

SIZE = (480, 270)
LENS = radial_lens(SIZE, 1050 * SIZE[0] / 1280, -0.30, 0.0225)  # strong barrel: the corners move ~25 px
LOGO = (12, 14, 110, 52)  # x0, y0, x1, y1 in the raw frame: near a corner, where the lens moves most
MAGENTA = (255, 0, 255)


@pytest.fixture(scope="module")
def burned_in(tmp_path_factory):
    """A clip whose raw frames carry an opaque magenta logo near the top-left corner over gray
    ground (nothing else magenta), the lens file, and a mask drawn over the logo in the raw frame
    (black = keep out, one pixel around it)."""
    folder = tmp_path_factory.mktemp("lens_mask")
    frames = []
    for k in range(6):
        gray = cv2.cvtColor(textured_image(*SIZE, seed=k), cv2.COLOR_RGB2GRAY)
        frame = np.repeat(gray[..., None], 3, axis=2)
        cv2.rectangle(frame, LOGO[:2], LOGO[2:], MAGENTA, -1)
        frames.append(frame)
    clip = write_clip(folder / "logo.mp4", frames)
    lens_file = folder / "lens.json"
    lens_file.write_text(json.dumps(LENS.to_json()))
    mask = np.full((SIZE[1], SIZE[0]), 255, np.uint8)
    cv2.rectangle(mask, (LOGO[0] - 1, LOGO[1] - 1), (LOGO[2] + 1, LOGO[3] + 1), 0, -1)
    mask_file = folder / "mask.png"
    cv2.imwrite(str(mask_file), mask)
    return clip, lens_file, mask_file


def logo_pixels(frame: np.ndarray) -> np.ndarray:
    """Where an RGB frame shows the logo (any magenta tint: the chroma's smear included)."""
    f = frame.astype(np.int16)
    return (f[..., 0] - f[..., 1] > 40) & (f[..., 2] - f[..., 1] > 40)


def test_undistort_mask_keeps_every_masked_pixel_masked():
    """The mask in the undistorted frame against OpenCV's map of each of its pixels: every pixel
    whose bilinear sample touches a masked raw pixel is masked; 0/255 only."""
    use = np.full((SIZE[1], SIZE[0]), 255, np.uint8)
    use[100:140, 5:60] = 0
    out = undistort_mask(use, LENS)
    assert set(np.unique(out)) <= {0, 255}
    mx, my = undistort_maps(LENS, SIZE)
    x0, y0 = np.floor(mx).astype(int), np.floor(my).astype(int)
    touches = np.zeros(out.shape, bool)
    for dx in (0, 1):
        for dy in (0, 1):
            xs, ys = np.clip(x0 + dx, 0, SIZE[0] - 1), np.clip(y0 + dy, 0, SIZE[1] - 1)
            weight = (1 - np.abs(mx - (x0 + dx))) * (1 - np.abs(my - (y0 + dy)))
            touches |= (use[ys, xs] == 0) & (weight > 1 / 64)
    assert np.all(out[touches] == 0)
    # and no more than a pixel's rim beyond it
    grown = cv2.dilate(touches.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    assert np.all(grown[out == 0])


def test_a_mask_drawn_over_a_burned_in_logo_covers_it_in_the_undistorted_frames(burned_in):
    from mosaic_cli.estimators.lens import choose_lens
    from mosaic_cli.overlay import MaskOptions, frame_mask, live_mask
    from mosaic_cli.video import open_video, probe

    clip, lens_file, mask_file = burned_in
    options = MaskOptions(file=mask_file, detect=False)
    info = probe(clip)
    choice = choose_lens(str(lens_file), clip)
    assert choice.lens is not None and choice.image_filter is not None
    use = frame_mask(clip, options, info, lens=choice.image_filter).use
    with open_video(clip, lens=choice.image_filter) as stream:
        frames = [np.asarray(f) for f in stream]
    live = choose_lens(str(lens_file), clip, live=True)
    assert np.array_equal(live_mask(options, SIZE, show_progress=False, lens=live.image_filter).use, use)
    shown = np.any([logo_pixels(f) for f in frames], axis=0)
    assert shown.sum() > 1000  # the logo is there, undistorted: moved off its raw rectangle
    assert np.all(use[shown] == 0), int(np.count_nonzero(use[shown]))
    # the mask as drawn (the raw frame's pixels) misses part of the undistorted logo
    raw_use = frame_mask(clip, options, info).use
    assert np.count_nonzero(raw_use[shown]) > 100, int(np.count_nonzero(raw_use[shown]))
    # and the undistorted mask keeps the ground: at most a few pixels' rim around the logo
    assert np.count_nonzero(use == 0) < 1.3 * np.count_nonzero(cv2.dilate(shown.astype(np.uint8), np.ones((5, 5), np.uint8)))


def test_overlays_found_by_the_detector_are_masked_whole_in_the_undistorted_frames(tmp_path):
    """The detector looks for overlays in the frames as decoded, where they were burned in, and
    the mask it finds is carried into the undistorted frame (as a ``--mask`` file's): every
    pixel of the logo is masked in the frames the tracking and the panorama see.  Looked for in
    the undistorted frames, the logo near a corner (stretched and resampled) came out with part
    of it unmasked, and a stitch drew it."""
    from mosaic_cli.geometry.lens import Undistortion
    from mosaic_cli.overlay import MaskOptions, frame_mask
    from mosaic_cli.video import open_video, probe

    frames = []
    for k in range(48):  # gray ground that changes under a logo that does not
        frame = np.repeat(cv2.cvtColor(textured_image(*SIZE, seed=100 + k), cv2.COLOR_RGB2GRAY)[..., None], 3, axis=2)
        cv2.rectangle(frame, LOGO[:2], LOGO[2:], MAGENTA, -1)
        frames.append(frame)
    clip = write_clip(tmp_path / "logo.mp4", frames)
    info, undistort = probe(clip), Undistortion(LENS)
    found = frame_mask(clip, MaskOptions(), info, lens=undistort)
    assert found.detection is not None and found.use is not None
    with open_video(clip, info=info, lens=undistort) as stream:
        shown = np.any([logo_pixels(np.asarray(f)) for f in stream], axis=0)
    assert shown.sum() > 3000  # the logo, undistorted
    assert np.count_nonzero(found.use[shown]) == 0, int(np.count_nonzero(found.use[shown]))
    # and the ground is kept: the mask is the logo and a rim about it
    assert np.count_nonzero(found.use == 0) < 2.0 * np.count_nonzero(cv2.dilate(shown.astype(np.uint8), np.ones((5, 5), np.uint8)))
