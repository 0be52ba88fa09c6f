"""LinuxCNC link: streams the linuxcnc-dialect program block by block as MDI, remotely through
linuxcncrsh (TCP) or locally through the ``linuxcnc`` Python module (drivers/linuxcnc_local.py).

Why MDI streaming: linuxcncrsh's ``set open FILE`` opens a path *on the LinuxCNC host* and it has
no upload command, and the dialect's ``(LOG,…)`` writes a file there too; neither needs a shared
file system when the daemon sends each block with ``set mdi`` (``set set_wait received``:
LinuxCNC takes a block once the previous one has finished) and reads each touch result back
through LinuxCNC's own message channel. Per program line (daemon/dialects.py,
gcode_templates/linuxcnc/README.md):

* ``%``, empty lines, plain comments, ``(LOGOPEN,…)``, ``(LOGCLOSE)``, ``M2``: not sent.
* ``o<n> if …`` / ``(abort,…)`` / ``o<n> endif`` (the miss check): not sent — LinuxCNC's G38.2
  raises its own error on a miss ("G38.2 move finished without making contact."), which this
  link reads with ``get error`` after the block and turns into ``ControllerAlarm`` naming the
  touch. (In MDI a failed G38.2 leaves #5070 at its previous value: it cannot be trusted there.)
* ``(LOG,RUMBA <seq> <rep> <pose> <ball> <touch> #5070 #5061 …)``: sent as ``(DEBUG,…)``;
  LinuxCNC substitutes the parameters and the text comes back through ``get operator_display``;
  the identity (seq, pose, ball, touch) is the program's (the session checks it against the
  program's touch table), the numbers LinuxCNC's.
* consecutive ``#<n> = <v>`` lines (result slots) are merged into MDI lines (RS274NGC sets all
  parameters of a line together, after substituting the line's message), the last of them
  together with the result line; everything else is sent as is.
After every sent block ``get error`` is drained: any error stops the run with LinuxCNC's text.
Cost: linuxcncrsh polls completion in 100 ms steps, so a block takes ≥ 0.1 s (~1.2 s per touch
measured, config/linuxcnc/README.md), mostly hidden behind the motion of each block.

Verdict write-back: ``M68 E<verdict_output> Q<code>`` (motion.analog-out-NN, immediate;
config/linuxcnc/rumba_xyzbc.hal nets analog-out-00 to ``rumba-verdict``) and
``M68 E<count_output> Q<n>`` with a counter of verdicts written by this link.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import re
import sys
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

from daemon.messages import ProbeHit
from drivers.base import (
    Capabilities,
    CncLink,
    ControllerAlarm,
    LinkError,
    ProgramJob,
    StartRequest,
    Verdict,
)
from drivers.link_config import LinuxCncLinkConfig

log = logging.getLogger("rumba.linuxcnc")
_ASSIGN = re.compile(r"^#\d+\s*=\s*(?:[-+]?[0-9.]+|#\d+)$")
_LOG = re.compile(r"^\(LOG,(RUMBA .*)\)$", re.IGNORECASE)
_SKIP = re.compile(r"^(%|\(.*\)|o\d+\s+(if|endif|else)\b.*|M0*2|M30)$", re.IGNORECASE)
_MAX_LINE = 240  # RS274NGC lines are < 256 characters
HELPER = Path(__file__).resolve().parent / "linuxcnc_local.py"


@dataclass(frozen=True)
class Step:
    """One thing to do for a program line: an MDI block, or read a result."""

    kind: str  # "mdi" | "result"
    text: str
    line: int  # 1-based program line
    touch: str = ""  # identity of the touch a probing block belongs to (for messages)
    prefix: str = ""  # result steps: parameter settings sent on the same MDI line


def plan_steps(text: str) -> list[Step]:
    """Turn the linuxcnc-dialect program into MDI steps (rules in the module docstring)."""
    lines = text.replace("\r\n", "\n").split("\n")
    steps: list[Step] = []
    pending: list[tuple[int, str]] = []

    def flush() -> None:
        while pending:
            first, merged = pending[0][0], pending[0][1]
            del pending[0]
            while pending and len(merged) + 1 + len(pending[0][1]) <= _MAX_LINE:
                merged += " " + pending.pop(0)[1]
            steps.append(Step("mdi", merged, first))

    for n, raw in enumerate(lines, 1):
        s = raw.strip()
        if not s:
            continue
        if len(s) > _MAX_LINE or not s.isascii() or "\x00" in s:
            raise LinkError(f"program line {n}: not a LinuxCNC MDI line (ASCII, < {_MAX_LINE})")
        m = _LOG.match(s)
        if m:
            # the last settings ride on the result's MDI line (one block less per touch);
            # LinuxCNC substitutes the message's parameters before the line's settings apply
            prefix: list[str] = []
            while pending and len(" ".join([pending[-1][1], *prefix])) + len(s) < _MAX_LINE:
                prefix.insert(0, pending.pop()[1])
            flush()
            steps.append(Step("result", m.group(1), n, prefix=" ".join(prefix)))
            continue
        if _SKIP.match(s):
            continue
        if _ASSIGN.match(s):
            pending.append((n, re.sub(r"\s*=\s*", "=", s)))
            continue
        flush()
        steps.append(Step("mdi", s, n))
    flush()
    # name each probing block by the identity of the result line that follows it
    ident = ""
    for i in range(len(steps) - 1, -1, -1):
        st = steps[i]
        if st.kind == "result":
            f = st.text.split()
            ident = f"touch seq {f[1]} pose {f[3]} ball {f[4]} touch {f[5]}" if len(f) > 5 else ""
        elif "G38" in st.text.upper():
            steps[i] = Step(st.kind, st.text, st.line, ident)
    return steps


class _Rsh:
    """linuxcncrsh line protocol over TCP (replies end in \\r\\n or \\n\\r; echo turned off)."""

    def __init__(self, cfg: LinuxCncLinkConfig) -> None:
        self.cfg = cfg
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None
        self._buf = b""

    async def open(self) -> None:
        c = self.cfg
        try:
            self.reader, self.writer = await asyncio.wait_for(
                asyncio.open_connection(c.host, c.port), c.connect_timeout_s)
        except (OSError, TimeoutError) as e:
            raise LinkError(f"linuxcncrsh at {c.host}:{c.port} unreachable: "
                            f"{e.strerror if isinstance(e, OSError) else 'timeout'}") from None
        rep = await self.ask(f"hello {c.hello_password} {c.client_name} 1.0")
        if not rep.startswith("HELLO ACK"):
            raise LinkError(f"linuxcncrsh refused hello: {rep!r} (check hello_password)")
        self.send("set echo off")  # echoed itself (or not): synchronise on the next reply
        self.send("get echo")
        while await self.line(self.cfg.connect_timeout_s) != "ECHO OFF":
            pass
        # set_wait received: a `set mdi` answers once LinuxCNC has taken the block (after the
        # previous one finished). `done` would poll completion in 100 ms steps (linuxcncrsh).
        for cmd in ("set verbose on", f"set enable {c.enable_password}",
                    "set set_wait received"):
            rep = await self.ask(cmd)
            if not rep.endswith("ACK"):
                raise LinkError(f"linuxcncrsh: {cmd.split()[1]} refused: {rep!r}")

    def send(self, cmd: str) -> None:
        if self.writer is None:
            raise LinkError("linuxcncrsh: not connected")
        self.writer.write(cmd.encode("ascii") + b"\r\n")

    async def line(self, timeout_s: float) -> str:
        assert self.reader is not None
        while True:
            m = re.search(rb"[^\r\n]+[\r\n]", self._buf)
            if m:
                self._buf = self._buf[m.end():]
                return m.group()[:-1].decode("ascii", "replace")
            try:
                data = await asyncio.wait_for(self.reader.read(4096), timeout_s)
            except TimeoutError:
                raise LinkError(f"linuxcncrsh silent for {timeout_s:g} s") from None
            except OSError as e:
                raise LinkError(f"linuxcncrsh connection lost: {e}") from None
            if not data:
                raise LinkError("linuxcncrsh closed the connection (LinuxCNC stopped?)")
            self._buf += data

    async def ask(self, cmd: str, timeout_s: float | None = None) -> str:
        self.send(cmd)
        return await self.line(timeout_s or self.cfg.command_timeout_s)

    async def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            with contextlib.suppress(Exception):
                await self.writer.wait_closed()
        self.reader = self.writer = None
        self._buf = b""


class _Local(_Rsh):
    """The same command subset answered by drivers/linuxcnc_local.py through the ``linuxcnc``
    module, in a child process of Debian's /usr/bin/python3 (the only one that has it)."""

    def __init__(self, cfg: LinuxCncLinkConfig) -> None:
        super().__init__(cfg)
        self.proc: asyncio.subprocess.Process | None = None

    async def open(self) -> None:
        try:
            env = dict(os.environ)
            if self.cfg.local_home:  # linuxcnc.stat() maps $HOME/.tool.mmap of the instance
                env["HOME"] = self.cfg.local_home
            self.proc = await asyncio.create_subprocess_exec(
                self.cfg.helper_python, "-I", str(HELPER), stdin=asyncio.subprocess.PIPE,
                stdout=asyncio.subprocess.PIPE, stderr=sys.stderr, env=env)
        except OSError as e:
            raise LinkError(f"cannot start {self.cfg.helper_python} {HELPER}: {e}") from None
        self.reader, self.writer = self.proc.stdout, self.proc.stdin  # type: ignore[assignment]
        rep = await self.line(self.cfg.connect_timeout_s)
        if not rep.startswith("HELLO ACK"):
            raise LinkError(f"local LinuxCNC helper: {rep}")

    async def close(self) -> None:
        if self.proc is not None and self.proc.returncode is None:
            with contextlib.suppress(Exception):
                self.proc.stdin.close()  # type: ignore[union-attr]
            try:
                await asyncio.wait_for(self.proc.wait(), 3)
            except TimeoutError:
                self.proc.kill()
                await self.proc.wait()
        self.proc = None
        self.reader = self.writer = None


