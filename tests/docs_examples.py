"""The manual's shell examples as a test runs them: every fenced ``sh`` block of docs/ carries a
marker comment on the line before it saying how it is checked —

* ``<!-- doctest: run [exit=N] [expect="text"] -->`` run in the page's session (bash, the
  variables of earlier blocks kept); the exit code must be N (default 0) and the output hold
  the text;
* ``<!-- doctest: background name=NAME ready="text" [port=N] -->`` started and left running
  until the page ends (a second terminal); ready once its output holds the text; ``port=N``:
  N is replaced by a free port in every block of the page and in the session's config copy;
* ``<!-- doctest: covered-by TEST runs="module" -->`` a ``make TARGET`` the named test runs
  already (the Makefile target must run that module and the test file name it);
* ``<!-- doctest: skip reason="…" -->`` not run, and the reason says why (root, a real control);

and every ``text`` block typed at a background process carries
``<!-- doctest: stdin name=NAME expect="text" -->``. A page is a session: a temp folder with a
copy of config/ and a link to .venv, HOME inside it."""

from __future__ import annotations

import contextlib
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
_BLOCK = re.compile(r"(?:<!--\s*doctest:\s*(?P<marker>.*?)\s*-->\s*\n)?"
                    r"^(?P<fence>```+)(?P<lang>[\w-]*)[^\n]*\n(?P<body>.*?)^(?P=fence)\s*$",
                    re.M | re.S)
KINDS = ("run", "background", "covered-by", "skip", "stdin")


@dataclass
class Block:
    page: str
    line: int
    lang: str
    body: str
    kind: str | None
    options: dict[str, str] = field(default_factory=dict)
    target: str = ""  # covered-by: the test file

    @property
    def where(self) -> str:
        return f"{self.page}:{self.line}"


def _options(text: str) -> tuple[str | None, str, dict[str, str]]:
    words = shlex.split(text)
    if not words:
        return None, "", {}
    kind, target, options = words[0], "", {}
    for w in words[1:]:
        if "=" in w:
            k, v = w.split("=", 1)
            options[k] = v
        else:
            target = w
    return kind, target, options


def blocks(path: Path) -> list[Block]:
    text = path.read_text(encoding="utf-8")
    out = []
    for m in _BLOCK.finditer(text):
        kind, target, options = _options(m.group("marker") or "")
        line = text.count("\n", 0, m.start("fence")) + 1
        out.append(Block(str(path.relative_to(ROOT)), line, m.group("lang"), m.group("body"),
                         kind, options, target))
    return out


