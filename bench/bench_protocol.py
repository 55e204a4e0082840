"""Protocol throughput: COLUMN_RESULT encode + decode in process; columns/s through a pty and TCP.

In process, one 40-channel column goes through the whole frame path both ways
(payload, header, CRC-32, COBS, delimiters; then the stream decoder and the payload
parser). The baseline is the same path with the construct-declared payload codec.
Through a pty and a loopback TCP socket, a DeviceEndpoint streams columns to a
HostLink scan (gap repair and all); the baseline is the same connection carrying
the same frame bytes with no protocol. :func:`bench_delivery` prints how often one
message of 200 B to 384 kB crosses a noisy line at once; on noisy ``virtual://`` lines
(bit errors both ways, reproducible by ``line_seed``) :func:`bench_lines` prints issue
42's targets as a table: the time to a byte-identical scan as a ratio to the clean line
with the same settings, and how many line seeds gave the clean bytes.
"""

from __future__ import annotations

import dataclasses
import os
import socket
import threading
import time
import tty
from collections.abc import Iterator

import numpy as np

from cdma_lidar.column_record import FIELD_NAMES
from cdma_lidar.errors import DeviceError
from cdma_lidar.protocol.columns import ColumnResult, decode_column, encode_column
from cdma_lidar.protocol.endpoint import DeviceApp, DeviceEndpoint
from cdma_lidar.protocol.framing import FrameDecoder, encode_frame
from cdma_lidar.protocol.link import HostLink
from cdma_lidar.protocol.messages import Info, MsgType
from cdma_lidar.protocol.ports import FdPort, open_port

K = 40
#: A whole configuration (the host checks every key and every column against it).
CONFIG = {"poly_u": (11, 2), "poly_v": (11, 8, 5, 2), "code_index": tuple(range(K)),
          "uid_bits": 1, "uid": 0, "samples_per_chip": 4, "averages": 10, "adc_bits": 12,
          "gate_start": 0, "gate_len": 8188, "peak_exclude": 8, "ghost_windows": (),
          "out_shift": 0, "rounding": "truncate", "out_bits": 32, "peaks": 1,
          "columns_per_frame": 1, "mode": "ranging", "cancel_rounds": 0, "cancel_snr_q8": 10192}


def make_column(channels: int = K, peaks: int = 1, uid_bits: int = 1) -> ColumnResult:
    """A realistic column: small lags and counts, 32-bit peaks, 64-bit noise sums."""
    rng = np.random.default_rng(1)
    e = peaks - 1
    return ColumnResult.from_arrays(
        7, 123, 12.5, peak_lag=rng.integers(0, 8188, channels),
        peak=rng.integers(-(2**28), 2**28, channels),
        neighbours=rng.integers(-(2**28), 2**28, (channels, 2)),
        noise_count=rng.integers(4000, 8000, channels),
        noise_sum=rng.integers(-(2**24), 2**24, channels),
        noise_sumsq=rng.integers(2**50, 2**60, channels),  # >= noise_sum^2 / count
        uid_signs=rng.choice([-1, 1], (channels, uid_bits)),
        uid_observed=rng.integers(0, 1 << uid_bits, channels),
        uid_match=rng.integers(0, 2, channels).astype(bool),
        saturated=rng.integers(0, 2, channels).astype(bool),
        extra_lag=rng.integers(0, 8188, (channels, e)) if e else None,
        extra_peak=rng.integers(-(2**20), 2**20, (channels, e)) if e else None,
        extra_signs=rng.choice([-1, 1], (channels, e, uid_bits)) if e else None)


def _rate(fn, min_time: float = 0.5) -> float:
    """Calls per second of ``fn`` (best of 3 runs of at least ``min_time``)."""
    n = 1
    while True:
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        dt = time.perf_counter() - t0
        if dt >= min_time / 5:
            break
        n *= 4
    best = 0.0
    for _ in range(3):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        best = max(best, n / (time.perf_counter() - t0))
    return best


def round_trip(col: ColumnResult, enc, dec) -> None:
    """Column -> wire bytes -> column."""
    wire = encode_frame(MsgType.COLUMN_RESULT, enc(col), 1, 0xA1B2C3D4)
    (frame,) = _DECODER.feed(wire)
    out = dec(frame.payload)
    assert out.column == col.column


