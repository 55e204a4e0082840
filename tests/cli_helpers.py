"""Running the ``cdma-lidar`` command in-process from tests (imported by name: the
``pythonpath`` of pytest's settings in pyproject.toml includes ``tests``)."""

from __future__ import annotations

from cdma_lidar.cli import main


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    """Exit status, stdout and stderr of ``cdma-lidar ARGV`` (argparse exits included)."""
    try:
        code = main(list(argv))
    except SystemExit as exc:  # argparse usage errors
        code = int(exc.code or 0)
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def one_line_error(capsys, *argv: str) -> str:
    """The one line a refused command prints on stderr (log lines aside); exit status 2."""
    code, _, err = run_cli(capsys, *argv)
    assert code == 2, err
    lines = [ln for ln in err.splitlines() if not ln.startswith(("WARNING", "INFO"))]
    assert len(lines) == 1, err
    return lines[0]
