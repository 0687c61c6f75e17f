"""Random mutations of a valid rig and recording.json through the loaders.

Every mutation either loads or raises ConfigError with a one-line message;
never another exception (the CLI turns ConfigError into one line and exit 2).
"""

from __future__ import annotations

import copy
import json
import random
from pathlib import Path

import cv2
import numpy as np
import pytest

from lightflow.app.core.errors import ConfigError
from lightflow.app.core.rig import load_rig
from lightflow.app.recording import RECORDING_FORMAT, read_recording

ROOT = Path(__file__).resolve().parents[1]
RIG_FILE = ROOT / "app" / "rigs" / "two-projector.json"
N_MUTATIONS = 120  # per loader: 240 in all

ODD_VALUES = [
    None, True, False, 0, -1, 1, 10**12, 10**400, -(10**400), 1e308, 1e-320, 1e6, -1e6,
    float("nan"), float("inf"), "", "1", "0.5", "x" * 5000, "frames/../../etc/passwd",
    "frames/./000000.png", "/etc/passwd", [], [1], [[1, 2], [3]], {}, {"a": 1}, [None] * 3,
    "\udcff", "é", "\x00",
]


def _paths(doc, prefix=()):
    """Every path to a value inside a JSON document."""
    yield prefix
    if len(prefix) > 12:  # inside an inserted deep nest: its outer levels are enough
        return
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield from _paths(v, prefix + (i,))


def _set(doc, path, value):
    if not path:
        return value
    node = doc
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return doc


def _mutate_doc(doc, rng: random.Random):
    doc = copy.deepcopy(doc)
    paths = list(_paths(doc))
    for _ in range(rng.randint(1, 3)):
        path = rng.choice(paths)
        kind = rng.random()
        try:
            if kind < 0.6:
                doc = _set(doc, path, copy.deepcopy(rng.choice(ODD_VALUES)))
            elif kind < 0.75 and path:
                parent = doc
                for key in path[:-1]:
                    parent = parent[key]
                del parent[path[-1]]
            elif kind < 0.85:
                node = doc
                for key in path:
                    node = node[key]
                if isinstance(node, dict):
                    node["unexpected"] = 1
                elif isinstance(node, list):
                    node.append(copy.deepcopy(node[0]) if node else 0)
            else:
                deep: list = []
                for _ in range(rng.choice((50, 5000))):
                    deep = [deep]
                doc = _set(doc, path, deep)
        except (KeyError, IndexError, TypeError):
            pass
        paths = list(_paths(doc))
    return doc


def _mutate_bytes(data: bytes, rng: random.Random) -> bytes:
    kind = rng.random()
    if kind < 0.2:
        return data.decode().encode("utf-16")
    if kind < 0.3:
        return b"\xef\xbb\xbf" + data
    if kind < 0.5:
        return data[: rng.randrange(len(data))]
    if kind < 0.6:
        return b"[" * 100000 + b"]" * 100000
    out = bytearray(data)
    for _ in range(rng.randint(1, 8)):
        out[rng.randrange(len(out))] = rng.randrange(256)
    return bytes(out)


def _mutations(doc, rng):
    text = json.dumps(doc, indent=1).encode()
    for i in range(N_MUTATIONS):
        if i % 3 == 2:
            yield _mutate_bytes(text, rng)
        else:
            mutated = _mutate_doc(doc, rng)
            try:
                yield json.dumps(mutated, indent=1).encode()
            except (RecursionError, ValueError):
                yield b"[" * 100000


def _check_one_line(exc: ConfigError):
    text = str(exc)
    assert text and "\n" not in text and len(text) < 2000, text


def test_fuzz_rig_loader(tmp_path):
    rng = random.Random(7)
    doc = json.loads(RIG_FILE.read_text())
    path = tmp_path / "rig.json"
    outcomes = {"loaded": 0, "rejected": 0}
    for data in _mutations(doc, rng):
        path.write_bytes(data)
        try:
            load_rig(path)
            outcomes["loaded"] += 1
        except ConfigError as exc:
            _check_one_line(exc)
            outcomes["rejected"] += 1
    assert outcomes["rejected"] > N_MUTATIONS // 2, outcomes


@pytest.fixture
def small_recording(tmp_path) -> Path:
    rig = json.loads(RIG_FILE.read_text())
    rig["camera"]["width"], rig["camera"]["height"] = 64, 48
    rec = tmp_path / "rec"
    (rec / "frames").mkdir(parents=True)
    for i in range(3):
        cv2.imwrite(str(rec / "frames" / f"{i:06d}.png"), np.full((48, 64, 3), 40, np.uint8))
    doc = {
        "format": RECORDING_FORMAT,
        "rig": rig,
        "exposure_s": 0.02,
        "frames": [{"file": f"frames/{i:06d}.png", "t": 0.1 * i} for i in range(3)],
    }
    (rec / "recording.json").write_text(json.dumps(doc))
    return rec