_DECODER = FrameDecoder()


def bench_in_process() -> None:
    # construct (the test extra) declares the baseline codec, the tests' oracle
    from tests.protocol.wire_oracle import decode_column_construct, encode_column_construct

    for peaks, uid_bits in ((1, 1), (8, 8)):
        col = make_column(peaks=peaks, uid_bits=uid_bits)
        size = len(encode_column(col))
        fast = _rate(lambda c=col: round_trip(c, encode_column, decode_column))
        slow = _rate(lambda c=col: round_trip(c, encode_column_construct,
                                             decode_column_construct), min_time=0.3)
        print(f"in-process encode+decode, {K} channels, P={peaks}, n={uid_bits} "
              f"({size} B payload): {fast:,.0f} columns/s (numpy dtype) vs "
              f"{slow:,.0f} columns/s (construct baseline): x{fast / slow:.0f}; "
              f"target 50,000: {'met' if fast >= 50_000 else 'NOT met'}")
    arrays = {name: getattr(col, name) for name in FIELD_NAMES}
    build = _rate(lambda: ColumnResult.from_arrays(7, 123, 12.5, **arrays), min_time=0.3)
    print(f"ColumnResult.from_arrays (device side, checks every field): {build:,.0f} columns/s")


class _FastApp(DeviceApp):
    """Streams copies of one precomputed column (measures the link, not the receiver)."""

    def __init__(self, columns: int) -> None:
        self.col = make_column()
        self.columns = columns

    def info(self) -> Info:
        return Info.nominal(serial="BENCH", firmware_version="bench",
                            wavelengths_m=1570e-9 + 0.875e-9 * np.arange(K),
                            grooves_per_mm=600.0, incidence_deg=60.0, tilt_deg=None,
                            reference_wavelength_m=1587e-9, chip_rate_hz=1e9,
                            column_start_deg=0.0, column_step_deg=0.01,
                            column_count=self.columns, max_channels=K)

    def get_config(self) -> dict:
        return dict(CONFIG, columns_per_frame=self.columns)  # a full scan: every column

    def set_config(self, values: dict) -> None:
        pass

    def scan(self, frame: int, first_column: int, columns: int) -> Iterator[ColumnResult]:
        return (dataclasses.replace(self.col, column=c, frame=frame)
                for c in range(first_column, first_column + columns))


PAPER = "virtual://paper-scene1?seed=3"
SHORT = "virtual://flat-wall?seed=3&instrument.columns=16"
#: Message sizes of the delivery table (bytes): a short reply, a column, a 40 x 160 power
#: matrix, the largest frame, a 1,200 x 160 power matrix.
SIZES = (200, 1_700, 12_800, 65_000, 384_000)


def _power(frame: int, shape: tuple[int, int]) -> np.ndarray:
    """The power matrix near-far control might send before ``frame`` (seeded)."""
    return np.random.default_rng(frame).integers(4_000, 16_000, shape)  # within the column cap


def virtual_scan(url: str, frames: int = 1, near_far: bool = False
                 ) -> tuple[float, list[bytes], int]:
    """(seconds after HELLO, column payloads, repairs: request retries and RESENDs) of
    ``frames`` scans of ``url``; with ``near_far`` a whole power matrix (POWER_SET) goes
    before every frame."""
    import cdma_lidar.virtual  # noqa: F401 - registers virtual://

    with HostLink(open_port(url), timeout_s=0.5) as link:
        info = link.hello()
        t0 = time.perf_counter()
        cols = []
        for f in range(frames):
            if near_far:
                link.set_power(_power(f, (info.channels, info.column_count)))
            cols += [encode_column(c) for c in link.scan(frame=7 + f)]
        return time.perf_counter() - t0, cols, link.stats.retries + link.stats.resend_requests


