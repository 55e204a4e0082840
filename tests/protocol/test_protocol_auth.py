"""Access control: key files, challenge-response HELLO, signed frames, refused forgeries."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
from protocol_fixtures import SteppedDevice, SyntheticApp, expected_column

from cdma_lidar.errors import ConfigError, DeviceError, LinkError
from cdma_lidar.host.connection import connect
from cdma_lidar.protocol import auth
from cdma_lidar.protocol.columns import encode_column
from cdma_lidar.protocol.framing import FrameDecoder, encode_frame
from cdma_lidar.protocol.link import HostLink
from cdma_lidar.protocol.messages import ErrorCode, MsgType, encode_payload

KEY = bytes(range(32))
TIMEOUT = 0.2


def test_key_file_is_created_private_and_read_back(tmp_path) -> None:
    path = tmp_path / "device.key"
    key, created = auth.load_or_create_key(path)
    assert created and len(key) == auth.KEY_BYTES
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert auth.load_or_create_key(path) == (key, False)
    assert auth.load_key(path) == key
    os.chmod(path, 0o644)
    with pytest.raises(ConfigError, match="0600"):
        auth.load_key(path)
    path.write_text("not hex")
    os.chmod(path, 0o600)
    with pytest.raises(ConfigError, match="hex digits"):
        auth.load_key(path)


def test_session_macs_are_one_key_per_direction_from_counter_zero() -> None:
    nonces = bytes(range(16, 32)), bytes(range(32, 48))
    to_dev, to_host = auth.session_macs(KEY, *nonces, 0xA1B2C3D4)
    assert to_dev.key != to_host.key and to_dev.counter == to_host.counter == 0
    assert auth.session_macs(KEY, *nonces, 0xA1B2C3D5)[0].key != to_dev.key


def _rig(key: bytes | None, host_key: bytes | None, app: SyntheticApp | None = None):
    """(device, host link, host port, device port, app): one thread, an injected clock."""
    app = app or SyntheticApp(channels=4, columns=20)
    port = SteppedDevice(app, key=key, heartbeat_s=0.05)
    link = HostLink(port, timeout_s=TIMEOUT, retries=2, key=host_key, clock=port.clock)
    return port, link, port, port.endpoint.port, app


def test_signed_session_scans_and_nothing_travels_unsigned() -> None:
    rd, link, host, _dev, _app = _rig(KEY, KEY)
    sent: list[bytes] = []
    write = host.write
    host.write = lambda data: (sent.append(bytes(data)), write(data))[1]  # type: ignore[method-assign]
    with rd as ep:
        info = link.hello()
        assert info.auth == 1
        cols = list(link.scan(frame=3))
        assert [c for c in cols] == [expected_column(3, c, 4, 1, 1) for c in range(20)]
        assert ep.stats.auth_rejected == 0 and link.stats.unauthenticated == 0
    frames = [f for w in sent for f in FrameDecoder().feed(w)]
    assert all(f.sig for f in frames if f.msg_type != MsgType.HELLO)
    assert not any(KEY in w or KEY.hex().encode() in w for w in sent)  # no key on the wire


def test_signed_info_in_fragments_opens_a_session() -> None:
    """A 40-channel INFO is longer than a 96-byte frame: it arrives in FRAGMENTs, each
    signed; the host checks those (the reassembled INFO carries no signature)."""
    port = SteppedDevice(SyntheticApp(channels=40, columns=3), key=KEY, heartbeat_s=0.05)
    link = HostLink(port, timeout_s=TIMEOUT, retries=2, key=KEY, max_frame=96, clock=port.clock)
    with port:
        info = link.hello()
        assert info.auth == 1 and len(link.reply_parts) > 1
        assert [c for c in link.scan(frame=3)] == [expected_column(3, c, 40, 1, 1)
                                                   for c in range(3)]


def test_keyless_host_is_refused_with_one_line() -> None:
    rd, link, *_ = _rig(KEY, None)
    with rd, pytest.raises(LinkError, match="requires a key") as exc:
        link.hello()
    assert "\n" not in str(exc.value) and "--key-file" in str(exc.value)


def test_unsigned_requests_are_refused_auth_required() -> None:
    rd, link, host, _dev, app = _rig(KEY, KEY)
    with rd as ep:
        info = link.hello()
        wire = encode_frame(MsgType.CONFIG_SET, encode_payload(MsgType.CONFIG_SET, {
            "items": [{"key": 16, "value": b"\x03"}]}), 999, info.session_id)
        host.write(wire)  # a local process without the key, in the right session
        ep.poll()
        assert link.get_config()["peaks"] == 1 and app.set_config_calls == 0
        assert ep.stats.naks == 1  # refused AUTH_REQUIRED, not dropped unseen


def test_unsigned_requests_in_pieces_are_refused_auth_required() -> None:
    """As a whole unsigned request: one in unsigned FRAGMENTs of the open signed session
    (an implementer who signs whole frames only) is refused, not dropped unseen."""
    from cdma_lidar.protocol.messages import split_message

    rd, link, host, _dev, app = _rig(KEY, KEY)
    with rd as ep:
        info = link.hello()
        payload = encode_payload(MsgType.CONFIG_SET, {"items": [{"key": 16, "value": b"\x03"}]})
        for piece in split_message(MsgType.CONFIG_SET, payload, 2, 999):
            host.write(encode_frame(MsgType.FRAGMENT, piece, 999, info.session_id))
        ep.poll()
        assert link.get_config()["peaks"] == 1 and app.set_config_calls == 0
        assert ep.stats.naks == 1 and ep.stats.auth_rejected == 0


def test_wrong_key_is_refused_auth_failed() -> None:
    rd, link, *_ = _rig(KEY, bytes(32))
    with rd, pytest.raises(DeviceError) as exc:
        link.hello()
    assert exc.value.code == ErrorCode.AUTH_FAILED


def test_a_keyed_host_refuses_a_device_without_the_key() -> None:
    rd, link, *_ = _rig(None, KEY)
    with rd, pytest.raises(LinkError, match="did not prove"):
        link.hello()


def test_forged_and_replayed_frames_are_dropped() -> None:
    rd, link, host, _dev, app = _rig(KEY, KEY)
    sent: list[bytes] = []
    write = host.write
    host.write = lambda data: (sent.append(bytes(data)), write(data))[1]  # type: ignore[method-assign]
    with rd as ep:
        info = link.hello()
        link.set_config(peaks=2)
        set_wire = sent[-1]
        assert app.set_config_calls == 1
        link.set_config(peaks=1)
        assert app.set_config_calls == 2
        write(set_wire)  # replayed: a valid signature, an old counter
        forged = encode_frame(MsgType.SCAN_ABORT, b"", 500, info.session_id,
                              signer=auth.FrameMac(bytes(32), counter=10**6))
        write(forged)  # signed with another key
        ep.poll()
        assert ep.stats.auth_rejected == 2
        assert app.set_config_calls == 2 and link.get_config()["peaks"] == 1


def test_a_column_injected_mid_scan_is_refused() -> None:
    app = SyntheticApp(channels=4, columns=30)
    rd, link, host, _dev, _app = _rig(KEY, KEY, app)
    with rd:
        info = link.hello()
        scan = link.scan(frame=8)
        first = next(scan)
        bad = expected_column(8, 5, 4, 1, 1)
        rec = bad.records.copy()
        rec["peak_lag"][:] = 7  # a plausible lie: every channel at lag 7
        lie = replace(bad, records=rec)
        for signer in (None, auth.FrameMac(bytes(32), counter=10**6)):
            host.rx.write(encode_frame(MsgType.COLUMN_RESULT, encode_column(lie), 1,
                                       info.session_id, signer=signer))
        rest = list(scan)
    got = [first, *rest]
    assert [c.column for c in got] == list(range(30))
    assert np.array_equal(got[5].peak_lag, expected_column(8, 5, 4, 1, 1).peak_lag)
    assert link.stats.unauthenticated >= 2


def _cli(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cdma_lidar.cli", *args], capture_output=True,
                          text=True, timeout=120, env=env)


def test_tcp_device_needs_a_key_file_or_insecure_loopback() -> None:
    r = _cli("device", "--scene", "flat-wall", "--tcp", "127.0.0.1:0")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "--key-file" in r.stderr
    r = _cli("device", "--scene", "flat-wall", "--tcp", "0.0.0.0:0", "--insecure")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "loopback" in r.stderr


def test_tcp_device_with_a_key_file_end_to_end(tmp_path) -> None:
    key_file = tmp_path / "dev.key"
    proc = subprocess.Popen(
        [sys.executable, "-m", "cdma_lidar.cli", "device", "--scene",
         "flat-wall?instrument.wavelengths.count=4&instrument.columns=2", "--tcp",
         "127.0.0.1:0", "--key-file", str(key_file)], stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True)
    try:
        url = proc.stdout.readline().strip()
        assert stat.S_IMODE(key_file.stat().st_mode) == 0o600
        with pytest.raises(LinkError, match="requires a key"):
            connect(url, timeout_s=2.0)
        with connect(url, timeout_s=2.0, key_file=str(key_file)) as dev:
            assert dev.info.auth == 1
            assert [c.column for c in dev.link.scan(frame=2)] == [0, 1]
        env = {**os.environ, "CDMA_LIDAR_KEY_FILE": str(key_file)}
        r = _cli("info", "--port", url, env=env)
        assert r.returncode == 0, r.stderr
        r = _cli("info", "--port", url)
        assert r.returncode == 2 and "requires a key" in r.stderr
    finally:
        proc.terminate()
        proc.wait(10)


def test_a_flood_of_wrong_macs_from_the_key_holders_address_never_keeps_it_out() -> None:
    """Guessers on 127.0.0.1 (one connection guessing fast, 30 more guessing once each)
    are slowed per connection and by the global budget; the key holder on the same
    address is checked at once (fake clock, no thread)."""
    from cdma_lidar.protocol.endpoint import DeviceCore, Engine

    now = [100.0]
    core = DeviceCore(SyntheticApp(channels=2, columns=4), key=KEY, clock=lambda: now[0],
                      engine=Engine(threaded=False))

    def conn() -> SteppedDevice:
        return SteppedDevice(None, core=core, now=now, peer="127.0.0.1")

    fast = conn()
    guesser = HostLink(fast, clock=fast.clock, key=bytes(32), retries=0, timeout_s=TIMEOUT)
    for _ in range(20):
        with pytest.raises(DeviceError) as exc:
            guesser.hello()
        assert exc.value.code == ErrorCode.AUTH_FAILED
    assert fast.endpoint.stats.auth_rejected < 5 < fast.endpoint.stats.auth_throttled
    for _ in range(30):
        dev = conn()
        with pytest.raises(DeviceError, match="does not match"):
            HostLink(dev, clock=dev.clock, key=bytes(32), retries=0, timeout_s=TIMEOUT).hello()
    # The budget is spent: a connection that guessed wrong now waits for it too.
    assert core.backoff.wait_s(1, now[0]) > 5.0
    holder_dev, start = conn(), now[0]
    holder = HostLink(holder_dev, clock=holder_dev.clock, key=KEY, retries=0, timeout_s=TIMEOUT)
    assert holder.hello().auth == 1
    assert now[0] - start < TIMEOUT  # at once: no retry, no back-off
    with pytest.raises(DeviceError, match="retry in"):  # the guesser is still held back
        guesser.hello()


def test_keyed_and_coded_on_a_noisy_line_with_requests_in_fragments() -> None:
    """Signed and Reed-Solomon coded both ways at a bit error rate of 1e-3, with a
    POWER_SET longer than the frame (signed pieces) and a scan: all arrive intact."""
    from cdma_lidar.virtual.line import Faults

    app = SyntheticApp(channels=8, columns=300)
    dev = SteppedDevice(app, key=KEY, max_frame=512, faults=Faults(bit_error_rate=1e-3), seed=3)
    link = HostLink(dev, clock=dev.clock, key=KEY, fec=True, timeout_s=TIMEOUT, retries=6)
    assert link.hello().auth == 1 and link.coded
    m = (np.arange(8 * 300).reshape(8, 300) * 5) % 65536
    link.set_power(m)
    np.testing.assert_array_equal(app.power, m)
    cols = list(link.scan(columns=20))
    assert all(c == expected_column(c.frame, c.column, 8, 1, 1) for c in cols)
    assert dev.endpoint.decoder.stats.corrected > 0 and dev.endpoint.stats.auth_rejected == 0


def test_a_request_of_an_ended_signed_session_gets_a_signed_wrong_session() -> None:
    """The host of a signed session drops unsigned frames: the device signs the NAK with
    the ended session's key, so the host hears it at once instead of timing out."""
    dev = SteppedDevice(SyntheticApp(channels=2, columns=4), key=KEY)
    link = HostLink(dev, clock=dev.clock, key=KEY, timeout_s=TIMEOUT)
    link.hello()
    rq = link
    rq.transact(MsgType.SESSION_END, {}, rq.new_seq())  # the link keeps its keys
    with pytest.raises(DeviceError) as exc:
        link.status()
    assert exc.value.code == ErrorCode.WRONG_SESSION
    assert link.stats.retries == 0 and link.stats.unauthenticated == 0


