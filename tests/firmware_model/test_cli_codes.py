"""The ``cdma-lidar codes`` CLI contract: forms, formats, exit status 2 on bad arguments."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cdma_lidar.cli import main
from cdma_lidar.firmware_model import cli, uid
from cdma_lidar.firmware_model.commands import format_chips
from cdma_lidar.firmware_model.gold import gold_code, gold_seeds
from cdma_lidar.firmware_model.lfsr import mseq
from cdma_lidar.firmware_model.pairs import preferred_pairs
from cdma_lidar.firmware_model.uid import necklaces


def run(capsys, *argv):
    """Run the CLI in-process; returns (status, stdout, stderr)."""
    try:
        status = main(list(argv))
    except SystemExit as exc:  # argparse usage errors
        status = exc.code
    out, err = capsys.readouterr()
    return status, out, err


def bits_of(line):
    return np.frombuffer(line.encode(), dtype=np.uint8) - ord("0")


def test_mseq_bits_default_one_period(capsys):
    status, out, err = run(capsys, "codes", "mseq", "--poly", "10,3")
    assert status == 0 and err == ""
    assert out.count("\n") == 1 and set(out.strip()) <= {"0", "1"}
    assert np.array_equal(bits_of(out.strip()), mseq((10, 3)))


def test_mseq_seed_chips_formats(capsys):
    seed = "1000000001"
    expected = mseq((10, 3), seed, chips=37)
    _, out, _ = run(capsys, "codes", "mseq", "--poly", "10,3", "--seed", seed, "--chips", "37",
                    "--format", "bits")
    assert np.array_equal(bits_of(out.strip()), expected)
    _, out, _ = run(capsys, "codes", "mseq", "--poly", "10,3", "--seed", seed, "--chips", "37",
                    "--format", "bipolar")
    assert [int(x) for x in out.split()] == (1 - 2 * expected.astype(int)).tolist()
    _, out, _ = run(capsys, "codes", "mseq", "--poly", "10,3", "--seed", seed, "--chips", "37",
                    "--format", "hex")
    line = out.strip()
    assert len(line) == 2 * 5  # ceil(37 / 8) bytes
    unpacked = np.unpackbits(np.frombuffer(bytes.fromhex(line), dtype=np.uint8))
    assert np.array_equal(unpacked[:37], expected) and not unpacked[37:].any()


def test_format_chips_hex_msb_first():
    assert format_chips(np.array([1, 0, 0, 0, 0, 0, 0, 1, 1]), "hex") == "8180"


def test_gold_member(capsys):
    argv = ["codes", "gold", "--poly-u", "10,3", "--poly-v", "10,9,8,6,3,2"]
    for k in (0, 3, 1023, 1024):
        status, out, _ = run(capsys, *argv, "--index", str(k))
        assert status == 0
        assert np.array_equal(bits_of(out.strip()), gold_code((10, 3), (10, 9, 8, 6, 3, 2), k))
    _, out, _ = run(capsys, *argv, "--index", "5", "--seed-u", "1010101010", "--seed-v",
                    "0000000001", "--chips", "3000")
    expected = gold_code((10, 3), (10, 9, 8, 6, 3, 2), 5, chips=3000, seed_u="1010101010",
                         seed_v="0000000001")
    assert np.array_equal(bits_of(out.strip()), expected)


def test_pairs_lists_table(capsys):
    status, out, _ = run(capsys, "codes", "pairs")
    assert status == 0
    rows = out.strip().splitlines()[1:]
    assert len(rows) == sum(len(preferred_pairs(m)) for m in range(5, 21) if m % 4)
    assert any(r.split()[:3] == ["11", "11,2", "11,8,5,2"] for r in rows)
    status, out, _ = run(capsys, "codes", "pairs", "--degree", "10", "--verify")
    assert status == 0
    rows = out.strip().splitlines()[1:]
    assert len(rows) == len(preferred_pairs(10)) and all(r.split()[5] == "yes" for r in rows)


def test_check_preferred_and_not(capsys):
    status, out, _ = run(capsys, "codes", "check", "--poly-u", "11,2", "--poly-v", "11,8,5,2")
    assert status == 0
    lines = out.strip().splitlines()
    counts = {int(a): int(b) for a, b in (line.split() for line in lines[2:-1])}
    assert counts == {-65: 496, -1: 1023, 63: 528}
    assert lines[-1] == "preferred: yes"
    _, out, _ = run(capsys, "codes", "check", "--poly-u", "11,9", "--poly-v", "11,10,9,7")
    assert out.strip().splitlines()[-1] == "preferred: no"


def test_uid(capsys):
    status, out, _ = run(capsys, "codes", "uid", "--bits", "4")
    assert status == 0
    lines = out.strip().splitlines()
    assert [int(line.split()[0]) for line in lines[1:-1]] == necklaces(4)
    assert lines[-1] == "u(4) = 6"


def test_the_help_s_uid_limit_is_the_model_s():
    """The parser writes the limit out (no numpy for --help); it must be uid's."""
    assert cli.MAX_UID_BITS == uid.MAX_UID_BITS


