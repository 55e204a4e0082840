"""Scene benchmark: one frame of paper-scene1 simulated and processed, and the cost of lit channels.

    python -m bench scene

1. paper-scene1 (40 x 160 pixels, R = 10, S = 4, degree 11): render every column's ADC
   codes and run the bit-exact fast receiver on them, as the virtual device does. The
   instrument's own acquisition time is 160 * 10 * 2047 chips / 62.5 Mchip/s = 52.4 ms.
2. "Model only what the scene requires": a 40-channel wall where every channel is lit
   (the baseline) against a 5-channel strip (only 5 channels' rays hit anything) and an
   empty field, same instrument, same columns. Each stage is timed on its own, per
   column: the per-channel echo kernel (the part that scales with lit channels), echo
   synthesis (kernel plus one inverse FFT per lit column), the R x L Gaussian noise
   draws and the ADC (fixed: every sample of every frame has its own noise and is
   quantised on its own), the whole rendering, the receive chain (fixed: the device
   correlates every configured channel, lit or not), and the virtual device's scan
   (rendering, receive chain and ColumnResults, in its batches of columns).

Times are CPU seconds of this process, best of several runs (see ``_best``).
"""

from __future__ import annotations

import time

import numpy as np

from cdma_lidar.scene import load_scene
from cdma_lidar.scene.instrument import Instrument, RenderSettings
from cdma_lidar.scene.scenefile import parse_scene
from cdma_lidar.virtual.board import VirtualFirmware

ACQ_S = 160 * 10 * 2047 / 62.5e6


def _best(fn, repeat: int = 5) -> float:
    """Best of ``repeat`` runs, in CPU seconds of this process.

    The machine is shared by several engineers' jobs, so wall time swings by 2x to 5x
    between runs; the process's CPU time (all its threads) is the stable measure.
    """
    best = np.inf
    for _ in range(repeat):
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
    return best


