"""What ``mosaic bench`` is asked: the estimators (named as on the command line, options
included), the simulated flight, video or folder of flights, and the flags checked."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mosaic_cli.errors import BadInput
from mosaic_cli.estimators import LEARNED
from mosaic_cli.inputs import check_weights_file
from mosaic_cli.simulate import SimulateOptions

DEFAULT_ESTIMATORS = (*LEARNED, "orb", "orb-paper", "identity")


def is_learned(label: str) -> bool:
    """Whether the estimator named ``label`` (options included) is a learned one."""
    from mosaic_cli.estimators import parse_spec

    return parse_spec(label)[0] in LEARNED


def estimator_labels(estimators: list[str] | None) -> list[str]:
    """The estimators' names as given (None: DEFAULT_ESTIMATORS), blanks dropped."""
    # Not lowercased: a weights=FILE option keeps its case (parse_spec lowercases names and keys).
    return [n.strip() for n in (estimators if estimators is not None else list(DEFAULT_ESTIMATORS)) if n.strip()]


def simulated_flight(**options: Any) -> SimulateOptions:
    """The benchmark's simulated flight (``options``: SimulateOptions' profile, frames, size,
    seed, ...): a short clip encoded fast, since the benchmark times the estimators, not the encoder."""
    return SimulateOptions(crf=18, preset="veryfast", **options)


@dataclass
class BenchOptions:
    """What ``mosaic bench`` times and scores: a simulated flight (``flight``), a ``video``
    (at most ``flight.frames`` of it) or a folder of ``flights``."""

    estimators: list[str] | None = None  # as on the command line, options included; None: DEFAULT_ESTIMATORS
    video: Path | None = None
    flights: Path | None = None
    map_image: Path | None = None  # the simulated flight's map; None: procedural
    flight: SimulateOptions = field(default_factory=simulated_flight)
    weights: str | None = None  # for the learned estimators
    work_width: int = 320  # of the classical estimators
    device: str = "auto"
    threads: int | None = None  # torch's CPU threads for the learned estimators

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """The flags (the simulated flight's checked themselves); the paths are the request's (:func:`check_request`)."""
        from mosaic_cli.device import check_device
        from mosaic_cli.estimators import check_work_width
        from mosaic_cli.inputs import check_threads

        if self.estimators is not None:
            labels = estimator_labels(self.estimators)
            if not labels:
                raise BadInput("--estimators is empty")
            if len(set(labels)) != len(labels):
                raise BadInput("--estimators names an estimator twice")
        if self.flights is not None and (self.video is not None or self.map_image is not None):
            raise BadInput("give --flights or --video/--map, not both")
        if self.video is not None and self.map_image is not None:
            raise BadInput("give --video or --map, not both")
        check_work_width(self.work_width)
        check_device(self.device)
        check_threads(self.threads)

    @property
    def labels(self) -> list[str]:
        return estimator_labels(self.estimators)


def check_request(options: BenchOptions) -> None:
    """The inputs exist, before any estimator is built or frame decoded."""
    if options.video is not None and not options.video.exists():
        raise BadInput(f"{options.video}: no such file or folder")
    if options.flights is not None and not options.flights.is_dir():
        raise BadInput(f"--flights {options.flights}: no such folder")
    if options.weights is not None:
        check_weights_file(options.weights)
    if options.map_image is not None and not options.map_image.exists():
        raise BadInput(f"{options.map_image}: no such file")
