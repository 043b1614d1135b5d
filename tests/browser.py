"""Loads the viewer in headless Chromium and waits until it has drawn, for tests/browser.sh.

Drives Chromium over the DevTools protocol on a pipe (--remote-debugging-pipe: JSON messages
ended by NUL on file descriptors 3 and 4), so it needs nothing beyond Python's standard library.
Waiting on the page's own state, in wall time, is what makes the check deterministic:
--virtual-time-budget lets virtual time race ahead while MapLibre's workers parse tiles on a
busy machine, and the screenshot then catches a map before it drew.

Usage: browser.py URL OUT_DIR [SECONDS]. Waits until #status says data-loaded="true", the
coast has points and the globe and the volume are ready or absent (or until the expression in READY_JS is true) (at most SECONDS, default 90), lets one more second of frames run, then
writes OUT_DIR/shot.png (1200 x 700), OUT_DIR/dom.html and OUT_DIR/console.txt: what the page
logged as errors, as Chromium saw them (uncaught exceptions, console.error), one per line, so
that the check does not rest on the page's own error counter. Exits 1 if the page never got
there (the files are still written, showing how far it got).
"""

import base64
import json
import os
import subprocess
import sys
import time

url, out = sys.argv[1], sys.argv[2]
deadline = time.monotonic() + float(sys.argv[3] if len(sys.argv) > 3 else 90)
profile = os.path.join(out, "profile")

to_chrome_r, to_chrome_w = os.pipe()
from_chrome_r, from_chrome_w = os.pipe()


def wire_fds():
    # In the child: Chromium reads commands on fd 3 and writes answers on fd 4.
    os.dup2(to_chrome_r, 3)
    os.dup2(from_chrome_w, 4)


chrome = subprocess.Popen(
    [
        "chromium", "--headless=new", "--no-sandbox", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-quic",
        "--user-data-dir=" + profile, "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
        "--window-size=1200,700", "--remote-debugging-pipe", "about:blank",
    ],
    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, preexec_fn=wire_fds, pass_fds=(3, 4),
)
os.close(to_chrome_r)
os.close(from_chrome_w)
writer = os.fdopen(to_chrome_w, "wb", buffering=0)
reader = os.fdopen(from_chrome_r, "rb", buffering=0)
pending = b""
next_id = 0
# JavaScript errors the page raised or logged, from the DevTools events.
logged = []


def note_event(event):
    method, params = event.get("method"), event.get("params", {})
    if method == "Runtime.exceptionThrown":
        d = params.get("exceptionDetails", {})
        text = d.get("exception", {}).get("description") or d.get("text", "exception")
        logged.append("exception: " + text.splitlines()[0])
    elif method == "Runtime.consoleAPICalled" and params.get("type") in ("error", "assert"):
        args = params.get("args", [])
        text = " ".join(str(a.get("value", a.get("description", ""))) for a in args)
        logged.append("console." + params["type"] + ": " + text.splitlines()[0] if text else "")


def call(method, params=None, session=None):
    """Sends one command and returns its result (events in between are skipped)."""
    global next_id, pending
    next_id += 1
    msg = {"id": next_id, "method": method, "params": params or {}}
    if session:
        msg["sessionId"] = session
    writer.write(json.dumps(msg).encode() + b"\0")
    while True:
        while b"\0" not in pending:
            chunk = reader.read(1 << 16)
            if not chunk:
                raise RuntimeError("Chromium closed the pipe")
            pending += chunk
        raw, pending = pending.split(b"\0", 1)
        answer = json.loads(raw)
        if "method" in answer:
            note_event(answer)
        if answer.get("id") == next_id:
            if "error" in answer:
                raise RuntimeError(f"{method}: {answer['error']}")
            return answer.get("result", {})


def evaluate(session, expression):
    r = call("Runtime.evaluate", {"expression": expression, "returnByValue": True}, session)
    return r.get("result", {}).get("value")


ok = False
try:
    target = call("Target.createTarget", {"url": "about:blank"})["targetId"]
    session = call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
    call("Emulation.setDeviceMetricsOverride",
         {"width": 1200, "height": 700, "deviceScaleFactor": 1, "mobile": False}, session)
    call("Page.enable", {}, session)
    call("Runtime.enable", {}, session)
    call("Page.navigate", {"url": url}, session)
    # READY_JS: another page's own test of being done (tests/wasm.sh's static page).
    ready = os.environ.get("READY_JS") or (
        "(() => { const s = document.getElementById('status');"
        " return !!s && s.dataset.loaded === 'true' && Number(s.dataset.coastPoints) > 0"
        " && (s.dataset.globe === 'ready' || s.dataset.globe === 'absent')"
        " && (s.dataset.volume === 'ready' || s.dataset.volume === 'absent'); })()"
    )
    while time.monotonic() < deadline:
        if evaluate(session, ready):
            ok = True
            break
        time.sleep(0.25)
    # The frame that follows the last 'idle' (and fades) on screen before the picture.
    time.sleep(1.0)
    shot = call("Page.captureScreenshot", {"format": "png"}, session)["data"]
    with open(os.path.join(out, "shot.png"), "wb") as f:
        f.write(base64.b64decode(shot))
    with open(os.path.join(out, "dom.html"), "w") as f:
        f.write(evaluate(session, "document.documentElement.outerHTML") or "")
    with open(os.path.join(out, "console.txt"), "w") as f:
        f.writelines(line + "\n" for line in logged)
    try:
        call("Browser.close")
    except RuntimeError:
        pass
finally:
    try:
        chrome.wait(timeout=10)
    except subprocess.TimeoutExpired:
        chrome.kill()
sys.exit(0 if ok else 1)
