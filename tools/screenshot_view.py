"""Screenshot of ``lc-view`` in headless Chromium: serves the web viewer for an episode and captures it.

Usage (from a checkout, Debian package ``chromium`` installed)::

    python tools/screenshot_view.py                       # records a small rule-driver episode first
    python tools/screenshot_view.py runs/ep.mcap --out docs/images/lc-view.png

The episode is served with :func:`lcdata.view.serve` on localhost; headless Chromium (software
WebGL through SwiftShader, a fresh profile) opens the web viewer, waits ``--wait-s`` seconds of real
time for the viewer to load and stream the data, and captures the page over the DevTools protocol.
The viewer's time cursor is at the end of the episode (the web viewer follows the stream).
"""

from __future__ import annotations

import argparse
import base64
import dataclasses
import json
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lcdata.record import record_episode  # noqa: E402
from lcdata.view import make_recordings, open_episodes, serve  # noqa: E402
from lcsim.config import paper_scenario  # noqa: E402


def record_demo(path: pathlib.Path, seed: int) -> pathlib.Path:
    """A short lane-change episode: the paper scenario over a 250 m route, rule-based driver."""
    config = dataclasses.replace(paper_scenario(), route_length_m=250.0, time_limit_s=40.0)
    return record_episode(config, seed, "rule", path, scenario="paper", overwrite=True).path


class Chromium:
    """Headless Chromium driven over the DevTools protocol on a pipe (``--remote-debugging-pipe``).

    Messages are NUL-terminated JSON; Chromium reads commands on fd 3 and answers on fd 4, so the
    standard library is enough (no WebSocket client, no browser-automation package).
    """

    def __init__(self, browser: str, profile: pathlib.Path, size: tuple[int, int]) -> None:
        to_chrome_r, self._to_chrome = os.pipe()
        self._from_chrome, from_chrome_w = os.pipe()
        cmd = [
            browser, "--headless", "--no-sandbox", "--disable-gpu", "--use-gl=angle", "--use-angle=swiftshader",
            "--enable-unsafe-swiftshader", "--disable-background-networking", "--no-first-run",
            "--disable-dev-shm-usage", f"--user-data-dir={profile}", "--hide-scrollbars",
            f"--window-size={size[0]},{size[1]}", "--remote-debugging-pipe", "about:blank",
        ]  # fmt: skip

        def fds() -> None:  # runs in the child: the pipe ends become fds 3 and 4
            r, w = os.dup(to_chrome_r), os.dup(from_chrome_w)  # out of the way of 3 and 4 first
            os.dup2(r, 3)
            os.dup2(w, 4)

        self.proc = subprocess.Popen(cmd, preexec_fn=fds, close_fds=False,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
        os.close(to_chrome_r)
        os.close(from_chrome_w)
        self._buf = b""
        self._id = 0

    def call(self, method: str, session: str | None = None, **params: object) -> dict:
        self._id += 1
        msg: dict[str, object] = {"id": self._id, "method": method, "params": params}
        if session:
            msg["sessionId"] = session
        os.write(self._to_chrome, json.dumps(msg).encode() + b"\0")
        while True:
            while b"\0" not in self._buf:
                chunk = os.read(self._from_chrome, 1 << 20)
                if not chunk:
                    raise RuntimeError("chromium closed the DevTools pipe")
                self._buf += chunk
            raw, self._buf = self._buf.split(b"\0", 1)
            reply = json.loads(raw)
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})

    def screenshot(self, url: str, out: pathlib.Path, wait_s: float, size: tuple[int, int]) -> None:
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        session = self.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        self.call("Emulation.setDeviceMetricsOverride", session, width=size[0], height=size[1],
                  deviceScaleFactor=1, mobile=False)  # fmt: skip
        self.call("Page.enable", session)
        self.call("Page.navigate", session, url=url)
        time.sleep(wait_s)
        data = self.call("Page.captureScreenshot", session, format="png")["data"]
        out.write_bytes(base64.b64decode(data))

    def close(self) -> None:
        try:
            self.call("Browser.close")
        except (RuntimeError, OSError):
            pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
        os.close(self._to_chrome)
        os.close(self._from_chrome)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("episode", nargs="?", type=pathlib.Path, help="episode .mcap (default: record one)")
    parser.add_argument("--out", type=pathlib.Path, default=ROOT / "docs/images/lc-view.png")
    parser.add_argument(
        "--seed", type=int, default=5, help="seed of the recorded episode (5 changes lanes twice)"
    )
    parser.add_argument("--wait-s", type=float, default=25.0, help="time for the viewer to load and stream")
    parser.add_argument("--width", type=int, default=1600)
    parser.add_argument("--height", type=int, default=1000)
    parser.add_argument("--web-port", type=int, default=9190)
    parser.add_argument("--grpc-port", type=int, default=9976)
    parser.add_argument("--browser", default=shutil.which("chromium") or "chromium")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        episode = args.episode or record_demo(pathlib.Path(tmp) / "paper_rule.mcap", args.seed)
        recordings = make_recordings(open_episodes([episode]), side_by_side=False)
        url = serve(recordings, grpc_port=args.grpc_port, web_port=args.web_port)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        print(f"serving {url}", flush=True)
        size = (args.width, args.height)
        browser = Chromium(args.browser, pathlib.Path(tmp) / "profile", size)
        try:
            browser.screenshot(url, args.out, args.wait_s, size)
        finally:
            browser.close()
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
