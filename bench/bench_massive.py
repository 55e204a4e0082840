"""Massive benchmark: where the time of a 1,200-channel frame goes (issue 40).

    python -m bench massive

``paper-massive`` (Gold degree 15, N = 32,767 chips, S = 2, R = 1, 160 columns, a 64-lag
gate) at K = 40, 400 and 1,200 channels (the same band, the spacing following K). One
row per K, every figure CPU seconds of this process per column (all its threads; best of
the runs shown in the row), measured in this run:

* ``chain``: the receive chain of the preset's configuration (its interference
  cancellation included: ``cancel_rounds`` more passes of the chain on the accumulators
  minus the echoes found, :mod:`cdma_lidar.firmware_model.cancel`) from the rendered
  repetition sums to the peaks (``FastReceiver.from_accumulators``, its ``auto`` kernel)
  on a batch of as many columns as the device hands it at once
  (:data:`cdma_lidar.scene.acquire.BATCH_VALUES`), against the GEMM floor of the
  multiply-adds it does: a (K, N) @ (N, 64) product per column and correlation (K x 64 x
  N multiply-adds: the gate's correlations in the chip domain), 1 + ``cancel_rounds``
  correlations, in float32 and float64, on one BLAS thread; ``single pass``: the same
  chain with ``cancel_rounds`` = 0 (one correlation, the paper's receiver) on the same
  batch, and the chain's ratio to it; ``chain by kernel``: each CPU kernel by name
  (and ``gpu`` where one is registered, wall seconds) on a few columns, each in a process
  of its own (``spawn``), with that process's peak RSS, and auto's ratio to the fastest
  on the same columns;
* ``render``: a cold frame's repetition sums (``Instrument.render_sums`` after
  ``forget()``: echoes synthesised, the per-configuration codebook kept) at both fidelity
  levels on the same batch (``accumulated``, the level made to be fast, is the one the
  scan uses; the targets take the faster of the two at the largest K);
  ``codebook``: the one-off cost of the first render of a configuration (code spectra
  and tables), per frame, not per column (the code spectra are then kept for the
  process, up to :data:`cdma_lidar.scene.codebook.SHARED_SPECTRA_BYTES`: the scan below
  finds them);
* ``scan``: ``run_scan`` of one whole 160-column frame through ``virtual://`` (device,
  link, host ranging and the point cloud file) at ``accumulated``, after a one-column
  warm-up, per column;
* ``memory``: the tracemalloc peak of building the device and its receiver, the first
  render (codebook included) and one batch's chain; that of connecting through
  ``virtual://`` and a first one-column scan; and this process's peak RSS so far (the
  kernels timed by name run in their own processes: their RSS is printed with them;
  ``matmul`` is left out where its operand would be large, see :data:`MATMUL_MAX_BYTES`).

Then where the time of the largest K's frame goes (render and chain measured apart, the
rest read off the scan's own callbacks: the columns' loop, the host's frame work, the
file), the issue's targets at K = 1,200, each met or not met (ratios from this run), and
whether a GPU kernel row could be measured. At K = 1,200 this takes minutes on 2 cores.
"""

from __future__ import annotations

import gc
import multiprocessing
import os
import resource
import tempfile
import time
import tracemalloc
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

import cdma_lidar.virtual  # noqa: F401  (registers the virtual:// URL scheme)
from cdma_lidar.firmware_model.chain import FastReceiver
from cdma_lidar.firmware_model.correlators import correlator_methods
from cdma_lidar.firmware_model.receiver import ReceiverConfig
from cdma_lidar.host.connection import connect
from cdma_lidar.host.scan import ScanOptions, run_scan
from cdma_lidar.scene import load_scene
from cdma_lidar.scene.acquire import BATCH_VALUES
from cdma_lidar.scene.instrument import SUM_TYPE
from cdma_lidar.virtual.board import VirtualFirmware

