"""Controller side of LSV2 (HEIDENHAIN's TNCremo protocol): a TCP server speaking the subset a
verification run needs, as a TNC 640 answers it — so that pylsv2, an independent client written
from the TNCremo plugin and traces of real controls, is what the tests drive it with.

Telegrams (pylsv2's low_level_com/const): 4 bytes payload length (big-endian), 4 ASCII
characters of command or response, payload. One response per request. Logins INSPECT, FILE and
DNC (DNC refused when the control does not allow it: ``dnc_allowed``; others, e.g. PLCDEBUG,
refused: T_ER_NO_PRIV); versions R_VR; system parameters R_PR (120 bytes, the block length the
client negotiates with C_CC SET_BUF…); system information R_CI (turbo mode, DNC allowed, axes
sampling rate); files: C_DC / R_DI / C_DM / R_FI / C_FD / C_FL (then S_FL blocks, T_FD) / R_FL
(S_FL blocks, the client's T_OK between, T_FD) — text files travel with NUL line ends; program
state R_RI (26 program state, 24 selected program, 23 execution state). Errors are T_ER with
two bytes (type, LSV2StatusCode). A file the control runs cannot be written or deleted
(T_ER_NO_DELETE / T_ER_FILE_ACCESS).

The control's side: files written under TNC: are its files (format files, the stop and verdict
programs a run calls: ``VirtualController.files`` by name); FN 16 output files are read back
from what the program printed (``VirtualController.print_files``); the start-of-shift program's
request file is written on ``raise_start_request``; the operator selects and starts a program
(``nc_start``), or the control does it when ``auto_start`` names the program just written (a
shop's PLC on the transferred program, as tests and demos run it).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import struct
import time
from typing import Any

from simulators.frontends import cancel_tasks

log = logging.getLogger(__name__)
# pylsv2's constants, spelled out: the server is written from the protocol, not from the client
T_ER_UNKNOWN_TELE, T_ER_NO_PRIV, T_ER_WRONG_PARA = 22, 23, 24
T_ER_BAD_FNAME, T_ER_NO_FILE, T_ER_FILE_EXISTS = 31, 32, 34
T_ER_NO_DELETE, T_ER_FILE_ACCESS, T_ER_CHANGE_PATH, T_ER_NO_LOGIN = 36, 45, 47, 49
PGM_STATE = {"running": 0, "hold": 1, "done": 2, "cancelled": 3, "alarm": 5, "idle": 7}
LOGINS = ("INSPECT", "FILE", "DNC")
MAX_TELEGRAM = 4096
ATTR_DIR, ATTR_CHANGEABLE = 0x20, 0x02


def telegram(code: str, payload: bytes = b"") -> bytes:
    return struct.pack("!L", len(payload)) + code.encode("ascii") + payload


def cstr(text: str) -> bytes:
    return text.encode("latin1") + b"\x00"


def norm(path: str) -> str:
    """A TNC path as the control compares it: upper case, backslashes, no trailing one."""
    p = path.replace("/", "\\").strip().upper()
    return p[:-1] if p.endswith("\\") and not p.endswith(":\\") else p.rstrip("\\")


class Lsv2Frontend:
    """One LSV2 server for one simulated TNC; ``await start()`` returns the port."""

    def __init__(self, controller: Any, *, dnc_allowed: bool = True,
                 auto_start: str | None = "TNC:\\RUMBA\\RUMBA.H",
                 request_file: str = "TNC:\\RUMBA\\RUMBA_REQ.TXT",
                 control: str = "TNC640", nc_software: str = "340595 10 SP6") -> None:
        self.ctrl = controller
        self.dnc_allowed = dnc_allowed
        self.auto_start = norm(auto_start) if auto_start else None
        self.request_file = norm(request_file)
        self.control, self.nc_software = control, nc_software
        self.files: dict[str, bytes] = {}
        self.dirs: set[str] = {"TNC:"}
        self.selected: str | None = None
        self.starts = 0  # NC starts given (operator / auto start)
        self.telegrams: list[str] = []  # every request command received (tests)
        self._cancelled = False
        self._server: asyncio.Server | None = None
        self._tasks: list[asyncio.Task] = []
        self._writers: set[asyncio.StreamWriter] = set()

    async def start(self, host: str = "127.0.0.1", port: int = 0) -> int:
        self._server = await asyncio.start_server(self._serve, host, port)
        self._tasks = [asyncio.create_task(self._events())]
        return self._server.sockets[0].getsockname()[1]

    async def stop(self) -> None:
        await cancel_tasks(self._tasks)
        if self._server is not None:
            self._server.close()
            for w in list(self._writers):
                w.transport.abort()
            await self._server.wait_closed()
            self._server = None

    def diagnose(self) -> str:
        """Where the simulated TNC stands, for a test's failure message."""
        return (f"selected {self.selected}, program state {self.program_state()}, files "
                f"{sorted(self.files)}, starts {self.starts}")

    def drop_connections(self) -> None:
        """The network cable pulled: every connection reset (the server stays)."""
        for w in list(self._writers):
            w.transport.abort()

    # ------------------------------------------------------------------ the control's side
    def program_state(self) -> int:
        state = self.ctrl.state
        if state == "idle" and self._cancelled:
            return PGM_STATE["cancelled"]
        return PGM_STATE.get(state, PGM_STATE["idle"])

    async def nc_start(self, path: str | None = None) -> None:
        """The operator selects ``path`` (default: the last selected) in Program Run and
        presses NC start (a held program goes on)."""
        if self.ctrl.state == "hold" and path is None:
            await self.ctrl.start()
            return
        path = norm(path or self.selected or "")
        data = self.files.get(path)
        if data is None:
            raise FileNotFoundError(path)
        await self.ctrl.load_program(data.decode("latin1"), "heidenhain")
        self.selected = path
        self._cancelled = False
        await self.ctrl.start()
        self.starts += 1

    async def _events(self) -> None:
        q = self.ctrl.subscribe()
        while True:
            ev = await q.get()
            kind = type(ev).__name__
            if kind == "RequestRaised":  # the start-of-shift program's FN 16 request line
                self._store(self.request_file, f"RUMBA REQUEST {ev.machine}\n".encode())
            elif kind == "StateChange" and ev.state == "idle" and self.ctrl.resets:
                self._cancelled = True  # a RESET (internal stop) of the running program
            elif kind == "FaultEvent" and ev.kind == "disconnect":
                self.drop_connections()

    def _store(self, path: str, data: bytes) -> None:
        self.files[path] = data
        name = path.rpartition("\\")[2]
        self.ctrl.files[name] = data.decode("latin1")
        self.ctrl.print_files.pop(name, None)  # a new file replaces what was printed
        if name == "RUMBAV.H":  # the production program calls it: its Q1598 is the verdict
            for line in data.decode("latin1").splitlines():
                if "Q1598" in line and "=" in line:
                    with contextlib.suppress(ValueError):
                        self.ctrl.variables["Q1598"] = float(line.split("=", 1)[1])

    def _printed(self, path: str) -> bytes | None:
        name = path.rpartition("\\")[2]
        lines = self.ctrl.print_files.get(name)
        return None if lines is None else "".join(f"{ln}\n" for ln in lines).encode("latin1")

    def _running(self, path: str) -> bool:
        return path == self.selected and self.ctrl.state in ("running", "hold")

    # ------------------------------------------------------------------ the wire
    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._writers.add(writer)
        conn = {"logins": set(), "cwd": "TNC:", "buffer": 256, "upload": None,
                "download": None, "secure": False}
        try:
            while True:
                head = await reader.readexactly(8)
                length = struct.unpack("!L", head[:4])[0]
                if length > MAX_TELEGRAM:
                    break  # garbage: a real control drops the connection
                payload = await reader.readexactly(length) if length else b""
                try:
                    code = head[4:8].decode("ascii")
                except UnicodeDecodeError:
                    break
                self.telegrams.append(code)
                answer = self._handle(conn, code, payload)
                if answer is not None:
                    writer.write(answer)
                    await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            self._writers.discard(writer)
            writer.close()

    def _error(self, code: int) -> bytes:
        return telegram("T_ER", struct.pack("!BB", 1, code))

    def _path(self, conn: dict, payload: bytes) -> str:
        raw = payload.split(b"\x00", 1)[0].decode("latin1")
        return norm(raw if ":" in raw else f"{conn['cwd']}\\{raw}")

    def _handle(self, conn: dict, code: str, payload: bytes) -> bytes | None:
        if code == "A_LG":
            parts = payload.split(b"\x00")
            login = parts[0].decode("latin1")
            if login not in LOGINS or (login == "DNC" and not self.dnc_allowed):
                return self._error(T_ER_NO_PRIV)
            conn["logins"].add(login)
            return telegram("T_OK")
        if code == "A_LO":
            login = payload.split(b"\x00")[0].decode("latin1")
            conn["logins"].discard(login) if login else conn["logins"].clear()
            return telegram("T_OK")
        if not conn["logins"]:
            return self._error(T_ER_NO_LOGIN)
        if code == "R_VR":
            return self._versions(payload)
        if code == "R_PR":
            return telegram("S_PR", self._parameters())
        if code == "R_CI":
            (which,) = struct.unpack("!L", payload[:4]) if len(payload) >= 4 else (0,)
            if which in (1, 2):
                on = False if which == 1 else self.dnc_allowed
                return telegram("S_CI", struct.pack("!L", 1) + struct.pack("!xxx?", on))
            if which == 3:
                return telegram("S_CI", struct.pack("!LL", 2, 3000))
            return self._error(T_ER_WRONG_PARA)
        if code == "C_CC":
            (cmd,) = struct.unpack("!H", payload[:2]) if len(payload) >= 2 else (0,)
            sizes = {3: 1024, 4: 512, 5: 2048, 6: 3072, 7: 4096}
            if cmd in sizes:
                conn["buffer"] = sizes[cmd]
                return telegram("T_OK")
            if cmd == 19:  # secure file send: T_FD acknowledged
                conn["secure"] = True
                return telegram("T_OK")
            return self._error(T_ER_WRONG_PARA)
        if code == "R_RI":
            return self._run_info(conn, payload)
        if "FILE" not in conn["logins"] and code in ("C_DC", "R_DI", "C_DM", "R_FI", "C_FD",
                                                     "C_FL", "R_FL"):
            return self._error(T_ER_NO_PRIV)
        return self._files(conn, code, payload)

    def _versions(self, payload: bytes) -> bytes:
        if not payload:
            return telegram("S_VR", b"".join(cstr(s) for s in (
                self.control, self.nc_software, "RUMBA-SIM PLC", "00000000")))
        which = payload[0]
        if which == 5:
            return telegram("S_VR", cstr("RUMBA-SIM 0001"))
        if which == 6:
            return telegram("S_VR", cstr("Release"))
        return self._error(T_ER_WRONG_PARA)

    def _parameters(self) -> bytes:
        """R_PR's 120 bytes: PLC memory layout (unused here), LSV2 version 2, block length
        4096 (the client then asks for SET_BUF4096), versions; nothing secret."""
        ints = [0] * 14
        values = (*ints, *([0] * 8), *([0] * 8), 2, 0, MAX_TELEGRAM, 1, 0, 1, 0, 0, 0, 0, 0, 0)
        return struct.pack("!14L8B8L2BH4B2L2HL", *values)

    def _run_info(self, conn: dict, payload: bytes) -> bytes:
        if "DNC" not in conn["logins"]:
            return self._error(T_ER_NO_PRIV)
        (which,) = struct.unpack("!H", payload[:2]) if len(payload) >= 2 else (0,)
        if which == 26:
            return telegram("S_RI", struct.pack("!H", self.program_state()))
        if which == 23:
            return telegram("S_RI", struct.pack("!H", 4))  # program run, full sequence
        if which == 24:
            main = self.selected or ""
            line = getattr(self.ctrl, "_line_no", 0)
            return telegram("S_RI", struct.pack("!L", line) + cstr(main) + cstr(main))
        return self._error(T_ER_WRONG_PARA)

    def _files(self, conn: dict, code: str, payload: bytes) -> bytes | None:
        if code == "C_DC":
            path = self._path(conn, payload)
            if path not in self.dirs:
                return self._error(T_ER_CHANGE_PATH)
            conn["cwd"] = path
            return telegram("T_OK")
        if code == "R_DI":
            attrs = b"".join(a.encode().ljust(4, b"\x00") for a in ("H", "A", "TXT", "TAB"))
            return telegram("S_DI", struct.pack("!L", 10**8) + attrs.ljust(128, b"\x00")
                            + bytes(32) + cstr(conn["cwd"] + "\\"))
        if code == "C_DM":
            path = self._path(conn, payload)
            if path.rpartition("\\")[0] not in self.dirs:
                return self._error(T_ER_CHANGE_PATH)
            self.dirs.add(path)
            return telegram("T_OK")
        if code == "R_FI":
            path = self._path(conn, payload)
            if path in self.dirs:
                return telegram("S_FI", struct.pack("!LLL", 0, int(time.time()), ATTR_DIR)
                                + cstr(path))
            data = self.files.get(path, self._printed(path))
            if data is None:
                return self._error(T_ER_NO_FILE)
            return telegram("S_FI", struct.pack("!LLL", len(data), int(time.time()),
                                                ATTR_CHANGEABLE) + cstr(path))
        if code == "C_FD":
            path = self._path(conn, payload)
            if self._running(path):
                return self._error(T_ER_NO_DELETE)
            name = path.rpartition("\\")[2]
            printed = self.ctrl.print_files.pop(name, None)
            if self.files.pop(path, None) is None and printed is None:
                return self._error(T_ER_NO_FILE)
            self.ctrl.files.pop(name, None)
            return telegram("T_OK")
        if code == "C_FL":
            path = self._path(conn, payload)
            if path.rpartition("\\")[0] not in self.dirs or not path.rpartition("\\")[2]:
                return self._error(T_ER_BAD_FNAME)
            if self._running(path):
                return self._error(T_ER_FILE_ACCESS)
            conn["upload"] = [path, bytearray()]
            return telegram("T_OK")
        if code == "S_FL" and conn["upload"] is not None:
            conn["upload"][1] += payload
            return telegram("T_OK")
        if code == "T_FD" and conn["upload"] is not None:
            path, data = conn["upload"]
            conn["upload"] = None
            self._store(path, bytes(data))
            if path == self.auto_start and self.ctrl.state not in ("running", "hold"):
                asyncio.get_running_loop().create_task(self.nc_start(path))
            return telegram("T_OK") if conn["secure"] else None
        if code == "R_FL":
            path = self._path(conn, payload)
            data = self.files.get(path, self._printed(path))
            if data is None:
                return self._error(T_ER_NO_FILE)
            binary = payload.split(b"\x00", 1)[1][:1] == b"\x01"
            if not binary:  # text travels with NUL line ends (the client turns them back)
                data = data.replace(b"\r\n", b"\n").replace(b"\n", b"\x00")
            step = conn["buffer"] - 8
            conn["download"] = [data[i:i + step] for i in range(0, len(data), step)]
            return self._next_block(conn)
        if code == "T_OK" and conn["download"] is not None:
            return self._next_block(conn)
        return self._error(T_ER_UNKNOWN_TELE)

    def _next_block(self, conn: dict) -> bytes:
        if conn["download"]:
            return telegram("S_FL", conn["download"].pop(0))
        conn["download"] = None
        return telegram("T_FD")
