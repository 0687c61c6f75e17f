"""Projector windows on real X servers: exact pixels, placement, show(), errors, CLI.

Every scenario that touches pyglet runs in a fresh Python subprocess: pyglet
caches its display on import, and a subprocess also keeps pyglet out of the
rest of the suite.  The subprocess grabs the screen with PIL while the windows
are up and saves the pixels as .npy; the assertions are made here.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import ImageGrab

from lightflow.app.core.patterns import pattern_image
from lightflow.app.core.rig import load_rig

try:
    from tests.xserver import start_xorg_two_heads, start_xvfb
except ImportError:  # tests/ is not a package and only it is on sys.path
    from xserver import start_xorg_two_heads, start_xvfb

ROOT = Path(__file__).resolve().parents[1]
RIGS = ROOT / "app" / "rigs"
SINGLE = load_rig(RIGS / "single-projector.json")
TWO = load_rig(RIGS / "two-projector.json")

pytestmark = pytest.mark.xserver

# Runs in the subprocess: open the rig's windows, grab the screen, optionally
# replace one image from a worker thread and grab again, report as JSON.
SCENARIO = r"""
import json, sys, threading
from dataclasses import asdict
import numpy as np
from PIL import ImageGrab
from lightflow.app.core.errors import LightflowError
from lightflow.app.core.patterns import pattern_image
from lightflow.app.core.rig import load_rig
from lightflow.drivers.projector import ProjectorWindows, list_screens

cfg = json.loads(sys.argv[1])
disp, out_dir = cfg["display"], cfg["out"]
res = {"screens": [asdict(s) for s in list_screens(disp)]}
if cfg.get("fake_geometry"):  # what the X server would say if a window manager moved it
    import lightflow.drivers.projector as P
    real, calls = P._x11_geometry, []

    def fake(window):
        calls.append(1)
        return tuple(cfg["fake_geometry"]) if len(calls) <= cfg["fake_times"] else real(window)
    P._x11_geometry = fake
rig = load_rig(cfg["rig"])
outputs = [(p.name, s, pattern_image(p)) for p, s in zip(rig.projectors, cfg["screens"])]
out = ProjectorWindows(outputs, display=disp, allow_size_mismatch=cfg.get("allow", False))
try:
    out.open()
except LightflowError as exc:
    res["error"] = str(exc)
    print(json.dumps(res))
    sys.exit(0)
res["placements"] = [[n, s.index] for n, s in out.placements]
stop, errors = threading.Event(), []

def grab(tag):
    img = np.asarray(ImageGrab.grab(xdisplay=disp).convert("RGB"))
    np.save(f"{out_dir}/{tag}.npy", img)

def worker():
    try:
        res["initial_presented"] = out.wait_presented(10)
        grab("initial")
        if cfg.get("replace"):
            out.show(cfg["replace"], np.load(f"{out_dir}/new.npy"))
            res["replaced_presented"] = out.wait_presented(10)
            grab("replaced")
        if cfg.get("escape"):
            import pyglet
            from pyglet.window import key
            win = next(iter(pyglet.app.windows))
            # Esc through pyglet's own key handler, posted onto the main thread
            pyglet.app.platform_event_loop.post_event(win, "on_key_press", key.ESCAPE, 0)
            return  # the loop must set `stop` itself
    except BaseException as exc:
        errors.append(repr(exc))
    stop.set()

th = threading.Thread(target=worker)
th.start()
with out:
    out.run(stop)
