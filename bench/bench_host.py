"""Host benchmarks: what sub-sample refinement buys, eq. 27, near-far loop, speed.

Run with ``python -m bench host``. Every figure is printed next to a baseline measured
in the same run:

* range error (median, 95th percentile) with parabolic and triangle refinement against
  the integer lag, on paper-scene1 and flat-wall rendered in-process (instrument +
  receive chain, perfect calibration), and the spread against eq. 27's precision;
* the neighbour-consistency rule on top of the SNR_XC threshold: false pixels and
  object pixels kept over ten frames of paper-scene1, against the threshold alone
  (the baseline); and what ``--interpolate`` fills at a stricter threshold;
* near-far: object pixels above the threshold per frame of the closed loop over ten
  frames on near-far, paper-scene1 and flat-wall, against uniform power (baseline);
* --combine: frame-to-frame precision and the deterministic bias against N on
  flat-wall (baseline: one frame);
* speed: the vectorised range pipeline against a per-pixel Python loop; point-cloud
  assembly and the PLY writer;
* partial scans: the once-a-second save of a scan after F finished frames (the frame in
  progress only, each finished frame having been written once) against the earlier
  scheme that stacked every finished frame into that save (the baseline).
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np

from cdma_lidar.host.cloud_formats.ply import write as write_ply
from cdma_lidar.host.pointcloud import assemble
from cdma_lidar.host.ranging import (
    RangingConfig,
    estimate_ranges,
    lag_to_range_m,
    precision_eq27_m,
    subsample_delta,
)
from cdma_lidar.study.simulate import eq27_from_configuration, simulate_frame
from cdma_lidar.units import delay_to_range_m


def _errors(sim, cfg: RangingConfig) -> tuple[float, float, float, float]:
    img = estimate_ranges(sim.frame, cfg)
    obj = np.isfinite(sim.truth_range_m)
    ok = img.valid & obj
    signed = (img.range_m - sim.truth_range_m)[ok]
    err = np.abs(signed)
    return (float(np.median(err)), float(np.percentile(err, 95)), float(np.std(signed)),
            float(np.mean(img.valid[obj])))


def bench_refinement() -> None:
    print("range error against the truth (m), perfect calibration:")
    for scene, threshold in (("paper-scene1", None), ("flat-wall", None)):
        sim = simulate_frame(scene, seed=3)
        base = dataclasses.replace(sim.ranging, offset_m=sim.true_offset_m)
        if threshold is not None:
            base = dataclasses.replace(base, snr_threshold_db=threshold)
        img = estimate_ranges(sim.frame, base)
        obj = np.isfinite(sim.truth_range_m)
        snr_med = float(np.median(img.snr_xc_db[img.valid & obj]))
        sigma = float(precision_eq27_m(base.chip_rate_hz, base.samples_per_symbol,
                                       snr_xc_db=snr_med))
        rows = {m: _errors(sim, dataclasses.replace(base, method=m))
                for m in ("none", "parabolic", "triangle")}
        med0 = rows["none"][0]
        print(f"  {scene} (threshold {base.snr_threshold_db:g} dB, median SNR_XC "
              f"{snr_med:.1f} dB; eq. 27 sigma {sigma:.4f} m from SNR_XC / N_s, "
              f"{eq27_from_configuration(scene):.4f} m from the configuration, eq. 30):")
        for m, (med, p95, sd, vf) in rows.items():
            print(f"    {m:9s} median {med:.4f}  p95 {p95:.4f}  std {sd:.4f}  valid "
                  f"{100 * vf:.1f} %  (median {med0 / med:.1f}x better than integer lag)")


def bench_support(frames: int = 10) -> None:
    """Threshold alone (baseline) against threshold + neighbour support, paper-scene1."""
    thresholds = (15.0, 16.0, 17.0, 18.0)
    supports = (0, 1, 2)
    false = {(s, t): [0, 0] for s in supports for t in thresholds}
    worst = {(s, t): 1.0 for s in supports for t in thresholds}
    fill: list[tuple[int, float, float]] = []
    for n in range(1, frames + 1):
        sim = simulate_frame("paper-scene1", seed=1, frame=n)
        obj = np.isfinite(sim.truth_range_m)
        base = dataclasses.replace(sim.ranging, offset_m=sim.true_offset_m)
        for key in false:
            img = estimate_ranges(sim.frame, dataclasses.replace(
                base, min_support=key[0], snr_threshold_db=key[1]))
            bad = int(np.count_nonzero(img.valid & ~obj))
            false[key][0] += bad
            false[key][1] += bad > 0
            worst[key] = min(worst[key], float(np.mean(img.valid[obj])))
        img = estimate_ranges(sim.frame, dataclasses.replace(base, snr_threshold_db=20.0,
                                                             interpolate=True))
        err = np.abs(img.range_m - sim.truth_range_m)
        filled = (img.flags == 1) & obj
        fill.append((int(np.count_nonzero(img.flags == 1)), float(np.median(err[filled])),
                     float(np.median(err[img.valid & obj]))))
    print(f"SNR_XC threshold and neighbour support, paper-scene1, {frames} frames "
          "(support 0 = threshold alone, the baseline):")
    print("  support  threshold  false pixels (frames with any)  worst object pixels kept")
    for (sup, thr), (bad, nfr) in false.items():
        print(f"  {sup:7d}  {thr:6.1f} dB  {bad:12d} ({nfr:2d} of {frames})"
              f"{100 * worst[sup, thr]:24.1f} %")
    n_fill = np.mean([f[0] for f in fill])
    print(f"  --interpolate at 20 dB: {n_fill:.0f} pixels filled per frame, median error "
          f"{np.median([f[1] for f in fill]):.4f} m (measured pixels "
          f"{np.median([f[2] for f in fill]):.4f} m)")


def bench_near_far(frames: int = 10) -> None:
    """Per-frame trajectory of the closed loop through virtual:// against uniform power."""
    import cdma_lidar.virtual  # noqa: F401 - registers virtual:// (bench only, not a layer)
    from cdma_lidar.host.connection import connect
    from cdma_lidar.host.scan import ScanOptions, run_scan
    from cdma_lidar.scene import load_scene
    from cdma_lidar.scene.truth import compute_truth

    print(f"near-far closed loop over {frames} frames (virtual://SCENE?seed=1, frame ids "
          "11..): object pixels above 16 dB per frame; baseline: the same frames at uniform "
          "power")
    for scene in ("near-far", "paper-scene1", "flat-wall"):
        obj = np.isfinite(compute_truth(load_scene(scene)).range_m)
        rows = {}
        with tempfile.TemporaryDirectory() as d:
            for loop in (False, True):
                with connect(f"virtual://{scene}?seed=1") as dev:
                    res = run_scan(dev, Path(d) / "nf.npz",
                                   ScanOptions(frames=frames, near_far=loop),
                                   progress=False, frame_id=11)
                rows[loop] = res
        thr = rows[True].image.config.snr_threshold_db
        for loop, label in ((False, "uniform"), (True, "loop")):
            fr = [100 * float(np.mean(m[obj] >= thr)) for m in rows[loop].snr_maps]
            print(f"  {scene:12s} {label:8s} " + " ".join(f"{f:5.1f}" for f in fr)
                  + f"   worst after frame 2: {min(fr[2:]):.1f} % (best {max(fr):.1f} %)")
        pw = rows[True].powers
        print(f"  {scene:12s} {'power':8s} " + " ".join(
            f"{float(np.median(p[obj])):5.3f}" for p in pw[:frames])
            + "   median object pixel (x max); largest column sum "
            + f"{max(float(p.sum(axis=0).max()) for p in pw):.2f} (cap {pw[0].shape[0] * 0.25:g})")


