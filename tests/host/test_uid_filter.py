"""UID filtering: own returns kept (from an extra peak if need be), others named by necklace."""

from __future__ import annotations

import numpy as np
import pytest

from cdma_lidar.errors import ConfigError
from cdma_lidar.firmware_model.uid import canonical_necklace
from cdma_lidar.host.frame import FrameData
from cdma_lidar.host.ranging import FLAG_FOREIGN, FLAG_REJECTED, RangingConfig, estimate_ranges
from cdma_lidar.host.uid_filter import canonical_uids, find_foreign, observed_uids, select_own

N = 3
OURS = 0b001


def _signs(uid: int, n: int = N, polarity: int = 1) -> np.ndarray:
    return np.array([-polarity if (uid >> p) & 1 else polarity for p in range(n)], np.int8)


def _frame() -> FrameData:
    """2 channels x 3 columns, 3 peaks each, hand-made receiver outputs."""
    f = FrameData.empty(2, 3, uid_bits=N, peaks=3)
    f.done[:] = True
    f.noise_count[:] = 40
    f.noise_sum[:] = 0
    f.noise_sumsq[:] = 40 * 100  # sigma = 10 -> SNR_XC = 20 log10(peak / 10)
    f.peak[:] = 5000
    f.peak_lag[:] = 20
    f.neighbours[:] = [4000, 4000]
    f.uid_signs[:] = _signs(OURS)
    f.uid_observed[:] = OURS
    f.uid_match[:] = True
    # Pixel (0, 1): a foreign user (UID 011) is strongest; our echo is extra peak 1.
    f.peak_lag[0, 1], f.peak[0, 1] = 7, 9000
    f.uid_signs[0, 1] = _signs(0b011)
    f.uid_observed[0, 1], f.uid_match[0, 1] = 0b011, False
    f.extra_lag[0, 1] = [40, 21]
    f.extra_peak[0, 1] = [800, 4800]
    f.extra_signs[0, 1] = [_signs(0b000), _signs(OURS)]
    # Pixel (1, 2): a foreign user (rotation 101 of 011) and no echo of ours at all.
    f.peak_lag[1, 2], f.peak[1, 2] = 50, 7000
    f.uid_signs[1, 2] = _signs(0b101)
    f.uid_observed[1, 2], f.uid_match[1, 2] = 0b101, False
    f.extra_peak[1, 2] = [30, 20]  # noise, below threshold
    f.extra_signs[1, 2] = [_signs(0b010), _signs(0b101)]
    # Pixel (1, 0): a zero sign -> no clear identity, not ours, not foreign.
    f.uid_signs[1, 0] = [1, 0, 1]
    f.uid_match[1, 0] = False
    return f


def test_observed_and_canonical():
    obs, clear = observed_uids(np.array([_signs(0b110), [1, 0, -1]]))
    assert obs.tolist() == [0b110, 0b100] and clear.tolist() == [True, False]
    vals = np.arange(8)
    assert canonical_uids(vals, 3).tolist() == [canonical_necklace(int(v), 3) for v in vals]
    assert canonical_uids(np.array([0b110, 0b101, 0b011]), 3).tolist() == [3, 3, 3]
    with pytest.raises(ConfigError, match="uid"):
        canonical_uids(np.array([8]), 3)


def test_select_own_uses_matching_extra_peak():
    own = select_own(_frame(), OURS)
    assert own.source.tolist() == [[0, 2, 0], [-1, 0, -1]]
    assert own.lag[0, 1] == 21 and own.peak[0, 1] == 4800
    assert not own.has_neighbours[0, 1]
    assert own.foreign.tolist() == [[False, False, False], [False, False, True]]


def test_find_foreign_names_users_by_necklace():
    f = find_foreign(_frame(), OURS, snr_threshold_db=20.0, column_support=False)
    got = sorted(zip(f.channel.tolist(), f.column.tolist(), f.lag.tolist(), f.user.tolist(),
                     strict=True))
    # (0,1) primary UID 011 -> user 3; (0,1) extra 0 (UID 000, 38 dB) -> user 0;
    # (1,2) primary 101 -> user 3 again. Noise extras (< 20 dB) are not reported.
    assert got == [(0, 1, 7, 3), (0, 1, 40, 0), (1, 2, 50, 3)]
    assert f.users() == {0: 1, 3: 2}
    # A user must repeat in an adjacent column (same channel, lag within 1.5 samples).
    assert len(find_foreign(_frame(), OURS, snr_threshold_db=20.0)) == 0
    fr = _frame()
    fr.peak_lag[0, 2], fr.peak[0, 2] = 8, 9000  # user 3 again, one column on, lag 8
    fr.uid_signs[0, 2] = _signs(0b011)
    fr.uid_match[0, 2] = False
    g = find_foreign(fr, OURS, snr_threshold_db=20.0)
    assert sorted(zip(g.column.tolist(), g.lag.tolist(), strict=True)) == [(1, 7), (2, 8)]


def test_complement_of_our_uid_is_cross_talk_not_a_user():
    fr = _frame()
    fr.uid_signs[1, 2] = _signs(0b110)  # ~001 = 110 -> our own signal, negative sidelobe
    f = find_foreign(fr, OURS, snr_threshold_db=20.0, column_support=False)
    assert (1, 2) not in set(zip(f.channel.tolist(), f.column.tolist(), strict=True))


def test_ranges_flag_foreign_and_keep_ours():
    cfg = RangingConfig(samples_per_chip=4, code_length=2047, snr_threshold_db=20.0,
                        foreign_threshold_db=20.0, uid=OURS, min_support=0)
    img = estimate_ranges(_frame(), cfg)
    assert img.flags[1, 2] == FLAG_REJECTED | FLAG_FOREIGN
    assert img.flags[1, 0] == FLAG_REJECTED  # unclear identity: rejected, not foreign
    assert img.flags[0, 1] == 0  # our echo recovered from the extra peak
    assert img.lag[0, 1] == 21.0  # no neighbours: integer lag
    assert img.range_m[0, 1] == pytest.approx(21 * 0.599584916)
    assert np.isnan(img.range_m[1, 2])
    assert len(img.foreign) == 3


def test_wrong_uid_rejected():
    with pytest.raises(ConfigError, match="uid"):
        select_own(_frame(), 8)


def test_unexplained_primary_does_not_hand_the_pixel_to_an_extra_peak():
    fr = _frame()
    # (1, 1): primary reads ~001 = 110 (our own cross-talk or noise), extra 0 reads ours.
    fr.uid_signs[1, 1] = _signs(0b110)
    fr.uid_match[1, 1] = False
    fr.extra_peak[1, 1], fr.extra_lag[1, 1] = [4000, 0], [33, 0]
    fr.extra_signs[1, 1] = [_signs(OURS), _signs(0)]
    own = select_own(fr, OURS)
    assert own.source[1, 1] == -1 and not own.foreign[1, 1]
    # The same extra peak is taken when the primary is another user's (UID 011).
    fr.uid_signs[1, 1] = _signs(0b011)
    own = select_own(fr, OURS)
    assert own.source[1, 1] == 1 and own.lag[1, 1] == 33
