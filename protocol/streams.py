"""Device column streams: SCAN_START, CALIBRATE, SCAN_ABORT, RESEND and the column worker.

:class:`Streams` owns one connection's streams: the running one, the ring of recent
columns (for RESEND) and what STATUS says of the last one. A stream's worker thread
pulls columns from the application's generator, keeps each in the ring and queues it
on the :class:`~cdma_lidar.protocol.transmit.Transmitter`; it sends replies and
repairs first and never runs ahead of the line. The application is called under the
core's ``app_lock`` only.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from collections import OrderedDict
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

from cdma_lidar.protocol.columns import ColumnResult, column_payload_size, encode_column
from cdma_lidar.protocol.framing import Frame
from cdma_lidar.protocol.messages import ErrorCode, MsgType, ScanEndReason, encode_payload
from cdma_lidar.protocol.transmit import FRESH, MAX_PIECES, REPAIR, Reply, Transmitter

__all__ = ["Stream", "Streams"]

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


class Streams:
    """The streams of one connection (see the module docstring).

    Args:
        app: the device application (called under ``app_lock`` only).
        tx: the connection's transmitter.
        app_lock: the core's lock around every call into the application.
        lock: the connection's lock, held while stream state changes (taken after
            ``app_lock``, never before).
        ring_columns: recent columns kept for RESEND.
        threads: start a worker thread per stream; False: the owner calls :meth:`step`.
        clock: monotonic clock (s).
        counted: called for every COLUMN_RESULT queued (new or resent).
        stopped: called when a stream ends (its idle time counts from then).
    """

    def __init__(self, app: Any, tx: Transmitter, app_lock: Any, lock: Any, *,
                 ring_columns: int, threads: bool, clock: Callable[[], float],
                 counted: Callable[[], None], stopped: Callable[[], None]) -> None:
        self.app, self.tx, self.app_lock, self.lock = app, tx, app_lock, lock
        self.ring_columns, self.threads, self.clock = ring_columns, threads, clock
        self._counted, self._stopped = counted, stopped
        self.stream: Stream | None = None
        self.latest: Stream | None = None  # the last stream started, running or not
        self.config: dict[str, Any] | None = None  # the app's config when it started
        self.last_frame = self.last_next = 0
        self.last_end = ScanEndReason.COMPLETE
        self.last_heartbeat = 0.0  # when the running stream's last HEARTBEAT went (s)
        #: Recent columns (frame, column) -> payload, for RESEND.
        self.ring: OrderedDict[tuple[int, int], bytes] = OrderedDict()

    def handlers(self) -> dict[MsgType, Callable[[Frame, dict, list], Reply]]:
        return {MsgType.SCAN_START: self._scan_start, MsgType.CALIBRATE: self._calibrate,
                MsgType.SCAN_ABORT: self._scan_abort, MsgType.RESEND: self._resend}

    def _start(self, req: Frame, gen_factory: Callable[[], Iterator[ColumnResult]],
               frame: int, first: int, count: int, calibration: bool,
               after: list[Callable[[], None]]) -> Reply:
        if self.stream is not None:
            return self.tx.nak(req, ErrorCode.BUSY, "", "a scan is running; abort it first")
        if self.latest is not None:  # we hold app_lock: its generator is not running
            self.finish(self.latest)  # close it (and abort) before the app starts another
        channels = self.app.info().channels
        self.config = self.app.get_config()
        peaks = int(self.config.get("peaks", 1))
        size = column_payload_size(channels, peaks)
        if not self.tx.fits(size):
            return self.tx.nak(req, ErrorCode.TOO_LARGE, "peaks",
                               f"a column of {channels} channels x {peaks} peaks ({size} bytes) "
                               f"needs more than {MAX_PIECES} fragments at max frame "
                               f"{self.tx.max_frame}")
        st = Stream(iter(gen_factory()), frame, first, count, calibration)
        self.stream = self.latest = st
        self.last_frame = frame
        self.last_heartbeat = self.clock()
        if self.threads:
            worker = threading.Thread(target=self._produce, args=(st,), daemon=True,
                                      name=f"cdma-lidar-frame-{frame}")
            after.append(worker.start)  # after the ACK is on the wire
        return self.tx.ack(req)

    def _scan_start(self, req: Frame, f: dict, after: list) -> Reply:
        return self._start(req, lambda: self.app.scan(f["frame"], f["first_column"], f["columns"]),
                      f["frame"], f["first_column"], f["columns"], False, after)

    def _calibrate(self, req: Frame, f: dict, after: list) -> Reply:
        return self._start(req, lambda: self.app.calibrate(f["frame"], f["shots"]),
                      f["frame"], 0, f["shots"], True, after)

    def _scan_abort(self, req: Frame, f: dict, after: list) -> Reply:
        if self.stream is not None:
            after.append(lambda: self.stop(ScanEndReason.ABORTED))
        return self.tx.ack(req)

    def _resend(self, req: Frame, f: dict, after: list) -> Reply:
        frame, st = f["frame"], self.stream
        if not f["columns"] and not f["fragments"]:
            return self.tx.nak(req, ErrorCode.MALFORMED, "columns",
                               "name at least one column or fragment")
        wanted = [(f"columns[{k}]", col, None) for k, col in enumerate(f["columns"])] + \
            [(f"fragments[{k}]", p["column"], p["index"]) for k, p in enumerate(f["fragments"])]
        todo = []
        for name, col, piece in wanted:
            payload = self.ring.get((frame, col))
            if payload is not None:
                todo.append(((frame, col), payload, None if piece is None else [piece]))
            elif not (st is not None and st.frame == frame and
                      st.next_column <= col < st.first + st.count):
                return self.tx.nak(req, ErrorCode.NOT_AVAILABLE, name,
                                   f"column {col} of frame {frame} is no longer kept")

        def resend() -> None:
            for key, payload, only in todo:
                self._counted()
                self.tx.send(REPAIR, MsgType.COLUMN_RESULT, payload, key=key, only=only)

        after.append(resend)
        return self.tx.ack(req)

    def _produce(self, st: Stream) -> None:
        """Worker thread of one stream."""
        while self.step(st):
            pass

    def step(self, st: Stream) -> bool:
        """Pull one column from the app and send it; False once the stream is over and
        finished (its worker then exits). Never runs ahead of the line."""
        try:
            if not st.stopped and st.produced < st.count:
                reason = self._next_column(st)
                if reason is None:
                    self.tx.flush(FRESH, wait=True)  # replies and repairs first, then this one
                    return True
            else:
                reason = ScanEndReason.COMPLETE
            with self.lock:
                if not st.stopped:
                    self.stop(reason)
            self.tx.flush(FRESH, wait=True)
        except OSError as exc:  # the port went away under us
            log.warning("column stream of frame %d stops: %s", st.frame, exc)
            with self.lock:
                if self.stream is st:
                    self.stream = None
                st.stopped = True
        except Exception:  # e.g. a column the frame size cannot carry: end it, stay alive
            log.exception("column stream of frame %d failed", st.frame)
            with self.lock:
                if not st.stopped:
                    try:  # marks it stopped before it sends SCAN_END
                        self.stop(ScanEndReason.ERROR)
                    except Exception:
                        log.exception("cannot send SCAN_END of frame %d", st.frame)
        with self.app_lock:
            self.finish(st)
        return False

    def _next_column(self, st: Stream) -> ScanEndReason | None:
        """Compute, keep and queue the next column; the reason to end the stream, or None."""
        try:
            with self.app_lock:
                if st.stopped:
                    return ScanEndReason.COMPLETE
                col = next(st.gen)
            if col.frame != st.frame or col.calibration != st.calibration:
                col = dataclasses.replace(col, frame=st.frame, calibration=st.calibration)
            payload = encode_column(col)
            if not self.tx.fits(len(payload)):
                log.error("frame %d column %d: %d bytes need more than %d fragments at max "
                          "frame %d", st.frame, col.column, len(payload), MAX_PIECES,
                          self.tx.max_frame)
                return ScanEndReason.ERROR
        except StopIteration:
            log.warning("application ended frame %d after %d of %d columns", st.frame,
                        st.produced, st.count)
            return ScanEndReason.ERROR
        except Exception:
            log.exception("application failed during frame %d", st.frame)
            return ScanEndReason.ERROR
        with self.lock:
            if st.stopped:
                return ScanEndReason.COMPLETE
            key = (st.frame, col.column)
            self.ring[key] = payload
            self.ring.move_to_end(key)
            while len(self.ring) > self.ring_columns:
                self.ring.popitem(last=False)
            st.produced += 1
            self._counted()
            self.tx.send(FRESH, MsgType.COLUMN_RESULT, payload, key=key)
            if st.produced >= st.count:
                # End the stream under the same lock that queued its last column: a
                # SCAN_START arriving right after must not find it still busy.
                self.stop(ScanEndReason.COMPLETE)
        return None

    def finish(self, st: Stream) -> None:
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
                self.app.abort()
        except Exception:  # the device must not die on an application's clean-up
            log.exception("application failed while ending frame %d", st.frame)

    def stop(self, reason: ScanEndReason, send_end: bool = True) -> None:
        """End the current stream (caller holds ``self.lock``); its worker notices and exits."""
        st = self.stream
        if st is None:
            return
        st.stopped = True
        self.stream = None
        self.last_next, self.last_end = st.next_column, reason
        self._stopped()  # idle time counts from the end of the stream
        if reason != ScanEndReason.COMPLETE:
            self.tx.drop(FRESH)  # aborted: its queued columns need not go (the ring keeps them)
        if send_end:  # after the columns queued before it
            self.tx.send(FRESH, MsgType.SCAN_END, encode_payload(MsgType.SCAN_END, {
                "frame": st.frame, "first_column": st.first, "columns": st.produced,
                "calibration": int(st.calibration), "reason": int(reason)}))
