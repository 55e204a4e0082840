"""``rx_adc_top``: the ADC deserialiser and clock-domain crossing, and R_MIN, against the model.

The fixed-rate ADC bench (``hdl_ref/tb/rx_adc_top_vectors_check.v``, plain Verilog, with
its clocks from ``rx_adc_top_vectors_tb.v`` under Icarus or from a C++ loop under
Verilator) plays ``cdma-lidar hdl vectors`` files one sample per ADC clock (4.000 ns) into
``rx_adc_top`` while the fabric clock runs unrelated to it (its own period and start
phase) and compares every word with the model's. R_MIN is derived once in Python
(``adc_top.r_min``) and once in Verilog (``r_min_rom.v``); they must agree everywhere.
"""

from __future__ import annotations

import dataclasses
import subprocess
from pathlib import Path

import pytest

from cdma_lidar.errors import ConfigError
from cdma_lidar.firmware_model.pairs import PAPER_PAIR
from cdma_lidar.firmware_model.receiver import ReceiverConfig
from cdma_lidar.hdl_ref import adc_top, cosim
from cdma_lidar.hdl_ref.vectors import VectorSpec, write_vectors

pytestmark = pytest.mark.skipif(not cosim.iverilog_available(),
                                reason="Icarus Verilog is not installed")

#: the normal suite's build: 4 samples per fabric clock, R_MIN = 6 at degree 6, S = 4
SMALL = cosim.TopParams(channels=2, lanes=4, max_deg=6, max_s=4, max_uid=1, max_r=8, max_g=8,
                        max_p=1, nghost=1, adc_w=12, out_w=32, samples_per_clock=4)
#: the paper's instrument at 62.5 MHz: 40 channels x 16 lanes, 4 samples per clock
PAPER_P4 = cosim.TopParams(channels=40, lanes=16, max_deg=11, max_s=4, max_uid=1, max_r=16,
                           max_g=64, max_p=1, nghost=1, adc_w=12, out_w=32,
                           samples_per_clock=4)
#: the paper's instrument at 250 MHz: 40 channels x 2 lanes, 1 sample per clock
PAPER_P1 = dataclasses.replace(PAPER_P4, lanes=2, samples_per_clock=1)
ADC_PS = 4000
#: both simulators of the bench (Verilator: a C++ clock loop, no --timing; one ~10 s build)
SIMS = ["icarus", pytest.param("verilator", marks=pytest.mark.skipif(
    not cosim.verilator_available(), reason="Verilator or g++ is not installed"))]
#: a fabric clock 312 ppm faster than 4 ADC periods (16 ns), started 1.3 ns after it
FAB_PS, PHASE_PS = 15995, 1300

RMIN_TB = adc_top.TB.parent / "r_min_tb.v"
SWEEP = [SMALL, PAPER_P4, PAPER_P1,
         dataclasses.replace(SMALL, samples_per_clock=1, lanes=1, channels=1),
         dataclasses.replace(SMALL, samples_per_clock=2, max_p=3, max_g=15, max_r=64),
         cosim.TopParams(channels=9, lanes=4, max_deg=7, max_s=3, max_uid=2, max_r=64,
                         max_g=31, max_p=2),
         cosim.TopParams(channels=8, lanes=5, max_deg=9, max_s=8, max_r=1024, max_g=256,
                         max_p=8, samples_per_clock=8),
         # at degree 3, process is a whole number of columns: R_MIN's "+ 1" decides there
         cosim.TopParams(channels=1, lanes=1, max_deg=5, max_s=2, max_r=64, max_g=31)]