def _where(step: Step) -> str:
    where = f"program line {step.line} '{step.text}'" if step.line else f"'{step.text}'"
    return where + (f" ({step.touch})" if step.touch else "")


class LinuxCncLink(CncLink):
    """A LinuxCNC controller (see the module docstring for the protocol)."""

    capabilities = Capabilities(start_request=False, streams_blocks=True, loads_program=False,
                                writes_verdict=True, can_abort=True)

    def __init__(self, cfg: LinuxCncLinkConfig) -> None:
        self.cfg = cfg
        self._ch: _Rsh | None = None
        self._verdicts = 0
        self.blocks_sent = 0
        self._prev: Step | None = None  # the block sent before the current one
        self._probe: Step | None = None  # the last probing block sent

    def _channel(self) -> _Rsh:
        return _Local(self.cfg) if self.cfg.mode == "local" else _Rsh(self.cfg)

    async def connect(self) -> None:
        if self._ch is not None:
            return
        ch = self._channel()
        try:
            await ch.open()
        except BaseException:
            await ch.close()
            raise
        self._ch = ch

    async def _ready(self) -> _Rsh:
        """Connected, estop off, machine on, homed, MDI mode, no stale error."""
        await self.connect()
        ch = self._ch
        assert ch is not None
        for cmd in ("set estop off", "set machine on"):
            await self._set(cmd)
        homed = await ch.ask("get joint_homed")
        if "NO" in homed.split()[1:1 + self.cfg.joints]:
            if not self.cfg.home_if_needed:
                raise ControllerAlarm(f"LinuxCNC joints not homed ({homed}); home the machine")
            await self._set("set mode manual")
            await self._set("set home -1")
            for _ in range(int(self.cfg.command_timeout_s * 10)):
                homed = await ch.ask("get joint_homed")
                if "NO" not in homed.split()[1:1 + self.cfg.joints]:
                    break
                await asyncio.sleep(0.1)
            else:
                raise ControllerAlarm(f"LinuxCNC homing did not finish: {homed}")
        await self._set("set mode mdi")
        await self._errors()  # stale messages of a previous (aborted) run: never read them
        for _ in range(50):  # as this run's results
            if (await ch.ask("get operator_display")).endswith(" OK"):
                break
        return ch

    async def _set(self, cmd: str) -> None:
        assert self._ch is not None
        rep = await self._ch.ask(cmd)
        if not rep.endswith(" ACK"):
            errs = await self._errors()
            raise ControllerAlarm(f"LinuxCNC refused '{cmd}': {rep}"
                                  + (f": {'; '.join(errs)}" if errs else ""))

    async def _errors(self) -> list[str]:
        """Drain ``get error`` (a queue: one message per call, ``ERROR OK`` when empty)."""
        assert self._ch is not None
        out = []
        for _ in range(50):
            rep = await self._ch.ask("get error")
            msg = rep.removeprefix("ERROR").strip()
            if msg == "OK":
                break
            out.append(msg)
        return out

    async def _mdi(self, step: Step) -> None:
        """Send one block. With ``set_wait received`` LinuxCNC takes a block once the previous
        one has finished, so the reply to block k means block k-1 is done: an error found now
        (a G38.2 miss, a limit) belongs to the previous block, a NAK to this one."""
        assert self._ch is not None
        rep = await self._ch.ask(f"set mdi {step.text}")
        self.blocks_sent += 1
        prev, self._prev = self._prev, step
        if "G38" in step.text.upper():
            self._probe = step
        errs = await self._errors()
        if rep != "SET MDI ACK":
            errs += await self._errors()
            raise ControllerAlarm(f"LinuxCNC: {'; '.join(errs) or 'block refused (' + rep + ')'}"
                                  f" at {_where(step)}")
        if errs:  # remote: found when the next block was taken; local: this block's own
            raise self._alarm(errs, step if self.cfg.mode == "local" else prev or step)

    def _alarm(self, errs: list[str], step: Step) -> ControllerAlarm:
        """LinuxCNC's own messages, naming the block (the probing one for a probe error)."""
        text = "; ".join(errs)
        if self._probe is not None and ("G38" in text or "probe" in text.lower()):
            step = self._probe
        return ControllerAlarm(f"LinuxCNC: {text} at {_where(step)}")

    async def _display(self, text: str, step: Step, prefix: str = "") -> str:
        """Send ``(DEBUG,text)`` and wait until LinuxCNC shows it (substituted) through
        ``get operator_display``; LinuxCNC interprets it once the blocks before it are done,
        so this is also the barrier that says they finished. Errors met on the way stop it."""
        assert self._ch is not None
        await self._mdi(Step("mdi", f"{prefix} (DEBUG,{text})".lstrip(), step.line, step.touch))
        head = " ".join(text.split()[:2]) + " "
        loop = asyncio.get_running_loop()
        end = loop.time() + self.cfg.command_timeout_s
        while True:
            disp = await self._ch.ask("get operator_display")
            shown = disp.removeprefix("OPERATOR_DISPLAY").strip()
            if (shown + " ").startswith(head):
                errs = await self._errors()
                if errs:
                    raise self._alarm(errs, self._prev or step)
                return shown
            errs = await self._errors()
            if errs:
                raise self._alarm(errs, self._prev or step)
            if loop.time() > end:
                raise LinkError(f"LinuxCNC did not reach program line {step.line} within "
                                f"{self.cfg.command_timeout_s:g} s")
            await asyncio.sleep(self.cfg.poll_interval_s)

    async def wait_start_request(self) -> StartRequest:
        raise LinkError("LinuxCNC link has no start request: start runs from the HMI, "
                        "the CAN panel or the CLI")

    async def run(self, job: ProgramJob) -> AsyncIterator[ProbeHit]:
        if job.dialect != "linuxcnc":
            raise LinkError(f"the LinuxCNC link streams the linuxcnc dialect, not {job.dialect}")
        if job.codec is None:
            raise LinkError("the LinuxCNC job carries no linuxcnc result decoder")
        dialect = job.codec
        steps = plan_steps(job.text)
        done = False
        try:
            await self._ready()
            self._prev = self._probe = None
            for cmd in self.cfg.prelude_mdi:
                await self._mdi(Step("mdi", cmd, 0))
            for st in steps:
                if st.kind == "mdi":
                    await self._mdi(st)
                    continue
                text = await self._display(st.text, st, st.prefix)
                try:
                    hit = dialect.parse_result(text)
                except ValueError as e:
                    raise LinkError(f"LinuxCNC result line {st.line}: {e}") from None
                if hit is None:
                    raise LinkError(f"LinuxCNC result line {st.line}: unexpected {text!r}")
                yield hit
            await self._display(f"RUMBA-END {job.run_id}", Step("mdi", "", len(steps)))
            done = True
        finally:
            if not done:  # a reply may still be due on this connection: never reuse it
                await self._drop()

    async def _drop(self) -> None:
        ch, self._ch = self._ch, None
        if ch is not None:
            await ch.close()

    async def write_verdict(self, verdict: Verdict) -> None:
        try:
            await self._ready()
            self._verdicts += 1
            for out, q in ((self.cfg.verdict_output, verdict.code),
                           (self.cfg.count_output, self._verdicts)):
                await self._mdi(Step("mdi", f"M68 E{out} Q{q}", 0))
        except (LinkError, ControllerAlarm):
            await self._drop()
            raise

    async def abort(self) -> None:
        """``set abort`` on a connection of its own: the run's connection may be waiting for a
        block to be taken and would answer only afterwards."""
        await self._drop()
        ch = self._channel()
        try:
            await ch.open()
            rep = await ch.ask("set abort", 10.0)
            if not rep.endswith("ACK"):
                raise LinkError(f"LinuxCNC abort refused: {rep}")
        finally:
            await ch.close()

    async def close(self) -> None:
        await self._drop()
