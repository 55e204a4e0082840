"""Device column streams: SCAN_START, CALIBRATE, SCAN_ABORT, RESEND and the column worker.

A stream's worker thread pulls columns from the application's generator, keeps each
in the connection's ring of recent columns (for RESEND) and queues it on the
:class:`~cdma_lidar.protocol.transmit.Transmitter`; it sends replies and repairs
first and never runs ahead of the line. The application is called under the core's
``app_lock`` only.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

from cdma_lidar.protocol.columns import ColumnResult, column_payload_size, encode_column
from cdma_lidar.protocol.framing import Frame
from cdma_lidar.protocol.handlers import Reply, ack, nak
from cdma_lidar.protocol.messages import ErrorCode, MsgType, ScanEndReason, encode_payload
from cdma_lidar.protocol.transmit import FRESH, MAX_PIECES, REPAIR

if TYPE_CHECKING:
    from cdma_lidar.protocol.endpoint import DeviceEndpoint

__all__ = ["HANDLERS", "Stream", "finish", "step", "stop_stream"]

log = logging.getLogger(__name__)


@dataclass
class Stream:
    """One scan (or calibration: column = shot) of ``count`` columns from ``first``."""

    gen: Iterator[ColumnResult]
    frame: int
    first: int
    count: int
    calibration: bool
    produced: int = 0
    stopped: bool = False  # set (under the endpoint lock) when the stream ends for any reason
    finished: bool = False  # generator closed and app.abort() called if due (under app_lock)

    @property
    def next_column(self) -> int:
        return self.first + self.produced


def _start(ep: DeviceEndpoint, req: Frame, gen_factory: Callable[[], Iterator[ColumnResult]],
           frame: int, first: int, count: int, calibration: bool,
           after: list[Callable[[], None]]) -> Reply:
    if ep.stream is not None:
        return nak(ep, req, ErrorCode.BUSY, "", "a scan is running; abort it first")
    if ep.latest is not None:  # we hold app_lock: its generator is not running
        finish(ep, ep.latest)  # close it (and abort) before the app starts another stream
    info = ep.info or ep.app.info()
    ep.config = ep.app.get_config()
    peaks = int(ep.config.get("peaks", 1))
    size = column_payload_size(info.channels, peaks)
    if not ep.tx.fits(size):
        return nak(ep, req, ErrorCode.TOO_LARGE, "peaks",
                   f"a column of {info.channels} channels x {peaks} peaks ({size} bytes) "
                   f"needs more than {MAX_PIECES} fragments at max frame {ep.tx.max_frame}")
    st = Stream(iter(gen_factory()), frame, first, count, calibration)
    ep.stream = ep.latest = st
    ep.last_frame = frame
    ep.last_heartbeat = ep.clock()
    if ep.threads:
        worker = threading.Thread(target=_produce, args=(ep, st), daemon=True,
                                  name=f"cdma-lidar-frame-{frame}")
        after.append(worker.start)  # after the ACK is on the wire
    return ack(ep, req)


def _scan_start(ep: DeviceEndpoint, req: Frame, f: dict, after: list) -> Reply:
    return _start(ep, req, lambda: ep.app.scan(f["frame"], f["first_column"], f["columns"]),
                  f["frame"], f["first_column"], f["columns"], False, after)


def _calibrate(ep: DeviceEndpoint, req: Frame, f: dict, after: list) -> Reply:
    return _start(ep, req, lambda: ep.app.calibrate(f["frame"], f["shots"]),
                  f["frame"], 0, f["shots"], True, after)


def _scan_abort(ep: DeviceEndpoint, req: Frame, f: dict, after: list) -> Reply:
    if ep.stream is not None:
        after.append(lambda: stop_stream(ep, ScanEndReason.ABORTED))
    return ack(ep, req)


def _resend(ep: DeviceEndpoint, req: Frame, f: dict, after: list) -> Reply:
    frame, st = f["frame"], ep.stream
    if not f["columns"] and not f["fragments"]:
        return nak(ep, req, ErrorCode.MALFORMED, "columns", "name at least one column or fragment")
    wanted = [(f"columns[{k}]", col, None) for k, col in enumerate(f["columns"])] + \
        [(f"fragments[{k}]", p["column"], p["index"]) for k, p in enumerate(f["fragments"])]
    todo = []
    for name, col, piece in wanted:
        payload = ep.ring.get((frame, col))
        if payload is not None:
            todo.append(((frame, col), payload, None if piece is None else [piece]))
        elif not (st is not None and st.frame == frame and
                  st.next_column <= col < st.first + st.count):
            return nak(ep, req, ErrorCode.NOT_AVAILABLE, name,
                       f"column {col} of frame {frame} is no longer kept")

    def resend() -> None:
        for key, payload, only in todo:
            ep.count_column()
            ep.tx.send(REPAIR, MsgType.COLUMN_RESULT, payload, key=key, only=only)

    after.append(resend)
    return ack(ep, req)


HANDLERS = {MsgType.SCAN_START: _scan_start, MsgType.CALIBRATE: _calibrate,
            MsgType.SCAN_ABORT: _scan_abort, MsgType.RESEND: _resend}


def _produce(ep: DeviceEndpoint, st: Stream) -> None:
    """Worker thread of one stream."""
    while step(ep, st):
        pass


def step(ep: DeviceEndpoint, st: Stream) -> bool:
    """Pull one column from the app and send it; False once the stream is over and
    finished (its worker then exits). Never runs ahead of the line."""
    try:
        if not st.stopped and st.produced < st.count:
            reason = _next_column(ep, st)
            if reason is None:
                ep.tx.flush(FRESH, wait=True)  # replies and repairs first, then this column
                return True
        else:
            reason = ScanEndReason.COMPLETE
        with ep.lock:
            if not st.stopped:
                stop_stream(ep, reason)
        ep.tx.flush(FRESH, wait=True)
    except OSError as exc:  # the port went away under us
        log.warning("column stream of frame %d stops: %s", st.frame, exc)
        with ep.lock:
            if ep.stream is st:
                ep.stream = None
            st.stopped = True
    except Exception:  # e.g. a column the frame size cannot carry: end it, stay alive
        log.exception("column stream of frame %d failed", st.frame)
        with ep.lock:
            if not st.stopped:
                try:  # marks it stopped before it sends SCAN_END
                    stop_stream(ep, ScanEndReason.ERROR)
                except Exception:
                    log.exception("cannot send SCAN_END of frame %d", st.frame)
    with ep.core.app_lock:
        finish(ep, st)
    return False


def _next_column(ep: DeviceEndpoint, st: Stream) -> ScanEndReason | None:
    """Compute, keep and queue the next column; the reason to end the stream, or None."""
    try:
        with ep.core.app_lock:
            if st.stopped:
                return ScanEndReason.COMPLETE
            col = next(st.gen)
        if col.frame != st.frame or col.calibration != st.calibration:
            col = dataclasses.replace(col, frame=st.frame, calibration=st.calibration)
        payload = encode_column(col)
        if not ep.tx.fits(len(payload)):
            log.error("frame %d column %d: %d bytes need more than %d fragments at max frame "
                      "%d", st.frame, col.column, len(payload), MAX_PIECES, ep.tx.max_frame)
            return ScanEndReason.ERROR
    except StopIteration:
        log.warning("application ended frame %d after %d of %d columns", st.frame, st.produced,
                    st.count)
        return ScanEndReason.ERROR
    except Exception:
        log.exception("application failed during frame %d", st.frame)
        return ScanEndReason.ERROR
    with ep.lock:
        if st.stopped:
            return ScanEndReason.COMPLETE
        key = (st.frame, col.column)
        ep.ring[key] = payload
        ep.ring.move_to_end(key)
        while len(ep.ring) > ep.ring_columns:
            ep.ring.popitem(last=False)
        st.produced += 1
        ep.count_column()
        ep.tx.send(FRESH, MsgType.COLUMN_RESULT, payload, key=key)
        if st.produced >= st.count:
            # End the stream under the same lock that queued its last column: a
            # SCAN_START arriving right after must not find it still busy.
            stop_stream(ep, ScanEndReason.COMPLETE)
    return None


def finish(ep: DeviceEndpoint, st: Stream) -> None:
    """Close the generator of an ended stream; call ``app.abort()`` if it ended early.

    Caller holds app_lock. Runs once per stream: in its worker when it exits, or
    earlier in the next SCAN_START / CALIBRATE / HELLO, so the application never sees
    the clean-up of an old stream after it was asked for a new one.
    """
    if st.finished or not st.stopped:
        return
    st.finished = True
    try:
        close = getattr(st.gen, "close", None)
        if close is not None:
            close()
        if st.produced < st.count:
            ep.app.abort()
    except Exception:  # the device must not die on an application's clean-up
        log.exception("application failed while ending frame %d", st.frame)


def stop_stream(ep: DeviceEndpoint, reason: ScanEndReason, send_end: bool = True) -> None:
    """End the current stream (caller holds ``ep.lock``); its worker notices and exits."""
    st = ep.stream
    if st is None:
        return
    st.stopped = True
    ep.stream = None
    ep.last_next, ep.last_end = st.next_column, reason
    ep.core.touch(ep)  # idle time counts from the end of the stream
    if reason != ScanEndReason.COMPLETE:
        ep.tx.drop(FRESH)  # aborted: its queued columns need not go out (kept in the ring)
    if send_end:  # after the columns queued before it
        ep.tx.send(FRESH, MsgType.SCAN_END, encode_payload(MsgType.SCAN_END, {
            "frame": st.frame, "first_column": st.first, "columns": st.produced,
            "calibration": int(st.calibration), "reason": int(reason)}))
