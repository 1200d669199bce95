"""The MAVLink link: one connection opened through pymavlink's factory
(``mavutil.mavlink_connection``: udpout:HOST:PORT, udpin:HOST:PORT, tcp:HOST:PORT,
/dev/ttyX[:BAUD]), pymavlink's MAVLink 2 encoder and parser on it, and the byte I/O done here so
that every failure is seen (pymavlink would print and carry on): writes that raise LinkError or
LinkBusy, bounded reads, what the kernel still holds, and MAVLink 2 signing.

The output (output.py) owns one ``MavlinkLink`` while the link is up and opens a new one after
a failure; the HEARTBEAT it sends on it is the output's (``MavlinkOutput._send_heartbeat``).
"""

from __future__ import annotations

import errno
import hashlib
import logging
import select
import socket
import struct
import time
from typing import Any, Callable, List, Optional, Tuple

from ..device_path import DeviceWatch
from ..worker import (
    LinkBusy,
    LinkError,
    PeerNotReading,
    discard_tty_output,
    fd_queued_bytes,
    hold_serial_port,
    is_pty,
    release_serial_port,
    tcp_unsent_bytes,
)

WRITE_TIMEOUT_S = 0.25
# Reading what comes back is bounded per tick, so that no amount of incoming data (a flood of
# junk datagrams) holds up the poses: at most this many reads, bytes and seconds of parsing.
RX_DATAGRAMS = 32
RX_BYTES = 4096
RX_SECONDS = 0.002
# A MAVLink 2 frame is at most 280 bytes; a datagram larger than an Ethernet frame is junk.
RX_MAX_DATAGRAM = 1500
# The kernel's send buffer of a TCP or UDP link (it doubles it): little can wait there, and
# what waits is measured before each write (SIOCOUTQ).
SEND_BUFFER_BYTES = 4096
_SIGNING_EPOCH_S = 1420070400  # MAVLink 2 signing time stamps count from 2015-01-01


def signing_key_bytes(key: str) -> bytes:
    """64 hex digits -> those 32 bytes; anything else is a passphrase hashed with SHA-256 (as MAVProxy)."""
    k = key.strip()
    if len(k) == 64:
        try:
            return bytes.fromhex(k)
        except ValueError:
            pass
    return hashlib.sha256(key.encode("utf-8")).digest()