def bench_delivery(tries: int = 20, max_frame: int = 16_384) -> None:
    """One message of each size through a noisy line once, coded as a FEC session sends
    it (in FRAGMENTs of ``max_frame`` when longer): how often every frame arrives."""
    from cdma_lidar.protocol.messages import piece_room, split_message
    from cdma_lidar.virtual.line import LineNoise

    room = piece_room(max_frame, signed=False)
    print(f"one message through the line once, Reed-Solomon coded, max frame {max_frame}:")
    print(f"{'bytes':>8} {'frames':>6}  " + "  ".join(f"{f'BER {b:g}':>16}" for b in (1e-3, 3e-3)))
    for size in SIZES:
        payload = bytes(np.random.default_rng(size).integers(0, 4, size, dtype=np.uint8))
        pieces = [payload] if size + 16 <= max_frame else split_message(0x04, payload, room, 1)
        wire = b"".join(encode_frame(MsgType.FRAGMENT if len(pieces) > 1 else 0x04, p, 1, 9,
                                     coded=True) for p in pieces)
        cells = []
        for ber in (1e-3, 3e-3):
            ok = 0
            for t in range(tries):
                got = FrameDecoder(fec=True).feed(LineNoise(ber, [size, t])(wire))
                ok += [f.payload for f in got] == pieces
            cells.append(f"{ok:>3}/{tries} delivered")
        print(f"{size:>8} {len(pieces):>6}  " + "  ".join(f"{c:>16}" for c in cells))


def bench_lines(paper_seeds: int = 10, short_seeds: int = 30, repeats: int = 3) -> None:
    """Issue 42's targets as a table: noisy ``virtual://`` scans against clean ones.

    paper-scene1 (160 columns of 40 channels) with near-far control (a whole power
    matrix before each of 2 frames), unpaced (time is the code's): at bit error rates
    1e-3 and 3e-3 every one of ``paper_seeds`` line seeds must give the clean scan's
    bytes; each noisy scan is timed against a clean scan run right before it.
    flat-wall, 16 columns, ``short_seeds`` line seeds (101 on) at 1e-3: the median and
    the worst time against the clean scan (targets 1.5 and 3: a lost frame costs a round
    trip, not a second). A 50 ms scan on a shared machine moves by a few times from one
    run to the next, so for each line seed a clean scan, the noisy one and a second
    clean one run ``repeats`` times in turn: the best noisy time goes over the best of
    the first clean ones, and the ``clean`` row gives the best of the second over the
    best of the first (what the machine alone moves that ratio by). A line seed damages
    the same bit positions each time, so a wait the protocol makes is in every repeat;
    ``repairs`` counts the request retries and RESENDs of all of them.
    """
    print(f"{'scene':<22} {'BER':>6} {'median s':>8} {'x clean':>8} {'worst':>8}  verdict")
    for scene, base, n, bers, kw, reps in (
            ("paper-scene1 near-far", PAPER, paper_seeds, (1e-3, 3e-3),
             {"frames": 2, "near_far": True}, 1),
            ("flat-wall 16 col", SHORT, short_seeds, (1e-3,), {}, repeats)):
        if not n:
            continue
        clean = virtual_scan(base, **kw)[1]
        rows, cleans, spread = [], [], []
        for ber in bers:
            times, ratios, same, repairs = [], [], 0, 0
            for seed in range(101, 101 + n):
                t: list[list[float]] = [[], [], []]  # clean, noisy, clean again
                for _ in range(reps):
                    t[0].append(virtual_scan(base, **kw)[0])
                    dt, cols, fixes = virtual_scan(
                        f"{base}&line_error_rate={ber:g}&line_seed={seed}", **kw)
                    t[1].append(dt)
                    same += cols == clean
                    repairs += fixes
                    if reps > 1:
                        t[2].append(virtual_scan(base, **kw)[0])
                best = [min(x) if x else 0.0 for x in t]
                cleans.append(best[0])
                times.append(best[1])
                ratios.append(best[1] / best[0])
                spread.append(best[2] / best[0])
            med, worst = float(np.median(ratios)), max(ratios)
            verdict = f"{same}/{n * reps} byte-identical, {repairs} repairs"
            if scene.startswith("flat"):
                verdict += (f", median <= 1.5: {'met' if med <= 1.5 else 'NOT met'}, worst <= 3: "
                            f"{'met' if worst <= 3 else 'NOT met'}")
            rows.append(f"{scene:<22} {ber:>6g} {float(np.median(times)):>8.3f} {med:>8.2f} "
                        f"{worst:>8.2f}  {verdict}")
        print(f"{scene:<22} {0:>6g} {float(np.median(cleans)):>8.3f} {1:>8.2f} {1:>8.2f}  "
              "reference")
        if reps > 1:
            print(f"{scene:<22} {'clean':>6} {float(np.median(cleans)):>8.3f} "
                  f"{float(np.median(spread)):>8.2f} {max(spread):>8.2f}  the machine's "
                  "own spread: clean over clean")
        print("\n".join(rows))
    print(f"(unpaced line; Reed-Solomon FEC on, the default for a serial line; x clean: "
          f"paper-scene1: each noisy scan over a clean one run just before it; flat-wall: "
          f"the best of {repeats} noisy scans over the best of {repeats} clean ones run in "
          f"turn with them)")


