"""``StitchOptions``: everything a stitch is told, one dataclass of each stage's own options
(:mod:`.keyframes`, :mod:`.features`, :mod:`.registration`, :mod:`.segments`, :mod:`.canvas`,
:mod:`.compose`, :mod:`.cluster`) and the stitch's own fields."""

from __future__ import annotations

from dataclasses import dataclass, field

from mosaic_cli.errors import BadInput
from mosaic_cli.geo.georef import GeorefOptions
from mosaic_cli.inputs import DEFAULT_TIMEOUT, check_max_frames, check_timeout
from mosaic_cli.overlay import MaskOptions
from mosaic_cli.stabilize.rolling import parse_rolling_shutter
from mosaic_cli.stitch.canvas import CanvasOptions
from mosaic_cli.stitch.cluster import ClusterOptions
from mosaic_cli.stitch.compose import ComposeOptions
from mosaic_cli.stitch.features import FeatureOptions
from mosaic_cli.stitch.keyframes import KeyframeOptions
from mosaic_cli.stitch.registration import RegistrationOptions
from mosaic_cli.stitch.segments import JoinOptions


@dataclass
class StitchOptions:
    # The estimator of the scan, as stabilize's (``make_estimator``), built once the input and
    # the outputs are checked: a learned one loads weights.
    estimator: str | None = None  # None: DEFAULT_ESTIMATOR, or the network --weights hold
    work_width: int | None = None  # --work-width; None: DEFAULT_WORK_WIDTH
    weights: str | None = None
    device: str = "auto"
    keyframes: KeyframeOptions = field(default_factory=KeyframeOptions)
    features: FeatureOptions = field(default_factory=FeatureOptions)
    registration: RegistrationOptions = field(default_factory=RegistrationOptions)
    joining: JoinOptions = field(default_factory=JoinOptions)
    canvas: CanvasOptions = field(default_factory=CanvasOptions)
    compose: ComposeOptions = field(default_factory=ComposeOptions)
    mask: MaskOptions = field(default_factory=MaskOptions)  # burned-in overlays, --mask
    start: int = 0
    max_frames: int | None = None
    # Hold keyframe pixels in a temporary folder ($TMPDIR) rather than in memory: a survey's
    # held pixels add up to several canvases (see spill.py).
    spill: bool = True
    # Telemetry to lay the mosaic on the ground with (see mosaic_cli/geo); None: a plain panorama.
    georef: GeorefOptions | None = None
    timeout: float = DEFAULT_TIMEOUT  # a live input (stitch/live.py) ends when it sends nothing for this long
    rolling_shutter: str | float = "off"  # auto, off or a readout in [0, 1]: each keyframe drawn row band by row band
    # Several flights with telemetry (stitch/flights.py): parts that join nothing by registration
    # are still drawn on one map, each where its log places it.
    one_map: bool = False
    # --workers / --scheduler: the flights' scans and the compose stage's tiles on a Dask cluster
    # (stitch/cluster.py); none asked: all here.
    cluster: ClusterOptions = field(default_factory=ClusterOptions)

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Its own fields; the stages' options checked themselves when they were made."""
        if self.start < 0:
            raise BadInput(f"--start must be 0 or more, got {self.start}")
        check_max_frames(self.max_frames)
        check_timeout(self.timeout)
        parse_rolling_shutter(self.rolling_shutter)
