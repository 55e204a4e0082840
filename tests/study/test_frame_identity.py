"""The contract of ``cdma-lidar study frame``: a study frame and a scan of the virtual device
over the protocol write the same arrays with equal values (the scan's wall-clock stamp aside).

Both go through one acquisition path (:func:`cdma_lidar.scene.acquire.acquire`) with the
device's receiver configuration and the scan's default power; here the scan goes through
``virtual://``, the protocol and the host's pipeline, the study frame through none of them.
"""

from __future__ import annotations

import numpy as np
import pytest
from cli_helpers import run_cli as _run

#: Flat wall with a reduced column count: a small frame through both paths.
SCENE = "flat-wall"


@pytest.mark.parametrize(("seed", "frame_id"), [(1, 0), (3, 2)])
def test_study_frame_writes_the_arrays_of_a_virtual_scan(capsys, tmp_path, seed, frame_id):
    scan, study = tmp_path / "scan.npz", tmp_path / "study.npz"
    code, _, _ = _run(capsys, "scan", "--port", f"virtual://{SCENE}?seed={seed}",
                      "--frame-id", str(frame_id), "--out", str(scan), "--no-progress")
    assert code == 0
    code, out, _ = _run(capsys, "study", "frame", SCENE, "--seed", str(seed),
                        "--frame-id", str(frame_id), "--out", str(study))
    assert code == 0
    assert str(study) in out
    with np.load(scan) as a, np.load(study) as b:
        assert sorted(a.files) == sorted(b.files)
        names = [n for n in a.files if n != "stamp_unix_s"]
        for name in names:
            x, y = a[name], b[name]
            assert x.dtype == y.dtype, name
            np.testing.assert_array_equal(x, y, err_msg=name)
        assert np.isfinite(a["range"]).any()  # the wall is ranged: not two empty clouds


def test_study_frames_of_other_seeds_differ(tmp_path, capsys):
    """The comparison can fail: another seed's frame is not the same arrays."""
    one, two = tmp_path / "one.npz", tmp_path / "two.npz"
    for path, seed in ((one, 1), (two, 2)):
        assert _run(capsys, "study", "frame", SCENE, "--seed", str(seed), "--out",
                    str(path))[0] == 0
    with np.load(one) as a, np.load(two) as b:
        assert not np.array_equal(a["snr_xc"], b["snr_xc"])


def test_study_frame_refuses_a_negative_seed_in_one_line(capsys, tmp_path):
    code, _, err = _run(capsys, "study", "frame", SCENE, "--seed", "-1", "--out",
                        str(tmp_path / "x.npz"))
    assert code == 2
    assert "--seed" in err and len(err.strip().splitlines()) == 1


def test_a_study_frames_power_is_refused_over_the_cap_as_the_device_refuses_it():
    """The study link keeps the device's power matrix: a column over the eye-safety cap
    is a DeviceError naming ``power`` (what the wire's NAK gives the host's scan)."""
    from cdma_lidar.errors import DeviceError
    from cdma_lidar.study.simulate import FrameLink

    link = FrameLink(f"{SCENE}?instrument.columns=2", 1)
    k = link.info.channels
    with pytest.raises(DeviceError) as info:
        link.set_power(np.full((k, 2), 65535))
    assert info.value.field == "power"
    link.set_power(np.full((k, 2), 7))
    (col,) = list(link.scan(0, 1, frame=0))
    assert col.column == 0 and col.frame == 0