def bench_latency(seconds: float = 6.0, aborts: int = 3) -> None:
    """What a host hears while paper-scene1 scans at averages 1024, S 16 (columns take
    seconds each): the reply times of STATUS_GET, the BUSY refusals (CONFIG_SET,
    SCAN_START) and CONFIG_GET, and the gaps between the device's stream frames
    (heartbeats), over ``seconds`` of probing through a real pty; then the reply times
    of ``aborts`` SCAN_ABORTs, each 0.3 s into a new frame's first batch."""
    from cdma_lidar.scene import load_scene
    from cdma_lidar.virtual.board import VirtualFirmware

    master, slave = os.openpty()
    tty.setraw(slave)
    dev_port = FdPort(master)
    ep = DeviceEndpoint(dev_port, VirtualFirmware(load_scene("paper-scene1"), 3))
    stop = threading.Event()
    th = threading.Thread(target=ep.serve_forever, args=(stop,), daemon=True)
    th.start()
    link = HostLink(open_port(os.ttyname(slave), timeout=0.005), timeout_s=5.0, fec=False)
    try:
        link.hello()
        link.set_config(averages=1024, samples_per_chip=16)
        link.request(MsgType.SCAN_START, {"frame": 1, "first_column": 0, "columns": 160})
        times: dict[str, list[float]] = {"STATUS_GET": [], "CONFIG_GET": [],
                                         "CONFIG_SET (BUSY)": [], "SCAN_START (BUSY)": []}
        gaps: list[float] = []
        heard = end = time.perf_counter()
        end += seconds
        seen = link.decoder.stats.frames
        while time.perf_counter() < end:
            for name, req, fields in (
                    ("STATUS_GET", MsgType.STATUS_GET, {}),
                    ("CONFIG_GET", MsgType.CONFIG_GET, {"keys": [16]}),
                    ("CONFIG_SET (BUSY)", MsgType.CONFIG_SET, {"items": []}),
                    ("SCAN_START (BUSY)", MsgType.SCAN_START,
                     {"frame": 2, "first_column": 0, "columns": 1})):
                t0 = time.perf_counter()
                try:
                    link.request(req, fields)
                except DeviceError:
                    pass
                times[name].append(time.perf_counter() - t0)
            t_end = time.perf_counter() + 0.1  # listen: every stream frame ends a gap
            while time.perf_counter() < t_end:
                link.pump()
                if link.decoder.stats.frames != seen:
                    now = time.perf_counter()
                    gaps.append(now - heard)
                    heard, seen = now, link.decoder.stats.frames
        # SCAN_ABORT while a batch computes: the ACK's reply time, then the next frame
        # starts (its SCAN_START waits for the engine to let the aborted batch go).
        times["SCAN_ABORT"] = []
        for frame in range(3, 3 + aborts):
            time.sleep(0.3)  # into the batch
            t0 = time.perf_counter()
            link.request(MsgType.SCAN_ABORT, {})
            times["SCAN_ABORT"].append(time.perf_counter() - t0)
            link.request(MsgType.SCAN_START, {"frame": frame, "first_column": 0,
                                                "columns": 160})
        link.abort()
    finally:
        stop.set()
        th.join(10.0)
        dev_port.close()
        os.close(slave)
    print(f"paper-scene1 scanning at averages 1024, S 16, {seconds:g} s of probing on a pty:")
    for name, ts in times.items():
        print(f"  {name:<18} reply: median {1e3 * float(np.median(ts)):6.1f} ms, worst "
              f"{1e3 * max(ts):6.1f} ms of {len(ts)} (target 50 ms: "
              f"{'met' if max(ts) <= 0.05 else 'NOT met'})")
    print(f"  stream frame gaps:  median {1e3 * float(np.median(gaps)):6.1f} ms, worst "
          f"{1e3 * max(gaps):6.1f} ms of {len(gaps)} (heartbeat target 200 ms: "
          f"{'met' if max(gaps) <= 0.2 else 'NOT met'})")