th.join()
res["stopped"] = stop.is_set()
res["errors"] = errors
print(json.dumps(res))
"""


def run_scenario(server, tmp_path: Path, rig: Path, screens, **cfg) -> dict:
    cfg = {"display": server.display, "out": str(tmp_path), "rig": str(rig),
           "screens": screens, **cfg}
    proc = subprocess.run(
        [sys.executable, "-c", SCENARIO, json.dumps(cfg)],
        env=server.env, capture_output=True, text=True, timeout=60, cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def xvfb(tmp_path_factory):
    srv = start_xvfb(tmp_path_factory.mktemp("xvfb"))
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def xvfb_large(tmp_path_factory):
    srv = start_xvfb(tmp_path_factory.mktemp("xvfb_large"), 1440, 900)
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def xorg2(tmp_path_factory):
    srv = start_xorg_two_heads(tmp_path_factory.mktemp("xorg2"))
    yield srv
    srv.stop()


def test_single_projector_on_xvfb_is_pixel_exact(xvfb, tmp_path):
    res = run_scenario(xvfb, tmp_path, RIGS / "single-projector.json", [0])
    assert res["screens"] == [
        {"index": 0, "name": "screen", "x": 0, "y": 0, "width": 1280, "height": 800}
    ]
    assert res["placements"] == [["main", 0]]
    assert res["initial_presented"] is True and res["errors"] == []
    shot = np.load(tmp_path / "initial.npy")
    expected = pattern_image(SINGLE.projectors[0])
    assert shot.shape == (800, 1280, 3)
    np.testing.assert_array_equal(shot, expected)
    # both patterns are really there: red and blue lines, no green
    assert shot[..., 0].any() and shot[..., 2].any() and not shot[..., 1].any()


def test_two_projectors_on_two_heads_are_pixel_exact(xorg2, tmp_path):
    res = run_scenario(xorg2, tmp_path, RIGS / "two-projector.json", [0, 1])
    assert [(s["name"], s["x"], s["width"], s["height"]) for s in res["screens"]] == [
        ("DUMMY0", 0, 1280, 800),
        ("DUMMY1", 1280, 1280, 800),
    ]
    assert res["placements"] == [["left", 0], ["right", 1]]
    shot = np.load(tmp_path / "initial.npy")
    assert shot.shape == (800, 2560, 3)
    np.testing.assert_array_equal(shot[:, :1280], pattern_image(TWO.projectors[0]))
    np.testing.assert_array_equal(shot[:, 1280:], pattern_image(TWO.projectors[1]))


def test_screens_selected_by_name_swap_the_heads(xorg2, tmp_path):
    res = run_scenario(xorg2, tmp_path, RIGS / "two-projector.json", ["DUMMY1", "DUMMY0"])
    assert res["placements"] == [["left", 1], ["right", 0]]
    shot = np.load(tmp_path / "initial.npy")
    np.testing.assert_array_equal(shot[:, 1280:], pattern_image(TWO.projectors[0]))
    np.testing.assert_array_equal(shot[:, :1280], pattern_image(TWO.projectors[1]))


def test_show_from_worker_thread_is_presented(xorg2, tmp_path):
    # random noise: any scaling, filtering or offset by one pixel would show
    new = np.random.default_rng(7).integers(0, 256, (800, 1280, 3), dtype=np.uint8)
    np.save(tmp_path / "new.npy", new)
    res = run_scenario(xorg2, tmp_path, RIGS / "two-projector.json", [0, 1], replace="right")
    assert res["replaced_presented"] is True and res["errors"] == []
    before, after = np.load(tmp_path / "initial.npy"), np.load(tmp_path / "replaced.npy")
    np.testing.assert_array_equal(before[:, 1280:], pattern_image(TWO.projectors[1]))
    np.testing.assert_array_equal(after[:, 1280:], new)
    np.testing.assert_array_equal(after[:, :1280], pattern_image(TWO.projectors[0]))


def test_escape_ends_the_loop_and_sets_stop(xvfb, tmp_path):
    res = run_scenario(xvfb, tmp_path, RIGS / "single-projector.json", [0], escape=True)
    assert res["stopped"] is True and res["errors"] == []


def test_wrong_screen_index_is_one_line_driver_error(xorg2, tmp_path):
    res = run_scenario(xorg2, tmp_path, RIGS / "two-projector.json", [0, 5])
    msg = res["error"]
    assert "\n" not in msg
    assert "no screen 5" in msg
    assert "0=DUMMY0 1280x800+0+0" in msg and "1=DUMMY1 1280x800+1280+0" in msg


def test_misplaced_window_is_recreated_unmanaged_then_refused(xorg2, tmp_path):
    # No window manager here moves windows, so the X11 geometry query is faked:
    # misplaced once, the driver retries with an override-redirect window.
    res = run_scenario(xorg2, tmp_path, RIGS / "two-projector.json", [0, 1],
                       fake_geometry=[0, 0, 1280, 800], fake_times=2)
    assert res["placements"] == [["left", 0], ["right", 1]] and res["errors"] == []
    shot = np.load(tmp_path / "initial.npy")
    np.testing.assert_array_equal(shot[:, 1280:], pattern_image(TWO.projectors[1]))
    # misplaced both times: a one-line error naming the projector, screen and positions
    res = run_scenario(xorg2, tmp_path, RIGS / "two-projector.json", [1],
                       fake_geometry=[0, 0, 1280, 800], fake_times=9)
    where = "1280x800+0+0 (pyglet: location 1280,0, size 1280x800, framebuffer 1280x800)"
    assert res["error"] == (
        f"projector 'left': window meant for screen 1 (DUMMY1 1280x800+1280+0) landed at "
        f"{where}, and at {where} when bypassing the window manager"
    )


def test_same_screen_twice_is_refused(xorg2, tmp_path):
    res = run_scenario(xorg2, tmp_path, RIGS / "two-projector.json", [1, "DUMMY1"])
    assert res["error"] == (
        "projector 'right': screen 1 (DUMMY1 1280x800+1280+0) is already used by "
        "projector 'left'"
    )


def test_larger_screen_is_refused_unless_allowed(xvfb_large, tmp_path):
    res = run_scenario(xvfb_large, tmp_path, RIGS / "single-projector.json", [0])
    assert res["error"].startswith(
        "projector 'main': image 1280x800 is smaller than screen 0 (screen 1440x900+0+0)"
    )
    assert "\n" not in res["error"]
    res = run_scenario(xvfb_large, tmp_path, RIGS / "single-projector.json", [0], allow=True)
    assert res["errors"] == []
    shot = np.load(tmp_path / "initial.npy")
    assert shot.shape == (900, 1440, 3)
    np.testing.assert_array_equal(shot[:800, :1280], pattern_image(SINGLE.projectors[0]))
    assert not shot[800:].any() and not shot[:, 1280:].any()


def cli(*args: str, **kw) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "lightflow.app.cli", *args],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, **kw,
    )


def test_cli_project_shows_patterns_until_ctrl_c(xorg2):
    proc = cli("project", str(RIGS / "two-projector.json"), "--screens", "0,DUMMY1",
               env=xorg2.env)
    try:
        lines = [proc.stdout.readline() for _ in range(3)]
        assert lines[:2] == [
            "projector left -> screen 0 (DUMMY0 1280x800+0+0)\n",
            "projector right -> screen 1 (DUMMY1 1280x800+1280+0)\n",
        ], proc.stderr.read() if proc.poll() is not None else lines
        assert lines[2].startswith("showing")
        # the first image is flipped before open() returns, i.e. before "showing"
        shot = np.asarray(ImageGrab.grab(xdisplay=xorg2.display).convert("RGB"))
        np.testing.assert_array_equal(shot[:, :1280], pattern_image(TWO.projectors[0]))
        np.testing.assert_array_equal(shot[:, 1280:], pattern_image(TWO.projectors[1]))
        proc.send_signal(signal.SIGINT)
        # ends in about a second; the bound only keeps a hang from blocking the suite (a
        # fresh-clone run on a loaded machine once took over 20 s to tear the windows down)
        assert proc.wait(timeout=90) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()
        proc.stderr.close()


def test_cli_project_wrong_screen_count_exits_2(xorg2):
    proc = cli("project", str(RIGS / "two-projector.json"), "--screens", "0", env=xorg2.env)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 2
    assert err == (
        "lightflow: error: --screens: expected 2 comma-separated screen(s) for "
        "projector(s) left, right, got '0'\n"
    )


def test_cli_project_unreachable_display_exits_2(tmp_path):
    # a display number no server here uses
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path), "DISPLAY": ":31999"}
    proc = cli("project", str(RIGS / "two-projector.json"), "--screens", "0,1", env=env)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 2
    assert err == "lightflow: error: X display :31999: cannot connect (is the X server running?)\n"
    proc = cli("project", str(RIGS / "two-projector.json"), "--screens", "0,1",
               env={k: v for k, v in env.items() if k != "DISPLAY"})
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 2
    assert err == (
        "lightflow: error: X display: DISPLAY is not set and no display was given (e.g. :0)\n"
    )


def test_cli_project_help_mentions_options():
    proc = cli("project", "--help")
    out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0
    for word in ("--screens", "--allow-size-mismatch", "--display", "Esc", "Ctrl-C"):
        assert word in out
