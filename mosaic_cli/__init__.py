"""mosaic: stabilise aerial video and stitch it into panoramas with a learned sequential homography estimator."""

__version__ = "0.1.0"
