"""Device column streams: SCAN_START, CALIBRATE, SCAN_ABORT, RESEND, and the measurement
engine that computes their columns (docs/protocol.md section 6.2).

:class:`Streams` owns one connection's streams: the running one, the ring of recent columns
(for RESEND) and what STATUS says of the last one. Between its reads the connection's loop
calls :meth:`Streams.collect` and :meth:`Streams.advance`: once the line has taken a
stream's last column the :class:`Engine` computes the next, so a stream never runs ahead of
the line.
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from typing import Any

from cdma_lidar.protocol.columns import ColumnResult, column_payload_size, encode_column
from cdma_lidar.protocol.framing import Frame
from cdma_lidar.protocol.messages import ErrorCode, MsgType, ScanEndReason, encode_payload
from cdma_lidar.protocol.transmit import FRESH, MAX_PIECES, REPAIR, Reply, Transmitter

__all__ = ["Engine", "Stream", "Streams"]

log = logging.getLogger(__name__)


class Engine:
    """The measurement engine of one device: runs the application's column steps and
    stream clean-ups one at a time, in the order submitted, on its own thread, which
    touches nothing but the application: a step cannot be bounded below the 50 ms in which
    the loops must answer (0.1-0.2 s for a column of paper-scene1 at averages 1024 and
    samples per chip 16 on 2 cores; the virtual board computes batches of seconds). The
    loops call the application only while the engine is :attr:`idle`. ``threaded=False``:
    each job runs at once in the caller (a test on a fake clock), otherwise the same code.
    """

    def __init__(self, threaded: bool = True) -> None:
        self.threaded = threaded
        self.last: Future | None = None  # the last job submitted
        self._jobs: queue.SimpleQueue | None = None  # the running thread's

    @property
    def idle(self) -> bool:
        """Every job submitted is done: the application may be called directly."""
        return self.last is None or self.last.done()

    def submit(self, fn: Callable[[], Any]) -> Future:
        """Run ``fn`` after the jobs before it (at once when not threaded); its future
        carries ``started``, when it was submitted (``time.monotonic``, s)."""
        job = self.last = Future()
        job.started = time.monotonic()  # type: ignore[attr-defined]
        if not self.threaded:
            _run(job, fn)
            return job
        if self._jobs is None:  # a daemon: a column never holds up the exit
            self._jobs = queue.SimpleQueue()
            threading.Thread(target=self._serve, args=(self._jobs,), daemon=True,
                             name="cdma-lidar-engine").start()
        self._jobs.put((job, fn))
        return job

    @staticmethod
    def _serve(jobs: queue.SimpleQueue) -> None:
        while (item := jobs.get()) is not None:
            _run(*item)

    def close(self) -> None:
        """Let the thread end after the jobs queued (a later job starts a new one)."""
        if self._jobs is not None:
            self._jobs.put(None)
            self._jobs = None


def _run(job: Future, fn: Callable[[], Any]) -> None:
    try:
        job.set_result(fn())
    except Exception as exc:  # the loop that collects the job decides
        job.set_exception(exc)


@dataclasses.dataclass
class Stream:
    """One scan (or calibration: column = shot) of ``count`` columns from ``first``."""

    config: dict[str, Any]  # the application's when it started (no CONFIG_SET while it runs)
    gen: Iterator[ColumnResult]
    frame: int
    first: int
    count: int
    calibration: bool
    produced: int = 0
    job: Future | None = None  # the column the engine computes, not yet collected

    @property
    def next_column(self) -> int:
        return self.first + self.produced


class Streams:
    """The streams of one connection (see the module docstring): ``app`` is called only
    while ``engine`` is idle, or by it; ``ring_columns`` recent columns are kept for RESEND;
    ``clock`` is monotonic (s); ``stopped()`` when a stream ends (idle time counts from then).
    """

    def __init__(self, app: Any, tx: Transmitter, engine: Engine, *, ring_columns: int,
                 clock: Callable[[], float], stopped: Callable[[], None]) -> None:
        self.app, self.tx, self.engine = app, tx, engine
        self.ring_columns, self.clock, self._stopped = ring_columns, clock, stopped
        self.stream: Stream | None = None  # the running one
        self.latest: Stream | None = None  # the last started, running or not
        self.last_end = ScanEndReason.COMPLETE  # SCAN_END reason of the last ended stream
        self.last_heartbeat = 0.0  # when the running stream's last HEARTBEAT went (s)
        #: Recent columns (frame, column) -> payload, for RESEND.
        self.ring: OrderedDict[tuple[int, int], bytes] = OrderedDict()

    def handlers(self) -> dict[MsgType, Callable[[Frame, dict], Reply]]:
        return {MsgType.SCAN_START: self._start, MsgType.CALIBRATE: self._start,
                MsgType.SCAN_ABORT: self._scan_abort, MsgType.RESEND: self._resend}

    def _start(self, req: Frame, f: dict) -> Reply:
        """SCAN_START or CALIBRATE (column = shot); the application is asked only when
        the stream is accepted."""
        if self.stream is not None:
            return self.tx.nak(req, ErrorCode.BUSY, "", "a scan is running; abort it first")
        channels = self.app.info().channels
        config = self.app.get_config()
        peaks = int(config.get("peaks", 1))
        size = column_payload_size(channels, peaks)
        if not self.tx.fits(size):
            return self.tx.nak(req, ErrorCode.TOO_LARGE, "peaks",
                               f"a column of {channels} channels x {peaks} peaks ({size} bytes) "
                               f"needs more than {MAX_PIECES} fragments at max frame "
                               f"{self.tx.max_frame}")
        frame, cal = f["frame"], req.msg_type == MsgType.CALIBRATE
        first, count = (0, f["shots"]) if cal else (f["first_column"], f["columns"])
        gen = self.app.calibrate(frame, count) if cal else self.app.scan(frame, first, count)
        self.stream = self.latest = Stream(config, iter(gen), frame, first, count, cal)
        self.last_heartbeat = self.clock()
        return self.tx.ack(req)

    def _scan_abort(self, req: Frame, f: dict) -> Reply:
        self.stop(ScanEndReason.ABORTED)  # its SCAN_END goes after the ACK (class FRESH)
        return self.tx.ack(req)

    def _resend(self, req: Frame, f: dict) -> Reply:
        frame, st = f["frame"], self.stream
        if not f["columns"] and not f["fragments"]:
            return self.tx.nak(req, ErrorCode.MALFORMED, "columns",
                               "name at least one column or fragment")
        wanted = [(f"columns[{k}]", col, -1) for k, col in enumerate(f["columns"])] + \
            [(f"fragments[{k}]", p["column"], p["index"]) for k, p in enumerate(f["fragments"])]
        for name, col, _ in wanted:  # all are kept or still to come, or none is sent
            if (frame, col) not in self.ring and not (st is not None and st.frame == frame and
                                                   st.next_column <= col < st.first + st.count):
                return self.tx.nak(req, ErrorCode.NOT_AVAILABLE, name,
                                   f"column {col} of frame {frame} is no longer kept")
        for _, col, piece in wanted:  # class REPAIR: after the ACK
            if (frame, col) in self.ring:
                self.tx.send(REPAIR, MsgType.COLUMN_RESULT, self.ring[frame, col],
                             key=(frame, col), only=[piece])
        return self.tx.ack(req)

    def _compute(self, st: Stream) -> tuple[int, bytes]:
        """The engine's step: the stream's next column, encoded."""
        col = next(st.gen)
        if col.frame != st.frame or col.calibration != st.calibration:
            col = dataclasses.replace(col, frame=st.frame, calibration=st.calibration)
        return col.column, encode_column(col)

    def collect(self) -> None:
        """Keep and queue the column the engine computed (if it is done)."""
        st = self.latest
        if st is None or st.job is None or not st.job.done():
            return
        job, st.job = st.job, None
        if st is not self.stream:
            return  # ended meanwhile: the column goes nowhere
        error = job.exception()
        column, payload = (0, b"") if error is not None else job.result()
        if error is not None or not self.tx.fits(len(payload)):
            if isinstance(error, StopIteration):
                log.warning("application ended frame %d after %d of %d columns", st.frame,
                            st.produced, st.count)
            elif error is not None:
                log.error("application failed during frame %d", st.frame, exc_info=error)
            else:
                log.error("frame %d column %d: %d bytes need more than %d fragments at max "
                          "frame %d", st.frame, column, len(payload), MAX_PIECES,
                          self.tx.max_frame)
            self.stop(ScanEndReason.ERROR)
            return
        key = (st.frame, column)
        self.ring[key] = payload
        self.ring.move_to_end(key)
        while len(self.ring) > self.ring_columns:
            self.ring.popitem(last=False)
        st.produced += 1
        self.tx.send(FRESH, MsgType.COLUMN_RESULT, payload, key=key)
        if st.produced >= st.count:
            self.stop(ScanEndReason.COMPLETE)

    def advance(self) -> None:
        """Hand the engine the running stream's next column once the line has taken the
        last one (and the engine is free)."""
        st = self.stream  # never complete here: collect stops it at its last column
        if st is not None and st.job is None and not self.tx.pending(FRESH) and \
                self.engine.idle:
            st.job = self.engine.submit(lambda: self._compute(st))

    def _finish(self, st: Stream) -> None:
        """The engine's clean-up of an ended stream: close its generator, and call
        ``app.abort()`` if it ended early."""
        try:
            getattr(st.gen, "close", lambda: None)()
            if st.produced < st.count:
                self.app.abort()
        except Exception:  # the device must not die on an application's clean-up
            log.exception("application failed while ending frame %d", st.frame)

    def stop(self, reason: ScanEndReason, send_end: bool = True) -> None:
        """End the current stream (if any) and hand its clean-up to the engine, behind
        the column in progress, so the application never sees it after a new request."""
        st = self.stream
        if st is None:
            return
        self.stream = None
        self.last_end = reason
        self._stopped()  # idle time counts from the end of the stream
        self.engine.submit(lambda: self._finish(st))
        if reason != ScanEndReason.COMPLETE:
            self.tx.drop(FRESH)  # aborted: its queued columns need not go (the ring keeps them)
        if send_end:  # after the columns queued before it
            self.tx.send(FRESH, MsgType.SCAN_END, encode_payload(MsgType.SCAN_END, {
                "frame": st.frame, "first_column": st.first, "columns": st.produced,
                "calibration": int(st.calibration), "reason": int(reason)}))
