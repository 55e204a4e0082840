"""Power you can check: cap in INFO, POWER_GET, exact integer cap, boot matrix within the cap."""

from __future__ import annotations

import numpy as np
import pytest

import cdma_lidar.virtual  # noqa: F401 - registers virtual://
from cdma_lidar.errors import DeviceError
from cdma_lidar.protocol.link import HostLink
from cdma_lidar.protocol.messages import ErrorCode, MsgType
from cdma_lidar.protocol.ports import open_port
from cdma_lidar.scene.acquire import within_cap

# 1 mW is exactly code 1000 at a 65.535 mW pixel maximum; 4 channels x 1 mW = the cap.
URL = ("virtual://flat-wall?instrument.wavelengths.count=4&instrument.columns=3"
       "&instrument.max_pixel_power_w=0.065535&instrument.total_power_cap_w=0.004"
       "&instrument.laser_power_w=0.001")


def test_cap_announced_matrix_read_back_and_checked_in_exact_integers() -> None:
    with HostLink(open_port(URL), timeout_s=1.0, max_frame=96) as link:
        info = link.hello()
        assert (info.pixel_power_max_uw, info.column_power_cap_uw) == (65535, 4000)
        boot = link.get_power()
        assert boot.shape == (4, 3) and (boot == 1000).all()  # exactly at the cap: kept
        link.set_power(np.full((4, 3), 1000))  # 4 x 1 mW = 4000 µW: exactly the cap
        over = np.full((4, 3), 1000)
        over[2, 1] = 1001
        with pytest.raises(DeviceError) as exc:
            link.set_power(over)
        assert exc.value.code == ErrorCode.OUT_OF_RANGE and exc.value.field == "power"
        assert "4001.000 µW" in str(exc.value) and "column 1" in str(exc.value)
        assert (link.get_power() == 1000).all()  # refused: unchanged
        link.set_power(np.full((4, 1), 500), column_start=2)  # lowering is always fine
        assert (link.get_power()[:, 2] == 500).all()
        with pytest.raises(DeviceError) as exc:
            link.request(MsgType.POWER_GET, {"channel_start": 3, "column_start": 0,
                                               "channels": 2, "columns": 1})
        assert exc.value.field == "channels"


def test_a_rounded_boot_matrix_is_brought_within_the_cap() -> None:
    codes = np.array([[32768, 10], [32768, 10]], dtype=np.int64)  # 65536 codes: 1 over
    out = within_cap(codes, pixel_uw=1000, cap_uw=1000)  # cap = 65535 codes per column
    assert out.sum(axis=0).tolist() == [65535, 20]
    assert (out <= codes).all()
