"""Screenshots of a running MLflow UI in headless Chromium, driven through the DevTools protocol over a pipe
(no extra Python package). First visit: the UI's assistant panel opens by itself; it is closed (as a user would,
once) before the screenshots.

    python experiments/mlflow_ui/screenshot.py OUT.png URL [OUT.png URL ...] [--width 1600 --height 900]
        [--wait 30] [--ready TEXT] [--js EXPRESSION]
"""

from __future__ import annotations

import argparse
import base64
import fcntl
import json
import os
import subprocess
import tempfile
import time
from pathlib import Path


class Browser:
    """Headless Chromium with --remote-debugging-pipe: commands on fd 3, replies on fd 4, NUL-separated JSON."""

    def __init__(self, width: int, height: int):
        self.profile = tempfile.TemporaryDirectory()
        to_chrome_r, self.to_chrome = os.pipe()
        self.from_chrome, from_chrome_w = os.pipe()
        command = ["chromium", "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                   "--remote-debugging-pipe", f"--user-data-dir={self.profile.name}", f"--window-size={width},{height}",
                   "about:blank"]  # fmt: skip

        def child_fds():  # the child's fds 3 and 4 become the pipe ends (copied high first: they may be 3 or 4)
            high = [fcntl.fcntl(fd, fcntl.F_DUPFD, 10) for fd in (to_chrome_r, from_chrome_w)]
            os.dup2(high[0], 3)
            os.dup2(high[1], 4)

        # close_fds=False: only fds 3 and 4 (inheritable after dup2) and the standard ones reach Chromium; Python's
        # own pipe fds are close-on-exec.
        self.process = subprocess.Popen(command, preexec_fn=child_fds, close_fds=False,  # noqa: PLW1509 (no threads)
                                        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
        os.close(to_chrome_r)
        os.close(from_chrome_w)
        self.buffer, self.next_id, self.session = b"", 0, None
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        self.session = self.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        self.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1, mobile=False)

    def call(self, method: str, **params):
        self.next_id += 1
        message = {"id": self.next_id, "method": method, "params": params}
        if self.session and not method.startswith("Target."):
            message["sessionId"] = self.session
        os.write(self.to_chrome, json.dumps(message).encode() + b"\0")
        while True:
            while b"\0" not in self.buffer:
                chunk = os.read(self.from_chrome, 1 << 20)
                if not chunk:
                    raise RuntimeError(f"chromium closed the pipe during {method}")
                self.buffer += chunk
            raw, self.buffer = self.buffer.split(b"\0", 1)
            reply = json.loads(raw)
            if reply.get("id") == self.next_id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})

    def evaluate(self, expression: str):
        return self.call("Runtime.evaluate", expression=expression, returnByValue=True).get("result", {}).get("value")

    def open(self, url: str, wait_s: float, ready: str | None = None) -> None:
        self.call("Page.navigate", url=url)
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline:  # until the page shows `ready` (or the wait is over)
            time.sleep(1)
            if ready and self.evaluate(f"document.body && document.body.innerText.includes({json.dumps(ready)})"):
                time.sleep(2)  # plots finish drawing
                return

    def screenshot(self, path: Path) -> None:
        data = self.call("Page.captureScreenshot", format="png")["data"]
        path.write_bytes(base64.b64decode(data))

    def close(self) -> None:
        self.process.terminate()
        self.process.wait()
        self.profile.cleanup()  # after Chromium has exited (it writes the profile until then)


def close_assistant(browser: Browser) -> None:
    """Store the assistant panel as closed (its localStorage entries hold JSON true/false) and reload."""
    browser.evaluate(
        "Object.keys(localStorage).filter(k => k.includes('assistant')).forEach(k => "
        "localStorage.setItem(k, localStorage.getItem(k).replace('true', 'false').replace('false', "
        "k.includes('autoOpened') ? 'true' : 'false')))"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("pairs", nargs="+", help="OUT.png URL [OUT.png URL ...]")
    parser.add_argument("--width", type=int, default=1600)
    parser.add_argument("--height", type=int, default=900)
    parser.add_argument("--wait", type=float, default=30, help="seconds at most per page")
    parser.add_argument("--ready", default=None, help="text the page shows once loaded")
    parser.add_argument("--js", default=None, help="JavaScript run on each page before its screenshot (e.g. a click)")
    args = parser.parse_args()
    if len(args.pairs) % 2:
        parser.error("expected pairs of OUT.png URL")
    browser = Browser(args.width, args.height)
    try:
        first_url = args.pairs[1]
        browser.open(first_url, args.wait, args.ready)  # the first visit opens the assistant panel
        close_assistant(browser)
        for out, url in zip(args.pairs[::2], args.pairs[1::2]):
            browser.open("about:blank", 0)
            browser.open(url, args.wait, args.ready)
            if args.js:
                browser.evaluate(args.js)
                time.sleep(2)
            browser.screenshot(Path(out))
            print(f"{out}: {Path(out).stat().st_size // 1024} KB  ({url})")
    finally:
        browser.close()


if __name__ == "__main__":
    main()
