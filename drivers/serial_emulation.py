"""Serve a byte-level device emulator on a pseudo-terminal or on a loopback TCP port.

A driver then opens the emulator exactly as it opens the hardware: the pty's slave path through
pyserial like `/dev/ttyS0`, or `socket://127.0.0.1:PORT`. The emulator only has to be an
`EmulatedLink`: it is fed the bytes the host sent and returns the bytes the device answers, and it
says when it next has something to say on its own (an await that finishes, a limit hit).
"""
from __future__ import annotations

import logging
import os
import pty
import select
import socket
import termios
import threading
from typing import Protocol

log = logging.getLogger(__name__)

# Longest single wait of the serving thread: bounds the cost of a clock-speed change made
# while it sleeps towards the emulator's next event.
_MAX_IDLE_WAIT_S = 0.05


class EmulatedLink(Protocol):
    """What a served emulator provides."""

    def feed(self, data: bytes) -> bytes:
        """Take bytes from the host; return the bytes the device sends back now."""

    def poll(self) -> bytes:
        """Return bytes the device sends on its own by now (await done, limit hit, ...)."""

    def wall_time_to_next_event(self) -> float | None:
        """Wall seconds until poll() may have something, or None if nothing is scheduled."""


def make_raw(fd: int) -> None:
    """Put a tty in raw mode so bytes pass unchanged: no echo, no CR/NL mapping, no signals."""
    attrs = termios.tcgetattr(fd)
    iflag, oflag, cflag, lflag = attrs[0], attrs[1], attrs[2], attrs[3]
    iflag &= ~(termios.IGNBRK | termios.BRKINT | termios.PARMRK | termios.ISTRIP | termios.INLCR
               | termios.IGNCR | termios.ICRNL | termios.IXON | termios.IXOFF | termios.INPCK)
    oflag &= ~termios.OPOST
    lflag &= ~(termios.ECHO | termios.ECHONL | termios.ICANON | termios.ISIG | termios.IEXTEN)
    cflag = (cflag & ~(termios.CSIZE | termios.PARENB)) | termios.CS8
    attrs[0], attrs[1], attrs[2], attrs[3] = iflag, oflag, cflag, lflag
    attrs[6][termios.VMIN] = 1
    attrs[6][termios.VTIME] = 0
    termios.tcsetattr(fd, termios.TCSANOW, attrs)


class EmulationServer:
    """Runs one emulator behind a transport on a daemon thread until stop()."""

    def __init__(self, device: EmulatedLink, thread_name: str):
        self._device = device
        self._stopping = threading.Event()
        self._wake_read, self._wake_write = os.pipe()
        self._unsent = bytearray()
        self._thread = threading.Thread(target=self._serve, name=thread_name, daemon=True)

    def start(self) -> EmulationServer:
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 2.0) -> None:
        """End the serving thread and close the transport; the device is then gone from the line."""
        if self._stopping.is_set():
            return
        self._stopping.set()
        os.write(self._wake_write, b"x")
        self._thread.join(timeout_s)
        self._close_transport()
        os.close(self._wake_read)
        os.close(self._wake_write)

    def __enter__(self) -> EmulationServer:
        return self

    def __exit__(self, *exc_info) -> None:
        self.stop()

    # Transport hooks.
    def _input_fds(self) -> list[int]:
        raise NotImplementedError

    def _on_readable(self, fd: int) -> None:
        raise NotImplementedError

    def _output_fd(self) -> int | None:
        raise NotImplementedError

    def _close_transport(self) -> None:
        raise NotImplementedError

    def _send(self, data: bytes) -> None:
        if data:
            self._unsent += data
        self._flush()

    def _flush(self) -> None:
        fd = self._output_fd()
        if fd is None:
            self._unsent.clear()  # nobody on the line: the bytes are lost, as on a real wire
            return
        while self._unsent:
            try:
                written = os.write(fd, self._unsent)
            except BlockingIOError:
                return  # the peer is not reading; keep the rest and wait for writability
            except OSError:
                self._unsent.clear()
                return
            del self._unsent[:written]

    def _serve(self) -> None:
        try:
            while not self._stopping.is_set():
                wait_s = self._device.wall_time_to_next_event()
                wait_s = _MAX_IDLE_WAIT_S if wait_s is None else min(max(wait_s, 0.0), _MAX_IDLE_WAIT_S)
                out_fd = self._output_fd()
                writable = [out_fd] if self._unsent and out_fd is not None else []
                readable, _, _ = select.select(self._input_fds() + [self._wake_read], writable, [], wait_s)
                if self._stopping.is_set():
                    break
                for fd in readable:
                    if fd != self._wake_read:
                        self._on_readable(fd)
                self._send(self._device.poll())
        except Exception:  # a dying server must say why, not vanish silently
            log.exception("emulation server %s stopped on an error", self._thread.name)


class PtyServer(EmulationServer):
    """An emulator behind a pseudo-terminal; `path` is the slave, to open like `/dev/ttyS0`."""

    def __init__(self, device: EmulatedLink):
        super().__init__(device, thread_name="pty-emulation")
        self._master, self._slave = pty.openpty()
        # Raw on the slave side, because the line discipline would otherwise echo the device's
        # replies back to it and map CR to NL; the client (pyserial) sets raw too, but only once
        # it opens the port.
        make_raw(self._slave)
        # We keep the slave open so the master never sees a hang-up between client sessions.
        self.path = os.ttyname(self._slave)
        os.set_blocking(self._master, False)

    def _input_fds(self) -> list[int]:
        return [self._master]

    def _on_readable(self, fd: int) -> None:
        try:
            data = os.read(fd, 4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:  # EIO: no slave open at the moment
            return
        if data:
            self._send(self._device.feed(data))

    def _output_fd(self) -> int | None:
        return self._master

    def _close_transport(self) -> None:
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass


class TcpServer(EmulationServer):
    """An emulator on a loopback TCP port, one client at a time, for `socket://host:port`."""

    def __init__(self, device: EmulatedLink, host: str = "127.0.0.1", port: int = 0):
        super().__init__(device, thread_name="tcp-emulation")
        self._listener = socket.create_server((host, port))
        self._listener.setblocking(False)
        self.host, self.port = self._listener.getsockname()[:2]
        self.url = f"socket://{self.host}:{self.port}"
        self._client: socket.socket | None = None

    def _input_fds(self) -> list[int]:
        fds = [self._listener.fileno()]
        if self._client is not None:
            fds.append(self._client.fileno())
        return fds

    def _on_readable(self, fd: int) -> None:
        if fd == self._listener.fileno():
            try:
                client, _ = self._listener.accept()
            except BlockingIOError:
                return
            self._drop_client()  # a serial line has one host: the newest connection wins
            client.setblocking(False)
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._client = client
            return
        try:
            data = self._client.recv(4096) if self._client is not None else b""
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            self._drop_client()
            return
        self._send(self._device.feed(data))

    def _output_fd(self) -> int | None:
        return None if self._client is None else self._client.fileno()

    def _drop_client(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None
            self._unsent.clear()

    def _close_transport(self) -> None:
        self._drop_client()
        self._listener.close()
