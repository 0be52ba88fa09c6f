"""LinuxCNC link: runs the linuxcnc-dialect program remotely through linuxcncrsh (TCP, MDI
streaming) or locally through the ``linuxcnc`` Python module (drivers/linuxcnc/local.py), there
streaming too (``run: mdi``, the default) or, opt-in, as one AUTO run of a file (``run: auto``).

Remote, why MDI streaming: linuxcncrsh's ``set open FILE`` opens a path *on the LinuxCNC host*
and it has no upload command, and the dialect's ``(LOG,…)`` writes a file there too; neither
needs a shared file system when the daemon sends each block with ``set mdi`` (``set set_wait
received``: LinuxCNC takes a block once the previous one has finished) and reads each touch
result back through LinuxCNC's own message channel. Per program line (programs/dialects,
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
Cost: every block starts and ends at rest, and linuxcncrsh polls completion in 100 ms steps
(~1.2 s per touch measured, config/linuxcnc/README.md).

Local AUTO run (``mode: local``, ``run: auto``): the program goes, line for line (so
LinuxCNC's line numbers are the program's), into a per-run file in a private folder
(``program_dir`` or the temp folder), with each ``(LOG,RUMBA …)`` as ``(DEBUG,RUMBA …)`` and the
other ``(LOG…)`` comments neutralised (``auto_program``); the miss check stays (LinuxCNC's own
G38.2 error aborts the program first). Prelude in MDI, then ``set mode auto``, ``set open``,
``set run``; ``wait event`` returns LinuxCNC's messages in channel order. Checked on LinuxCNC
2.9: a ``(DEBUG,…)`` after a G38.2 is shown once the probe move ended (a probe is a queue
buster: the interpreter waits for the motion before it reads #5061…), in program order; a miss
is an operator error "G38.2 move finished without making contact." with ``motion_line`` = the
G38.2 line, and the program stops. A result → a hit; an error → ``ControllerAlarm`` naming the
program line and touch; the end of the program with every touch → done (fewer: alarm). An
absolute path needs no PROGRAM_PREFIX. After the run ``set plan_init`` unloads the file before
it is deleted (else LinuxCNC's next MDI O-word call fails to reopen it); a run cancelled (abort)
or failed drops the helper, which aborts its program and unloads the file; a killed LinuxCNC is
``LOST`` in the helper → ``LinkError``, hits already yielded kept. Gain: no per-block stop or
poll, 1 ms of daemon CPU per touch instead of 3-30 ms; the run is then bound by the program's
own motion (14 poses: 318 s AUTO, 339 s remote MDI, 378 s local MDI). Why not the default:
LinuxCNC 2.9's task can read the line after a G38.2 before the motion status shows the probe
queued, and stops the program with "Queue is not empty after probing" (LinuxCNC issues #263,
#662, #3650; fix PR #3971, not in 2.9) — seen here once in ~1750 AUTO touches; MDI waits for an
empty queue and is immune. config/linuxcnc/README.md.

Verdict write-back: ``M68 E<verdict_output> Q<code>`` (motion.analog-out-NN, immediate;
config/linuxcnc/rumba_xyzbc.hal nets analog-out-00 to ``rumba-verdict``) and
``M68 E<count_output> Q<n>`` with a counter of verdicts written by this link.
"""

from __future__ import annotations

import asyncio
import logging
import os
import re
import shutil
import tempfile
from collections.abc import AsyncIterator
from pathlib import Path

from contracts.jobs import ProgramJob, Verdict
from contracts.messages import ProbeHit
from contracts.temperatures import TemperatureChannel
from drivers.base import (
    Capabilities,
    CncLink,
    ControllerAborted,
    ControllerAlarm,
    LinkError,
    StartRequest,
)
from drivers.linuxcnc.channel import LocalChannel, RshChannel
from drivers.linuxcnc.program import Step, auto_program, name_error, plan_steps, where
from drivers.linuxcnc.schema import LinuxCncLinkConfig