#: channel counts, and per K the columns each kernel is timed on by name (and the GEMM
#: floor's product: GATE x this many right-hand columns, as the floor was first measured)
KERNEL_COLUMNS = {40: 8, 400: 2, 1200: 1}
GATE = 64
COLUMNS = 160
#: runs per timing (best of), per K
REPEAT = {40: 3, 400: 2, 1200: 1}
GIB = 1 << 30
#: matmul's exact operand is a Hankel block of the codes, N x K x ceil(gate / S) floats
#: (firmware_model/correlators/matmul.py): 10 GB at K = 1,200 in float64, 15 GB of RSS
#: measured. It is timed only where that block stays under this many bytes (the
#: machine is shared); the row says when it was not.
MATMUL_MAX_BYTES = 4 << 30
LEVELS = ("accumulated", "exact")
#: the fidelity level the scan runs at
SCANNED = "accumulated"


def _cpu(fn, repeat: int) -> float:
    """Best of ``repeat`` runs of ``fn``, CPU seconds of this process (all threads)."""
    best = np.inf
    for _ in range(repeat):
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
    return best


def _load() -> str:
    return "load average {:.2f} {:.2f} {:.2f} on {} CPUs".format(*os.getloadavg(),
                                                                 os.cpu_count())


def _rss_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / GIB  # kB on Linux


def _scene(k: int, level: str) -> str:
    return f"paper-massive?channels={k}&fidelity={level}"


def _gemm(k: int, n: int, cols: int, dtype: type, repeat: int) -> float:
    """CPU s per column of a (K, N) @ (N, GATE * cols) product in ``dtype``, on one BLAS
    thread: the work itself (idle BLAS threads spin, and on a shared machine their CPU
    time swings with the load)."""
    from threadpoolctl import threadpool_limits  # deferred, as in the receive chain

    rng = np.random.default_rng(0)
    a = rng.choice(np.array([-1.0, 1.0], dtype=dtype), size=(k, n))
    b = rng.integers(-2048, 2048, size=(n, GATE * cols)).astype(dtype)
    with threadpool_limits(1):
        return _cpu(lambda: a @ b, repeat) / cols


def _kernel_apart(cfg: ReceiverConfig, codes: np.ndarray, method: str, sums: np.ndarray,
                  repeat: int) -> tuple[float, float, float]:
    """(CPU s per column, wall s per column, peak RSS GiB) of the chain of ``cfg`` and
    ``codes`` with kernel ``method`` on ``sums``, timed in this process (:func:`_kernels`
    runs it in a process of its own)."""
    named = FastReceiver(cfg, codes, method=method)
    named.from_accumulators(sums[:1])  # its tables, once
    cpu, wall = np.inf, np.inf
    for _ in range(repeat):
        t0, w0 = time.process_time(), time.perf_counter()
        named.from_accumulators(sums)
        cpu = min(cpu, time.process_time() - t0)
        wall = min(wall, time.perf_counter() - w0)
    return cpu / len(sums), wall / len(sums), _rss_gib()


