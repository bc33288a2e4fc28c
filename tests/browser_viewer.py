"""Open a ``.rrd`` recording as a reviewer would: ``rerun --serve-web FILE`` and rerun's web viewer
in headless Chromium (Debian's ``chromium``, WebGL 2 through SwiftShader), driven by Playwright.

:func:`open_in_viewer` returns what the viewer shows: the entities of the recording it loaded
(read back from the viewer itself, ``WebHandle.save_recording()``, decoded by ``rerun rrd
print``; the recording counts as loaded once that copy holds every row of the file), its
blueprint's views, the console errors and a screenshot; it raises :class:`ViewerError` when the
viewer does not load the recording. The server runs in its own session (process group): the
``rerun`` command is a wrapper that spawns the server as a child, so the whole group is ended,
always.

Used by ``tests/test_recording_browser.py`` and ``scripts/screenshots.sh``.
"""

from __future__ import annotations

import base64
import contextlib
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import quote, urlparse

import numpy as np

#: Debian's Chromium (``apt-get install chromium``); Playwright's own download is not used.
CHROMIUM = os.environ.get("GRAPHOPT_CHROMIUM", "/usr/bin/chromium")
#: WebGL 2 without a GPU: ANGLE on SwiftShader.
CHROMIUM_ARGS = ["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                 "--no-sandbox", "--disable-dev-shm-usage"]
#: The browser window (CSS pixels) of the test, and of the docs' screenshots (larger: the text
#: is legible; the software rasteriser takes longer). Regions are fractions of it.
VIEWPORT = {"width": 1100, "height": 700}
DOCS_VIEWPORT = {"width": 1600, "height": 1000}
#: Seconds to wait for the server, the viewer's start and the recording (a shared machine with
#: a software rasteriser is slow: generous).
TIMEOUT = 90.0


#: Top-level entities of a blueprint (the file holds it beside the recording; the viewer's copy
#: of the recording does not).
BLUEPRINT_ROOTS = {"view", "container", "viewport", "blueprint_panel", "selection_panel",
                   "time_panel", "top_panel"}


class ViewerError(AssertionError):
    """The viewer did not open the recording (an assertion: tests fail with it)."""


def rerun_exe() -> Path:
    """The ``rerun`` command beside the running Python (the venv's)."""
    return Path(sys.executable).with_name("rerun")


def missing() -> str | None:
    """Why the browser test cannot run here (None if it can)."""
    if not Path(CHROMIUM).is_file():
        return f"{CHROMIUM} not found (Debian: apt-get install chromium)"
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "playwright is not installed (pip install -e '.[browser]')"
    if not rerun_exe().is_file():
        return f"{rerun_exe()} not found (rerun-sdk's command)"
    return None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def serve(rrd: Path, log: Path) -> Iterator[str]:
    """``rerun --serve-web rrd`` in its own process group; yields the viewer's URL.

    Args:
        rrd: The recording.
        log: File that receives the server's output.
    """
    web, grpc = _free_port(), _free_port()
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            [str(rerun_exe()), "--serve-web", "--web-viewer-port", str(web), "--port", str(grpc),
             "--threads", "1", str(rrd)],
            stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            start_new_session=True)
    try:
        deadline = time.monotonic() + TIMEOUT
        while True:
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", web), 1):
                break
            if proc.poll() is not None or time.monotonic() > deadline:
                raise ViewerError(f"rerun --serve-web did not start: {log.read_text()[-2000:]}")
            time.sleep(0.2)
        proxy = quote(f"rerun+http://127.0.0.1:{grpc}/proxy", safe="")
        yield f"http://127.0.0.1:{web}/?url={proxy}"
    finally:
        stop_group(proc)


def stop_group(proc: subprocess.Popen[Any]) -> None:
    """End a process and its children (its whole process group): TERM, then KILL."""
    for sig, wait in ((signal.SIGTERM, 10.0), (signal.SIGKILL, 10.0)):
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, sig)
        try:
            proc.wait(wait)
        except subprocess.TimeoutExpired:
            continue
        # The leader is gone; children that ignored TERM get KILL too.
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        return


