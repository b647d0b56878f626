"""AEDAT4 recordings (iniVation DV software, e.g. a DAVIS 346C) through the `aedat` package.

Polarity events are kept; the APS frames are kept on request (`load_aedat4(keep_frames=True)`,
`iter_aedat4_frames`: chequerboard calibration, `fastenerf import --frames`) and otherwise
looked at only to tell a colour sensor from a mono one; IMU samples and triggers are skipped.
DV timestamps are absolute µs since the Unix epoch; frames can start before the first event
and the header's `tsOffset` is not the start of the data, so the time origin is the first
event *kept*: the returned stream starts at t = 0 and `Recording.t_origin_us` maps it back to
the file's clock.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import InputError
from ..events import EventStream


@dataclass(frozen=True)
class Frame:
    """One APS frame. t_us: DV clock (µs since the epoch), the middle of the exposure (the
    frame's own timestamp where the file gives no exposure); pixels: (H, W) uint8 for "L",
    uint16 for "I;16", (H, W, C) in the channel order `format` names for colour."""

    t_us: int
    pixels: np.ndarray
    format: str

    def rgb(self) -> np.ndarray:
        """Pixels ready for a PNG: gray (H, W) as stored, colour reordered to RGB(A)."""
        f, px = self.format, self.pixels
        if f.startswith("BGR") and px.ndim == 3:
            return np.concatenate([px[..., 2::-1], px[..., 3:]], -1)
        return px


@dataclass(frozen=True)
class Recording:
    """What one AEDAT4 file holds, as far as fastenerf uses it.

    events: time-shifted stream (t = 0 at the first kept event); t_origin_us: absolute DV
    time (µs since the epoch) of that event; frame_formats: pixel formats of the frame
    stream(s) ("L" gray, "RGB"/"BGR"… colour), empty when the file has no frames.
    """

    events: EventStream
    t_origin_us: int
    frame_formats: tuple[str, ...]
    frames: tuple[Frame, ...] = ()

    @property
    def color_frames(self) -> bool:
        """True when the frames are colour (a DAVIS 346C with demosaicing on)."""
        return any(f not in ("L", "I;16") for f in self.frame_formats)


def load_aedat4(
    path: str | Path,
    t_crop_us: tuple[int, int] | None = None,
    expect_size: tuple[int, int] | None = None,
    keep_frames: bool = False,
) -> Recording:
    """Decode the polarity events of an AEDAT4 file.

    t_crop_us: keep events with T0 <= t - t_first < T1, in µs after the file's first event
    (a turntable capture is cropped to whole revolutions); expect_size: (width, height) the
    sensor must have, e.g. (346, 260) for a DAVIS 346; keep_frames: also return the APS frames
    (all of them: the crop applies to events only). Every problem raises one-line
    `InputError` naming the file.
    """
    src = str(path)
    if t_crop_us is not None:
        c0, c1 = (int(v) for v in t_crop_us)
        if c0 < 0 or c1 <= c0:
            raise InputError(f"{src}: crop [{c0}, {c1}) µs must satisfy 0 <= T0 < T1")
    decoder, streams = _open(path)
    ev_ids = [i for i, s in streams.items() if s.get("type") == "events"]
    if not ev_ids:
        kinds = ", ".join(sorted({str(s.get("type")) for s in streams.values()})) or "nothing"
        raise InputError(f"{src}: no event stream in this AEDAT4 file (it holds {kinds})")
    if len(ev_ids) > 1:
        raise InputError(f"{src}: {len(ev_ids)} event streams; only single-sensor files are read")
    sid = ev_ids[0]
    width, height = int(streams[sid]["width"]), int(streams[sid]["height"])
    if expect_size is not None and (width, height) != tuple(expect_size):
        raise InputError(
            f"{src}: sensor is {width}x{height}, expected {expect_size[0]}x{expect_size[1]}"
        )

    parts: list[np.ndarray] = []
    formats: set[str] = set()
    frames: list[Frame] = []
    t_first = None
    try:
        for packet in decoder:
            if "frame" in packet:
                formats.add(str(packet["frame"]["format"]))
                if keep_frames:
                    frames.append(_frame(packet["frame"]))
                continue
            if "events" not in packet or packet["stream_id"] != sid:
                continue
            ev = packet["events"]
            if len(ev) == 0:
                continue
            if t_first is None:
                t_first = int(ev["t"][0])
            if t_crop_us is not None:
                rel = ev["t"] - np.uint64(t_first)
                if rel[0] >= c1:
                    break  # DV timestamps never decrease: nothing later can be kept
                ev = ev[(rel >= c0) & (rel < c1)]
            parts.append(ev)
    except RuntimeError as e:
        raise InputError(f"{src}: truncated or corrupt AEDAT4 file ({e})") from None

    ev = np.concatenate(parts) if parts else np.zeros(0, dtype=[("t", "<u8")])
    if len(ev) == 0:
        what = "no events" if t_first is None else f"no events in the crop {list(t_crop_us)} µs"
        raise InputError(f"{src}: the event stream has {what}")
    t_abs = ev["t"].astype(np.int64)
    origin = int(t_abs[0])
    stream = EventStream.from_arrays(
        ev["x"], ev["y"], t_abs - origin, ev["on"], width, height, source=src
    )
    return Recording(stream, origin, tuple(sorted(formats)), tuple(frames))


def iter_aedat4_frames(path: str | Path) -> Iterator[Frame]:
    """The APS frames of an AEDAT4 file, in file order (DV timestamps never decrease).

    One-line `InputError` when the file cannot be read or has no frame stream (a recording
    made with frames off); a frame stream with no frames yields nothing.
    """
    src = str(path)
    decoder, streams = _open(path)
    if not any(s.get("type") == "frame" for s in streams.values()):
        kinds = ", ".join(sorted({str(s.get("type")) for s in streams.values()})) or "nothing"
        raise InputError(
            f"{src}: no frame stream in this AEDAT4 file (it holds {kinds}); record with "
            "the APS frames on"
        )
    try:
        for packet in decoder:
            if "frame" in packet:
                yield _frame(packet["frame"])
    except RuntimeError as e:
        raise InputError(f"{src}: truncated or corrupt AEDAT4 file ({e})") from None


def _open(path: str | Path):
    """(aedat.Decoder, its id -> stream description) with one-line errors."""
    import aedat

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such AEDAT4 file")
    try:
        decoder = aedat.Decoder(path)
        return decoder, decoder.id_to_stream()
    except RuntimeError as e:
        raise InputError(f"{path}: not a readable AEDAT4 file ({e})") from None


def _frame(f: dict) -> Frame:
    b, e = int(f.get("exposure_begin_t", 0)), int(f.get("exposure_end_t", 0))
    # The middle of the exposure is when the (turning) scene was seen.
    t = (b + e) // 2 if 0 < b <= e else int(f["t"])
    return Frame(t, np.asarray(f["pixels"]), str(f["format"]))


def read_aedat4(
    path: str | Path,
    t_crop_us: tuple[int, int] | None = None,
    expect_size: tuple[int, int] | None = None,
) -> EventStream:
    """The polarity events of an AEDAT4 file, t = 0 at the first kept event (µs).

    See `load_aedat4` for the arguments; this drops the file's absolute time origin.
    """
    return load_aedat4(path, t_crop_us, expect_size).events