def _kernels(rx: FastReceiver, sums: np.ndarray, k: int, s: int, repeat: int,
             out: dict[str, float]) -> None:
    """Each kernel auto chooses from (and ``gpu`` where registered), by name, in a fresh
    process of its own; ``out[name]`` its CPU s per column (wall for ``gpu``; NaN: not
    run) and ``out[name + "_rss"]`` that process's peak RSS (GiB)."""
    hankel = ((1 << 15) - 1) * k * -(-GATE // s) * 8
    out["matmul_gib"] = hankel / GIB
    spawn = multiprocessing.get_context("spawn")
    for method in _methods():
        if method == "matmul" and hankel > MATMUL_MAX_BYTES:
            out[method] = out[method + "_rss"] = np.nan
            continue
        with ProcessPoolExecutor(1, mp_context=spawn) as pool:
            cpu, wall, rss = pool.submit(_kernel_apart, rx.cfg, np.asarray(rx.codes), method,
                                          sums, repeat).result()
        out[method], out[method + "_rss"] = (wall if method == "gpu" else cpu), rss


def _methods() -> list[str]:
    """The kernels timed by name: every registered one but auto and ``xp`` (numpy's twin
    of ``gpu``, which auto never picks)."""
    return [m for m in correlator_methods() if m not in ("auto", "xp")]


def _device_costs(k: int) -> dict[str, float]:
    """Chain, GEMM floors, renders and memory of one K (module docstring)."""
    repeat = REPEAT[k]
    out: dict[str, float] = {}
    tracemalloc.start()
    for level in LEVELS:
        fw = VirtualFirmware(load_scene(_scene(k, level)), 1)
        fw.set_config({"gate_len": GATE})
        cfg = fw.render_settings()
        cols = max(1, min(COLUMNS, BATCH_VALUES // cfg.frame_samples))  # the device's batch
        sums = np.empty((cols, cfg.uid_bits, cfg.frame_samples // cfg.uid_bits), dtype=SUM_TYPE)
        columns = list(range(COLUMNS // 2 - cols // 2, COLUMNS // 2 - cols // 2 + cols))
        t0 = time.process_time()
        fw.instrument.render_sums(columns, cfg, 1, out=sums)   # the codebook, once
        out[f"codebook_{level}"] = time.process_time() - t0
        if level == LEVELS[0]:
            rx = fw.receiver()
            rx.from_accumulators(sums)
            out["memory_gib"] = tracemalloc.get_traced_memory()[1] / GIB
            tracemalloc.stop()
            out["batch"] = cols
            out["rounds"] = rx.cfg.cancel_rounds
            out["kernel"] = rx.kernel_for(cols).method  # type: ignore[assignment]
            out["chain"] = _cpu(lambda rx=rx, sums=sums: rx.from_accumulators(sums),
                                repeat) / cols
            single = FastReceiver(rx.cfg.replace(cancel_rounds=0), rx.codes)
            single.from_accumulators(sums)  # its tables, once, as rx's above
            out["chain_single"] = _cpu(lambda rx=single, sums=sums: rx.from_accumulators(sums),
                                       repeat) / cols
            del single
            few = sums[:KERNEL_COLUMNS[k]]
            out["auto_few"] = _cpu(lambda rx=rx, few=few: rx.from_accumulators(few),
                                   repeat) / len(few)
            out["kernel_few"] = rx.kernel_for(len(few)).method  # type: ignore[assignment]
            _kernels(rx, few, k, cfg.samples_per_chip, repeat, out)
            del rx
        inst = fw.instrument

        def cold(inst=inst, cfg=cfg, columns=columns, sums=sums) -> None:
            inst.forget()
            inst.render_sums(columns, cfg, 2, out=sums)

        out[f"render_{level}"] = _cpu(cold, repeat) / cols
        del fw, inst, sums
        gc.collect()
    n = (1 << 15) - 1
    for bits, dtype in ((32, np.float32), (64, np.float64)):
        # one correlation's product; the chain correlates 1 + rounds times
        out[f"gemm{bits}_single"] = _gemm(k, n, KERNEL_COLUMNS[k], dtype, repeat)
        out[f"gemm{bits}"] = (1 + out["rounds"]) * out[f"gemm{bits}_single"]
    gc.collect()
    return out


def _scan_cost(k: int, level: str) -> dict[str, float]:
    """A whole frame's scan through virtual:// at fidelity ``level`` (after a one-column
    warm-up that builds the device's codebook): CPU s per column (``scan``), the frame's
    CPU s until its last column was stored (``columns_s``), then the host's frame work
    (ranges, intensity, cloud, the frame kept for a resume: ``frame_s``) and the file
    (``file_s``), read off the scan's own callbacks; the tracemalloc peak (GiB) of
    connecting and the warm-up (``scan_memory_gib``)."""
    tracemalloc.start()
    marks: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp, \
            connect(f"virtual://{_scene(k, level)}&seed=1") as dev:
        # the host's fixed 30 s no-progress limit (issue 40 item 3) stops a 1,200-channel
        # column on a loaded 2-core machine; the bench waits as long as a column takes
        dev.link.progress_timeout_s = 600.0
        dev.link.set_config(gate_len=GATE, columns_per_frame=1)
        dev.refresh_config()
        run_scan(dev, Path(tmp) / "warm.ply", ScanOptions(), progress=False, frame_id=1)
        peak = tracemalloc.get_traced_memory()[1] / GIB
        tracemalloc.stop()
        dev.link.set_config(columns_per_frame=COLUMNS)
        dev.refresh_config()
        t0 = time.process_time()
        run_scan(dev, Path(tmp) / "m.ply", ScanOptions(), progress=False, frame_id=2,
                 on_column=lambda f, c: marks.__setitem__("column", time.process_time()),
                 on_frame=lambda f, cl, p: marks.__setitem__("frame", time.process_time()))
        end = time.process_time()
    return {"scan": (end - t0) / COLUMNS, "columns_s": marks["column"] - t0,
            "frame_s": marks["frame"] - marks["column"], "file_s": end - marks["frame"],
            "scan_memory_gib": peak}


def _verdict(ok: bool) -> str:
    return "met" if ok else "NOT met"


def _row(k: int, row: dict) -> None:
    """Print one K's rows."""
    passes = 1 + int(row["rounds"])
    print(f"K={k:5d}  chain {row['chain']:8.3f} s ({row['kernel']}, batches of "
          f"{int(row['batch'])} columns; the preset's chain: {int(row['rounds'])} rounds of "
          f"interference cancellation, {passes} correlations; GEMM floor of their "
          f"multiply-adds ({passes} x K x {GATE} x N) float32 {row['gemm32']:.3f} s: "
          f"x{row['chain'] / row['gemm32']:.2f}, float64 {row['gemm64']:.3f} s: "
          f"x{row['chain'] / row['gemm64']:.2f})", flush=True)
    print(f"         single pass {row['chain_single']:8.3f} s (cancel_rounds = 0: one "
          f"correlation, the paper's receiver; the chain with cancellation takes x"
          f"{row['chain'] / row['chain_single']:.2f} its time; GEMM floor of one correlation "
          f"float32 x{row['chain_single'] / row['gemm32_single']:.2f}, float64 "
          f"x{row['chain_single'] / row['gemm64_single']:.2f})", flush=True)
    timed = [m for m in _methods() if np.isfinite(row[m])]
    best = min(timed, key=lambda m: row[m])

    def kernel(m: str) -> str:
        if not np.isfinite(row[m]):
            return f"{m} not run (its operand: {row['matmul_gib']:.1f} GiB)"
        unit = "s wall" if m == "gpu" else "s"
        return f"{m} {row[m]:.3f} {unit} ({row[m + '_rss']:.1f} GiB RSS)"

    print(f"         chain by kernel on {KERNEL_COLUMNS[k]} columns, each in its own process: "
          + ", ".join(kernel(m) for m in _methods())
          + f"; auto ({row['kernel_few']}) {row['auto_few']:.3f} s, x"
            f"{row['auto_few'] / row[best]:.2f} the fastest run ({best})", flush=True)
    print(f"         render accumulated {row['render_accumulated']:8.3f} s "
          f"(x{row['render_accumulated'] / row['chain']:.2f} chain), exact "
          f"{row['render_exact']:.3f} s (x{row['render_exact'] / row['chain']:.2f} chain); "
          f"codebook once per configuration: "
          f"{row['codebook_accumulated']:.1f} s accumulated, {row['codebook_exact']:.1f} s exact",
          flush=True)
    print(f"         scan {row['scan']:8.3f} s ({SCANNED}; "
          f"x{row['scan'] / row['chain']:.2f} chain; "
          f"a whole {COLUMNS}-column frame scanned: {row['scan'] * COLUMNS:.1f} s); per "
          f"channel {row['scan'] / k * 1e3:.3f} ms", flush=True)
    print(f"         memory peak {row['memory_gib']:.2f} GiB traced (device, receiver, "
          f"first render, one batch's chain), {row['scan_memory_gib']:.2f} GiB traced "
          f"(connect and a first scan); {row['rss_gib']:.2f} GiB RSS of this process so far "
          f"(the kernels by name apart); {_load()}", flush=True)


def _stages(k: int, row: dict) -> None:
    """Where a frame's time goes at K = ``k``: stage, CPU s per frame, share."""
    render, chain = row[f"render_{SCANNED}"] * COLUMNS, row["chain"] * COLUMNS
    total = row["scan"] * COLUMNS
    stages = (
        (f"render ({SCANNED}, cold: echoes, noise, sums)", render),
        (f"receive chain ({row['kernel']}, {int(row['rounds'])} rounds of cancellation)",
         chain),
        ("device loop, column records, framing, link, host store", row["columns_s"]
         - render - chain),
        ("host frame: ranges, intensity, cloud, resume copy", row["frame_s"]),
        ("host file: the point cloud written", row["file_s"]),
    )
    print(f"where a {k}-channel frame's time goes ({COLUMNS} columns scanned once through "
          "virtual://, CPU s of this process; render and chain measured apart on the "
          "device's batches, the rest read off the scan's callbacks):")
    print(f"  {'stage':56s} {'seconds':>8s} {'share':>6s}")
    for label, seconds in stages:
        print(f"  {label:56s} {seconds:8.1f} {seconds / total:6.0%}")
    print(f"  {'one scan, all of it':56s} {total:8.1f} {1:6.0%}")


def main() -> None:
    print(f"paper-massive: degree 15 (N = 32767), S = 2, R = 1, {COLUMNS} columns, a {GATE}-lag "
          f"gate; CPU s per column (all threads), best of the row's runs; {_load()}")
    rows: dict[int, dict] = {}
    for k in KERNEL_COLUMNS:
        row: dict = _device_costs(k)
        row.update(_scan_cost(k, SCANNED))
        row["rss_gib"] = _rss_gib()
        rows[k] = row
        _row(k, row)
    top_k, mid_k = sorted(rows)[-1], sorted(rows)[-2]
    top, mid = rows[top_k], rows[mid_k]
    _stages(top_k, top)
    per_channel = (top["scan"] / top_k) / (mid["scan"] / mid_k)
    fast = min(LEVELS, key=lambda level: top[f"render_{level}"])
    print(f"targets at K = {top_k} (issue 40; ratios from this run; the chain is the "
          f"preset's, {int(top['rounds'])} rounds of interference cancellation, its GEMM floor "
          f"that of its {1 + int(top['rounds'])} correlations):")
    for label, value, limit in (
            ("chain / float32 GEMM floor", top["chain"] / top["gemm32"], 1.5),
            ("chain / float64 GEMM floor", top["chain"] / top["gemm64"], 1.5),
            (f"render (the fastest level, {fast}) / chain", top[f"render_{fast}"] / top["chain"],
             1.0),
            ("render (exact) / chain", top["render_exact"] / top["chain"], 2.0),
            ("scan / chain", top["scan"] / top["chain"], 3.0),
            (f"scan time per channel, K = {top_k} / K = {mid_k}", per_channel, 1.5),
            ("peak memory (GiB, traced, device stages)", top["memory_gib"], 4.0),
            ("peak memory (GiB, traced, a first scan)", top["scan_memory_gib"], 4.0),
            ("peak memory (GiB, RSS of this process)", top["rss_gib"], 4.0)):
        print(f"  {label:48s} {value:8.2f}  (at most {limit:g}): {_verdict(value <= limit)}")
    print(f"  one frame {top['scan'] * COLUMNS / 60:.1f} min (CPU; the issue's guide: about "
          "2 min)")
    print("gpu: " + ("its kernel's row is in chain by kernel above (wall s)" if "gpu" in
                     _methods() else "no GPU here (CuPy absent, no CUDA device, or CUPY_TF32 "
                     "set): no gpu row"))
    print(f"({_load()} after)")


if __name__ == "__main__":
    main()
