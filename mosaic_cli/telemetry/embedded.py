"""Telemetry carried inside the video: a DJI SRT subtitle track or a MISB KLV data stream.

The streams are found in the video's probe (:func:`mosaic_cli.video.probe`, done once per
command); a KLV stream's packets and their timestamps are demuxed in-process with PyAV, a
subtitle track is converted to SRT text by the bundled ffmpeg."""

from __future__ import annotations

import subprocess
from dataclasses import dataclass
from pathlib import Path

import av

from mosaic_cli.errors import BadInput
from mosaic_cli.telemetry.flight_log import FlightLog
from mosaic_cli.telemetry.klv import decode_stream, log_from_packets
from mosaic_cli.telemetry.srt import parse_srt_text
from mosaic_cli.video.reader import VideoInfo, probe

# Text subtitle codecs (libav's names) ffmpeg converts to SRT; a DJI track is one of these.
SUBTITLE_CODECS = ("subrip", "srt", "mov_text", "text", "ass", "ssa", "webvtt")


@dataclass(frozen=True)
class EmbeddedStream:
    kind: str  # "srt" or "klv"
    index: int  # stream index in the file
    codec: str


def find_streams(video: str | Path, info: VideoInfo | None = None) -> list[EmbeddedStream]:
    """Subtitle and KLV data streams of ``video`` that may hold telemetry (none for an image
    folder).  ``info``: the video's probe, when the caller has it."""
    if Path(video).is_dir():
        return []
    info = info if info is not None else probe(video)
    found = []
    for stream in info.streams:
        if stream.kind == "subtitle" and stream.codec in SUBTITLE_CODECS:
            found.append(EmbeddedStream("srt", stream.index, stream.codec))
        elif stream.kind == "data" and (stream.codec in ("klv", "bin_data") or stream.tag == "KLVA"):
            # bin_data: a private stream (what ffmpeg makes of raw KLV it muxes); read if it holds ST 0601
            found.append(EmbeddedStream("klv", stream.index, stream.codec))
    return found


def read_embedded(video: str | Path, stream: EmbeddedStream) -> FlightLog:
    source = f"{video} stream {stream.index}"
    if stream.kind == "srt":
        import imageio_ffmpeg

        result = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-nostdin", "-v", "error", "-i", str(video),
                                 "-map", f"0:{stream.index}", "-f", "srt", "-"], capture_output=True, timeout=300)
        if result.returncode != 0:
            raise BadInput(f"{source}: ffmpeg could not read the subtitle track")
        return parse_srt_text(result.stdout.decode("utf-8", "replace"), source)
    payloads, stamps = _demux(video, stream.index, source)
    packets, dropped = decode_stream(b"".join(payloads))
    # The container's timestamps when there is one per KLV packet; else the packets' own clocks.
    times = stamps if not dropped and len(stamps) == len(packets) and len(set(stamps)) == len(stamps) else None
    track = log_from_packets(packets, source, times)
    if dropped:
        track.notes.append(f"{dropped} KLV packets failed their checksum and were dropped")
    return track


def _demux(video, index: int, source: str) -> tuple[list[bytes], list[float]]:
    """The payloads of stream ``index``'s packets, and their timestamps in seconds from the
    video's start (empty when any packet has none)."""
    try:
        with av.open(str(video), metadata_errors="replace") as container:
            data = container.streams[index]
            pictures = container.streams.video
            first_video = 0.0
            if pictures and pictures[0].start_time is not None and pictures[0].time_base:
                first_video = float(pictures[0].start_time * pictures[0].time_base)
            payloads, stamps = [], []
            timed = True
            for packet in container.demux(data):
                if packet.size == 0:
                    continue  # the demuxer's end-of-stream marker
                payloads.append(bytes(packet))
                if packet.pts is None or packet.time_base is None:
                    timed = False
                else:
                    stamps.append(float(packet.pts * packet.time_base) - first_video)
    except (av.error.FFmpegError, OSError, ValueError, IndexError):
        raise BadInput(f"{source}: ffmpeg could not read the KLV data stream") from None
    return payloads, stamps if timed else []