def pages() -> list[Path]:
    return sorted(p for p in DOCS.rglob("*.md") if "gen" not in p.relative_to(DOCS).parts)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Session:
    """One page's terminal(s): a temp folder with config/ copied, .venv linked, HOME inside."""

    def __init__(self, tmp: Path) -> None:
        self.dir = tmp / "work"
        self.dir.mkdir()
        shutil.copytree(ROOT / "config", self.dir / "config")
        (self.dir / ".venv").symlink_to(ROOT / ".venv")
        self.home = tmp / "home"
        self.home.mkdir()
        self.state = tmp / "state.sh"
        self.env = {**os.environ, "HOME": str(self.home), "TERM": "dumb", "COLUMNS": "120",
                    "PATH": f"{ROOT / '.venv' / 'bin'}:{os.environ.get('PATH', '')}"}
        self.ports: dict[str, str] = {}
        self.background: dict[str, tuple[subprocess.Popen, Path]] = {}

    def ports_of(self, page_blocks: list[Block]) -> None:
        """Every ``port=N`` of the page → a free port, in the blocks and the config copy."""
        for b in page_blocks:
            if "port" in b.options and b.options["port"] not in self.ports:
                self.ports[b.options["port"]] = str(free_port())
        for old, new in self.ports.items():
            for f in (self.dir / "config").rglob("*.yaml"):
                text = f.read_text(encoding="utf-8")
                if old in text:
                    f.write_text(re.sub(rf"\b{old}\b", new, text), encoding="utf-8")

    def text(self, body: str) -> str:
        for old, new in self.ports.items():
            body = re.sub(rf"\b{old}\b", new, body)
        return body

    def run(self, b: Block, timeout_s: float = 600) -> str:
        script = (f"set -eo pipefail\nset -a\n[ -f {self.state} ] && . {self.state}\n"
                  f"{self.text(b.body)}\nexport -p > {self.state}\n")
        p = subprocess.run(["bash", "-c", script], cwd=self.dir, env=self.env,
                           capture_output=True, text=True, timeout=timeout_s,
                           stdin=subprocess.DEVNULL)
        out = p.stdout + p.stderr
        want = int(b.options.get("exit", "0"))
        assert p.returncode == want, (f"{b.where}: exit {p.returncode}, expected {want}:\n"
                                      f"{b.body}\n---\n{out[-3000:]}")
        if "expect" in b.options:
            assert b.options["expect"] in out, (f"{b.where}: {b.options['expect']!r} not in the "
                                                f"output:\n{out[-3000:]}")
        return out

    def start(self, b: Block, timeout_s: float = 120) -> None:
        log = self.dir.parent / f"{b.options['name']}.log"
        out = log.open("wb")
        script = f"set -a\n[ -f {self.state} ] && . {self.state}\n{self.text(b.body)}"
        proc = subprocess.Popen(["bash", "-c", script],
                                cwd=self.dir, env=self.env, stdin=subprocess.PIPE, stdout=out,
                                stderr=subprocess.STDOUT, start_new_session=True)
        self.background[b.options["name"]] = (proc, log)
        self._wait(b.options["name"], b.options.get("ready", ""), timeout_s, b.where)

    def _wait(self, name: str, text: str, timeout_s: float, where: str, after: int = 0) -> None:
        proc, log = self.background[name]
        deadline = time.monotonic() + timeout_s
        while True:
            got = log.read_text(encoding="utf-8", errors="replace")
            if text in got[after:]:
                return
            assert proc.poll() is None, f"{where}: {name} ended ({proc.returncode}):\n{got[-3000:]}"
            assert time.monotonic() < deadline, f"{where}: {text!r} not seen:\n{got[-3000:]}"
            time.sleep(0.1)

    def type_into(self, b: Block, timeout_s: float = 180) -> None:
        proc, log = self.background[b.options["name"]]
        after = len(log.read_text(encoding="utf-8", errors="replace"))
        home_text = self.text(b.body).replace("~/", f"{self.home}/")
        proc.stdin.write(home_text.encode())
        proc.stdin.flush()
        self._wait(b.options["name"], b.options.get("expect", ""), timeout_s, b.where, after)

    def close(self) -> None:
        for proc, _ in self.background.values():
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGTERM)
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
            if proc.stdin:
                proc.stdin.close()


def make_recipe(target: str) -> str:
    """The recipe lines of a Makefile target."""
    lines = (ROOT / "Makefile").read_text(encoding="utf-8").splitlines()
    out, inside = [], False
    for line in lines:
        if re.match(rf"^{re.escape(target)}:", line):
            inside = True
            continue
        if inside:
            if line.startswith("\t"):
                out.append(line.strip())
            elif line.strip():
                break
    return "\n".join(out)


def run_page(path: Path, tmp: Path) -> int:
    """Run a page's examples in order; the number of blocks run."""
    page_blocks = [b for b in blocks(path) if b.kind in ("run", "background", "stdin")]
    if not page_blocks:
        return 0
    session = Session(tmp)
    session.ports_of(page_blocks)
    try:
        for b in page_blocks:
            if b.kind == "run":
                session.run(b)
            elif b.kind == "background":
                session.start(b)
            else:
                session.type_into(b)
    finally:
        session.close()
    return len(page_blocks)