class MavlinkLink:
    """One open connection: pymavlink's opener and MAVLink 2 encoder, with our own byte I/O."""

    def __init__(
        self,
        kind: str,
        device: str,
        baud: int,
        source_system: int,
        source_component: int,
        signing_key: Optional[bytes],
        on_ignored: Callable[[str], None] = lambda cause: None,
        before_send: Callable[[int], None] = lambda n: None,
        after_send: Callable[[int], None] = lambda n: None,
        on_discarded: Callable[[], None] = lambda: None,
    ) -> None:
        """``on_ignored(cause)``: counts received data not believed; ``before_send(nbytes)``: the
        output's last check, called right before each write (it may raise to refuse the
        bytes); ``after_send(nbytes)``: called once they were handed to the kernel;
        ``on_discarded()``: a full buffer's stale bytes were discarded."""
        from pymavlink import mavutil

        # ArduPilot's dialect: common.xml and ArduPilot's own messages (EKF_STATUS_REPORT #193),
        # so that those are decoded, CRC- and signature-checked, with their sender, rather than
        # left as MAVLink_unknown (sender 0, nothing checked). PX4 speaks only common messages.
        from pymavlink.dialects.v20 import ardupilotmega as mavlink2

        self.kind = kind
        self._on_ignored = on_ignored  # counts received data not believed, by cause
        self._before_send = before_send
        self._after_send = after_send
        self._on_discarded = on_discarded
        self._rx_buf = bytearray(RX_MAX_DATAGRAM + 1)
        if kind == "udpin":
            warn_if_udp_port_taken(device)
        self.conn = mavutil.mavlink_connection(
            device,
            baud=baud,
            source_system=source_system,
            source_component=source_component,
            retries=0,
            autoreconnect=False,
        )
        if kind == "serial":
            try:
                hold_serial_port(self.conn.port.fd, device)
            except OSError:
                self.conn.close()
                raise
        # MAVLink 2 whatever MAVLINK20 says, writing through self so that errors surface.
        self.mav = mavlink2.MAVLink(self, srcSystem=source_system, srcComponent=source_component)
        self.mav.robust_parsing = True
        self.conn.mav = self.mav
        if signing_key is not None:
            self.mav.signing.secret_key = signing_key
            self.mav.signing.sign_outgoing = True
            self.mav.signing.link_id = 0
            self.mav.signing.timestamp = int((max(time.time(), _SIGNING_EPOCH_S) - _SIGNING_EPOCH_S) * 1e5)
            # With a key only correctly signed messages are believed: no unsigned callback, so
            # pymavlink turns an unsigned or badly signed message into BAD_DATA (counted below).
            self.mav.signing.allow_unsigned_callback = None
        port = self.conn.port
        self.pty = False
        self.heard_from_peer = False  # a TCP peer sent bytes on this connection (it services it)
        self._watch: Optional[DeviceWatch] = None  # a serial path's device, checked each read
        if kind == "serial":
            port.write_timeout = WRITE_TIMEOUT_S
            self.pty = is_pty(port.fd)
            self._watch = DeviceWatch(device, port.fd)
        else:
            port.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER_BYTES)
            if kind == "tcp":
                port.settimeout(WRITE_TIMEOUT_S)

    def queued_bytes(self) -> Optional[int]:
        """Bytes taken but not yet on the wire (None: a pseudo-terminal cannot tell)."""
        if self.kind == "serial":
            return None if self.pty else fd_queued_bytes(self.conn.port.fd)
        if self.kind == "tcp":
            return tcp_unsent_bytes(self.conn.port.fileno())  # not yet sent: a delayed ACK is no stall
        return fd_queued_bytes(self.conn.port.fileno())

    def rate_Bps(self) -> Optional[float]:
        """A serial line's byte rate (8N1: baud / 10); None for sockets and ptys."""
        return self.conn.baud / 10.0 if self.kind == "serial" and not self.pty and self.conn.baud else None

    def discard_queued(self) -> bool:
        """Throw away what waits: TCOFLUSH on a serial port; a TCP connection is reset (RST, the
        queue dropped) and LinkError raised so that it is reopened; UDP cannot (False)."""
        if self.kind == "serial":
            discard_tty_output(self.conn.port.fd)
            return True
        if self.kind == "tcp":
            try:
                self.conn.port.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
                self.conn.port.close()
            except OSError:
                pass
            raise PeerNotReading("peer not reading: the connection held poses older than the budget; reset")
        return False

    # pymavlink's encoder calls this for every packed message.
    def write(self, buf: bytes) -> int:
        data = bytes(buf)
        self._before_send(len(data))  # the output's last check, right before the bytes go out
        self._send(data)
        self._after_send(len(data))
        return len(data)

    def _send(self, data: bytes) -> None:
        try:
            if self.kind == "serial":
                n = self.conn.port.write(data)
                if n is not None and n < len(data):
                    raise LinkBusy(f"serial write timed out after {n} of {len(data)} bytes")
                return
            if self.kind == "udpout":
                try:
                    self.conn.port.sendto(data, self.conn.destination_addr)
                except ConnectionRefusedError:
                    pass  # an ICMP "port unreachable" from an earlier datagram: nobody listens yet
                except BlockingIOError as exc:
                    raise LinkBusy("UDP send buffer full") from exc
                return
            if self.kind == "udpin":
                self.conn.write(data)  # to every peer heard from (none yet: nothing is sent)
                return
            self.conn.port.sendall(data)
        except LinkBusy:
            self._timed_out()
            raise
        except Exception as exc:
            if type(exc).__name__ == "SerialTimeoutException" or isinstance(exc, socket.timeout):
                self._timed_out()
                raise LinkBusy(f"{self.kind} write timed out (peer not reading?)") from exc
            raise LinkError(f"write failed: {exc}") from exc

    def _timed_out(self) -> None:
        """A full buffer: the reader stopped. What waits for it is stale; a serial port discards
        it (TCOFLUSH), a TCP connection is left for the queue check to reset."""
        if self.kind == "serial":
            discard_tty_output(self.conn.port.fd)  # LinkError when the port is gone
            self._on_discarded()

    def read_messages(self) -> List[Any]:
        """The complete messages waiting on the link (non-blocking), within a strict budget per
        call (RX_DATAGRAMS, RX_BYTES, RX_SECONDS): what is left waits for the next call, so
        reading never holds up sending however much arrives. A datagram larger than
        RX_MAX_DATAGRAM is junk: dropped unparsed and counted as ``oversized``."""
        if self._watch is not None:
            self._watch.check()  # unplugged, reset or replaced behind its path: LinkError, reopen
        out: List[Any] = []
        t_end = time.perf_counter() + RX_SECONDS
        budget = RX_BYTES
        for _ in range(RX_DATAGRAMS):
            got = self._read_some(budget)
            if got is None:
                break
            data, sender = got
            if not data:
                continue
            budget -= len(data)
            good = False
            for msg in self.mav.parse_buffer(data) or []:
                if msg.get_type() != "BAD_DATA":
                    out.append(msg)
                    good = True
                elif "signature" in str(getattr(msg, "reason", "")).lower():
                    self._on_ignored("bad_signature")
            if good and sender is not None and self.kind == "udpin":
                # A peer to send to: only one that sent a real (with a key: signed) message,
                # so junk from anywhere cannot redirect the stream.
                self.conn.clients.add(sender)
                self.conn.clients_last_alive[sender] = time.time()
            if budget <= 0 or time.perf_counter() >= t_end:
                break
        return out

    def wait_readable(self, timeout_s: float) -> bool:
        """True once bytes are waiting to be read, False after ``timeout_s`` without."""
        port = self.conn.port
        try:
            fd = port.fd if self.kind == "serial" else port.fileno()
            return bool(select.select([fd], [], [], max(0.0, timeout_s))[0])
        except (OSError, ValueError, AttributeError):
            return False

    def _read_some(self, budget: int) -> Optional[Tuple[bytes, Any]]:
        """(bytes, sender) of one read of at most ``budget`` bytes; (b"", None) for a datagram
        dropped unparsed; None when nothing is waiting."""
        port = self.conn.port
        try:
            if self.kind == "serial":
                n = min(port.in_waiting, budget)
                return (port.read(n), None) if n else None
            if self.kind in ("udpout", "udpin"):
                # MSG_TRUNC: the datagram's real length, though only the buffer's worth is copied.
                n, sender = port.recvfrom_into(self._rx_buf, len(self._rx_buf), socket.MSG_TRUNC)
                if n > RX_MAX_DATAGRAM:
                    self._on_ignored("oversized")
                    return b"", None
                return bytes(self._rx_buf[:n]), sender
            # select, not MSG_DONTWAIT: the socket has a send timeout, which recv would wait out.
            if not select.select([port], [], [], 0.0)[0]:
                return None
            data = port.recv(max(1, min(budget, 4096)))
            if not data:
                raise LinkError("connection closed by peer")
            self.heard_from_peer = True
            return data, None
        except LinkError:
            raise
        except OSError as exc:
            if exc.errno in (errno.EAGAIN, errno.EWOULDBLOCK, errno.ECONNREFUSED):
                return None
            raise LinkError(f"read failed: {exc}") from exc
        except Exception as exc:
            raise LinkError(f"read failed: {exc}") from exc

    def close(self) -> None:
        if self.kind == "serial":
            release_serial_port(self.conn.port.fd)
        self.conn.close()


