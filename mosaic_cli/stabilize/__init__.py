"""Video stabilisation: the L1-optimal camera path (Grundmann et al. 2011) over any estimator.

    from mosaic_cli.stabilize import stabilize, StabilizeOptions
    result = stabilize("shaky.mp4", "steady.mp4", StabilizeOptions(model="similarity"))

Stages, each its own module: :mod:`.path` (camera motion in the chosen model),
:mod:`.smoothing` (L1 linear program or Gaussian), :mod:`.crop` (crop window, warps),
:mod:`.render` (warp, borders, encode, side-by-side), :mod:`.metrics` (cropping, distortion,
residual jitter), :mod:`.pipeline` (the command's table of contents).
"""

from mosaic_cli.stabilize.pipeline import StabilizeOptions, StabilizeResult, stabilize, write_warps  # noqa: F401