def test_a_piece_from_outside_the_session_cannot_replace_part_of_a_signed_request() -> None:
    """A signed CONFIG_SET in FRAGMENTs of one byte: after its genuine pieces but the last,
    a man in the middle sends a piece of the same (type, seq) that carries another session
    id and another value. The device never joins it into the signed request: the request
    it applies is the key holder's."""
    from cdma_lidar.protocol.messages import split_message

    rd, link, host, _dev, _app = _rig(KEY, KEY)
    with rd as ep:
        info = link.hello()
        sess, signer = info.session_id, link.signer
        payload = encode_payload(MsgType.CONFIG_SET, {"items": [   # peaks 3, out_shift 0
            {"key": 16, "value": b"\x03"}, {"key": 13, "value": b"\x00"}]})
        seq = link.seq = (link.seq + 1) & 0xFFFF  # the host's next
        pieces = split_message(MsgType.CONFIG_SET, payload, 1, seq)
        at = payload.index(b"\x03")   # the first item's value: a piece before the last
        assert at < len(pieces) - 1
        for p in pieces[:-1]:
            host.write(encode_frame(MsgType.FRAGMENT, p, seq, sess, signer=signer))
        evil = split_message(MsgType.CONFIG_SET, payload[:at] + b"\x02" + payload[at + 1:],
                             1, seq)[at]
        host.write(encode_frame(MsgType.FRAGMENT, evil, seq, sess ^ 1))
        host.write(encode_frame(MsgType.FRAGMENT, pieces[-1], seq, sess, signer=signer))
        ep.poll()
        assert ep.stats.naks == 0
        assert link.get_config()["peaks"] == 3