def test_seeds(capsys):
    _, out, _ = run(capsys, "codes", "seeds", "--poly-u", "11,2", "--poly-v", "11,8,5,2",
                    "--index", "77")
    assert tuple(out.split()) == gold_seeds((11, 2), (11, 8, 5, 2), 77)


@pytest.mark.parametrize(
    ("argv", "names"),
    [
        (["mseq", "--poly", "10,4"], "--poly"),
        (["mseq", "--poly", "10,x"], "--poly"),
        (["mseq", "--poly", "40,3"], "--poly"),
        (["mseq", "--poly", "10,3", "--seed", "0000000000"], "--seed"),
        (["mseq", "--poly", "10,3", "--seed", "101"], "--seed"),
        (["mseq", "--poly", "10,3", "--chips", "-4"], "--chips"),
        (["mseq", "--poly", "10,3", "--chips", "many"], "--chips"),
        (["mseq", "--poly", "10,3", "--format", "octal"], "--format"),
        (["gold", "--poly-u", "10,3", "--poly-v", "11,2", "--index", "0"], "--poly-v"),
        (["gold", "--poly-u", "10,3", "--poly-v", "10,8,3,2", "--index", "1025"], "--index"),
        (["gold", "--poly-u", "10,3", "--poly-v", "10,8,3,2"], "--index"),
        (["gold", "--poly-u", "10,3", "--poly-v", "10,8,3,2", "--index", "1",
          "--seed-v", "2"], "--seed-v"),
        (["pairs", "--degree", "12"], "--degree"),
        (["pairs", "--degree", "21"], "--degree"),
        (["check", "--poly-u", "11,2", "--poly-v", "11,1"], "--poly-v"),
        (["uid", "--bits", "0"], "--bits"),
        (["uid", "--bits", "25"], "--bits"),
        (["mseq", "--poly", "32,22,2,1"], "--chips"),  # one period is 4 G chips
        (["mseq", "--poly", "10,3", "--chips", str((1 << 26) + 1)], "--chips"),
        (["gold", "--poly-u", "32,22,2,1", "--poly-v", "32,7,5,3,2,1", "--index", "0"],
         "--chips"),
        (["check", "--poly-u", "25,3", "--poly-v", "25,3"], "--poly-u"),
        (["seeds", "--poly-u", "5,2", "--poly-v", "5,4,3,2", "--index", "34"], "--index"),
    ],
)
def test_bad_arguments_exit_2_with_one_line(capsys, argv, names):
    status, out, err = run(capsys, "codes", *argv)
    assert status == 2
    assert out == ""
    assert err.count("\n") == 1 and names in err


def test_long_codes_print_only_the_requested_chips(capsys):
    status, out, err = run(capsys, "codes", "gold", "--poly-u", "32,22,2,1", "--poly-v",
                           "32,7,5,3,2,1", "--index", str((1 << 32) - 1 - 3), "--chips", "64")
    assert status == 0 and err == ""
    want = mseq((32, 22, 2, 1), chips=64) ^ mseq((32, 7, 5, 3, 2, 1), chips=67)[3:]
    assert np.array_equal(bits_of(out.strip()), want)
    status, out, _ = run(capsys, "codes", "mseq", "--poly", "32,22,2,1", "--chips", "16",
                         "--format", "hex")
    assert status == 0 and out == "ffff\n"  # default seed: the first 32 chips are ones


def test_console_script_subprocess():
    exe = Path(sys.executable).with_name("cdma-lidar")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "cdma_lidar.cli"]
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    res = subprocess.run([*cmd, "codes", "gold", "--poly-u", "11,2", "--poly-v", "11,8,5,2",
                          "--index", "3", "--chips", "32", "--format", "bits"],
                         capture_output=True, text=True, env=env, timeout=60, check=False)
    assert res.returncode == 0 and res.stderr == ""
    assert res.stdout == format_chips(gold_code((11, 2), (11, 8, 5, 2), 3, chips=32), "bits") + "\n"
    bad = subprocess.run([*cmd, "codes", "pairs", "--degree", "8"], capture_output=True,
                         text=True, env=env, timeout=60, check=False)
    assert bad.returncode == 2 and bad.stdout == "" and bad.stderr.count("\n") == 1