def _bench_link(label: str, dev_port, host_port, columns: int) -> None:
    """Scan ``columns`` columns from a DeviceEndpoint on ``dev_port`` to a HostLink on
    ``host_port``; baseline: the same frame bytes through the same connection, raw."""
    ep = DeviceEndpoint(dev_port, _FastApp(columns), heartbeat_s=0.2, ring_columns=4096)
    stop = threading.Event()
    th = threading.Thread(target=ep.serve_forever, args=(stop,), daemon=True)
    th.start()
    link = HostLink(host_port, timeout_s=0.5, retries=3)
    link.hello()
    proto = 0.0
    for _ in range(3):  # best of 3 scans: the machine is shared
        t0 = time.perf_counter()
        n = sum(1 for _ in link.scan())
        proto = max(proto, n / (time.perf_counter() - t0))
    frame_len = len(encode_frame(MsgType.COLUMN_RESULT, encode_column(make_column()), 1, 1))
    stop.set()
    th.join(1.0)

    # Baseline: the same bytes through the same connection, no protocol (writer thread,
    # reader here, the same read pattern as HostLink), best of 3.
    blob = encode_frame(MsgType.COLUMN_RESULT, encode_column(make_column()), 1, 1) * 200
    total = frame_len * columns
    raw = 0.0
    for _ in range(3):
        writer = threading.Thread(target=lambda: [dev_port.write(blob)
                                                  for _ in range(columns // 200)], daemon=True)
        t0 = time.perf_counter()
        writer.start()
        got = 0
        while got < (columns // 200) * len(blob):
            got += len(host_port.read(max(1, host_port.in_waiting)))
        raw = max(raw, got / frame_len / (time.perf_counter() - t0))
        writer.join()
    link.close()
    print(f"{label} scan, {K} channels ({frame_len} B/frame): {proto:,.0f} columns/s "
          f"({proto * frame_len / 1e6:.1f} MB/s) vs raw {label} {raw:,.0f} frames/s: "
          f"x{proto / raw:.2f} of the raw byte rate ({total / 1e6:.1f} MB per scan)")


def bench_pty(columns: int = 3000) -> None:
    """Device on a pty master (FdPort), host on the slave path through pyserial."""
    master, slave = os.openpty()
    tty.setraw(slave)
    dev_port = FdPort(master)
    try:
        _bench_link("pty", dev_port, open_port(os.ttyname(slave), timeout=0.02), columns)
    finally:
        dev_port.close()
        os.close(slave)


def bench_tcp(columns: int = 3000) -> None:
    """Device on an accepted TCP socket (FdPort), host on ``socket://`` through open_port."""
    server = socket.create_server(("127.0.0.1", 0))
    box: list[socket.socket] = []
    th = threading.Thread(target=lambda: box.append(server.accept()[0]), daemon=True)
    th.start()
    host_port = open_port(f"socket://127.0.0.1:{server.getsockname()[1]}", timeout=0.02)
    th.join(5.0)
    conn = box[0]
    conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    try:
        _bench_link("tcp", FdPort(conn.fileno()), host_port, columns)
    finally:
        conn.close()
        server.close()


def main() -> None:
    """Print the figures (ratios against baselines measured in the same run) and the
    machine's load before and after (the line benchmarks' times are wall clock)."""
    print("load average {:.2f} {:.2f} {:.2f} on {} CPUs".format(*os.getloadavg(), os.cpu_count()))
    bench_in_process()
    bench_pty()
    bench_tcp()
    bench_delivery()
    bench_lines()
    bench_latency()
    print("load average {:.2f} {:.2f} {:.2f} after".format(*os.getloadavg()))


if __name__ == "__main__":
    main()