def test_a_request_in_pieces_of_an_ended_signed_session_gets_a_signed_wrong_session() -> None:
    """As a whole request: a POWER_SET longer than the frame, sent in signed FRAGMENTs
    after the session ended, gets its NAK WRONG_SESSION signed with the ended session's
    key, so the host hears it at once instead of timing out."""
    dev = SteppedDevice(SyntheticApp(channels=8, columns=300), key=KEY, max_frame=512)
    link = HostLink(dev, clock=dev.clock, key=KEY, timeout_s=TIMEOUT)
    link.hello()
    link.transact(MsgType.SESSION_END, {}, link.new_seq())  # the link keeps its keys
    with pytest.raises(DeviceError) as exc:
        link.set_power(np.ones((8, 300), np.uint16))
    assert exc.value.code == ErrorCode.WRONG_SESSION
    assert link.stats.retries == 0 and link.stats.unauthenticated == 0


def test_a_forged_piece_of_a_signed_request_counts_against_the_back_off(caplog) -> None:
    """As a forged whole frame does: a FRAGMENT of the open signed session with a wrong
    signature is dropped, logged once, and drawn on the global budget of checked MACs."""
    import logging

    from cdma_lidar.protocol.messages import split_message

    rd, link, host, _dev, _app = _rig(KEY, KEY)
    with rd as ep, caplog.at_level(logging.WARNING, logger="cdma_lidar.protocol"):
        sess = link.hello().session_id
        payload = encode_payload(MsgType.CONFIG_SET, {"items": [{"key": 16, "value": b"\x03"}]})
        piece = split_message(MsgType.CONFIG_SET, payload, 2, 900)[0]
        forger = auth.FrameMac(bytes(32))  # another key
        for _ in range(40):
            host.write(encode_frame(MsgType.FRAGMENT, piece, 900, sess, signer=forger))
        ep.poll()
        assert ep.stats.auth_rejected == 40
        # 40 at once spend the budget (10 at once): a connection that failed waits for it.
        assert ep.core.backoff.wait_s(1, ep.clock() - 10.0) > 5.0
    assert "a frame failed authentication" in caplog.text


