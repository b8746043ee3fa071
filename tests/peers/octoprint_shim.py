#!/usr/bin/env python3
"""OctoPrint's virtual printer (PyPI `octoprint`, pinned in .ci/run) on a pty, for
tests/octoprint_peer.rs: a Marlin model written by others, with its own fault injection.

    octoprint_shim.py --link PATH --log FILE [--resend-ratio N] [--busy]
                      [--simulated-errors 100:resend,105:resend_with_timeout,...]

Creates a pty, symlinks PATH to its slave end, prints `ready PATH` and relays bytes
between the pty and `VirtualPrinter.write`/`readline` until stdin closes. Every command
the printer accepted (after its line number and checksum checks and its own resend
injection, with N and the checksum stripped) is appended to FILE, one a line.
"""

import argparse
import os
import sys
import threading
import time
import tty


class Settings:
    """The plugin settings object VirtualPrinter reads: the plugin's defaults with
    overrides."""

    def __init__(self, values, basefolder):
        self._values = values
        self._basefolder = basefolder

    def get(self, path, merged=False):
        v = self._values
        for p in path:
            v = v.get(p) if isinstance(v, dict) else None
        return v

    def get_int(self, path):
        v = self.get(path)
        return None if v is None else int(v)

    def get_float(self, path):
        v = self.get(path)
        return None if v is None else float(v)

    def get_boolean(self, path):
        return bool(self.get(path))

    def global_get_basefolder(self, name):
        path = os.path.join(self._basefolder, name)
        os.makedirs(path, exist_ok=True)
        return path


def fix_resend_ratio(printer):
    """The virtual printer's resend ratio (1.6 to 1.11.8, the same code) rejects line L
    *after* taking it (`lastN = L`) and asks for L + 1, which says "I have L": line L is
    lost without a trace. A real Marlin asks for the line it rejected. Only that call
    is changed: it comes from `_processIncoming` once the line's text (`data`) is a str;
    every other caller passes `expected` or still holds the raw bytes."""
    import inspect

    original = printer._triggerResend

    def trigger(expected=None, actual=None, checksum=None):
        caller = inspect.currentframe().f_back
        data = caller.f_locals.get("data") if caller else None
        if (
            checksum
            and expected is None
            and actual is None
            and isinstance(data, str)
            and caller.f_code.co_name == "_processIncoming"
        ):
            expected = printer.lastN
        return original(expected=expected, actual=actual, checksum=checksum)

    printer._triggerResend = trigger


class NoHooks:
    def get_hooks(self, name):
        return {}


class LoggingRegex:
    """Stands in for VirtualPrinter.command_regex: `match` is called once for every
    command the printer goes on to run, after every check that could reject the line."""

    def __init__(self, regex, log):
        self._regex = regex
        self._log = log
        self._lock = threading.Lock()

    def match(self, data):
        with self._lock:
            self._log.write(data.strip() + "\n")
            self._log.flush()
        return self._regex.match(data)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--link", required=True)
    ap.add_argument("--log", required=True)
    ap.add_argument("--resend-ratio", type=int, default=0)
    ap.add_argument("--busy", action="store_true")
    ap.add_argument("--simulated-errors", default="")
    ap.add_argument("--trace", help="append the bytes both ways to this file")
    ap.add_argument(
        "--keep-resend-ratio-bug",
        action="store_true",
        help="leave the resend ratio as it is (it loses the line it rejects)",
    )
    args = ap.parse_args()

    import octoprint
    from octoprint.plugins.virtual_printer import VirtualPrinterPlugin
    from octoprint.plugins.virtual_printer import virtual

    values = VirtualPrinterPlugin().get_settings_defaults()
    values["resend_ratio"] = args.resend_ratio
    values["sendBusy"] = args.busy
    values["busyInterval"] = 0.5
    values["simulated_errors"] = [e for e in args.simulated_errors.split(",") if e]
    # No temperature reports or SD card chatter: the peer test is about the line protocol.
    values["capabilities"]["AUTOREPORT_TEMP"] = False
    values["capabilities"]["AUTOREPORT_SD_STATUS"] = False
    values["enable_eeprom"] = False
    data = os.path.dirname(os.path.abspath(args.log))
    virtual.plugin_manager = lambda: NoHooks()
    log = open(args.log, "w", encoding="ascii", errors="replace")
    virtual.VirtualPrinter.command_regex = LoggingRegex(
        virtual.VirtualPrinter.command_regex, log
    )
    printer = virtual.VirtualPrinter(
        Settings(values, data), None, data, read_timeout=0.05, write_timeout=10.0
    )

    if not args.keep_resend_ratio_bug:
        fix_resend_ratio(printer)

    master, slave = os.openpty()
    tty.setraw(slave)
    slave_path = os.ttyname(slave)
    if os.path.islink(args.link):
        os.remove(args.link)
    os.symlink(slave_path, args.link)

    stop = threading.Event()
    trace = open(args.trace, "a", encoding="ascii", errors="replace") if args.trace else None

    def traced(way, data):
        if trace:
            trace.write(f"{time.monotonic():.3f} {way} {data!r}\n")
            trace.flush()

    def to_host():
        while not stop.is_set():
            line = printer.readline()
            if line:
                traced(">>>", line)
                # Its readline() is one reply; most carry no line end of their own.
                os.write(master, line if line.endswith(b"\n") else line + b"\n")

    def from_host():
        # The virtual printer takes one line per write() (as OctoPrint writes them): a
        # second line in the same write waits in its buffer until the next write comes.
        # A serial port has no writes, only bytes: hand it whole lines, one at a time.
        pending = b""
        while not stop.is_set():
            try:
                chunk = os.read(master, 4096)
            except OSError:
                stop.wait(0.05)  # the host has the pty closed for now
                continue
            traced("<<<", chunk)
            pending += chunk
            while b"\n" in pending:
                line, pending = pending.split(b"\n", 1)
                line += b"\n"
                while line:
                    n = printer.write(line)
                    line = line[n:]

    for f in (to_host, from_host):
        threading.Thread(target=f, daemon=True).start()
    print(f"ready {args.link} octoprint {octoprint.__version__}", flush=True)
    sys.stdin.read()
    stop.set()
    printer.close()
    os.remove(args.link)
    log.close()
    os._exit(0)


if __name__ == "__main__":
    main()