def _verilog_table(params: cosim.TopParams, tmp: Path) -> tuple[int, dict]:
    vvp = tmp / "r_min.vvp"
    gen = {"K": params.channels, "L": params.lanes, "P_IN": params.samples_per_clock,
           "MAX_DEG": params.max_deg, "MAX_S": params.max_s, "MAX_R": params.max_r,
           "MAX_G": params.max_g, "MAX_P": params.max_p}
    subprocess.run(["iverilog", "-g2005", "-o", str(vvp),
                    *(a for k, v in gen.items() for a in ("-P", f"r_min_tb.{k}={v}")),
                    str(RMIN_TB), str(cosim.default_rtl_dir() / "r_min_rom.v")],
                   check=True, capture_output=True, text=True)
    lines = subprocess.run(["vvp", "-n", str(vvp)], check=True, capture_output=True,
                           text=True).stdout.split("\n")
    head = int(lines[0].split()[1])
    table = {(int(d), int(s)): int(r) for d, s, r in (x.split() for x in lines[1:] if x)}
    return head, table


@pytest.mark.hdl
@pytest.mark.parametrize("params", SWEEP, ids=lambda p: f"K{p.channels}L{p.lanes}P"
                         f"{p.samples_per_clock}D{p.max_deg}")
def test_r_min_verilog_equals_python(params, tmp_path):
    """Every degree and samples_per_chip code of the build: the same R_MIN both sides (eight
    builds: the paper's at P_IN = 1 and 4, other P_IN, lanes, gates and peaks)."""
    head, table = _verilog_table(params, tmp_path)
    assert head == adc_top.r_min(params, params.max_deg, params.max_s)
    assert len(table) == (1 << params.max_deg.bit_length()) * (1 << params.max_s.bit_length())
    assert table == {(d, s): adc_top.r_min(params, d, s) for d, s in table}
    assert any(r <= params.max_r for r in table.values())      # some configuration runs


