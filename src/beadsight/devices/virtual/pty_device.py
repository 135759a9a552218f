"""A device on a pseudo-terminal: the host opens :attr:`PtyDevice.port` with pyserial.

The device keeps the pty's master side; its slave path (``/dev/pts/N``) is what a real
driver opens, exactly like a USB serial adapter. The device notices the host opening
and closing the port (Linux reports EIO on the master while no one holds the slave),
which lets it behave like an Arduino that reboots when the port opens.

Subclasses implement :meth:`on_host_open`, :meth:`on_host_close`, :meth:`on_line` and
:meth:`on_tick`; all run on the device's own thread.
"""

from __future__ import annotations

import errno
import fcntl
import logging
import os
import pty
import select
import threading
import tty

from beadsight.devices.clock import SimClock
from beadsight.devices.reader import ReaderThread

logger = logging.getLogger(__name__)

POLL_S = 0.01  # host seconds between checks for input, ticks and host open/close
MAX_INPUT_LINE = 1024  # bytes; longer input without a newline is dropped
STOP_WAIT_S = 2.0  # close(): how long to wait for the device thread


class PtyDevice:
    """Base class: a background thread serving one pty. Use as a context manager."""

    def __init__(self, name: str, clock: SimClock | None = None):
        self.name = name
        self.clock = clock if clock is not None else SimClock()
        master, slave = pty.openpty()
        tty.setraw(slave)
        self.port = os.ttyname(slave)
        os.close(slave)  # the host opens the slave by path; EIO on the master means "closed"
        flags = fcntl.fcntl(master, fcntl.F_GETFL)
        fcntl.fcntl(master, fcntl.F_SETFL, flags | os.O_NONBLOCK)
        self._master: int | None = master
        self._inbuf = bytearray()
        self._write_lock = threading.Lock()
        self._reader = ReaderThread(name, self._run)
        self._stop = self._reader.stop_event
        self.host_open = False
        self.bytes_dropped = 0  # output the host did not read in time (buffer full)

    # --- lifecycle --------------------------------------------------------------------
    def start(self) -> PtyDevice:
        if not self._reader.started and not self._stop.is_set():
            self._reader.start()
        return self

    def close(self) -> None:
        """Stop the thread and remove the port."""
        self._reader.stop(STOP_WAIT_S)
        self._close_master()

    def unplug(self) -> None:
        """Simulate pulling the USB cable: the port disappears; the host's reads fail."""
        self.close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def _close_master(self) -> None:
        with self._write_lock:
            master, self._master = self._master, None
        if master is not None:
            os.close(master)

    # --- output -----------------------------------------------------------------------
    def write_line(self, text: str) -> None:
        """Send one line (``\\r\\n`` terminated, as Arduino's println) if the host is there."""
        self.write_raw(text.encode("ascii", errors="replace") + b"\r\n")

    def write_raw(self, data: bytes) -> None:
        with self._write_lock:
            if self._master is None or not self.host_open:
                return
            try:
                written = os.write(self._master, data)
            except BlockingIOError:
                written = 0
            except OSError as e:  # the host closed between the check and the write
                if e.errno not in (errno.EIO, errno.EAGAIN):
                    raise
                written = 0
            self.bytes_dropped += len(data) - written

    # --- hooks ------------------------------------------------------------------------
    def on_host_open(self) -> None:
        """The host opened the port (an Arduino would reboot now)."""

    def on_host_close(self) -> None:
        """The host closed the port."""

    def on_line(self, line: str) -> None:
        """One line received from the host (without its line ending)."""

    def on_tick(self) -> None:
        """Called every POLL_S while the host holds the port."""

    # --- thread -----------------------------------------------------------------------
    def _run(self, stop: threading.Event) -> None:
        try:
            while not stop.is_set():
                self._poll_once()
        except Exception:  # noqa: BLE001 - a crashed virtual device must say why
            logger.exception("%s crashed", self.name)

    def _poll_once(self) -> None:
        master = self._master
        if master is None:
            self._stop.set()
            return
        readable, _, _ = select.select([master], [], [], POLL_S)
        if readable:
            try:
                data = os.read(master, 4096)
            except BlockingIOError:
                data = b""
            except OSError:  # EIO: no one holds the slave side
                self._set_host_open(False)
                self._stop.wait(POLL_S)
                return
            self._set_host_open(True)
            self._feed_input(data)
        else:
            self._set_host_open(True)
        if self.host_open:
            self.on_tick()

    def _set_host_open(self, is_open: bool) -> None:
        if is_open == self.host_open:
            return
        self.host_open = is_open
        self._inbuf.clear()
        if is_open:
            logger.debug("%s: host opened %s", self.name, self.port)
            self.on_host_open()
        else:
            logger.debug("%s: host closed %s", self.name, self.port)
            self.on_host_close()

    def _feed_input(self, data: bytes) -> None:
        self._inbuf.extend(data)
        while True:
            cut = min(
                (i for i in (self._inbuf.find(b"\n"), self._inbuf.find(b"\r")) if i >= 0),
                default=-1,
            )
            if cut < 0:
                if len(self._inbuf) > MAX_INPUT_LINE:
                    self._inbuf.clear()
                return
            raw = bytes(self._inbuf[:cut])
            del self._inbuf[: cut + 1]
            line = raw.decode("ascii", errors="replace").strip()
            if line:
                self.on_line(line)
