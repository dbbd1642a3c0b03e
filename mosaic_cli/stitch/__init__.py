"""``mosaic stitch``: a streaming panorama with drift control and bounded memory.

The stages live in their own modules (see :mod:`.pipeline` for the order):
:mod:`.keyframes` (streaming pass), :mod:`.features` and :mod:`.registration` (drift control),
:mod:`.canvas`, :mod:`.compose` and :mod:`.output`.
"""

from mosaic_cli.stitch.canvas import CanvasOptions  # noqa: F401
from mosaic_cli.stitch.compose import ComposeOptions  # noqa: F401
from mosaic_cli.stitch.features import FeatureOptions  # noqa: F401
from mosaic_cli.stitch.keyframes import KeyframeOptions  # noqa: F401
from mosaic_cli.stitch.options import StitchOptions  # noqa: F401
from mosaic_cli.stitch.pipeline import StitchResult, stitch  # noqa: F401
from mosaic_cli.stitch.registration import RegistrationOptions  # noqa: F401