@dataclass
class ViewerResult:
    """What the viewer showed.

    Args:
        entities: Entity paths of the recording the viewer holds (sorted).
        views: ``(class, name, origin)`` of the blueprint's views, e.g.
            ``("TimeSeries", "log10 chi2", "metrics/log10_chi2")``.
        console_errors: Console errors and page errors (offline noise removed).
        screenshot: The screenshot file.
        image: ``(h, w, 3)`` uint8 pixels of the screenshot.
    """

    entities: list[str]
    views: list[tuple[str, str, str]]
    console_errors: list[str]
    screenshot: Path
    image: np.ndarray = field(repr=False)

    def colourful_fraction(self, box: tuple[float, float, float, float]) -> float:
        """Fraction of saturated pixels (max − min channel > 60) in a region: the error
        colours; the viewer's background, grid and text are grey.

        Args:
            box: ``(x0, y0, x1, y1)`` as fractions of the screenshot's width and height.
        """
        h, w = self.image.shape[:2]
        x0, y0, x1, y1 = box
        part = self.image[int(y0 * h):int(y1 * h), int(x0 * w):int(x1 * w)].astype(int)
        chroma = part.max(axis=2) - part.min(axis=2)
        return float((chroma > 60).mean())


def _rows(rrd_bytes: bytes) -> dict[str, int]:
    """Entity path → rows, over all chunks of an ``.rrd`` (``rerun rrd print``)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "viewer.rrd"
        path.write_bytes(rrd_bytes)
        out = subprocess.run([str(rerun_exe()), "rrd", "print", str(path)],
                             capture_output=True, text=True, timeout=60)
    rows: dict[str, int] = {}
    for n, entity in re.findall(r"with (\d+) rows .* - (/\S*) - data columns", out.stdout):
        rows[entity] = rows.get(entity, 0) + int(n)
    return rows


def _views(rbl_bytes: bytes) -> list[tuple[str, str, str]]:
    """``(class, name, origin)`` of the views in a blueprint (``rerun rrd print -vvv``)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "viewer.rbl"
        path.write_bytes(rbl_bytes)
        out = subprocess.run([str(rerun_exe()), "rrd", "print", "-vvv", str(path)],
                             capture_output=True, text=True, timeout=60)
    # The ViewBlueprint rows: ... ┆ [3D] ┆ [name] ┆ [origin] │
    row = r"┆ \[(\w*[A-Za-z]\w*)\]\s+┆ \[([^\]]*)\]\s+┆ \[([^\]]*)\]\s+│"
    return sorted(set(re.findall(row, out.stdout)))


def _bytes(page: Any, method: str) -> bytes:
    """The bytes a ``WebHandle`` method returns (as base64: a JSON array would be slow)."""
    text = page.evaluate(
        "(m) => { const b = window._handle[m](); let s = '';"
        " for (let i = 0; i < b.length; i += 0x8000)"
        " s += String.fromCharCode.apply(null, b.subarray(i, i + 0x8000));"
        " return btoa(s); }", method)
    return base64.b64decode(text)


def _offline_noise(text: str, url: str) -> bool:
    """A resource of another host that cannot load here (no internet): fonts, telemetry."""
    host = urlparse(url).hostname or ""
    return text.startswith("Failed to load resource") and host not in ("127.0.0.1", "localhost")


