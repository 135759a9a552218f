"""Line-oriented serial I/O shared by the printer and scale drivers (wraps pyserial).

:func:`open_serial` turns pyserial's errors into :class:`DeviceNotConnectedError` with a
hint (absent port, busy port, missing permission); :class:`SerialLines` reads whole
lines with deadlines, so callers never block forever and never see half a line.
"""

from __future__ import annotations

import errno
import logging
import os
import sys
import threading
import time

from beadsight.devices.base import DeviceNotConnectedError

logger = logging.getLogger(__name__)

POLL_S = 0.05  # longest single blocking read; bounds how late a deadline or stop is noticed
WRITE_TIMEOUT_S = 2.0  # a write that cannot drain in this time means the device is wedged
MAX_LINE_BYTES = 4096  # a "line" longer than this without a newline is garbage; it is cut
_URL_PREFIXES = ("socket://", "rfc2217://", "loop://", "spy://", "hwgrep://", "alt://")


def _import_serial():
    try:
        import serial
    except ImportError:  # pragma: no cover - pyserial is in the [hardware] extra
        raise ImportError(
            "talking to the printer or scale needs pyserial: pip install 'beadsight[hardware]'"
        ) from None
    return serial


def _port_listing_hint(port: str) -> str:
    if sys.platform.startswith("win"):
        return "check the COM port in Device Manager"
    if "ACM" in port:
        return "is the Arduino plugged in? ls /dev/ttyACM*"
    if "USB" in port:
        return "is the printer plugged in and powered? ls /dev/ttyUSB*"
    return "is the device plugged in? ls /dev/ttyACM* /dev/ttyUSB*"


def open_serial(port: str, baudrate: int, *, device: str):
    """Open ``port`` exclusively and return the pyserial ``Serial``.

    device: name used in error messages, e.g. ``"scale /dev/ttyACM0"``.
    Raises DeviceNotConnectedError naming the port when it is absent, busy or not
    permitted.
    """
    serial = _import_serial()
    is_path = not port.startswith(_URL_PREFIXES) and not sys.platform.startswith("win")
    if is_path and not os.path.exists(port):
        raise DeviceNotConnectedError(
            device, f"serial port {port} does not exist", _port_listing_hint(port)
        )
    try:
        if port.startswith(_URL_PREFIXES):
            ser = serial.serial_for_url(
                port, baudrate=baudrate, timeout=POLL_S, write_timeout=WRITE_TIMEOUT_S
            )
        else:
            ser = serial.Serial(
                port,
                baudrate=baudrate,
                timeout=POLL_S,
                write_timeout=WRITE_TIMEOUT_S,
                exclusive=True,
            )
    except serial.SerialException as e:
        raise _open_error(port, device, e) from None
    except (OSError, ValueError) as e:
        raise DeviceNotConnectedError(
            device, f"cannot open serial port {port}: {e}", _port_listing_hint(port)
        ) from None
    return ser


def _open_error(port: str, device: str, e: Exception) -> DeviceNotConnectedError:
    text = str(e)
    code = getattr(e, "errno", None)
    if "exclusively lock" in text or code in (errno.EBUSY, errno.EAGAIN):
        return DeviceNotConnectedError(
            device,
            f"serial port {port} is busy",
            "another program holds it: close the Arduino IDE serial monitor, OctoPrint, "
            "Pronterface or another beadsight process (lsof " + port + ")",
        )
    if code == errno.EACCES or "Permission denied" in text:
        return DeviceNotConnectedError(
            device,
            f"no permission to open serial port {port}",
            "add yourself to the dialout group: sudo usermod -aG dialout $USER, then log in again",
        )
    if code == errno.ENOENT or "No such file" in text:
        return DeviceNotConnectedError(
            device, f"serial port {port} does not exist", _port_listing_hint(port)
        )
    return DeviceNotConnectedError(
        device, f"cannot open serial port {port}: {text}", _port_listing_hint(port)
    )


class SerialLines:
    """Whole-line reads and writes over an open pyserial port, safe for one reader thread
    and any number of writer threads.

    Lines are decoded as ASCII (undecodable bytes become U+FFFD), stripped of ``\\r\\n``.
    A failing port (unplugged, closed by the device) raises DeviceNotConnectedError.
    """

    def __init__(self, ser, device: str):
        self._ser = ser
        self.device = device
        self._buf = bytearray()
        self._write_lock = threading.Lock()
        self.port = getattr(ser, "port", None) or "?"

    def write_line(self, text: str) -> None:
        """Send ``text`` followed by ``\\n``."""
        data = text.encode("ascii") + b"\n"
        serial = _import_serial()
        with self._write_lock:
            try:
                self._ser.write(data)
                self._ser.flush()
            except (serial.SerialException, OSError) as e:
                raise DeviceNotConnectedError(
                    self.device,
                    f"writing to {self.port} failed ({e}); was it unplugged?",
                    _port_listing_hint(self.port),
                ) from None

    def read_line(self, deadline_mono: float) -> str | None:
        """The next complete line, or None when ``deadline_mono`` (time.monotonic) passes.

        A deadline in the past still returns lines that have already arrived.
        """
        serial = _import_serial()
        while True:
            line = self._pop_line()
            if line is not None:
                return line
            try:
                waiting = self._ser.in_waiting
                if not waiting and time.monotonic() >= deadline_mono:
                    return None
                chunk = self._ser.read(max(1, min(waiting, MAX_LINE_BYTES)))
            except (serial.SerialException, OSError, TypeError, AttributeError) as e:
                # TypeError/AttributeError: pyserial's fd vanished because the port was closed
                raise DeviceNotConnectedError(
                    self.device,
                    f"lost the serial port {self.port} ({e}); was it unplugged?",
                    _port_listing_hint(self.port),
                ) from None
            self._buf.extend(chunk)

    def _pop_line(self) -> str | None:
        idx = self._buf.find(b"\n")
        if idx < 0:
            if len(self._buf) > MAX_LINE_BYTES:  # runaway garbage without newlines
                data = bytes(self._buf)
                self._buf.clear()
                return data.decode("ascii", errors="replace")
            return None
        data = bytes(self._buf[:idx])
        del self._buf[: idx + 1]
        return data.decode("ascii", errors="replace").strip("\r\n\x00 ")

    def close(self) -> None:
        try:
            self._ser.close()
        except Exception as e:  # noqa: BLE001 - closing a dead port must not raise
            logger.debug("closing %s: %s", self.port, e)
