"""Items made on a thread of their own, a few ahead of the reader: the PyAV decoder's frames
(:mod:`.pyav_decoder`), the stabiliser's render's."""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterator

READ_AHEAD = 4  # frames the PyAV decoder's thread may decode before they are read (a 4K RGB frame: 25 MB)


class ReadAhead:
    """The items of ``source`` (an iterator) made on a thread of its own, at most ``depth`` of them
    ahead of the reader; an error raised making them is raised to the reader, in its turn.
    :meth:`stop` ends the thread (and closes ``source``) whether or not it was read to the end."""

    _END = object()

    def __init__(self, source: Iterator, depth: int):
        self._queue: queue.Queue = queue.Queue(max(1, depth))
        self._stop = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, args=(source,), name="mosaic-decode", daemon=True)
        self._thread.start()

    def _run(self, source: Iterator) -> None:
        try:
            for item in source:
                if not self._put(item):
                    return
        except BaseException as exc:  # noqa: BLE001 - handed to the reader, who raises it
            self._error = exc
        finally:
            close = getattr(source, "close", None)
            if close is not None:
                close()
            self._put(self._END)

    def _put(self, item: object) -> bool:
        """Queue ``item``, waiting for room; False once stopped."""
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def __iter__(self) -> Iterator:
        while True:
            item = self._queue.get()
            if item is self._END:
                if self._error is not None:
                    raise self._error
                return
            yield item

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join()
