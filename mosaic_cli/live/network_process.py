"""A live run's network in a process of its own, behind the estimator interface.

Loaded in the live process itself, torch's import (1.5 s of Python alone on this 2-core machine)
shares one interpreter lock with the stream's threads: beside a 720p stream it took 7 s, and ORB
tracked 210 of the first 299 pairs meanwhile (``python -m benchmarks live stabilize``).  In a
child process the import competes only for a core, the stream's threads never wait on it, and
the network's work afterwards runs beside theirs too.

The two processes speak over the child's standard input and output: each message is a JSON
header and raw bytes (a gray image, a mask), each framed by their two lengths.  No pickle.
"""

from __future__ import annotations

import json
import os
import signal
import struct
import subprocess
import sys
from types import SimpleNamespace
from typing import IO, Any

import numpy as np

from mosaic_cli.errors import BadInput, ProcessingError
from mosaic_cli.estimators.base import PairEstimate

_FRAME = struct.Struct("<II")  # header bytes, payload bytes
CLOSE_SECONDS = 2.0  # how long a closing child may take before it is killed
NICENESS = 10  # the child's, added to the live process's


def _send(stream: IO[bytes], header: dict, payload: bytes = b"") -> None:
    data = json.dumps(header).encode()
    stream.write(_FRAME.pack(len(data), len(payload)) + data + payload)
    stream.flush()


def _read_exactly(stream: IO[bytes], size: int) -> bytes:
    chunks, left = [], size
    while left:
        chunk = stream.read(left)
        if not chunk:
            raise EOFError
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def _receive(stream: IO[bytes]) -> tuple[dict, bytes]:
    header_size, payload_size = _FRAME.unpack(_read_exactly(stream, _FRAME.size))
    header = json.loads(_read_exactly(stream, header_size))
    return header, _read_exactly(stream, payload_size)


def _image(header: dict, payload: bytes) -> np.ndarray | None:
    if header.get("shape") is None:
        return None
    return np.frombuffer(payload, np.uint8).reshape(header["shape"]).copy()


def _estimates(items: list) -> list[PairEstimate]:
    return [PairEstimate(np.array(H, float).reshape(3, 3), float(confidence), path) for H, confidence, path in items]


class NetworkProcess:
    """:func:`~mosaic_cli.estimators.make_estimator` (``build``'s keyword arguments, checked by
    :func:`~mosaic_cli.estimators.plan_estimator` first) run in a child process.  Constructing
    it waits until the network has loaded there: call it on a thread of its own
    (:func:`~.loading.built_beside`).  Its error, if it cannot load, is raised here, in one line."""

    def __init__(self, build: dict[str, Any], wait: bool = True):
        # The child ignores Ctrl-C and SIGTERM (sent to its process group by a terminal or by
        # `timeout`): the live command decides what a signal means (the first ends the stream
        # as its end would) and closes the child's input, which ends it.
        self._child = subprocess.Popen([sys.executable, "-m", "mosaic_cli.live.network_process", json.dumps(build)],
                                       stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        self.loaded = False
        if wait:
            self.wait_loaded()

    def wait_loaded(self) -> NetworkProcess:
        """Wait until the network has loaded in the child (``wait=False``: on a thread of its own)."""
        ready = self._reply()[0]
        self.name: str = ready["name"]
        self.input_width: int = ready["input_width"]
        self.config = SimpleNamespace(chunk=ready["chunk"])
        self.loaded = True
        return self

    def set_mask(self, use: np.ndarray | None) -> None:
        self._ask(*_image_message("mask", use))

    def reset(self, full_size: tuple[int, int]) -> None:
        self._ask({"op": "reset", "size": [int(full_size[0]), int(full_size[1])]})

    def feed(self, gray: np.ndarray) -> list[PairEstimate]:
        return _estimates(self._ask(*_image_message("feed", gray))[0]["estimates"])

    def finish(self) -> list[PairEstimate]:
        return _estimates(self._ask({"op": "finish"})[0]["estimates"])

    def close(self) -> None:
        """End the child: its input closed, then killed if it has not ended within
        :data:`CLOSE_SECONDS`; killed at once while it still loads (a stream that ended first
        does not wait for torch's import)."""
        if not self.loaded:
            self._child.kill()
        try:
            assert self._child.stdin is not None
            self._child.stdin.close()
        except OSError:
            pass
        try:
            self._child.wait(CLOSE_SECONDS)
        except subprocess.TimeoutExpired:
            self._child.kill()
            self._child.wait()

    def _ask(self, header: dict, payload: bytes = b"") -> tuple[dict, bytes]:
        assert self._child.stdin is not None
        try:
            _send(self._child.stdin, header, payload)
        except OSError:
            pass  # the child has ended: its reply says so
        return self._reply()

    def _reply(self) -> tuple[dict, bytes]:
        assert self._child.stdout is not None
        try:
            reply = _receive(self._child.stdout)
        except (EOFError, OSError):
            self.close()
            raise ProcessingError(f"the network's process ended (exit status {self._child.returncode})") from None
        if "error" in reply[0]:
            self.close()
            raise (BadInput if reply[0].get("bad_input") else ProcessingError)(reply[0]["error"])
        return reply


def _image_message(op: str, image: np.ndarray | None) -> tuple[dict, bytes]:
    if image is None:
        return {"op": op, "shape": None}, b""
    image = np.ascontiguousarray(image, np.uint8)
    return {"op": op, "shape": list(image.shape)}, image.tobytes()


def _serve(build: dict[str, Any], requests: IO[bytes], replies: IO[bytes]) -> None:
    """The child's side: build the estimator, say so, then answer each request until the input ends."""
    from mosaic_cli.errors import MosaicError
    from mosaic_cli.estimators import make_estimator

    def said(exc: BaseException) -> dict:
        return {"error": str(exc) if isinstance(exc, MosaicError) else f"{type(exc).__name__}: {exc}",
                "bad_input": isinstance(exc, BadInput)}

    try:
        estimator = make_estimator(**build)
    except Exception as exc:  # noqa: BLE001 - told to the live process, which raises it there
        _send(replies, said(exc))
        return
    chunk = getattr(getattr(estimator, "config", None), "chunk", 1)
    _send(replies, {"name": estimator.name, "input_width": estimator.input_width, "chunk": chunk})
    with estimator:
        while True:
            try:
                header, payload = _receive(requests)
            except EOFError:
                return
            try:
                op = header["op"]
                if op == "mask":
                    estimator.set_mask(_image(header, payload))
                    _send(replies, {})
                elif op == "reset":
                    estimator.reset(tuple(header["size"]))
                    _send(replies, {})
                else:
                    made = estimator.feed(_image(header, payload)) if op == "feed" else estimator.finish()
                    _send(replies, {"estimates": [[e.H.ravel().tolist(), e.confidence, e.path] for e in made]})
            except Exception as exc:  # noqa: BLE001 - see above
                _send(replies, said(exc))
                return


def main() -> None:
    # Below the live process's stages in the CPU's queue: on a machine with no core to spare,
    # the network's load (seconds of torch's import) waits rather than the frames in flight,
    # which ORB tracks meanwhile.
    os.nice(NICENESS)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    # The replies go out on the standard output as it was; anything printed goes to stderr.
    replies = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    _serve(json.loads(sys.argv[1]), sys.stdin.buffer, replies)


if __name__ == "__main__":
    main()
