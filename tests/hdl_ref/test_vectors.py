"""``cdma-lidar hdl vectors`` round trip: files from the model, checked by plain Verilog.

The exported files drive ``hdl_ref/tb/rx_top_vectors_tb.v`` under Icarus with no
Python in the loop; it must report PASS, and FAIL once one expected word is
changed (the comparison can fail). Bad ``--set`` values exit with status 2 and
one line naming the key.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from cdma_lidar.cli import main
from cdma_lidar.hdl_ref import cosim

TB = Path(cosim.RTL_DIR).parent / "tb" / "rx_top_vectors_tb.v"
SOURCES = cosim.TOP_FILES
SETTINGS = ["degree=6", "channels=4", "lanes=2", "uid_bits=2", "uid=1", "peaks=2",
            "ghost=50:3", "out_shift=3", "rounding=convergent", "averages=3"]


def _run_tb(vec: Path, tmp: Path) -> str:
    vvp = tmp / "tb.vvp"
    rtl = cosim.default_rtl_dir()
    subprocess.run(["iverilog", "-g2005", "-I", str(vec), "-o", str(vvp), str(TB),
                    *(str(rtl / n) for n in SOURCES)], check=True, capture_output=True,
                   text=True)
    out = subprocess.run(["vvp", "-n", str(vvp), f"+VEC={vec}/"], check=True,
                         capture_output=True, text=True, timeout=300).stdout
    return [line for line in out.splitlines() if line.startswith("rx_top vectors:")][-1]


@pytest.fixture(scope="module")
def vec(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("vectors")
    args = ["hdl", "vectors", *[a for s in SETTINGS for a in ("--set", s)],
            "--columns", "3", "--seed", "5", "--out", str(out)]
    assert main(args) == 0
    return out


def test_vector_files_and_readme(vec):
    names = {p.name for p in vec.iterdir()}
    assert names == {"README.md", "params.vh", "config.hex", "adc.hex", "corr.hex",
                     "results.hex"}
    readme = (vec / "README.md").read_text()
    for name in names - {"README.md"}:
        assert f"`{name}`" in readme
    params = (vec / "params.vh").read_text()
    n_adc = int(params.split("VEC_N_ADC ")[1].split()[0])
    assert len((vec / "adc.hex").read_text().split()) == n_adc == 3 * 3 * 2 * 63 * 2


@pytest.mark.hdl
def test_rtl_passes_its_vectors_without_python(vec, tmp_path):
    if not cosim.iverilog_available():
        pytest.skip("Icarus Verilog is not installed")
    assert _run_tb(vec, tmp_path).startswith("rx_top vectors: PASS")
    bad = tmp_path / "bad"
    shutil.copytree(vec, bad)
    lines = (bad / "results.hex").read_text().splitlines()
    lines[3] = format(int(lines[3], 16) ^ 1, f"0{len(lines[3])}x")   # res_peak of channel 0
    (bad / "results.hex").write_text("\n".join(lines) + "\n")
    assert _run_tb(bad, tmp_path).startswith("rx_top vectors: FAIL 1 of")


#: Builds whose MAX_G = 2^k - 1 (the correlation-RAM address is one bit wider than the
#: gate index there), with two peaks so the second peak's index sits next to the first's
#: in the packed register; gate_len=31 alone is the contract of issue 27.
EDGE_SETS = {
    "gate31": ["gate_len=31"],
    "gate31-two-peaks": ["degree=6", "gate_len=31", "peaks=2", "peak_exclude=1",
                         "gate_start=100", "noise=0.2"],
    "gate15-two-peaks": ["degree=5", "gate_len=15", "peaks=2", "samples_per_chip=1",
                         "channels=2", "gate_start=3"],
    "gate63-two-peaks": ["degree=6", "gate_len=63", "peaks=2", "uid_bits=2", "uid=2"],
    # P samples per clock: the file is read P words at a time
    "two-per-clock": ["samples_per_clock=2", "samples_per_chip=2", "lanes=3", "uid_bits=2"],
    "four-per-clock": ["samples_per_clock=4", "samples_per_chip=4", "degree=5", "channels=3",
                       "peaks=2"],
}


@pytest.mark.hdl
@pytest.mark.parametrize("name", sorted(EDGE_SETS))
def test_edge_builds_pass_their_vectors(tmp_path, name):
    if not cosim.iverilog_available():
        pytest.skip("Icarus Verilog is not installed")
    vec = tmp_path / "vec"
    args = ["hdl", "vectors", *[a for s in EDGE_SETS[name] for a in ("--set", s)],
            "--columns", "2", "--seed", "3", "--out", str(vec)]
    assert main(args) == 0
    assert _run_tb(vec, tmp_path).startswith("rx_top vectors: PASS")


@pytest.mark.parametrize(("setting", "named"), [
    ("degree=3", "degree"), ("averages=x", "averages"), ("colour=1", "--set"),
    ("ghost=5", "ghost"), ("gate_len=999", "gate_len"),
    ("samples_per_clock=3", "samples_per_clock"),
])
def test_bad_setting_exits_2_with_one_line(tmp_path, capsys, setting, named):
    assert main(["hdl", "vectors", "--set", setting, "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and named in err[0]