def _wall(strip_channels: int | None, columns: int = 32, dark: bool = False) -> object:
    inst = {"wavelengths": {"count": 40}, "azimuth_deg": [-1.0, 1.0], "columns": columns,
            "incidence_deg": 60.02, "link_gain_v_m2_per_w": 100.0, "snr_db": -10.0}
    plane = {"kind": "plane", "name": "wall", "position_m": [5.0, 0.0, 0.0],
             "size_m": [20.0, 20.0], "reflectivity": 0.5}
    if strip_channels is not None:
        probe = Instrument(parse_scene({"instrument": inst, "objects": [plane]}), 0)
        z = probe.truth.hits.point_m[..., 2]  # (K, C) heights on the wall
        mid = 20
        lo = z[mid + strip_channels // 2 + 1].max()  # below the strip (lower channel)
        hi = z[mid - (strip_channels - strip_channels // 2)].min()  # above the strip
        centre, height = (lo + hi) / 2, hi - lo
        plane = dict(plane, position_m=[5.0, 0.0, float(centre)], size_m=[20.0, float(height)])
    return parse_scene({"instrument": inst, "objects": [] if dark else [plane]})


def _kernel_args(inst: Instrument, cfg: RenderSettings, column: int) -> tuple | None:
    """The arguments echo() hands the per-channel kernel at ``column`` (None: nothing lit)."""
    f, _ = inst._frame_bins(cfg)
    chans = inst.lit_channels(column)
    if chans.size == 0:
        return None
    amps = inst.gain_v_per_w[chans, column] * inst.default_power_w[chans, column]
    taus = inst.delay_s[chans, column] + inst._sample_shift_s(cfg)
    members = tuple(int(cfg.code_index[c]) for c in chans)
    rows = inst._spectrum_rows(cfg, members, cfg.uid, cfg.uid_bits)
    return f[1], f.size, amps, taus, [rows[i] for i in members]


def _cost(scene) -> dict[str, float]:
    """CPU seconds per column of each stage of rendering and receiving ``scene``."""
    fw = VirtualFirmware(scene, 0)
    inst = fw.instrument
    cfg = RenderSettings.from_spec(inst.spec)
    cols = range(inst.columns)
    for c in cols:  # warm the spectrum cache, as a running device has
        inst.echo(c, cfg)
    rx = fw.receiver()
    args = [a for a in (_kernel_args(inst, cfg, c) for c in cols) if a is not None]
    total = cfg.frame_samples * cfg.averages
    scale = inst.noise_rms_v * inst._fine_scale()[0]

    def noise() -> list:
        return [np.multiply(np.random.default_rng([0, 0, 1, c]).standard_normal(
            total, dtype=np.float32), scale, dtype=np.float64) for c in cols]

    fines = noise()
    copies: list[list] = []

    def adc() -> None:
        batch = copies.pop()
        for x in batch:
            inst._quantise_fine(x)

    def fresh() -> None:
        copies[:] = [[x.copy() for x in fines] for _ in range(5)]

    fresh()
    t_adc = _best(adc)
    samples = np.stack([inst.render(c, cfg, 1) for c in cols])
    t = {
        "kernel": _best(lambda: [Instrument._sum_delayed(*a) for a in args]),
        "echo": _best(lambda: [inst.echo(c, cfg) for c in cols]),
        "noise": _best(noise),
        "adc": t_adc,
        "render": _best(lambda: [inst.render(c, cfg, 1) for c in cols]),
        # The receive chain's GEMMs run on BLAS threads, whose CPU time swings most
        # when other jobs share the cores: more runs for these two.
        "rx": _best(lambda: rx.frame(samples), 11),
        "scan": _best(lambda: list(fw.scan(1, 0, inst.columns)), 11),
    }
    out = {k: v / inst.columns for k, v in t.items()}
    lit = inst.truth.hits.lit.sum(axis=0)
    out.update(lit_min=int(lit.min()), lit_max=int(lit.max()), lit=float(lit.mean()),
               columns=inst.columns)
    return out


def main() -> None:
    scene = load_scene("paper-scene1")
    fw = VirtualFirmware(scene, 0)
    inst = fw.instrument
    cfg = fw.render_settings()
    rx = fw.receiver()
    list(fw.scan(0, 0, 160))  # warm up caches
    t_render = _best(lambda: [inst.render(c, cfg, 1) for c in range(160)], 2)
    samples = np.stack([inst.render(c, cfg, 1) for c in range(160)])
    t_rx = _best(lambda: rx.frame(samples), 2)
    t_scan = _best(lambda: list(fw.scan(2, 0, 160)), 2)
    lit = inst.truth.hits.lit
    print(f"paper-scene1: 40 x 160 pixels, {int(lit.sum())} lit "
          f"({lit.sum(axis=0).mean():.1f} lit channels per column on average), "
          f"gate {fw.get_config()['gate_len']} lags")
    print(f"  render one frame (160 columns x {samples.shape[1]} samples): "
          f"{t_render * 1e3:8.1f} ms")
    print(f"  receive chain on it (fast, bit-exact):              {t_rx * 1e3:8.1f} ms")
    print(f"  VirtualFirmware.scan, all 160 ColumnResults:         {t_scan * 1e3:8.1f} ms")
    print(f"  instrument acquisition time {ACQ_S * 1e3:.1f} ms -> real-time factor "
          f"{ACQ_S / t_scan:.2f}")

    full = _cost(_wall(None))
    strip = _cost(_wall(5))
    dark = _cost(_wall(None, dark=True))
    print(f"lit-channel cost per column ({full['columns']} columns, CPU us; baseline: every "
          f"channel lit; strip: {strip['lit_min']}..{strip['lit_max']} lit, mean "
          f"{strip['lit']:.2f}, ideal ratio {strip['lit'] / 40:.3f}):")
    print(f"  {'':40s}{'40 lit':>9s}{'5 lit':>9s}{'ratio':>7s}{'0 lit':>9s}")
    rows = (
        ("kernel", "per-channel echo kernel (scales)"),
        ("echo", "echo synthesis (kernel + 1 inverse FFT)"),
        ("noise", "noise: R x L Gaussian draws (fixed)"),
        ("adc", "ADC of R x L samples (fixed)"),
        ("render", "render = echo + noise + ADC"),
        ("rx", "receive chain, all 40 channels (fixed)"),
        ("scan", "VirtualFirmware.scan (all of it)"),
    )
    for key, label in rows:
        ratio = strip[key] / full[key] if full[key] > 0 else float("nan")
        print(f"  {label:40s}{full[key] * 1e6:9.0f}{strip[key] * 1e6:9.0f}{ratio:7.3f}"
              f"{dark[key] * 1e6:9.0f}")
    fixed = full["noise"] + full["adc"]
    print(f"  noise + ADC are {100 * fixed / full['render']:.0f} % of the 40-lit rendering and "
          f"{100 * (strip['noise'] + strip['adc']) / strip['render']:.0f} % of the 5-lit one; "
          "they are the same for any scene (R x L independent samples, each frame "
          "quantised on its own)")


if __name__ == "__main__":
    main()
