"""``python -m docs.gen.screenshots [--path-shots DIR]``: the manual's pictures, taken with
headless Chromium from the real thing — the operator page of ``make demo-hmi`` after a check
and the report of that run (``docs/img/hmi.png``, ``docs/img/report.png``) — and, with
``--path-shots``, a newcomer's path through README, manual, first check and first compensation
(README → tutorial → the check on the operator page → the compensation confirmed → PASS)."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import html
import os
import re
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
IMG = ROOT / "docs" / "img"


async def _demo(out: Path) -> tuple[asyncio.subprocess.Process, str, str, str]:
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "demos.hmi", "--port", "0", "--time-scale", "0", "--out", str(out),
        cwd=ROOT, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT)
    text = ""
    async with asyncio.timeout(300):
        while not text.rstrip().endswith("Ctrl-C stops the daemon and the simulated CNC"):
            line = (await proc.stdout.readline()).decode()
            if not line:
                raise RuntimeError("demo-hmi ended:\n" + text)
            text += line
    url = re.search(r"^HMI:\s+(\S+)$", text, re.M)[1]
    user, password = re.search(r"^login:\s+user (\S+)\s+password (\S+)", text, re.M).groups()
    return proc, url, user, password


async def _check(cdp, sid: str, card: str, verdict: str) -> None:
    from tests.browser import tick_preflight

    await cdp.eval(sid, f"{card}.querySelector('.start').click(); true")
    await tick_preflight(cdp, sid)
    await cdp.wait_for(sid, f"{card}.querySelector('.state').textContent === 'CAPTURE'", 300)
    await cdp.wait_for(sid, f"{card}.querySelector('.state').textContent === 'IDLE' && "
                            f"{card}.querySelector('.verdict').textContent.includes('{verdict}')",
                       600)


async def _report(folder: Path) -> Path:
    """The run's HTML report once its job wrote it (after the verdict) and its PDF."""
    async with asyncio.timeout(300):
        while True:
            found = sorted(p for p in folder.glob("*.html") if p.with_suffix(".pdf").exists())
            if found:
                return found[-1]
            await asyncio.sleep(0.2)


async def _metrics(cdp, sid: str, height: int) -> None:
    await cdp.call("Emulation.setDeviceMetricsOverride", sid, width=1280, height=height,
                   deviceScaleFactor=1, mobile=False)


async def _scroll_to(cdp, sid: str, element: str) -> None:
    await cdp.eval(sid, f"{element}.scrollIntoView(); true")
    await asyncio.sleep(0.5)


async def _page(cdp, sid: str, url: str, shot: Path, height: int = 900) -> None:
    await _metrics(cdp, sid, height)
    await cdp.call("Page.navigate", sid, url=url)
    await cdp.wait_for(sid, "document.readyState === 'complete'")
    await asyncio.sleep(0.5)  # fonts and images laid out
    await cdp.screenshot(sid, shot)


def _readme_html(work: Path) -> Path:
    """README.next.md rendered as GitHub would show it (Python-Markdown, images from the
    repository's root)."""
    import markdown

    body = markdown.markdown((ROOT / "docs/README.next.md").read_text(encoding="utf-8"),
                             extensions=["tables", "fenced_code"])
    page = work / "readme.html"
    page.write_text(f"<!doctype html><meta charset=utf-8><base href='{ROOT.as_uri()}/'>"
                    "<style>body{font:15px/1.5 sans-serif;max-width:980px;margin:2em auto}"
                    "img{max-width:100%}table{border-collapse:collapse}td,th{border:1px solid "
                    "#ccc;padding:4px}pre{background:#f6f8fa;padding:8px}</style>"
                    f"<title>{html.escape('README')}</title>{body}", encoding="utf-8")
    return page


async def take(path_shots: Path | None) -> None:
    from tests.browser import chromium

    IMG.mkdir(exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        site = work / "site"
        if path_shots is not None:
            path_shots.mkdir(parents=True, exist_ok=True)
            subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet",
                            "--site-dir", str(site)], cwd=ROOT, check=True,
                           env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
        proc, url, user, password = await _demo(work / "demo")
        try:
            async with chromium(work / "profile") as cdp:
                sid = await cdp.page()
                if path_shots is not None:
                    await _page(cdp, sid, _readme_html(work).as_uri(),
                                path_shots / "1-readme.png", 1400)
                    await _page(cdp, sid, (site / "index.html").as_uri(),
                                path_shots / "2-manual-home.png")
                    await _page(cdp, sid, (site / "tutorials/first-check.html").as_uri(),
                                path_shots / "3-tutorial-first-check.png")
                await _metrics(cdp, sid, 1000)
                await cdp.sign_in_user(sid, url, user, password)
                card = "document.querySelector('.machine')"
                await _check(cdp, sid, card, "FAIL")
                await cdp.wait_for(sid, f"!{card}.querySelector('.comp-confirm').disabled", 120)
                report = await _report(work / "demo" / "reports")
                await cdp.wait_for(sid, f"{card}.querySelector('.report-state').hidden", 120)
                await _metrics(cdp, sid, 1500)
                await cdp.eval(sid, "window.scrollTo(0, 0); true")
                await asyncio.sleep(0.5)
                await cdp.screenshot(sid, IMG / "hmi.png")
                if path_shots is not None:
                    await _metrics(cdp, sid, 1000)
                    await _scroll_to(cdp, sid, f"{card}.querySelector('.comp')")
                    await cdp.screenshot(sid, path_shots / "4-first-check-fail.png")
                    await _page(cdp, sid, (site / "tutorials/first-compensation.html").as_uri(),
                                path_shots / "5-tutorial-first-compensation.png")
                    await cdp.call("Page.navigate", sid, url=url)  # still signed in
                    await cdp._hmi_live(sid)
                    await cdp.eval(sid, "window.confirm = () => true; "
                                        f"{card}.querySelector('.comp-confirm').click(); true")
                    await cdp.wait_for(sid, f"{card}.textContent.includes('Applied')", 120)
                    await _scroll_to(cdp, sid, f"{card}.querySelector('.comp')")
                    await cdp.screenshot(sid, path_shots / "6-compensation-confirmed.png")
                    await asyncio.sleep(3)  # the demo's operator loads the program (every 1 s)
                    await _check(cdp, sid, card, "PASS")
                    await cdp.eval(sid, "window.scrollTo(0, 0); true")
                    await asyncio.sleep(0.5)
                    await cdp.screenshot(sid, path_shots / "7-verification-pass.png")
                await _page(cdp, sid, report.as_uri(), IMG / "report.png", 1100)
                if path_shots is not None:
                    await cdp.screenshot(sid, path_shots / "8-report.png")
        finally:
            proc.send_signal(signal.SIGINT)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(60):
                    await proc.communicate()
            if proc.returncode is None:
                proc.kill()
                await proc.wait()


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="python -m docs.gen.screenshots", description=__doc__)
    ap.add_argument("--path-shots", type=Path, help="also the newcomer's path, into this folder")
    args = ap.parse_args(argv)
    asyncio.run(take(args.path_shots))
    for p in sorted(IMG.glob("*.png")):
        print(f"wrote {p.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