def test_an_unsigned_piece_in_the_session_cannot_replace_part_of_a_signed_request() -> None:
    """The same man in the middle with the open session's own id: his unsigned piece
    replaces a genuine one, so the joined request is refused AUTH_REQUIRED, never applied
    with his value."""
    from cdma_lidar.protocol.messages import split_message

    rd, link, host, _dev, app = _rig(KEY, KEY)
    with rd as ep:
        info = link.hello()
        sess, signer = info.session_id, link.signer
        payload = encode_payload(MsgType.CONFIG_SET, {"items": [{"key": 16, "value": b"\x03"}]})
        seq = link.seq = (link.seq + 1) & 0xFFFF  # the host's next
        pieces = split_message(MsgType.CONFIG_SET, payload, 1, seq)
        at = payload.index(b"\x03")
        for p in pieces[:-1]:
            host.write(encode_frame(MsgType.FRAGMENT, p, seq, sess, signer=signer))
        evil = split_message(MsgType.CONFIG_SET, payload[:at] + b"\x02" + payload[at + 1:],
                             1, seq)[at]
        host.write(encode_frame(MsgType.FRAGMENT, evil, seq, sess))
        host.write(encode_frame(MsgType.FRAGMENT, pieces[-1], seq, sess, signer=signer))
        ep.poll()
        assert ep.stats.naks == 1 and app.set_config_calls == 0
        assert link.get_config()["peaks"] == 1


