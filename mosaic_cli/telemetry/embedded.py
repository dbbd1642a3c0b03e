"""Telemetry carried inside the video: a DJI SRT subtitle track or a MISB KLV data stream,
demuxed with the bundled ffmpeg."""

from __future__ import annotations

import re
import subprocess
from dataclasses import dataclass
from pathlib import Path

from mosaic_cli.errors import BadInput
from mosaic_cli.telemetry.klv import decode_stream, track_from_packets
from mosaic_cli.telemetry.srt import parse_srt_text
from mosaic_cli.telemetry.track import Track

_STREAM = re.compile(r"Stream #0:(\d+)(?:\[[^\]]*\])?(?:\([^)]*\))?: (Subtitle|Data): (\S+)(.*)")


@dataclass(frozen=True)
class EmbeddedStream:
    kind: str  # "srt" or "klv"
    index: int  # stream index in the file
    codec: str


def _ffmpeg() -> str:
    import imageio_ffmpeg

    return imageio_ffmpeg.get_ffmpeg_exe()


def _run(args: list[str], timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([_ffmpeg(), "-hide_banner", "-nostdin", *args], capture_output=True, timeout=timeout)


def find_streams(video: str | Path) -> list[EmbeddedStream]:
    """Subtitle and KLV data streams of ``video`` that may hold telemetry (none for an image folder)."""
    if Path(video).is_dir():
        return []
    result = _run(["-i", str(video)], timeout=60)
    found = []
    for m in _STREAM.finditer(result.stderr.decode("utf-8", "replace")):
        index, what, codec, rest = int(m.group(1)), m.group(2), m.group(3).rstrip(","), m.group(4)
        if what == "Subtitle" and codec in ("subrip", "srt", "mov_text", "text", "ass", "ssa", "webvtt"):
            found.append(EmbeddedStream("srt", index, codec))
        elif what == "Data" and (codec in ("klv", "bin_data") or "KLVA" in rest):
            # bin_data: a private stream (what ffmpeg makes of raw KLV it muxes); read if it holds ST 0601
            found.append(EmbeddedStream("klv", index, codec))
    return found


def read_embedded(video: str | Path, stream: EmbeddedStream) -> Track:
    source = f"{video} stream {stream.index}"
    if stream.kind == "srt":
        result = _run(["-v", "error", "-i", str(video), "-map", f"0:{stream.index}", "-f", "srt", "-"])
        if result.returncode != 0:
            raise BadInput(f"{source}: ffmpeg could not read the subtitle track")
        return parse_srt_text(result.stdout.decode("utf-8", "replace"), source)
    data = _run(["-v", "error", "-i", str(video), "-map", f"0:{stream.index}", "-c", "copy", "-f", "data", "-"])
    if data.returncode != 0:
        raise BadInput(f"{source}: ffmpeg could not read the KLV data stream")
    packets, dropped = decode_stream(data.stdout)
    times = _packet_times(video, stream.index, len(packets)) if not dropped else None
    track = track_from_packets(packets, source, times)
    if dropped:
        track.notes.append(f"{dropped} KLV packets failed their checksum and were dropped")
    return track


def _packet_times(video, index: int, expected: int) -> list[float] | None:
    """The container's timestamps (seconds from the video's start) of the data stream's
    packets, when there is one per KLV packet; else None (the packets' own clocks are used)."""
    result = _run(["-v", "error", "-i", str(video), "-map", f"0:{index}", "-c", "copy", "-f", "framecrc", "-"])
    text = result.stdout.decode("utf-8", "replace")
    base = re.search(r"#tb \d+: (\d+)/(\d+)", text)
    if result.returncode != 0 or base is None:
        return None
    tb = int(base.group(1)) / int(base.group(2))
    pts = []
    for line in text.splitlines():
        if line.startswith("#"):
            continue
        parts = [p.strip() for p in line.split(",")]
        if len(parts) >= 3 and parts[2].lstrip("-").isdigit():
            pts.append(int(parts[2]) * tb)
    if len(pts) != expected or len(set(pts)) != len(pts):
        return None
    first_video = _video_start(video)
    return [t - first_video for t in pts]


def _video_start(video) -> float:
    result = _run(["-v", "error", "-i", str(video), "-map", "0:v:0", "-c", "copy", "-frames:v", "1", "-f", "framecrc", "-"])
    text = result.stdout.decode("utf-8", "replace")
    base = re.search(r"#tb \d+: (\d+)/(\d+)", text)
    for line in text.splitlines():
        parts = [p.strip() for p in line.split(",")]
        if base and not line.startswith("#") and len(parts) >= 3 and parts[2].lstrip("-").isdigit():
            return int(parts[2]) * int(base.group(1)) / int(base.group(2))
    return 0.0
