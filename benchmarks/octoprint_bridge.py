"""Serve OctoPrint's bundled virtual printer on a pseudo-terminal (run by OctoPrint's python).

OctoPrint's ``virtual_printer`` plugin is the Marlin emulator hosts test against; its
``VirtualPrinter`` is a serial-like object (``write`` / ``readline``). This script puts it
on a pty, so that a driver opens ``/dev/pts/N`` exactly like a USB serial port. It does
not import beadsight: run it with the python of a separate venv holding OctoPrint::

    python3 -m venv /work/peers/octoprint && /work/peers/octoprint/bin/pip install OctoPrint
    /work/peers/octoprint/bin/python benchmarks/octoprint_bridge.py --log /tmp/received.txt

Protocol with the caller (stdin / stdout, one line each):

* stdout ``PORT /dev/pts/N`` once ready, ``VERSION <octoprint version>``;
* stdin ``DEBUG <command>``: hand ``!!DEBUG:<command>`` to the virtual printer (its fault
  injection: ``trigger_resend_checksum``, ``dont_answer``, ``resend_ratio 10`` ...);
  answered ``DONE``;
* stdin ``DUPOK``: the next ``ok`` the printer sends goes out twice, the copy when the host
  sends its next line (a duplicated acknowledgement on the wire); answered ``DONE``;
* stdin ``QUIT`` (or end of input): stop.

When the host opens the port the printer is reset (``!!DEBUG:reset``: it prints its boot
lines), as a board with DTR reset. Every line the host sends is appended to ``--log``.
"""

from __future__ import annotations

import argparse
import errno
import json
import os
import pty
import select
import sys
import tempfile
import threading
import tty

POLL_S = 0.01  # seconds between checks of the pty
READ_TIMEOUT_S = 0.05  # the virtual printer's readline timeout


class Settings:
    """The part of OctoPrint's settings API the virtual printer reads, from plain values."""

    def __init__(self, values: dict, base_folder: str):
        self.values = values
        self.base_folder = base_folder

    def get(self, path, merged=False, **kwargs):
        value = self.values
        for key in path:
            value = value[key]
        return value

    def get_int(self, path):
        return int(self.get(path))

    def get_float(self, path):
        return float(self.get(path))

    def get_boolean(self, path):
        return bool(self.get(path))

    def global_get_basefolder(self, name):
        return self.base_folder


def make_printer(overrides: dict):
    import octoprint.plugins.virtual_printer.virtual as virtual
    from octoprint.plugins.virtual_printer import VirtualPrinterPlugin

    # outside a running OctoPrint server there is no plugin manager: no custom hooks
    virtual.plugin_manager = lambda: type("NoPlugins", (), {"get_hooks": lambda self, n: {}})()
    values = VirtualPrinterPlugin().get_settings_defaults()
    values.update(overrides)
    folder = tempfile.mkdtemp(prefix="octoprint-virtual-")
    return virtual.VirtualPrinter(
        Settings(values, folder), None, folder, read_timeout=READ_TIMEOUT_S
    )


class Bridge:
    def __init__(self, printer, log_path: str | None):
        self.printer = printer
        self.log = open(log_path, "a", buffering=1) if log_path else None  # noqa: SIM115
        master, slave = pty.openpty()
        tty.setraw(slave)
        self.port = os.ttyname(slave)
        os.close(slave)  # the host opens it by path; EIO on the master means nobody has
        self.master = master
        self.host_open = False
        self.stop = threading.Event()
        self.lock = threading.Lock()
        self.dup_ok = False
        self.held_ok = False

    def host_to_printer(self) -> None:
        buf = b""
        while not self.stop.is_set():
            readable, _, _ = select.select([self.master], [], [], POLL_S)
            if not readable:
                self.set_open(True)
                continue
            try:
                data = os.read(self.master, 4096)
            except OSError as e:  # EIO: the host does not hold the port
                if e.errno != errno.EIO:
                    raise
                self.set_open(False)
                self.stop.wait(POLL_S)
                continue
            self.set_open(True)
            buf += data
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                self.on_host_line(line.rstrip(b"\r"))

    def on_host_line(self, line: bytes) -> None:
        if self.log is not None:
            self.log.write(line.decode("ascii", "replace") + "\n")
        with self.lock:
            if self.held_ok:
                self.held_ok = False
                self.to_host(b"ok\n")
        self.printer.write(line + b"\n")

    def set_open(self, is_open: bool) -> None:
        if is_open and not self.host_open:
            self.printer.write(b"!!DEBUG:reset\n")  # the board resets when the port opens
        self.host_open = is_open

    def printer_to_host(self) -> None:
        while not self.stop.is_set():
            data = self.printer.readline()
            if not data:
                continue
            for line in data.replace(b"\r", b"").split(b"\n"):
                if line:
                    self.forward(line + b"\n")

    def forward(self, line: bytes) -> None:
        with self.lock:
            if self.dup_ok and line.startswith(b"ok"):
                self.dup_ok = False
                self.held_ok = True
        self.to_host(line)

    def to_host(self, data: bytes) -> None:
        if not self.host_open:
            return
        try:
            os.write(self.master, data)
        except OSError:
            pass  # the host closed the port meanwhile

    def control(self) -> None:
        for raw in sys.stdin:
            command = raw.strip()
            if command == "QUIT":
                break
            if command.startswith("DEBUG "):
                self.printer.write(b"!!DEBUG:" + command[6:].encode("ascii") + b"\n")
            elif command == "DUPOK":
                with self.lock:
                    self.dup_ok = True
            print("DONE", flush=True)
        self.stop.set()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--log", help="append every line the host sends to this file")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=JSON",
        help="override a virtual printer setting, e.g. --set sendBusy=true",
    )
    args = parser.parse_args()
    overrides = {}
    for item in args.set:
        key, _, value = item.partition("=")
        overrides[key] = json.loads(value)
    import octoprint

    bridge = Bridge(make_printer(overrides), args.log)
    for target in (bridge.host_to_printer, bridge.printer_to_host):
        threading.Thread(target=target, daemon=True).start()
    print(f"VERSION {octoprint.__version__}", flush=True)
    print(f"PORT {bridge.port}", flush=True)
    bridge.control()
    bridge.printer.close()
    os._exit(0)  # the virtual printer's own threads are not daemons


if __name__ == "__main__":
    main()
