"""Host end of the link: :class:`HostLink`, the requests a host makes and its scans.

A scan repairs its gaps, and gives up, as docs/protocol.md section 6.2 says.
"""

from __future__ import annotations

import contextlib
import logging
from collections import deque
from collections.abc import Iterator
from typing import Any, Self

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdma_lidar.checks import is_int
from cdma_lidar.errors import DeviceError, FieldError, LinkError, LinkTimeout, out_of_range
from cdma_lidar.protocol.columns import ColumnResult
from cdma_lidar.protocol.config_keys import config_key, decode_config, encode_config
from cdma_lidar.protocol.framing import frame_size
from cdma_lidar.protocol.messages import (
    MAX_PIECES,
    CaptureKind,
    ErrorCode,
    MsgType,
    State,
    Status,
    piece_room,
)
from cdma_lidar.protocol.reassembly import ColumnReassembler, StreamEnded
from cdma_lidar.protocol.requests import DIAG_NO_ANSWER, Requests, SessionLost, diagnose
from cdma_lidar.protocol.trust import ColumnChecker, DeviceLied, check_config

__all__ = ["PATIENCE", "HostLink", "ScanStalled", "SessionLost", "StreamEnded", "patience_s",
           "power_codes"]

log = logging.getLogger(__name__)

#: Column times (STATUS.column_time_ms) a stream may go without progress, beyond the floor.
PATIENCE = 3.0


def patience_s(floor_s: float, status: Status | None) -> float:
    """The no-progress limit of a stream (s): ``floor_s`` (latency, the host's own work)
    plus :data:`PATIENCE` column times as ``status`` (the last HEARTBEAT) states, so a column
    of minutes is waited for and a device heartbeating without moving is still caught."""
    return floor_s + (PATIENCE * (status.column_time_ms * 1e-3) if status is not None else 0.0)


class ScanStalled(StreamEnded, LinkTimeout):
    """The device kept the stream alive (heartbeats, STATUS "scanning") but nothing moved
    for the no-progress limit (:func:`patience_s`)."""

    def __init__(self, message: str, *, frame: int, next_column: int) -> None:
        StreamEnded.__init__(self, message, frame=frame, next_column=next_column, reason=None)
        self.diagnosis = DIAG_NO_ANSWER


def power_codes(matrix: ArrayLike) -> NDArray[np.int64]:
    """A (channels, columns) power matrix as the wire's codes (1/65535 of the per-pixel
    maximum, 0..65535), checked: integers as they are, fractions 0..1 rounded to the grid."""
    m = np.asarray(matrix)
    if m.ndim != 2 or m.size == 0:
        raise out_of_range("power", "a non-empty (channels, columns) matrix",
                           f"shape {m.shape}", FieldError)
    if m.dtype.kind == "f":
        if not np.isfinite(m).all() or m.min() < 0 or m.max() > 1:
            raise out_of_range("power", "fractions from 0 to 1", m, FieldError)
        return np.rint(m * 65535.0).astype(np.int64)
    if m.dtype.kind not in "iu" or m.min() < 0 or m.max() > 65535:
        raise out_of_range("power", "integers from 0 to 65535", m, FieldError)
    return m.astype(np.int64)