def test_r_min_is_the_real_time_edge():
    """At R_MIN the worst configuration keeps up, at R_MIN - 1 it falls behind; the paper
    builds' values (P = 4 with 16 lanes: the issue's "R >= 10")."""
    assert adc_top.r_min(PAPER_P4, 11, 4) == 10
    assert adc_top.r_min(PAPER_P1, 11, 4) == 10
    # at R = 1 no lane count helps: the post-processing alone outlasts the column
    paper = {"cfg_degree": 11, "cfg_spc": 4, "cfg_uid_bits": 1, "cfg_averages": 1,
             "cfg_gate_len": 64, "cfg_peaks": 1}
    t = cosim.top_timing(paper, PAPER_P4)
    post = t["process"] - t["stream"] - 40 * 16 - 17
    assert (t["column_clocks"], post) == (2047, 5560)
    exact = 0               # entries whose process is a whole number of R = 1 columns
    for params in SWEEP:
        for d in range(3, params.max_deg + 1):
            for s in range(1, params.max_s + 1):
                r = adc_top.r_min(params, d, s)
                if r > params.max_r:
                    continue
                worst = {"cfg_degree": d, "cfg_spc": s, "cfg_uid_bits": 1,
                         "cfg_gate_len": params.max_g, "cfg_peaks": params.max_p}
                t = [cosim.top_timing({**worst, "cfg_averages": x}, params) for x in (r - 1, r)]
                assert t[1]["process"] + 1 <= t[1]["column_clocks"]
                assert r == 1 or t[0]["process"] + 1 > t[0]["column_clocks"]
                exact += t[1]["process"] % (t[1]["column_clocks"] // r) == 0
    assert exact > 0        # the sweep reaches the boundary where process + 1 matters


def _spec(averages: int, params: cosim.TopParams = SMALL) -> VectorSpec:
    cfg = ReceiverConfig(adc_bits=12, samples_per_chip=4, averages=averages,
                         gate_len=params.max_g, gate_start=40)
    return VectorSpec(cfg=cfg, degree=params.max_deg, channels=params.channels,
                      lanes=params.lanes, samples_per_clock=params.samples_per_clock)


def test_python_refuses_below_r_min():
    r = adc_top.r_min(SMALL, 6, 4)
    spec = _spec(r)
    adc_top.adc_ports(spec.cfg, *spec.polys(), spec.indices(), SMALL)
    with pytest.raises(ConfigError, match=f"averages must be {r}..8"):
        spec = _spec(r - 1)
        adc_top.adc_ports(spec.cfg, *spec.polys(), spec.indices(), SMALL)


@pytest.fixture(scope="module")
def small_vectors(tmp_path_factory) -> dict[int, Path]:
    """Vector folders (3 columns) at R_MIN and R_MIN - 1 of the small build."""
    r = adc_top.r_min(SMALL, 6, 4)
    return {x: write_vectors(_spec(x), 3, 1, tmp_path_factory.mktemp(f"adc_r{x}"),
                             params=SMALL) for x in (r, r - 1)}


@pytest.mark.hdl
@pytest.mark.parametrize("sim", SIMS)
def test_two_clocks_every_sample_arrives_exact(small_vectors, tmp_path, sim):
    """R_MIN, fabric 312 ppm fast and 1.3 ns late: every sample taken, every word the model's;
    a changed expected word fails (the comparison can fail), under both simulators."""
    vec = small_vectors[adc_top.r_min(SMALL, 6, 4)]
    line = adc_top.run_adc_bench(vec, tmp_path, ADC_PS, FAB_PS, PHASE_PS, simulator=sim)
    assert line.startswith("rx_adc_top vectors: PASS") and "4536 samples taken" in line
    assert adc_top.run_adc_bench(_changed_word(vec, tmp_path), tmp_path, ADC_PS, FAB_PS,
                                 PHASE_PS, simulator=sim).startswith(
        "rx_adc_top vectors: FAIL 1 of")


@pytest.mark.hdl
@pytest.mark.parametrize("fab_ps, phase_ps", [(16_000, 0), (15_996, 3_700), (16_005, 2_100),
                                              (12_000, 900)])
def test_other_fabric_clocks_and_phases(small_vectors, tmp_path, fab_ps, phase_ps):
    """The same stream through other phases, a fabric clock 312 ppm slow (its FIFO takes up
    the lag over a run this short) and a much faster one."""
    vec = small_vectors[adc_top.r_min(SMALL, 6, 4)]
    assert adc_top.run_adc_bench(vec, tmp_path, ADC_PS, fab_ps, phase_ps).startswith(
        "rx_adc_top vectors: PASS")


@pytest.mark.hdl
def test_source_pauses(small_vectors, tmp_path):
    """adc_valid drops for 37 ADC clocks after every 1 001 samples (mid-word too): the FIFO
    runs empty, and no word is read twice or early."""
    vec = small_vectors[adc_top.r_min(SMALL, 6, 4)]
    line = adc_top.run_adc_bench(vec, tmp_path, ADC_PS, FAB_PS, PHASE_PS, gap=(1001, 37))
    assert line.startswith("rx_adc_top vectors: PASS") and "4536 samples taken" in line


@pytest.mark.hdl
@pytest.mark.parametrize("sim", SIMS)
def test_slow_fabric_clock_flags_overflow(small_vectors, tmp_path, sim):
    """A fabric clock of 20 ns takes 200 MS/s of a 250 MS/s stream: err_overflow rises."""
    vec = small_vectors[adc_top.r_min(SMALL, 6, 4)]
    line = adc_top.run_adc_bench(vec, tmp_path, ADC_PS, 20_000, PHASE_PS, simulator=sim)
    assert line.startswith("rx_adc_top vectors: FAIL overflow (err_overflow)")


@pytest.mark.hdl
def test_r_min_minus_one_is_refused_by_the_rtl(small_vectors, tmp_path):
    """R_MIN - 1: start is refused (err_config), rx_top never starts."""
    vec = small_vectors[adc_top.r_min(SMALL, 6, 4) - 1]
    assert adc_top.run_adc_bench(vec, tmp_path, ADC_PS, FAB_PS, PHASE_PS) == \
        "rx_adc_top vectors: REFUSED (err_config)"


#: the DDR pins: the converter's data clock at 8.000 ns (125 MHz, 250 MS/s on both edges)
DCO_PS = 8000


def _changed_word(vec: Path, tmp_path: Path) -> Path:
    """A copy of the vector folder whose 6th expected correlation word has its LSB flipped."""
    lines = (vec / "corr.hex").read_text().splitlines()
    lines[5] = format(int(lines[5], 16) ^ 1, f"0{len(lines[5])}x")
    bad = tmp_path / "bad"
    bad.mkdir(exist_ok=True)
    for f in vec.iterdir():
        (bad / f.name).write_text(f.read_text())
    (bad / "corr.hex").write_text("\n".join(lines) + "\n")
    return bad


@pytest.mark.hdl
@pytest.mark.parametrize("sim", SIMS)
def test_ddr_pins_every_sample_arrives_exact(small_vectors, tmp_path, sim):
    """PINS = 1: the samples on the 12 DDR pins of a 125 MHz data clock (both edges, never
    stopping) through IDDRX2F (our model), the FIFO and rx_top at 312 ppm fast and 1.3 ns
    late: every sample taken in order, every word the model's, no overflow although the
    FIFO drops the words nobody wants after the last column; a changed word fails."""
    vec = small_vectors[adc_top.r_min(SMALL, 6, 4)]
    line = adc_top.run_adc_bench(vec, tmp_path, DCO_PS, FAB_PS, PHASE_PS, simulator=sim,
                                 pins=True)
    assert line == "rx_adc_top vectors: PASS 132 words compared, 4536 samples taken"
    assert adc_top.run_adc_bench(_changed_word(vec, tmp_path), tmp_path, DCO_PS, FAB_PS,
                                 PHASE_PS, simulator=sim, pins=True).startswith(
        "rx_adc_top vectors: FAIL 1 of")


@pytest.mark.hdl
@pytest.mark.parametrize("fab_ps, phase_ps", [(16_000, 0), (15_996, 3_700), (16_005, 2_100),
                                              (12_000, 900)])
def test_ddr_pins_other_fabric_clocks(small_vectors, tmp_path, fab_ps, phase_ps):
    """The DDR pins into other fabric phases and rates (in phase with sclk, 312 ppm slow,
    much faster): the same words."""
    vec = small_vectors[adc_top.r_min(SMALL, 6, 4)]
    assert adc_top.run_adc_bench(vec, tmp_path, DCO_PS, fab_ps, phase_ps, pins=True) == \
        "rx_adc_top vectors: PASS 132 words compared, 4536 samples taken"


@pytest.mark.hdl
@pytest.mark.parametrize("sim", SIMS)
def test_ddr_pins_slow_fabric_clock_flags_overflow(small_vectors, tmp_path, sim):
    """A 20 ns fabric clock behind the 250 MS/s pins: a word is lost while rx_top still
    takes them, and err_overflow rises."""
    vec = small_vectors[adc_top.r_min(SMALL, 6, 4)]
    line = adc_top.run_adc_bench(vec, tmp_path, DCO_PS, 20_000, PHASE_PS, simulator=sim,
                                 pins=True)
    assert line.startswith("rx_adc_top vectors: FAIL overflow (err_overflow)")


@pytest.mark.hdl
@pytest.mark.parametrize("sim", SIMS)
def test_ddr_pins_restart(small_vectors, tmp_path, sim):
    """Three acquisitions through the never-stopping pins, each started 24 clocks after the
    last one's done: the FIFO is drained while idle, so each gives the model's words."""
    vec = small_vectors[adc_top.r_min(SMALL, 6, 4)]
    assert adc_top.run_adc_bench(vec, tmp_path, DCO_PS, FAB_PS, PHASE_PS, simulator=sim,
                                 pins=True, runs=3) == \
        "rx_adc_top vectors: PASS 396 words compared, 13608 samples taken"


@pytest.mark.hdl
@pytest.mark.parametrize("sim", SIMS)
def test_ddr_pins_early_restart_is_refused(small_vectors, tmp_path, sim):
    """A start sooner than 2^FIFO_AW + 8 = 24 clocks after done would take a word of the
    last capture still in the FIFO as sample 0: rx_adc_top refuses it (err_config), and
    the first acquisition's words were the model's."""
    vec = small_vectors[adc_top.r_min(SMALL, 6, 4)]
    assert adc_top.run_adc_bench(vec, tmp_path, DCO_PS, FAB_PS, PHASE_PS, simulator=sim,
                                 pins=True, runs=2, restart=10) == \
        "rx_adc_top vectors: REFUSED (err_config)"


def test_ddr_pins_refuse_what_the_pins_cannot_do(small_vectors, tmp_path):
    """The DDR pins make words of 4 samples and never pause: other P_IN or a gap is refused
    by name before anything is compiled, and so are restarts without the pins."""
    vec = small_vectors[adc_top.r_min(SMALL, 6, 4)]
    with pytest.raises(ConfigError, match="gap must be"):
        adc_top.run_adc_bench(vec, tmp_path, DCO_PS, pins=True, gap=(1001, 37))
    with pytest.raises(ConfigError, match="runs must be"):
        adc_top.run_adc_bench(vec, tmp_path, ADC_PS, runs=2)
    p2 = tmp_path / "p2"
    p2.mkdir()
    (p2 / "params.vh").write_text("`define VEC_P 2\n")
    with pytest.raises(ConfigError, match=r"samples_per_clock must be 4 .*, not 2"):
        adc_top.run_adc_bench(p2, tmp_path, DCO_PS, pins=True)


@pytest.mark.hdl
@pytest.mark.slow
@pytest.mark.skipif(not cosim.verilator_available(), reason="Verilator or g++ is not installed")
def test_paper_p4_build_at_r_min(tmp_path):
    """The P = 4 paper build (40 channels x 16 lanes) at R = R_MIN = 10: three columns
    from a 250 MS/s ADC through the FIFO, nothing lost, every word the model's (Verilator:
    25 s with its build; Icarus takes about 17 minutes on the 640 lanes); and the same
    from the DDR pins through adc_pins (a second Verilator build)."""
    r = adc_top.r_min(PAPER_P4, 11, 4)
    cfg = ReceiverConfig(adc_bits=12, samples_per_chip=4, averages=r, gate_len=64,
                         gate_start=3000, out_shift=6, rounding="convergent", out_bits=16)
    spec = VectorSpec(cfg=cfg, degree=11, channels=40, lanes=16, samples_per_clock=4,
                      amplitude=0.02, noise=0.05)
    assert spec.polys() == tuple(PAPER_PAIR)
    adc_top.adc_ports(cfg, *spec.polys(), spec.indices(), PAPER_P4, columns=3)
    vec = write_vectors(spec, 3, 40, tmp_path / "vec", params=PAPER_P4)
    line = adc_top.run_adc_bench(vec, tmp_path, ADC_PS, FAB_PS, PHASE_PS, timeout_s=1800,
                                 simulator="verilator")
    assert line.startswith("rx_adc_top vectors: PASS") and f"{3 * r * 2047 * 4} samples" in line
    # 312 ppm slow: the fabric falls 77 samples behind over the run, more than the FIFO's
    # 16 words of 4 hold besides rx_top's own pauses, so the crossing needs a fabric clock
    # at or above a quarter of the ADC's
    line = adc_top.run_adc_bench(vec, tmp_path, ADC_PS, 16_005, 2_100, simulator="verilator")
    assert line.startswith("rx_adc_top vectors: FAIL overflow (err_overflow)")
    # the same three columns from the DDR pins (125 MHz data clock, IDDRX2F models): exact
    line = adc_top.run_adc_bench(vec, tmp_path, DCO_PS, FAB_PS, PHASE_PS, timeout_s=1800,
                                 simulator="verilator", pins=True)
    assert line.startswith("rx_adc_top vectors: PASS") and f"{3 * r * 2047 * 4} samples" in line