def test_fuzz_recording_loader(small_recording):
    rng = random.Random(11)
    path = small_recording / "recording.json"
    doc = json.loads(path.read_text())
    outcomes = {"loaded": 0, "rejected": 0}
    for data in _mutations(doc, rng):
        path.write_bytes(data)
        try:
            read_recording(small_recording)
            outcomes["loaded"] += 1
        except ConfigError as exc:
            _check_one_line(exc)
            outcomes["rejected"] += 1
    assert outcomes["rejected"] > N_MUTATIONS // 2, outcomes


# ----------------------------------------------------------------------------- the CLI

NASTY_RIGS = {
    "utf-16": lambda rig: rig.decode().encode("utf-16"),
    "latin-1 byte": lambda rig: rig.replace(b'"left"', b'"l\xe9ft"', 1),
    "nested 100000 deep": lambda rig: b"[" * 100000 + b"]" * 100000,
    "width 1e12": lambda rig: rig.replace(b'"width": 1600,', b'"width": 1000000000000,', 1),
    "K entry as a string": lambda rig: rig.replace(b"1800.0", b'"1800.0"', 1),
    "integer of 5000 digits": lambda rig: rig.replace(
        b'"width": 1600,', b'"width": 1' + b"0" * 5000 + b",", 1
    ),
    "distortion 1e6": lambda rig: rig.replace(b'"dist": [\n      0.0', b'"dist": [1e6', 1),
    "NaN": lambda rig: rig.replace(b"1800.0", b"NaN", 1),
}


def _cli(*args):
    import subprocess
    import sys

    return subprocess.run(
        [sys.executable, "-m", "lightflow.app.cli", *map(str, args)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip


def _assert_one_error_line(proc, path):
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"lightflow: error: {path}"), lines[0]
    assert len(lines[0]) < 400


@pytest.mark.parametrize("name", sorted(NASTY_RIGS))
def test_cli_rig_check_nasty_rig_is_one_line_exit_2(tmp_path, name):
    original = RIG_FILE.read_bytes()
    data = NASTY_RIGS[name](original)
    assert data != original  # the mutation applied
    path = tmp_path / "rig.json"
    path.write_bytes(data)
    _assert_one_error_line(_cli("rig", "check", path), path)


def test_cli_simulate_with_nasty_rig_is_one_line_exit_2(tmp_path):
    path = tmp_path / "rig.json"
    path.write_bytes(NASTY_RIGS["utf-16"](RIG_FILE.read_bytes()))
    _assert_one_error_line(_cli("simulate", "--rig", path, "--out", tmp_path / "o"), path)


def test_cli_replay_and_verify_nasty_recordings(small_recording):
    root = small_recording
    doc = json.loads((root / "recording.json").read_text())
    # timestamps that do not increase: replay refuses before any work, verify names it
    doc["frames"][1]["t"] = doc["frames"][0]["t"]
    (root / "recording.json").write_text(json.dumps(doc))
    proc = _cli("replay", root)
    _assert_one_error_line(proc, root / "recording.json")
    assert "frames[1].t: " in proc.stderr and "does not increase" in proc.stderr
    proc = _cli("verify", root, "--rig", "two-projector")
    assert proc.returncode == 2 and "does not increase" in proc.stdout
    # bytes that are not UTF-8
    (root / "recording.json").write_bytes(b"\xff\xfe{\x00")
    _assert_one_error_line(_cli("replay", root), root / "recording.json")
    # a recording that lists no frames
    doc["frames"] = []
    (root / "recording.json").write_text(json.dumps(doc))
    _assert_one_error_line(_cli("replay", root), root / "recording.json")
    proc = _cli("verify", root)
    assert proc.returncode == 2 and "lists no frame" in proc.stdout


# ----------------------------------------------------------------------------- sessions


def _session_doc() -> dict:
    """A valid calibration session.json (formats.md section 4), frames not on disk."""
    n = 2 + 2 * (11 + 10)  # graycode/1 for 1280x800
    projectors = [
        {"name": name, "width": 1280, "height": 800,
         "patterns": [{"channel": ch, "kind": "uniform", "pitch_px": pitch, "width_px": 3.0,
                       "offset_px": 0.0}]}
        for name, ch, pitch in (("left", "red", 40.0), ("right", "blue", 18.0))
    ]  # fmt: skip
    return {
        "format": "lightflow-calibration/1",
        "board": {"kind": "checkerboard", "inner_corners": [9, 6], "square_m": 0.03},
        "camera": {"width": 160, "height": 120},
        "projectors": projectors,
        "sequence": "graycode/1",
        "poses": [
            {"name": "pose00", "frames": {
                p: [f"pose00/{p}/{i:03d}.png" for i in range(n)] for p in ("left", "right")
            }}
        ],
    }


def test_fuzz_session_loader(tmp_path):
    from lightflow.calibration.session import read_session

    doc = _session_doc()
    path = tmp_path / "cal" / "session.json"
    path.parent.mkdir()
    path.write_text(json.dumps(doc))
    read_session(path, check_files=False)  # the base document is valid
    rng = random.Random(5)
    for i, data in enumerate(_mutations(doc, rng)):
        path.write_bytes(data)
        try:
            read_session(path, check_files=False)
        except ConfigError as exc:
            _check_one_line(exc)
        if i + 1 >= N_MUTATIONS:
            break
