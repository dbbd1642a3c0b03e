"""The render's warps on a torch device: what ``render.warp_yuv`` / ``render.warp_frame`` and the
rolling shutter's row warper (``rolling.RollingCorrection.warper``) compute, with
:mod:`mosaic_cli.geometry.warp`, the same frames within a grey level.

On a GPU each frame goes up from pinned host memory on a stream of its own, is warped on a
second and comes back on a third into pinned memory, so with two frames in flight
(:meth:`DeviceWarper.stream`) frame t+1's copy in overlaps frame t's warp and its copy out, and
the host writes frame t+2 into pinned memory meanwhile.  Nothing small is copied from pageable
memory (such a copy waits for its stream): the warp and the rows' corrections go up in the
frame's pinned parameters.  On the CPU the same torch code runs where it is called, so the tests
exercise it there; a renderer without a GPU keeps OpenCV's warps, an order of magnitude faster
there (one thread, a 1280x720 yuv420p frame: 2.5-2.8 ms against 25-30 ms, on the 2-core machine).

Imported only where a device renders (it needs torch).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from mosaic_cli.geometry.warp import YUV_BLACK, Border, remap, warp_perspective, warp_yuv420, yuv420_planes

if TYPE_CHECKING:
    from mosaic_cli.stabilize.rolling import RollingCorrection

# The render's --border names (render.BORDERS) as geometry.warp's; "reflect" is BORDER_REFLECT in both.
BORDER_NAMES: dict[str, Border] = {"black": "constant", "replicate": "replicate", "reflect": "reflect"}
RGB_BLACK = (0, 0, 0)


def rolling_maps(inverse: Tensor, table: Tensor, size: tuple[int, int]) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The rolling shutter's sampling maps of one frame, as ``RollingCorrection.warper`` builds them.

    inverse (3, 3) float64: the frame's warp inverted (output -> input pixels); table (h, 4): each
    input row's correction channels (``RollingCorrection.row_channels``, float32 values); size
    (w, h).  Each output point goes back through the warp, then its row's correction is undone to
    first order (``geometry.rolling_shutter.undo_row_correction``), on the chroma grid (pixel
    centres at luma 2 j + 0.5), in float64 as numpy does; the luma maps are those resized to
    full size as cv2.resize does (bilinear, half-pixel centres, edges extrapolated flat).
    Returns map_x, map_y (1, h, w) and the chroma ones (1, h/2, w/2) in chroma pixels, float32."""
    w, h = size
    cw, ch = w // 2, h // 2
    gx = (torch.arange(cw, dtype=torch.float64, device=inverse.device) * 2 + 0.5).view(1, cw)
    gy = (torch.arange(ch, dtype=torch.float64, device=inverse.device) * 2 + 0.5).view(ch, 1)
    m = inverse.to(torch.float64).reshape(9)
    z = m[6] * gx + m[7] * gy + m[8]
    x = (m[0] * gx + m[1] * gy + m[2]) / z
    y = (m[3] * gx + m[4] * gy + m[5]) / z
    r = torch.nan_to_num(y.round(), nan=0.0).clamp(0, h - 1).long()
    dx, dy, rot, sc = table.to(torch.float64)[r].unbind(-1)
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    u = (x - (dx + sc * (x - cx) - rot * (y - cy))).float()
    v = (y - (dy + rot * (x - cx) + sc * (y - cy))).float()
    full = F.interpolate(torch.stack([u, v])[None], size=(h, w), mode="bilinear", align_corners=False)[0]
    return full[0:1], full[1:2], ((u + 0.5) / 2 - 0.5)[None], ((v + 0.5) / 2 - 0.5)[None]


class Pending:
    """A frame submitted to a :class:`DeviceWarper`: :meth:`result` waits for it."""

    def __init__(self, out: Tensor, done: torch.cuda.Event | None = None):
        self._out, self._done = out, done

    def result(self) -> np.ndarray:
        """The warped frame: a numpy view of the (pinned, on a GPU) host buffer it was copied into."""
        if self._done is not None:
            self._done.synchronize()
        return self._out.numpy()


