"""Burned-in overlays (logos, OSD text, timestamps, letterbox bars) found in frames sampled
over a clip, merged with the user's ``--mask`` into one use mask (uint8, full resolution,
255 = ground to use):

- :mod:`~mosaic_cli.overlay.detect`: what stays put while the ground moves (the detector);
- :mod:`~mosaic_cli.overlay.samples`: the frames it looks at, read one at a time;
- :mod:`~mosaic_cli.overlay.merge`: ``--mask``'s options and a video's merged use mask, also
  while it is still being looked for (:class:`PendingMask`);
- :mod:`~mosaic_cli.overlay.speculate`: tracking that starts before the mask is known, and
  starts again if an overlay is found.

The mask operations every stage uses (:func:`~mosaic_cli.mask.load_mask`,
:func:`~mosaic_cli.mask.work_mask`, :func:`~mosaic_cli.mask.fill_masked`) live in
:mod:`mosaic_cli.mask`, below the estimators; they are re-exported here."""

from mosaic_cli.mask import fill_masked, load_mask, work_mask
from mosaic_cli.overlay.detect import Detection, Letterbox, OverlayOptions, detect_overlays
from mosaic_cli.overlay.merge import (
    LIVE_DETECTION_SKIPPED,
    DetectionStopped,
    FrameMask,
    MaskOptions,
    PendingMask,
    check_mask_file,
    frame_mask,
    frame_mask_pending,
    frame_mask_while,
    live_mask,
)
from mosaic_cli.overlay.samples import VideoSamples, sample_frames, sample_width
from mosaic_cli.overlay.speculate import Gate, MaskChanged, Speculation, speculate

__all__ = [
    "LIVE_DETECTION_SKIPPED",
    "Detection",
    "DetectionStopped",
    "FrameMask",
    "Gate",
    "Letterbox",
    "MaskChanged",
    "MaskOptions",
    "OverlayOptions",
    "PendingMask",
    "Speculation",
    "VideoSamples",
    "check_mask_file",
    "detect_overlays",
    "fill_masked",
    "frame_mask",
    "frame_mask_pending",
    "frame_mask_while",
    "live_mask",
    "load_mask",
    "sample_frames",
    "sample_width",
    "speculate",
    "work_mask",
]
