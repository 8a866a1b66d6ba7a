"""Check that a recording opens in the stock viewers: the web viewer of `contact-viz SESSION --serve` in a
real Chromium, and the native `rerun FILE.rrd --renderer vulkan`, both on a virtual X display (Xvfb).

Run by hand (it needs Debian's chromium and xvfb, `sudo apt-get install chromium xvfb`, which
scripts/bootstrap.sh does not install, and takes 2-4 minutes; it is not part of the test suite,
which must not depend on a browser or on software rendering's timing):

    .venv/bin/python benchmarks/check_viewers.py [SESSION] [--web] [--native] [--out docs/] [--view-args "..."]

Without SESSION it renders a small synthetic session (640x360, 40 frames). The web check runs
`contact-viz SESSION --serve`, opens the printed URL in Chromium (software WebGL, SwiftShader) and
takes screenshots of the X display every few seconds until the left image pane shows the video
(decoded by the browser's WebCodecs); the native check saves the recording with --save and opens
it in the native viewer the same way. "Shows the video" means: in the pane where the default
layout puts the left image, at least MIN_COLOURS distinct colours and a pixel spread (standard
deviation) of at least MIN_STD, which the viewer's own UI (flat dark panels and text) does not
reach; the screenshot is saved so a person can look at it. Exit status 0 when every check passed.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

SCREEN = (1600, 900)  # virtual display and browser window size, px
MIN_COLOURS = 3000  # distinct colours in the image pane when a video frame is drawn
MIN_STD = 12.0  # standard deviation of the image pane's pixel values when a frame is drawn
# where the default blueprint puts the left image, as fractions of the viewer window (x0, y0, x1, y1): the left
# 60 % column, its top 47 %, of which the left image takes two thirds; a margin for the panels and titles
LEFT_PANE = (0.03, 0.08, 0.36, 0.40)
SETTLE_S = float(os.environ.get("CHECK_VIEWERS_SETTLE_S", "5"))  # wait after the first drawn frame, s
TIMEOUT_S = 240.0  # give up after this long (software rendering on a busy 2-core machine is slow), s


def free_display() -> int:
    for number in range(90, 200):
        if not Path(f"/tmp/.X11-unix/X{number}").exists() and not Path(f"/tmp/.X{number}-lock").exists():
            return number
    raise SystemExit("no free X display number between :90 and :199")


def grab(display: int) -> np.ndarray:
    """Screenshot of the whole X display as (H, W, 3) uint8 RGB (Pillow's X11 grab)."""
    from PIL import ImageGrab

    return np.asarray(ImageGrab.grab(xdisplay=f":{display}").convert("RGB"))


def pane_drawn(shot: np.ndarray) -> tuple[bool, int, float]:
    """Whether the left image pane of the screenshot shows an image: (drawn, distinct colours, std)."""
    height, width = shot.shape[:2]
    x0, y0, x1, y1 = LEFT_PANE
    pane = shot[int(y0 * height):int(y1 * height), int(x0 * width):int(x1 * width)].reshape(-1, 3)
    colours = len(np.unique(pane.astype(np.int32) @ np.array([65536, 256, 1]), axis=0))
    std = float(pane.std())
    return colours >= MIN_COLOURS and std >= MIN_STD, colours, std


def wait_for_frame(display: int, what: str, out: Path, proc: subprocess.Popen) -> bool:
    """Screenshots until the pane is drawn (saved to ``out``) or TIMEOUT_S passes."""
    from PIL import Image

    started = time.monotonic()
    colours, std = 0, 0.0
    while time.monotonic() - started < TIMEOUT_S:
        time.sleep(10)
        if proc.poll() is not None:
            print(f"{what}: the viewer exited (status {proc.returncode})")
            return False
        shot = grab(display)
        drawn, colours, std = pane_drawn(shot)
        print(f"  {what} after {time.monotonic() - started:.0f} s: {colours} colours, std {std:.1f} in the image pane",
              flush=True)
        if drawn:
            time.sleep(SETTLE_S)  # let the rest of the layout settle for the saved picture
            Image.fromarray(grab(display)).save(out)
            print(f"{what}: a frame is drawn (screenshot {out})")
            return True
    Image.fromarray(grab(display)).save(out)
    print(f"{what}: NO frame drawn within {TIMEOUT_S:.0f} s ({colours} colours, std {std:.1f}); screenshot {out}")
    return False


def stop(proc: subprocess.Popen | None) -> None:
    if proc is not None and proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def contact_viz() -> list[str]:
    return [sys.executable, "-m", "contact_viz.cli"]


def check_web(session: Path, display: int, env: dict, out: Path, profile: Path, view_args: list[str]) -> bool:
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        print("web: chromium is not installed (Debian: apt-get install chromium)")
        return False
    grpc_port, web_port = 19876 + display, 19090 + display
    server = subprocess.Popen(contact_viz() + [str(session), "--serve", "--grpc-port", str(grpc_port),
                                               "--web-port", str(web_port)] + view_args,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    browser = None
    try:
        url = None
        for line in server.stdout:
            print(f"  contact-viz: {line.rstrip()}")
            match = re.search(r"web viewer: (\S+)", line)
            if match:
                url = match.group(1)
            if "serving" in line:
                break
        if url is None:
            print("web: contact-viz --serve printed no URL")
            return False
        browser = subprocess.Popen(
            [chromium, "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
             "--disable-background-networking", "--disable-component-update", "--no-first-run",
             f"--user-data-dir={profile}", f"--window-size={SCREEN[0]},{SCREEN[1]}", "--window-position=0,0",
             "--app=" + url],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
        return wait_for_frame(display, "web viewer (chromium)", out / "screenshot_web_viewer.png", browser)
    finally:
        stop(browser)
        stop(server)


def check_native(session: Path, display: int, env: dict, out: Path, workdir: Path, view_args: list[str]) -> bool:
    rrd = workdir / "check.rrd"
    subprocess.run(contact_viz() + [str(session), "--save", str(rrd)] + view_args, check=True, env=env,
                   stdout=subprocess.DEVNULL)
    rerun = Path(sys.executable).with_name("rerun")
    viewer = subprocess.Popen([str(rerun) if rerun.exists() else "rerun", str(rrd), "--renderer", "vulkan"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    try:
        return wait_for_frame(display, "native viewer (vulkan)", out / "screenshot_native_viewer.png", viewer)
    finally:
        stop(viewer)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("session", nargs="?", type=Path, help="session directory (default: a synthetic one)")
    parser.add_argument("--web", action="store_true", help="check the web viewer (default: both)")
    parser.add_argument("--native", action="store_true", help="check the native viewer (default: both)")
    parser.add_argument("--out", type=Path, default=Path("docs"), help="directory for the screenshots")
    parser.add_argument("--view-args", default="", help='more options of `contact-viz SESSION`, e.g. "--start 28 --end 36"')
    args = parser.parse_args()
    both = not (args.web or args.native)
    if shutil.which("Xvfb") is None:
        raise SystemExit("Xvfb is not installed (Debian: apt-get install xvfb)")
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="contact-viz-check-") as tmp:
        workdir = Path(tmp)
        session = args.session
        if session is None:
            session = workdir / "session"
            subprocess.run(contact_viz() + ["synth", str(session), "--frames", "40", "--size", "640x360",
                                            "--seed", "2"], check=True, stdout=subprocess.DEVNULL)
        display = free_display()
        # without the Composite extension: with it Xvfb offers a 32-bit ARGB visual, the native viewer asks for a
        # transparent window, and its Vulkan (lavapipe) frames never reach the screen (the window stays black)
        xvfb = subprocess.Popen(["Xvfb", f":{display}", "-screen", "0", f"{SCREEN[0]}x{SCREEN[1]}x24", "-nolisten",
                                 "tcp", "-extension", "COMPOSITE"], stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
        env = dict(os.environ, DISPLAY=f":{display}", XDG_RUNTIME_DIR=str(workdir),
                   CONTACT_VIZ_CACHE=str(workdir / "cache"))
        env.pop("WAYLAND_DISPLAY", None)
        results = {}
        try:
            time.sleep(2)
            if args.web or both:
                results["web"] = check_web(session, display, env, args.out, workdir / "chromium", args.view_args.split())
            if args.native or both:
                results["native"] = check_native(session, display, env, args.out, workdir, args.view_args.split())
        finally:
            stop(xvfb)
    print("; ".join(f"{k}: {'frame drawn' if v else 'FAILED'}" for k, v in results.items()))
    raise SystemExit(0 if all(results.values()) else 1)


if __name__ == "__main__":
    main()