def open_in_viewer(browser: Any, rrd: Path, screenshot: Path, *, settle: float = 3.0,
                   timeout: float = TIMEOUT, viewport: dict[str, int] | None = None
                   ) -> ViewerResult:
    """Serve ``rrd`` with rerun's web viewer, open it in ``browser`` and take a screenshot.

    Args:
        browser: A Playwright ``Browser`` (Chromium).
        rrd: The recording.
        screenshot: Where to write the PNG.
        settle: Seconds to let the viewer draw once the recording is loaded.
        timeout: Seconds to wait for the viewer and the recording.
        viewport: The window's size in CSS pixels (:data:`VIEWPORT` if None).

    Raises:
        ViewerError: The server or the viewer did not start, or the viewer has no recording
            (an unreadable file) within ``timeout``.
    """
    import cv2

    log = screenshot.with_suffix(".server.log")
    page = browser.new_page(viewport=viewport or VIEWPORT)
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error"
            and not _offline_noise(m.text, m.location.get("url", "")) else None)
    page.on("pageerror", lambda e: errors.append(f"page error: {e}"))
    # No internet here (nor in CI): answer the viewer's requests to other hosts (fonts,
    # telemetry, release checks) with an empty response at once instead of a network error.
    page.route(re.compile(r"^https?://(?!127\.0\.0\.1[:/]|localhost[:/])"),
               lambda route: route.fulfill(status=204, body=""))
    with serve(rrd, log) as url:
        try:
            t0 = time.monotonic()
            page.goto(url, timeout=timeout * 1000)
            page.wait_for_function("window._handle !== undefined", timeout=timeout * 1000)
            t1 = time.monotonic()
            deadline, size, last = time.monotonic() + timeout, 0, -1
            # Loaded: the viewer's own copy of the recording (save_recording raises while it
            # has none) stopped growing and holds every row of every entity of the file (it
            # re-encodes the data: not byte for byte). An unreadable file has none: never.
            expected = {e: n for e, n in _rows(rrd.read_bytes()).items()
                        if e.split("/")[1] not in BLUEPRINT_ROOTS}
            while True:
                size = page.evaluate("(() => { try { return window._handle.save_recording()"
                                     ".length } catch (e) { return 0 } })()")
                if size and size == last and expected:
                    held = _rows(_bytes(page, "save_recording"))
                    if all(held.get(e, 0) >= n for e, n in expected.items()):
                        listed = sorted(held)
                        break
                failed = [line for line in log.read_text(errors="replace").splitlines()
                          if "Failed to import" in line]
                if failed:  # the server could not read the file: nothing will come
                    raise ViewerError(f"rerun could not load {rrd}: {failed[0][-300:]}")
                if time.monotonic() > deadline or page.evaluate("window._handle.has_panicked()"):
                    raise ViewerError(
                        f"the viewer did not load {rrd} within {timeout:g} s; console errors: "
                        f"{errors[:5]}; server: {log.read_text()[-1500:]}")
                last = size
                if os.environ.get("GRAPHOPT_BROWSER_DEBUG"):
                    print(f"  {time.monotonic() - t1:.1f} s: {size} bytes", file=sys.stderr)
                time.sleep(0.5)
            blueprint = _bytes(page, "save_blueprint")
            if os.environ.get("GRAPHOPT_BROWSER_DEBUG"):
                print(f"{rrd.name}: viewer started in {t1 - t0:.1f} s, recording loaded after "
                      f"{time.monotonic() - t1:.1f} s more", file=sys.stderr)
            time.sleep(settle)
            page.screenshot(path=str(screenshot))
        finally:
            page.close()  # before the server stops: its stream's end is no viewer error
    image = cv2.imread(str(screenshot))[:, :, ::-1]
    return ViewerResult(listed, _views(blueprint), errors, screenshot,
                        np.ascontiguousarray(image))


def launch(playwright: Any) -> Any:
    """Headless Debian Chromium with software WebGL 2.

    Args:
        playwright: The ``sync_playwright()`` object.
    """
    return playwright.chromium.launch(executable_path=CHROMIUM, headless=True,
                                      args=CHROMIUM_ARGS)


def copy_screenshot(shot: Path, dest_dir: str | None) -> None:
    """Copy a screenshot to ``dest_dir`` (e.g. ``docs/images``) when one is given."""
    if dest_dir:
        Path(dest_dir).mkdir(parents=True, exist_ok=True)
        shutil.copyfile(shot, Path(dest_dir) / shot.name)