def bench_combine(frames: int = 8) -> None:
    """Precision and bias of --combine mean/median against N on flat-wall (baseline N = 1)."""
    import cdma_lidar.virtual  # noqa: F401 - registers virtual:// (bench only, not a layer)
    from cdma_lidar.host.combine import combine
    from cdma_lidar.host.connection import connect
    from cdma_lidar.host.scan import ScanOptions, image_from_cloud, run_scan
    from cdma_lidar.scene import load_scene
    from cdma_lidar.scene.truth import compute_truth

    scene = load_scene("flat-wall")
    truth = compute_truth(scene).range_m
    offset = delay_to_range_m(scene.instrument.system_delay_s)
    runs = []
    with tempfile.TemporaryDirectory() as d:
        for fid in (100, 200):
            with connect("virtual://flat-wall?seed=1") as dev:
                res = run_scan(dev, Path(d) / "w.npz", ScanOptions(frames=frames,
                                                                 offset_m=offset),
                               progress=False, frame_id=fid)
            runs.append([image_from_cloud(c, res.image.config) for c in res.clouds])
    print(f"--combine on flat-wall (two independent {frames}-frame scans, perfect calibration):"
          " precision = std(A - B) / sqrt(2) over pixels, bias = median |(A + B)/2 - truth|")
    base = None
    for mode in ("mean", "median"):
        for n in (1, 2, 4, 8):
            if n > frames or (mode == "median" and n < 3 and n != 1):
                continue
            ra, rb = (combine(r[:n], mode).range_m for r in runs)
            ok = np.isfinite(ra) & np.isfinite(rb)
            prec = float(np.std((ra - rb)[ok]) / np.sqrt(2))
            bias = float(np.median(np.abs(0.5 * (ra + rb) - truth)[ok]))
            base = prec if base is None else base
            print(f"  {mode:6s} N={n}: precision {1e3 * prec:6.2f} mm ({base / prec:4.2f}x "
                  f"better than N=1; 1/sqrt(N) predicts {np.sqrt(n):4.2f}x), bias "
                  f"{1e3 * bias:6.2f} mm")


