"""Each app's default recording, opened as a reviewer would: ``rerun --serve-web`` and rerun's web
viewer in headless Chromium (see ``browser_viewer.py``).

Marked ``browser``: it runs where Debian's ``chromium`` and Playwright are installed (``bash
scripts/bootstrap.sh`` installs both, so CI runs it) and skips, saying why, elsewhere. With
``GRAPHOPT_SCREENSHOTS=docs/images`` the screenshots are copied there (the docs show them).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import browser_viewer as bv
import numpy as np
import pytest

pytestmark = [pytest.mark.browser,
              pytest.mark.skipif(bv.missing() is not None, reason=str(bv.missing()))]

#: The world view's region of the screenshot (fractions of width and height), inside the
#: blueprint's left 3/5 beside the blueprint panel.
WORLD_VIEW = (0.25, 0.10, 0.62, 0.70)
#: Least share of saturated (error-coloured) pixels in it: a blank view has none.
MIN_COLOURFUL = 0.002

#: Per app: the command (argument list of its ``main``), the entities its recording must hold.
COMMON = ["/world/before", "/world/after", "/metrics/log10_chi2", "/metrics/iteration_seconds",
          "/summary"]
APPS: dict[str, tuple[str, list[str], list[str]]] = {
    "bal": ("bal", [], ["/world/after/points", "/world/after/cameras/0"]),
    "direct_ba": ("direct_ba", [], ["/world/after/points", "/images/0/image",
                                    "/images/6/patches"]),
    "g2o_2d": ("g2o", [], ["/world/after/trajectory", "/world/after/loop_closures",
                           "/world/truth/trajectory"]),
    "g2o_3d": ("g2o", ["{helix}"], ["/world/after/trajectory", "/world/after/loop_closures"]),
}


def _quaternion(yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    """``(n, 4)`` ``[qx, qy, qz, qw]`` of a rotation by ``yaw`` about z, then ``pitch`` about y."""
    cy, sy, cp, sp = np.cos(yaw / 2), np.sin(yaw / 2), np.cos(pitch / 2), np.sin(pitch / 2)
    return np.column_stack([-sy * sp, cy * sp, sy * cp, cy * cp])


def write_helix(path: Path, n: int = 120, turn: int = 30, seed: int = 0) -> None:
    """A small 3-D pose graph (g2o ``VERTEX_SE3:QUAT``/``EDGE_SE3:QUAT``): poses on a helix
    with odometry, loop closures one turn apart and a drifting start.

    Args:
        path: Destination file.
        n: Poses.
        turn: Poses per turn (loop closures join ``i`` and ``i + turn``).
        seed: Noise seed.
    """
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    yaw = 2 * np.pi * np.arange(n) / turn
    pos = np.column_stack([5 * np.cos(yaw), 5 * np.sin(yaw), 0.2 * np.arange(n)])
    rot = Rotation.from_euler("z", (yaw + np.pi / 2)[:, None])
    info = " ".join(str(v) for v in [100, 0, 0, 0, 0, 0, 100, 0, 0, 0, 0, 100, 0, 0, 0,
                                     400, 0, 0, 400, 0, 400])
    lines = []
    est_rot, est_pos = rot, pos.copy()
    drift = Rotation.from_rotvec(rng.normal(0, 0.01, (n, 3)))
    est_pos = pos + np.cumsum(rng.normal(0, 0.05, (n, 3)), axis=0)
    est_rot = drift * rot
    for i in range(n):
        q = est_rot[i].as_quat()
        lines.append(f"VERTEX_SE3:QUAT {i} " + " ".join(f"{v:.9g}" for v in (*est_pos[i], *q)))
    pairs = [(i, i + 1) for i in range(n - 1)] + [(i, i + turn) for i in range(0, n - turn, 3)]
    for i, j in pairs:
        rel_rot = rot[i].inv() * rot[j]
        rel_pos = rot[i].inv().apply(pos[j] - pos[i]) + rng.normal(0, 0.02, 3)
        q = (Rotation.from_rotvec(rng.normal(0, 0.01, 3)) * rel_rot).as_quat()
        lines.append(f"EDGE_SE3:QUAT {i} {j} " + " ".join(f"{v:.9g}" for v in (*rel_pos, *q))
                     + " " + info)
    lines.append("FIX 0")
    path.write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = bv.launch(p)
        try:
            yield b
        finally:
            b.close()


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("browser")
    write_helix(folder / "helix.g2o")
    return folder


def _record(name: str, folder: Path) -> Path:
    """Run an app's default (or the helix) with ``--rrd``."""
    import importlib

    module, args, _ = APPS[name]
    rrd = folder / f"{name}.rrd"
    argv = [a.format(helix=folder / "helix.g2o") for a in args]
    app = importlib.import_module(f"graphopt.apps.{module}")
    assert app.main([*argv, "--quiet", "--rrd", str(rrd)]) == 0
    return rrd


def check_recording(browser: Any, rrd: Path, entities: list[str], shot: Path) -> bv.ViewerResult:
    """Open ``rrd`` in the viewer and check what a reviewer must see (raises AssertionError).

    Args:
        browser: The Playwright browser.
        rrd: The recording.
        entities: Entity paths (or their parents) the viewer must list.
        shot: The screenshot's file.
    """
    docs = bool(os.environ.get("GRAPHOPT_SCREENSHOTS"))
    res = bv.open_in_viewer(browser, rrd, shot, viewport=bv.DOCS_VIEWPORT if docs else None)
    assert not res.console_errors, res.console_errors
    listed = set(res.entities)
    for entity in entities:
        assert entity in listed or any(e.startswith(entity + "/") for e in listed), (
            f"{entity} not in the viewer's recording: {sorted(listed)[:30]}")
    kinds = {(cls, origin) for cls, _, origin in res.views}
    assert {("TimeSeries", "metrics/log10_chi2"), ("TimeSeries", "metrics/iteration_seconds"),
            ("TextDocument", "summary")} <= kinds, res.views
    assert ("3D", "world") in kinds, res.views
    colourful = res.colourful_fraction(WORLD_VIEW)
    assert colourful >= MIN_COLOURFUL, f"the 3-D view looks blank ({colourful:.4f} coloured)"
    return res


@pytest.mark.parametrize("name", list(APPS))
def test_default_recording_opens_in_the_web_viewer(name: str, browser: Any,
                                                   workdir: Path) -> None:
    rrd = _record(name, workdir)
    shot = workdir / f"viewer_{name}.png"
    check_recording(browser, rrd, COMMON + APPS[name][2], shot)
    bv.copy_screenshot(shot, os.environ.get("GRAPHOPT_SCREENSHOTS"))


def test_a_corrupt_recording_fails_the_check(browser: Any, workdir: Path) -> None:
    bad = workdir / "corrupt.rrd"
    bad.write_bytes(b"RRF2" + np.random.default_rng(0).bytes(20_000))
    with pytest.raises(AssertionError, match="could not load|did not load"):
        check_recording(browser, bad, COMMON, workdir / "corrupt.png")