__all__ = ["LinuxCncLink", "Step", "auto_program", "plan_steps"]

log = logging.getLogger("rumba.linuxcnc")
_WAIT_S = 0.5  # local AUTO: longest helper wait per `wait event` (abort and kill stay prompt)


class LinuxCncLink(CncLink):
    """A LinuxCNC controller (see the module docstring for the protocol)."""

    capabilities = Capabilities(start_request=False, streams_blocks=True, loads_program=False,
                                writes_verdict=True, can_abort=True)

    def __init__(self, cfg: LinuxCncLinkConfig) -> None:
        self.cfg = cfg
        if cfg.run == "auto":
            self.capabilities = Capabilities(start_request=False, streams_blocks=False,
                                             loads_program=True, writes_verdict=True,
                                             can_abort=True)
        self._ch: RshChannel | None = None
        self._verdicts = 0
        self.blocks_sent = 0
        self._prev: Step | None = None  # the block sent before the current one
        self._probe: Step | None = None  # the last probing block sent

    def _channel(self) -> RshChannel:
        return LocalChannel(self.cfg) if self.cfg.mode == "local" else RshChannel(self.cfg)

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

    async def _ready(self) -> RshChannel:
        """Connected, estop off, machine on, homed, MDI mode, no stale error. linuxcncrsh obeys
        the last client that sent ``set enable`` (an operator's client, a check, the link's own
        abort): each run takes it back on its channel first (remote mode; the local helper
        talks to LinuxCNC through its ``linuxcnc`` module, no enable there)."""
        await self.connect()
        ch = self._ch
        assert ch is not None
        enable = [f"set enable {self.cfg.enable_password}"] if self.cfg.mode == "remote" else []
        for cmd in (*enable, "set estop off", "set machine on"):
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
            why = f"{'; '.join(errs) or 'block refused (' + rep + ')'} at {where(step)}"
            if self.cfg.mode == "remote" and await self._ch.ask("get enable") == "ENABLE OFF":
                # linuxcncrsh obeys the last client that sent 'set enable': an operator's
                # client took the control (to abort it, as the pendant's abort does)
                raise ControllerAborted(f"another linuxcncrsh client took the control "
                                        f"(set enable); LinuxCNC: {why}")
            raise ControllerAlarm(f"LinuxCNC: {why}")
        if errs:  # remote: found when the next block was taken; local: this block's own
            raise self._alarm(errs, step if self.cfg.mode == "local" else prev or step)

    def _alarm(self, errs: list[str], step: Step) -> ControllerAlarm:
        """LinuxCNC's own messages, naming the block (the probing one for a probe error)."""
        text = "; ".join(errs)
        if self._probe is not None and ("G38" in text or "probe" in text.lower()):
            step = self._probe
        return ControllerAlarm(f"LinuxCNC: {text} at {where(step)}")

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
        steps = plan_steps(job.text)  # also checks every line before anything moves
        auto = self.cfg.run == "auto"
        program = auto_program(job.text) if auto else ""
        done = False
        try:
            await self._ready()
            self._prev = self._probe = None
            if auto:  # unload a program file a crashed run may have left loaded (helper doc)
                await self._set("set plan_init")
            for cmd in self.cfg.prelude_mdi:
                await self._mdi(Step("mdi", cmd, 0))
            if auto:
                async for hit in self._run_auto(job, program, steps):
                    yield hit
                done = True
                return
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
            if not done:  # a reply may still be due on this connection: never reuse it; the
                await self._drop()  # local helper aborts a program it started when dropped

    async def _run_auto(self, job: ProgramJob, program: str,
                        steps: list[Step]) -> AsyncIterator[ProbeHit]:
        """Local AUTO run: the program in a per-run file, opened and run by LinuxCNC; results
        and errors read in channel order through ``wait event`` (drivers/linuxcnc/local.py)."""
        assert self._ch is not None and job.codec is not None
        ch, parse = self._ch, job.codec.parse_result
        probes = [st for st in steps if st.touch]  # the probing blocks, in program order
        lines = job.text.replace("\r\n", "\n").split("\n")
        where = self.cfg.program_dir or tempfile.gettempdir()
        try:
            folder = tempfile.mkdtemp(prefix="rumba-lcnc-", dir=where)
        except OSError as e:
            raise LinkError(f"cannot write the LinuxCNC program in {where}: {e.strerror} "
                            "(link config program_dir)") from None
        try:
            name = re.sub(r"[^A-Za-z0-9_.-]", "_", job.run_id)[:64]
            path = Path(folder) / f"rumba_{name}.ngc"
            try:
                os.chmod(folder, 0o755)  # LinuxCNC may run as another user; only we write
                path.write_text(program, encoding="ascii")
                path.chmod(0o644)
            except OSError as e:
                raise LinkError(f"cannot write the LinuxCNC program {path}: {e.strerror}") from None
            for cmd in ("set mode auto", f"set open {path}", "set run"):
                await self._set(cmd)
            n, loop = 0, asyncio.get_running_loop()
            quiet_since = loop.time()
            while True:
                rep = await ch.ask(f"wait event {_WAIT_S}", _WAIT_S + self.cfg.command_timeout_s)
                kind, _, rest = rep.removeprefix("EVENT ").partition(" ")
                if kind == "DISPLAY":
                    try:
                        hit = parse(rest)
                    except ValueError as e:
                        raise LinkError(f"LinuxCNC result after touch {n}: {e}") from None
                    if hit is None:  # an operator message of the machine's own (a remap)
                        log.info("LinuxCNC: %s", rest)
                        continue
                    n += 1
                    quiet_since = loop.time()
                    yield hit
                elif kind == "ERROR":
                    errs = [rest]
                    while len(errs) < 10:  # what LinuxCNC said right after, in order
                        more = await ch.ask("wait event 0")
                        if not more.startswith("EVENT ERROR "):
                            break
                        errs.append(more.removeprefix("EVENT ERROR "))
                    msg = f"LinuxCNC: {name_error(errs, n, probes, lines)}"
                    if "Queue is not empty after probing" in msg:
                        msg += (" - a LinuxCNC AUTO-mode race after G38.2 (LinuxCNC issues "
                                "#263, #662, #3650; fix PR #3971): use run: mdi")
                    raise ControllerAlarm(msg)
                elif kind == "IDLE":
                    break
                elif kind == "NONE":
                    if loop.time() - quiet_since > self.cfg.command_timeout_s:
                        raise LinkError(f"no result from LinuxCNC for "
                                        f"{self.cfg.command_timeout_s:g} s after touch {n}")
                else:
                    raise LinkError(f"local LinuxCNC helper: unexpected reply {rep!r}")
            if n != job.touch_count:  # idle, no error: stopped there (abort, Esc in AXIS)
                raise ControllerAborted(f"LinuxCNC program stopped after {n} of "
                                        f"{job.touch_count} touches without an error")
            await self._set("set plan_init")  # unload the file before deleting it (helper doc)
        finally:
            shutil.rmtree(folder, ignore_errors=True)

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

    async def read_temperature(self, channel: TemperatureChannel) -> float:
        """A HAL pin (``halcmd getp``, as the kinematics pins are read: drivers/linuxcnc/
        halkins.py), on the PC LinuxCNC runs on: local mode or linuxcncrsh on loopback."""
        from drivers.linuxcnc import halkins

        try:
            value = await asyncio.to_thread(halkins.getp, channel.address)
        except halkins.HalError as e:
            raise LinkError(f"LinuxCNC temperature {channel.name}: {e}") from None
        return value * channel.scale + channel.offset_c

    async def close(self) -> None:
        await self._drop()