class DeviceWarper:
    """The render's warp of each frame, on ``device``.

    ``size`` (w, h) of the frames; ``border`` a render --border name (black, replicate, reflect).
    Frames are yuv420p (h * 3 // 2, w) uint8 arrays (the planes one after the other, even sizes)
    or RGB (h, w, 3); each output has its input's layout and size.  ``warp(frame, W)`` is
    ``render.warp_yuv`` / ``render.warp_frame``; ``row_warper(rolling)`` is
    ``rolling.warper``'s ``(frame, t, warp) -> frame``; :meth:`stream` keeps two frames in flight."""

    def __init__(self, device: torch.device | str, size: tuple[int, int], border: str = "black"):
        if border not in BORDER_NAMES:
            raise ValueError(f"border must be one of {', '.join(BORDER_NAMES)}, got {border!r}")
        self.device = torch.device(device)
        self.size = size
        self.border: Border = BORDER_NAMES[border]
        self.cuda = self.device.type == "cuda"
        # Copies in, warps and copies out each on a stream of their own (None on the CPU).
        self._up: Any = None
        self._work: Any = None
        self._down: Any = None
        if self.cuda:
            self._up, self._work, self._down = (torch.cuda.Stream(self.device) for _ in range(3))

    # --- one frame ---------------------------------------------------------------------------

    def warp(self, frame: np.ndarray, warp: np.ndarray) -> np.ndarray:
        """``frame`` resampled so that input pixel x lands on ``warp @ x`` (3, 3)."""
        return self.submit(frame, warp).result()

    def row_warper(self, rolling: RollingCorrection) -> Callable[[np.ndarray, int, np.ndarray], np.ndarray]:
        """``rolling.warper(border, black)``'s ``(frame, t, warp) -> frame``, on the device."""
        return lambda frame, t, warp: self.submit(frame, warp, rolling, t).result()

    def submit(self, frame: np.ndarray, warp: np.ndarray, rolling: RollingCorrection | None = None, t: int = 0) -> Pending:
        """Start warping ``frame`` by ``warp`` (3, 3), per row by ``rolling``'s correction of frame
        ``t`` when given; on a GPU this returns before the warp is done."""
        rgb = self._layout(frame)
        W = np.asarray(warp, dtype=np.float64)
        if rolling is None:
            params = W.reshape(-1)
        else:  # the inverse (taken here, in float64, as the CPU warper does) and each row's correction
            table = rolling.row_channels(t, np.arange(self.size[1], dtype=np.float64)).astype(np.float32)
            params = np.concatenate([np.linalg.inv(W).reshape(-1), table.reshape(-1)])
        frames, values = self._upload([frame], [params])
        with self._on(self._work):
            if rolling is None:
                out = self._warp_batch(frames, values[:, :9].reshape(-1, 3, 3), rgb)
            else:
                out = self._remap_rows(frames, values[0, :9].reshape(3, 3), values[0, 9:].reshape(-1, 4), rgb)
        return self._download(out)[0]

    # --- many frames -------------------------------------------------------------------------

    def stream(self, items: Iterable[tuple[Any, ...]], depth: int = 2) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """Each input frame with its warped frame, in order.  ``items``: the arguments of
        :meth:`submit` (``(frame, warp)`` or ``(frame, warp, rolling, t)``), taken ``depth`` ahead of
        the results: on a GPU frame t+1 is copied in while frame t is warped.  An input frame is
        copied to the device when it is taken, so the caller may reuse it then."""
        pending: deque[tuple[np.ndarray, Pending]] = deque()
        for item in items:
            pending.append((item[0], self.submit(*item)))
            if len(pending) >= depth:
                frame, result = pending.popleft()
                yield frame, result.result()
        while pending:
            frame, result = pending.popleft()
            yield frame, result.result()

    def warp_many(self, frames: Sequence[np.ndarray], warps: np.ndarray | Sequence[np.ndarray]) -> list[np.ndarray]:
        """:meth:`warp` of each frame by its warp (N, 3, 3), as one batch on the device: one copy
        each way, one launch per plane."""
        if not frames:
            return []
        rgb = self._layout(frames[0])
        W = np.asarray(warps, dtype=np.float64).reshape(-1, 3, 3)
        if len(W) != len(frames):
            raise ValueError(f"{len(frames)} frames but {len(W)} warps")
        batch, values = self._upload(frames, list(W))
        with self._on(self._work):
            out = self._warp_batch(batch, values[:, :9].reshape(-1, 3, 3), rgb)
        pendings = self._download(out)
        return [p.result() for p in pendings]

    # --- the work ----------------------------------------------------------------------------

    def _layout(self, frame: np.ndarray) -> bool:
        """True for an RGB frame, False for yuv420p; a frame of another shape is refused."""
        w, h = self.size
        if frame.shape == (h, w, 3):
            return True
        if frame.shape == (h * 3 // 2, w) and w % 2 == 0 and h % 2 == 0:
            return False
        raise ValueError(f"a {w}x{h} frame must be yuv420p ({h * 3 // 2}, {w}) or RGB ({h}, {w}, 3), got {frame.shape}")

    def _warp_batch(self, frames: Tensor, H: Tensor, rgb: bool) -> Tensor:
        if rgb:
            images = frames.permute(0, 3, 1, 2)
            return warp_perspective(images, H, self.size, self.border, list(RGB_BLACK)).permute(0, 2, 3, 1).contiguous()
        return warp_yuv420(frames, H, self.size, self.border, YUV_BLACK)

    def _remap_rows(self, frames: Tensor, inverse: Tensor, table: Tensor, rgb: bool) -> Tensor:
        u, v, cu, cv = rolling_maps(inverse, table, self.size)
        if rgb:
            return remap(frames.permute(0, 3, 1, 2), u, v, self.border, list(RGB_BLACK)).permute(0, 2, 3, 1).contiguous()
        out = torch.empty_like(frames)
        y, uv = yuv420_planes(frames, self.size)
        out_y, out_uv = yuv420_planes(out, self.size)
        out_y.copy_(remap(y, u, v, self.border, YUV_BLACK[0]))
        out_uv.copy_(remap(uv, cu, cv, self.border, list(YUV_BLACK[1:])))
        return out

    def _on(self, stream: Any) -> Any:
        return torch.cuda.stream(stream) if self.cuda else _Nothing()

    def _upload(self, frames: Sequence[np.ndarray], params: Sequence[np.ndarray]) -> tuple[Tensor, Tensor]:
        """The frames (N, ...) uint8 and their parameters (P, K) float64, each row one of
        ``params`` flattened and zero-padded, on the device (on a GPU, ready on the work stream)."""
        width = max(p.size for p in params)
        host_params = torch.zeros((len(params), width), dtype=torch.float64, pin_memory=self.cuda)
        params_np = host_params.numpy()
        for i, p in enumerate(params):
            params_np[i, :p.size] = p.reshape(-1)
        if not self.cuda:  # the frames as they are, no copy
            if len(frames) == 1 and frames[0].flags.writeable and frames[0].dtype == np.uint8:
                return torch.from_numpy(np.ascontiguousarray(frames[0]))[None], host_params
            return torch.from_numpy(np.stack(frames).astype(np.uint8, copy=False)), host_params
        host_frames = torch.empty((len(frames), *frames[0].shape), dtype=torch.uint8, pin_memory=True)
        frames_np = host_frames.numpy()
        for i, frame in enumerate(frames):
            frames_np[i] = frame
        with torch.cuda.stream(self._up):
            dev_frames = host_frames.to(self.device, non_blocking=True)
            dev_params = host_params.to(self.device, non_blocking=True)
        # Allocated on the copy stream, used on the work stream: keep their memory until it is done.
        self._work.wait_stream(self._up)
        dev_frames.record_stream(self._work)
        dev_params.record_stream(self._work)
        return dev_frames, dev_params

    def _download(self, out: Tensor) -> list[Pending]:
        """``out`` (N, ...) back on the host, one :class:`Pending` a frame."""
        if not self.cuda:
            return [Pending(o) for o in out]
        host = torch.empty(out.shape, dtype=out.dtype, pin_memory=True)
        self._down.wait_stream(self._work)
        out.record_stream(self._down)
        with torch.cuda.stream(self._down):
            host.copy_(out, non_blocking=True)
            done = torch.cuda.Event()
            done.record(self._down)
        return [Pending(h, done) for h in host]


class _Nothing:
    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc: object) -> None:
        return None
