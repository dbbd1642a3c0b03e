"""Pure homography algebra (numpy). No I/O, no state.

Conventions used everywhere in mosaic:

* Pixel coordinates follow OpenCV: pixel (i, j) has its centre at x = j, y = i; the image
  spans [-0.5, w - 0.5] x [-0.5, h - 0.5].
* A homography ``H`` maps homogeneous column vectors: ``x_dst ~ H @ [x, y, 1]``.
* ``pairwise[t]`` maps pixels of frame t to frame t+1.  The chain
  ``H_[t,s] = H_{s-1} @ ... @ H_{t+1} @ H_t`` maps frame t to frame s (the paper's notation).

The same algebra on torch tensors, with the same names, is :mod:`mosaic_cli.geometry.tensor`
(not imported here: it needs torch).
"""

from mosaic_cli.geometry.homography import *  # noqa: F401,F403