def warn_if_udp_port_taken(device: str) -> None:
    """One log line when another socket has the udpin address bound already: pymavlink binds
    with SO_REUSEADDR, so a second daemon would share the port silently and the datagrams would
    go to one of them only. Probed with a bind without SO_REUSEADDR, which fails then. When the
    other socket does not share (no SO_REUSEADDR) or the bind fails for another reason, the
    link cannot open: LinkError saying that the bind failed and why."""
    host, _, port = device.partition(":")[2].rpartition(":")
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        probe.bind((host, int(port)))
    except OSError as exc:
        if exc.errno != errno.EADDRINUSE:
            raise LinkError(f"cannot bind UDP {host}:{port}: {exc.strerror or exc}") from None
        if not _binds_shared(host, int(port)):
            raise LinkError(
                f"cannot bind UDP {host}:{port}: {exc.strerror or exc} (another program holds it "
                f"and does not share it; see which with: ss -ulpn 'sport = :{port}')"
            ) from None
        logging.getLogger("pose_daemon.outputs.mavlink").warning(
            "mavlink output: UDP port %s:%s is bound by another socket too (another pose-daemon or "
            "ground station?): datagrams from the autopilot reach only one of them",
            host,
            port,
        )
    finally:
        probe.close()


def _binds_shared(host: str, port: int) -> bool:
    """Whether a bind with SO_REUSEADDR (as pymavlink's) succeeds on a taken address."""
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        probe.bind((host, port))
        return True
    except OSError:
        return False
    finally:
        probe.close()
