"""Screenshots of a recording in rerun's real web viewer, in headless Chromium, with no extra
dependency: ``rerun <rrd> --web-viewer`` serves the viewer and the recording, and Chromium is
driven over the DevTools protocol on a pipe (``--remote-debugging-pipe``: JSON messages ended by
a NUL byte on file descriptors 3 and 4), so neither a websocket client nor playwright is needed.
WebGL runs on SwiftShader (``--use-angle=swiftshader --enable-unsafe-swiftshader``).

    with WebViewer(rrd) as v:
        png = v.screenshot(wait=lambda png: ..., timeout=120)

Used by tests/test_web_viewer.py (slow) and to look at a recording by hand:
``python -m tests.web_viewer recording.rrd shot.png``.
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def chromium() -> str | None:
    """The Chromium executable (Debian's ``chromium``), or None."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


def rerun_cli() -> str:
    """The ``rerun`` executable beside this Python's (the venv's), else the one on PATH."""
    here = Path(sys.executable).parent / "rerun"
    return str(here) if here.exists() else (shutil.which("rerun") or "rerun")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class _Pipe:
    """The DevTools protocol over Chromium's ``--remote-debugging-pipe``."""

    def __init__(self, exe: str, width: int, height: int, log):
        to_chrome_r, self._w = os.pipe()
        self._r, from_chrome_w = os.pipe()

        def fds():   # the child reads commands on fd 3 and writes replies on fd 4
            a, b = os.dup(to_chrome_r), os.dup(from_chrome_w)
            os.dup2(a, 3)
            os.dup2(b, 4)

        args = [exe, "--headless", "--no-sandbox", "--remote-debugging-pipe", "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist", "--no-first-run", "--disable-extensions",
                f"--window-size={width},{height}", f"--user-data-dir={log.parent / 'chromium-profile'}",
                "about:blank"]
        self.proc = subprocess.Popen(args, pass_fds=(3, 4), preexec_fn=fds, stdout=log.open("wb"),
                                     stderr=subprocess.STDOUT)
        os.close(to_chrome_r)
        os.close(from_chrome_w)
        self._buf = b""
        self._id = 0
        self.size = (width, height)

    def call(self, method: str, params: dict | None = None, session: str | None = None, timeout: float = 60.0):
        self._id += 1
        msg = {"id": self._id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        os.write(self._w, json.dumps(msg).encode() + b"\0")
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            while b"\0" in self._buf:
                raw, self._buf = self._buf.split(b"\0", 1)
                reply = json.loads(raw)
                if reply.get("id") == self._id:
                    if "error" in reply:
                        raise RuntimeError(f"{method}: {reply['error']}")
                    return reply.get("result", {})
            chunk = os.read(self._r, 1 << 20)
            if not chunk:
                raise RuntimeError(f"{method}: Chromium closed the DevTools pipe")
            self._buf += chunk
        raise TimeoutError(f"{method}: no reply in {timeout} s")

    def close(self):
        try:
            self.call("Browser.close", timeout=10)
        except Exception:   # noqa: BLE001  (it may be gone already)
            pass
        for fd in (self._w, self._r):
            try:
                os.close(fd)
            except OSError:
                pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


class WebViewer:
    """``rerun <rrd> --web-viewer`` and a headless Chromium page on it (a context manager)."""

    def __init__(self, rrd: str | Path, workdir: str | Path, width: int = 1600, height: int = 1000):
        self.rrd, self.workdir = Path(rrd), Path(workdir)
        self.width, self.height = width, height

    def __enter__(self):
        exe = chromium()
        if exe is None:
            raise FileNotFoundError("chromium is not installed")
        self.workdir.mkdir(parents=True, exist_ok=True)
        web, grpc = free_port(), free_port()
        env = {**os.environ, "RERUN_ANALYTICS": "0"}
        self.server = subprocess.Popen([rerun_cli(), str(self.rrd), "--web-viewer", "--bind", "127.0.0.1",
                                        "--web-viewer-port", str(web), "--port", str(grpc)], env=env,
                                       stdout=(self.workdir / "rerun.log").open("wb"), stderr=subprocess.STDOUT,
                                       start_new_session=True)   # its own group: see __exit__
        self._wait_port(web)
        self.chrome = _Pipe(exe, self.width, self.height, self.workdir / "chromium.log")
        target = self.chrome.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        self.session = self.chrome.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        self.chrome.call("Emulation.setDeviceMetricsOverride", {"width": self.width, "height": self.height,
                                                                "deviceScaleFactor": 1, "mobile": False},
                         session=self.session)
        self.url = url = (f"http://127.0.0.1:{web}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc}%2Fproxy"
                          "&renderer=webgl")
        self.chrome.call("Page.navigate", {"url": url}, session=self.session)
        return self

    def _wait_port(self, port: int, timeout: float = 30.0) -> None:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.server.poll() is not None:
                raise RuntimeError(f"rerun --web-viewer exited ({self.server.returncode}); see "
                                   f"{self.workdir / 'rerun.log'}")
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", port)) == 0:
                    return
            time.sleep(0.2)
        raise TimeoutError(f"rerun --web-viewer did not listen on port {port} in {timeout} s")

    def _attach(self) -> None:
        """Attach to the viewer's page again (its target is replaced when the page is swapped)."""
        pages = [t for t in self.chrome.call("Target.getTargets")["targetInfos"] if t["type"] == "page"]
        ours = [t for t in pages if t.get("url", "").startswith(self.url.split("?")[0])]
        pages = ours or pages   # the viewer's page, not headless Chromium's own blank one
        if not pages:
            raise RuntimeError("Chromium has no page left (the viewer's tab crashed?); see "
                               f"{self.workdir / 'chromium.log'}")
        self.session = self.chrome.call("Target.attachToTarget", {"targetId": pages[-1]["targetId"],
                                                                  "flatten": True})["sessionId"]

    def screenshot(self) -> bytes:
        """The page as PNG bytes."""
        for attempt in range(10):   # the page's target is swapped while the viewer loads, maybe more than once
            try:
                data = self.chrome.call("Page.captureScreenshot", {"format": "png"}, session=self.session,
                                        timeout=240)["data"]
                return base64.b64decode(data)
            except RuntimeError as exc:
                if "Not attached" not in str(exc) or attempt == 9:
                    raise
                time.sleep(2.0)
                self._attach()

    def screenshot_when(self, ready, timeout: float = 150.0, every: float = 3.0) -> tuple[bytes, bool]:
        """Screenshots every ``every`` s until ``ready(png)`` or ``timeout``: (the last one, ready)."""
        end = time.monotonic() + timeout
        while True:
            png = self.screenshot()
            if ready(png):
                return png, True
            if time.monotonic() >= end:
                return png, False
            time.sleep(every)

    def __exit__(self, *exc):
        if getattr(self, "chrome", None) is not None:
            self.chrome.close()
        # .venv/bin/rerun is a Python wrapper that starts the viewer binary as its child: ending only
        # the wrapper left the binary serving (and using CPU) after the test; end the whole group
        self._signal_group(signal.SIGTERM)
        try:
            self.server.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self._signal_group(signal.SIGKILL)
            self.server.wait()
        time.sleep(0.5)
        self._signal_group(signal.SIGKILL)   # a child that outlived the wrapper

    def _signal_group(self, sig) -> None:
        try:
            os.killpg(self.server.pid, sig)
        except (ProcessLookupError, PermissionError):
            pass


def main(argv=None):
    import argparse

    ap = argparse.ArgumentParser(description="Screenshot a recording in rerun's web viewer (headless Chromium).")
    ap.add_argument("rrd")
    ap.add_argument("png")
    ap.add_argument("--wait", type=float, default=60.0, help="seconds to let the viewer load and play")
    ap.add_argument("--size", default="1600x1000")
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.size.split("x"))
    with WebViewer(args.rrd, Path(args.png).with_suffix(".d"), w, h) as v:
        time.sleep(args.wait)
        Path(args.png).write_bytes(v.screenshot())
    print(f"wrote {args.png}")


if __name__ == "__main__":
    main()