def test_a_hello_in_unsigned_pieces_of_the_open_signed_session_is_answered_as_a_whole_one(
        ) -> None:
    """HELLO is the one request accepted in any session (docs/protocol.md section 4): one
    sent in unsigned FRAGMENTs that carry the open signed session's id gets its CHALLENGE,
    then with the MAC takes the device, as the same HELLO sent whole does (never NAK
    AUTH_REQUIRED)."""
    from protocol_fixtures import hello_fields

    from cdma_lidar.protocol.messages import decode_payload, split_message

    rd, link, host, _dev, _app = _rig(KEY, KEY)
    with rd as ep:
        sess = link.hello().session_id
        dec = FrameDecoder()

        def hello(fields: dict, seq: int) -> list[tuple[int, dict]]:
            payload = encode_payload(MsgType.HELLO, fields)
            for piece in split_message(MsgType.HELLO, payload, 20, seq):
                host.write(encode_frame(MsgType.FRAGMENT, piece, seq, sess))
            ep.poll()
            return [(f.msg_type, decode_payload(f.msg_type, f.payload))
                    for f in dec.feed(host.rx.read(1 << 16, 0)) if f.seq == seq]

        fields = hello_fields(7, flags=1)  # take over
        ((kind, challenge),) = hello(fields, 999)
        assert kind == MsgType.CHALLENGE
        fields["device_nonce"] = challenge["device_nonce"]
        fields["mac"] = auth.hello_mac(KEY, challenge["device_nonce"], fields["host_nonce"],
                                       fields["flags"], fields["host_max_frame"])
        ((kind, info),) = hello(fields, 1000)
        assert kind == MsgType.INFO and info["session_id"] != sess and ep.stats.naks == 0


def test_a_key_file_that_cannot_be_read_or_created_is_one_error_naming_it(tmp_path) -> None:
    with pytest.raises(ConfigError, match=f"key file '{tmp_path}' cannot be read") as exc:
        auth.load_key(tmp_path)  # a directory
    assert exc.value.field == "key_file"
    missing = tmp_path / "no" / "such" / "dir" / "key"
    with pytest.raises(ConfigError, match="cannot be created") as exc:
        auth.load_or_create_key(missing)
    assert exc.value.field == "key_file" and str(missing) in str(exc.value)


def test_the_back_off_remembers_a_bounded_number_of_guessing_addresses(caplog) -> None:
    """Wrong MACs from ever new addresses cost the device a bounded table: the oldest
    address is forgotten (and warned about again if it comes back)."""
    import logging

    now = [0.0]
    backoff = auth.Backoff(lambda: now[0])
    with caplog.at_level(logging.WARNING, logger="cdma_lidar.protocol.auth"):
        for k in range(5000):
            backoff.failed(f"10.0.{k // 256}.{k % 256}", "HELLO with a wrong MAC")
        assert len(backoff._peers) == 4096
        warned = len(caplog.records)
        backoff.failed("10.0.0.0", "HELLO with a wrong MAC")  # forgotten: a first failure again
        backoff.failed("10.0.19.135", "HELLO with a wrong MAC")  # the newest: still quiet
    assert warned == 5000 and len(caplog.records) == warned + 1