class HostLink(Requests):
    """Host end of the protocol over a port; one HostLink per port, one thread at a time.

    Args:
        port: from :func:`~cdma_lidar.protocol.ports.open_port`, an ``FdPort``, or anything
            with ``read``, ``write``, ``in_waiting`` and ``timeout``.
        timeout_s: wait for one reply, and longest silence in a scan (s).
        retries: retransmissions of a request before LinkTimeout.
        column_retries: RESENDs of one missing column before LinkTimeout; default
            ``10 * (retries + 1)``.
        max_frame: largest frame the device may send (bytes, 64..65535), announced in
            HELLO; longer replies and columns come in FRAGMENTs. Requests stay within
            min(INFO.max_frame, max(max_frame, 256)).
        key: shared secret (32 bytes, :func:`cdma_lidar.protocol.auth.load_key`) of a
            device that requires one: HELLO answers its challenge, it must prove it holds
            the key too, every frame is signed. None: the device must not ask for a key.
        take_over: HELLO ends another host's live session instead of failing BUSY.
        keep_config: the new session keeps the previous one's configuration and power.
        fec: Reed-Solomon coded frames both ways, asked for in HELLO; None:
            :func:`~cdma_lidar.protocol.ports.default_fec` (on for a serial line).
        progress_timeout_s: floor of the no-progress limit (:func:`patience_s`, s).
        clock: monotonic clock (s) of every wait and deadline; tests pass a fake one that
            their port moves.
    """

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- requests ---------------------------------------------------------------------
    def get_config(self, *names: str) -> dict[str, Any]:
        """Configuration values by key name (all keys when no names are given)."""
        keys = [config_key(n).id for n in names]
        reply = self.request(MsgType.CONFIG_GET, {"keys": keys})
        try:
            values = decode_config(reply["items"]).values
        except Exception as exc:  # FrameError from the strict decoder
            raise DeviceLied(f"device sent an invalid CONFIG: {exc}") from None
        if not names or self.config is not None:  # keep the full configuration, checked
            merged = {**self.config, **values} if names else dict(values)  # type: ignore[dict-item]
            check_config(merged, self.info)  # type: ignore[arg-type]
            self.config = merged
        return values

    def set_config(self, **values: Any) -> None:
        """Set configuration keys (python values, see ``CONFIG_KEYS``), all or none:
        FieldError for what the wire cannot carry, DeviceError when the device refuses."""
        if not values:
            return
        self.config = None  # read again (checked) before the next stream
        self.request(MsgType.CONFIG_SET, {"items": encode_config(values,
                                                                  allow_read_only=False)})

    def set_power(self, matrix: ArrayLike, channel_start: int = 0, column_start: int = 0) -> None:
        """Send a (channels, columns) laser-power matrix (:func:`power_codes`): one
        POWER_SET, in FRAGMENTs when longer than a frame, several beyond MAX_PIECES."""
        if self.info is None:  # the size of a piece depends on the session's max frame
            self.hello()
        m = power_codes(matrix)
        rows, cols = m.shape
        room = (MAX_PIECES * piece_room(self.max_frame, self.signer is not None) - 8) // 2
        step_c = min(cols, room)
        step_r = max(1, min(rows, room // step_c))
        for r0 in range(0, rows, step_r):
            for c0 in range(0, cols, step_c):
                block = m[r0:r0 + step_r, c0:c0 + step_c]
                self.request(MsgType.POWER_SET, {
                    "channel_start": channel_start + r0, "column_start": column_start + c0,
                    "channels": block.shape[0], "columns": block.shape[1],
                    "power": block.ravel()})

    def get_power(self) -> NDArray[np.uint16]:
        """The device's (K, C = INFO.column_count) power matrix (1/65535 of the per-pixel
        maximum), read in blocks of whole rows (16384 values, or one row)."""
        info = self.info or self.hello()
        k, c = info.channels, info.column_count
        out = np.zeros((k, c), dtype=np.uint16)
        rows = max(1, 16384 // c)  # c >= 1: the decoder's
        for r0 in range(0, k, rows):
            n = min(rows, k - r0)
            d = self.request(MsgType.POWER_GET, {"channel_start": r0, "column_start": 0,
                                                  "channels": n, "columns": c})
            if (d["channel_start"], d["column_start"], d["channels"], d["columns"]) != \
                    (r0, 0, n, c):
                raise DeviceLied(f"device answered POWER_GET of rows {r0}..{r0 + n - 1} with "
                                 f"rows {d['channel_start']}.. x {d['channels']}", "power")
            out[r0:r0 + n] = np.asarray(d["power"], dtype=np.uint16).reshape(n, c)
        return out

    def status(self) -> Status:
        return Status(**self.request(MsgType.STATUS_GET, {}))

    def abort(self) -> None:
        """Stop a running scan or calibration (harmless when idle)."""
        self.request(MsgType.SCAN_ABORT, {})

    def capture(self, kind: str | int = "raw", column: int = 0, channel: int = 0) -> NDArray:
        """Debug capture of one column, read in chunks: raw ADC samples or a channel's
        correlation trace (``kind`` ``"raw"``, ``"corr"`` or a CaptureKind), int16/32/64."""
        if isinstance(kind, str):
            if kind not in ("raw", "corr"):
                raise out_of_range("kind", "'raw' or 'corr'", kind, FieldError)
            kind = CaptureKind[kind.upper()]
        parts: list[NDArray] = []
        offset, total = 0, None
        while total is None or offset < total:
            d = self.request(MsgType.CAPTURE, {"kind": int(kind), "column": column,
                                                "channel": channel, "offset": offset,
                                                "max_count": 65535})
            dt = {2: "<i2", 4: "<i4", 8: "<i8"}.get(d["elem_bytes"])
            if dt is None or d["offset"] != offset or len(d["data"]) % d["elem_bytes"]:
                raise LinkError(f"CAPTURE_DATA out of step: offset {d['offset']} (wanted "
                                f"{offset}), {d['elem_bytes']} bytes per element")
            chunk = np.frombuffer(d["data"], dtype=dt)
            total = d["total"]
            if chunk.size == 0 and offset < total:
                raise LinkError("CAPTURE_DATA chunk is empty before the end of the capture")
            parts.append(chunk)
            offset += chunk.size
        return np.concatenate(parts)  # the loop runs at least once

    def scan(self, first_column: int = 0, columns: int | None = None, frames: int = 1,
             frame: int | None = None) -> Iterator[ColumnResult]:
        """Scan ``frames`` frames of ``columns`` columns (default: ``columns_per_frame``)
        from ``first_column``: ColumnResults in order, each once, gaps repaired. Leaving
        the loop early aborts the scan on the device."""
        if not is_int(frames) or frames < 1:
            raise out_of_range("frames", "an integer of at least 1", frames)
        if columns is None:  # columns_per_frame (section 6.2; check_config: <= column_count)
            columns = int((self.config or self.get_config())["columns_per_frame"]) - first_column
        for k in range(frames):
            yield from self._stream_columns(MsgType.SCAN_START, frame if k == 0 else None,
                                            first_column, columns, first_column=first_column,
                                            columns=columns)

    def calibrate(self, shots: int, frame: int | None = None) -> list[ColumnResult]:
        """Zeroth-order calibration: ``shots`` columns flagged ``calibration``."""
        return list(self._stream_columns(MsgType.CALIBRATE, frame, 0, shots, shots=shots))

    # ---- streams ------------------------------------------------------------------------
    def _stream_columns(self, req: MsgType, frame: int | None, first: int, count: int,
                        **fields_: Any) -> Iterator[ColumnResult]:
        """Start a stream with ``req`` (frame id ``frame``, default: the next one); yield
        columns first..first+count-1 in order, once each. A stream the device ends early
        still delivers every column it sent before the error; leaving early aborts it."""
        fid = fields_["frame"] = self._next_frame_id if frame is None else frame
        self._next_frame_id = (fid + 1) & 0xFFFFFFFF
        checker = ColumnChecker(self.info or self.hello(),  # HELLO, then CONFIG of all keys
                                self.config or self.get_config(), req == MsgType.CALIBRATE)
        self.stream = deque()  # stream frames go there from now on
        finished = False
        try:
            try:
                self.request(req, fields_)
            except DeviceError as exc:
                if exc.code != ErrorCode.BUSY:
                    raise
                # Only our own previous stream can be running (repairs asked for earlier
                # still going out): let it end (within the reply timeout times the retries,
                # else BUSY stands), then ask once more.
                deadline = self.clock() + self.timeout_s * (self.retries + 1)
                while self.status().state != State.IDLE:
                    if self.clock() >= deadline:
                        raise exc
                    self.pump()
                self.stream.clear()
                self.request(req, fields_)
            # A key is asked again after a request's reply wait (doubled per try; repairs
            # go ahead of new columns), at most a quarter of the reply timeout.
            asm = ColumnReassembler(fid, first, first + count, checker, lambda tries:
                                    self.reply_wait(0, tries - 1, self.timeout_s / 4),
                                    self.stats)
            yield from self._drive(asm)
            finished = True
        finally:
            self.end_stream()
            if not finished and self.session is not None:
                with contextlib.suppress(LinkError):
                    self.abort()

    def _drive(self, asm: ColumnReassembler) -> Iterator[ColumnResult]:
        """Feed ``asm`` the stream until it is done; ask STATUS after a silence, RESEND
        what is due, fail a stream that stays alive without moving."""
        heard = moved = self.clock()  # last sign of life, last progress
        progress = asm.progress
        while not asm.done:
            alive = False  # heard something of this frame (other frames are no sign of life)
            while self.stream:
                alive = asm.feed(*self.stream.popleft()) or alive
            yield from asm.ready()
            if asm.done:
                break
            now = self.clock()
            if asm.progress != progress:
                progress, moved = asm.progress, now
            elif now - moved >= (limit := patience_s(self.progress_timeout_s,
                                                      self.last_status)):
                raise ScanStalled(
                    f"frame {asm.fid} made no progress for {limit:g} s on "
                    f"{self.port_name}: the device says it is still working but column "
                    f"{asm.nxt} never came; {asm.nxt - asm.first} columns were delivered",
                    frame=asm.fid, next_column=asm.nxt)
            if alive:
                heard = now
            elif now - heard >= self.timeout_s:
                st = self.status()  # silence: how far did it get? (else LinkTimeout)
                if st.frame != asm.fid:
                    raise LinkError(f"device is {st.state_name} with frame {st.frame}, not "
                                    f"frame {asm.fid}: it lost the scan (restarted or "
                                    "another host took over)")
                asm.sent(st.next_column, st.last_end if st.state == State.IDLE else None)
                heard = self.clock()
                continue
            if due := asm.due(now):  # one RESEND, then read: its answer is in the stream
                self._resend(asm, due, now)
                heard = self.clock()
            self.pump()
        if asm.failure is not None:
            raise asm.failure

    def _resend(self, asm: ColumnReassembler, due: list[Any], now: float) -> None:
        """RESEND the due columns (ints) and fragments ((column, index)), at most 255 of
        each and what fits a request."""
        room = self.max_frame - frame_size(6, self.signer is not None)  # the counts: 6 bytes
        cols = [k for k in due if isinstance(k, int)][:min(255, room // 2)]
        pieces = [k for k in due if not isinstance(k, int)][
            :min(255, (room - 2 * len(cols)) // 3)]
        for key in cols + pieces:
            if (tries := asm.tries(key)) >= self.column_retries:
                diag, why = diagnose((0,) * 6, self._counters())  # over the whole link
                what = f"column {key}" if isinstance(key, int) else \
                    f"fragment {key[1]} of column {key[0]}"
                raise LinkTimeout(f"{what} of frame {asm.fid} never arrived after {tries} resend "
                                  f"requests on {self.port_name}: {why}", diag)
        asm.ask(cols + pieces, now)
        self.stats.resend_requests += 1
        self.stats.resent_columns += len(cols) + len(pieces)
        log.debug("frame %d: asking again for %d columns and %d fragments", asm.fid,
                  len(cols), len(pieces))
        # Not waited for: the columns are the answer; a lost RESEND is asked again once
        # its wait (ColumnReassembler.due) passes.
        self.send_unawaited(MsgType.RESEND, {
            "frame": asm.fid, "columns": cols,
            "fragments": [{"column": c, "index": k} for c, k in pieces]})