def _loop_ranges(frame, cfg: RangingConfig) -> np.ndarray:
    """Baseline: the same range conversion, one pixel at a time."""
    k, c = frame.shape
    out = np.full((k, c), np.nan)
    for i in range(k):
        for j in range(c):
            d = float(subsample_delta(frame.peak[i, j], frame.neighbours[i, j], cfg.method))
            out[i, j] = float(lag_to_range_m(frame.peak_lag[i, j] + d, cfg.samples_per_chip,
                                             cfg.chip_rate_hz, cfg.offset_m))
    return out


def _best(fn, repeat: int = 3) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def bench_speed() -> None:
    sim = simulate_frame("paper-scene1", seed=3)
    cfg = dataclasses.replace(sim.ranging, offset_m=sim.true_offset_m)
    t_vec = _best(lambda: estimate_ranges(sim.frame, cfg))
    t_loop = _best(lambda: _loop_ranges(sim.frame, cfg), repeat=1)
    print(f"range pipeline on 40 x 160 pixels: {1e3 * t_vec:.1f} ms (incl. SNR, UID, "
          f"support) vs per-pixel loop (lag -> range only) {1e3 * t_loop:.1f} ms: "
          f"{t_loop / t_vec:.1f}x")
    img = estimate_ranges(sim.frame, cfg)
    cloud = assemble(img, sim.geometry, sim.wavelengths_m, sim.rotations_deg)
    with tempfile.TemporaryDirectory() as d:
        t_write = _best(lambda: write_ply(cloud, Path(d) / "c.ply"))
    t_asm = _best(lambda: assemble(img, sim.geometry, sim.wavelengths_m, sim.rotations_deg))
    print(f"point cloud: assemble (eqs. 45-49) {1e3 * t_asm:.1f} ms, PLY write (atomic, "
          f"fsync) {1e3 * t_write:.1f} ms")


def bench_partial_save(counts: tuple[int, ...] = (10, 100, 1000)) -> None:
    """Time and bytes of one periodic save after F finished frames, new and old scheme."""
    from cdma_lidar.fileio import atomic_open
    from cdma_lidar.host.frame import FrameData
    from cdma_lidar.host.scan import ScanState

    sim = simulate_frame("paper-scene1", seed=3)
    img = estimate_ranges(sim.frame, sim.ranging)
    rec = assemble(img, sim.geometry, sim.wavelengths_m, sim.rotations_deg).grid_records()
    k, c = img.range_m.shape
    data = FrameData.empty(k, c, 1, 1)
    state = ScanState(header={"device": {}}, frame_index=0, frame_base=0, data=data)
    with tempfile.TemporaryDirectory() as d:
        new, old = Path(d) / "new.npz", Path(d) / "old.npz"

        def stacked(frames: int) -> None:  # the baseline: every past frame in every save
            arrays = {f"frame_{key}": v for key, v in data.to_arrays().items()}
            arrays["past"] = np.stack([rec] * frames)
            arrays["snr_maps"] = np.zeros((frames, k, c))
            with atomic_open(old, "wb") as fh:
                np.savez(fh, **arrays)

        for frames in counts:
            t_new = _best(lambda: state.save(new))
            t_old = _best(lambda f=frames: stacked(f))
            print(f"partial scan save after {frames} frames ({k} x {c}): {1e3 * t_new:.1f} ms, "
                  f"{new.stat().st_size / 1e6:.2f} MB vs stacking every frame "
                  f"{1e3 * t_old:.1f} ms, {old.stat().st_size / 1e6:.1f} MB: "
                  f"{t_old / t_new:.0f}x")


def main() -> None:
    bench_refinement()
    bench_support()
    bench_near_far()
    bench_combine()
    bench_speed()
    bench_partial_save()


if __name__ == "__main__":
    main()
