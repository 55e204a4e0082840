"""RTL engine benchmark: columns per second through ``rx_top`` under Verilator, against the model.

The virtual board's receive chain with ``engine="rtl"`` (``cdma_lidar.hdl_ref.engine``:
the reference RTL compiled by Verilator, driven with the accumulated periods) against
the model engine (``FastReceiver.from_accumulators``, the baseline), both measured in
this run on the same accumulators of a flat-wall scan (K = 40 channels, the paper's
code, S = 4, n = 1), and checked equal. The one-time Verilator build (cached under
``~/.cache/cdma-lidar/rtl-engine``) is timed separately and not counted.

Run: ``.venv/bin/python -m bench hdl``.
"""

from __future__ import annotations

import time

import numpy as np

from cdma_lidar.hdl_ref import engine
from cdma_lidar.scene import load_scene
from cdma_lidar.virtual.board import VirtualFirmware

COLUMNS = 16


def main() -> None:
    why = engine.missing_simulator()
    if why:
        print(f"  skipped: {why}")
        return
    scene = load_scene(f"flat-wall?instrument.columns={COLUMNS}")
    fw = VirtualFirmware(scene, 0)
    cfg = fw.render_settings()
    model = fw.receiver()
    accs, _ = fw.instrument.render_sums(list(range(COLUMNS)), cfg, 1,
                                        [fw.power_w()[:, c] for c in range(COLUMNS)],
                                        calibration=False, complete=True)
    accs = np.array(accs)
    t0 = time.perf_counter()
    rtl = VirtualFirmware(scene, 0, engine="rtl").receiver()   # the board's RTL engine
    build_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    want = model.from_accumulators(accs)
    model_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    got = rtl.from_accumulators(accs)
    rtl_s = time.perf_counter() - t0
    assert all(not w.mismatches(g) for w, g in zip(want, got, strict=True)), "RTL != model"
    p = rtl.params
    print(f"  flat-wall, {COLUMNS} columns, K={p.channels} channels, L={p.lanes} lanes, "
          f"degree {p.max_deg}, S={p.max_s}: RTL outputs equal the model's")
    print(f"  Verilator build (cached after the first run)  {build_s:8.2f} s")
    print(f"  model (FastReceiver)              {COLUMNS / model_s:10.1f} columns/s")
    print(f"  RTL (rx_top under Verilator)      {COLUMNS / rtl_s:10.2f} columns/s")
    print(f"  RTL / model                       {model_s / rtl_s:10.4f} x the model's rate")


if __name__ == "__main__":
    main()
