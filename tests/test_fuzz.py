"""Fuzzing the loaders: any bytes in a rig or recording.json end in one ConfigError line.

Seeded random mutations (byte-level and structural) of a valid rig file and a
valid recording.json go through :func:`load_rig` and :func:`read_recording`.
Each must either load or raise :class:`ConfigError` with a one-line message
naming the file; any other exception (UnicodeDecodeError, RecursionError,
MemoryError, ValueError, OverflowError...) is a bug.
"""

from __future__ import annotations

import copy
import json
import random
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lightflow.app.errors import ConfigError, FrameError
from lightflow.app.recording import RecordingWriter, load_frame, read_recording
from lightflow.app.rig import load_rig
from lightflow.drivers.base import Frame

RIG_FILE = Path(__file__).resolve().parents[1] / "app" / "rigs" / "two-projector.json"
N_MUTATIONS = 240  # per file kind

NASTY_VALUES = [
    None, True, False, 0, -1, 1.5, -1e308, 1e308, 10**400, -(10**30), "", "1800", "x" * 5000,
    "\u202e\u0000", [], [[]], {}, {"a": 1}, [1, 2, 3], [[1, 2], [3]], 16385, 10**12, 1e6, 1e-320,
    "frames/./000000.png", "../../etc/passwd", "/abs.png", "frames/x.jpg",
]  # fmt: skip


def _paths(doc, prefix=()):
    """Every (container, key) path into a parsed JSON document."""
    if isinstance(doc, dict):
        items = doc.items()
    elif isinstance(doc, list):
        items = enumerate(doc)
    else:
        return
    for k, v in items:
        yield (*prefix, k)
        yield from _paths(v, (*prefix, k))


def _get(doc, path):
    for k in path:
        doc = doc[k]
    return doc


def mutate_structure(doc, rnd: random.Random):
    doc = copy.deepcopy(doc)
    for _ in range(rnd.randint(1, 3)):
        paths = list(_paths(doc))
        if not paths:
            break
        path = rnd.choice(paths)
        parent, key = _get(doc, path[:-1]), path[-1]
        op = rnd.random()
        if op < 0.6:
            parent[key] = copy.deepcopy(rnd.choice(NASTY_VALUES))
        elif op < 0.75 and isinstance(parent, dict):
            del parent[key]
        elif op < 0.85 and isinstance(parent, dict):
            parent["extra" + str(rnd.randint(0, 9))] = 1
        elif op < 0.95:
            value = parent[key]
            if isinstance(value, (int, float)) and not isinstance(value, bool):
                parent[key] = value * rnd.choice([-1, 1e6, 1e-9, 10**20])
            else:
                parent[key] = str(value)  # strings for numbers and everything else
        else:
            parent[key] = [[[[0]]]]
    return json.dumps(doc).encode()


def mutate_bytes(data: bytes, rnd: random.Random) -> bytes:
    op = rnd.randrange(8)
    if op == 0:  # flip a few bytes to arbitrary values (often invalid UTF-8)
        b = bytearray(data)
        for _ in range(rnd.randint(1, 5)):
            b[rnd.randrange(len(b))] = rnd.randrange(256)
        return bytes(b)
    if op == 1:
        return data[: rnd.randrange(len(data))]
    if op == 2:
        return data.decode().encode(rnd.choice(["utf-16", "utf-16-le", "utf-32", "latin-1"]))
    if op == 3:  # deep nesting
        depth = rnd.choice([500, 5000, 100000])
        return b"[" * depth + b"]" * depth
    if op == 4:
        return b'{"format": ' + b"[" * 50000 + b"1" + b"]" * 50000 + b"}"
    if op == 5:
        return data.replace(b"1.0", b"1" + b"0" * rnd.choice([400, 5000]), 1)
    if op == 6:
        return data.replace(b"0.0", rnd.choice([b"NaN", b"Infinity", b"-Infinity", b"1e999"]), 1)
    return bytes(rnd.randrange(256) for _ in range(rnd.randint(0, 64)))


def check_one_line(exc: ConfigError, path: Path) -> None:
    msg = str(exc)
    assert "\n" not in msg and "\r" not in msg, msg
    assert str(path) in msg, msg
    assert len(msg) < 600, msg


@pytest.fixture(scope="module")
def rig_bytes():
    return RIG_FILE.read_bytes()


@pytest.fixture(scope="module")
def recording_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("fuzz") / "rec"
    rig = load_rig(RIG_FILE).scaled(0.05)
    rng = np.random.default_rng(0)
    with RecordingWriter(root, rig, 0.02) as w:
        for i in range(2):
            w.write(Frame(i, i / 30, 0.02, rng.integers(0, 255, (60, 80, 3), dtype=np.uint8)))
    return root


def test_fuzz_rig(tmp_path, rig_bytes):
    rnd = random.Random(7)
    doc = json.loads(rig_bytes)
    outcomes = {"loaded": 0, "ConfigError": 0}
    for i in range(N_MUTATIONS):
        data = mutate_structure(doc, rnd) if i % 2 else mutate_bytes(rig_bytes, rnd)
        path = tmp_path / f"rig{i}.json"
        path.write_bytes(data)
        try:
            load_rig(path)
            outcomes["loaded"] += 1
        except ConfigError as exc:
            check_one_line(exc, path)
            outcomes["ConfigError"] += 1
    # most mutations break the file; the few harmless ones load
    assert outcomes["ConfigError"] >= 0.8 * N_MUTATIONS, outcomes


def test_fuzz_recording(tmp_path, recording_dir):
    rnd = random.Random(11)
    original = (recording_dir / "recording.json").read_bytes()
    doc = json.loads(original)
    outcomes = {"loaded": 0, "ConfigError": 0}
    for i in range(N_MUTATIONS):
        data = mutate_structure(doc, rnd) if i % 2 else mutate_bytes(original, rnd)
        (recording_dir / "recording.json").write_bytes(data)
        path = recording_dir / "recording.json"
        try:
            rec = read_recording(recording_dir)
        except ConfigError as exc:
            check_one_line(exc, path)
            outcomes["ConfigError"] += 1
            continue
        outcomes["loaded"] += 1
        for j in range(len(rec.frames)):
            try:
                load_frame(rec, j)
            except FrameError as exc:
                assert "\n" not in str(exc)
    (recording_dir / "recording.json").write_bytes(original)
    assert outcomes["ConfigError"] >= 0.8 * N_MUTATIONS, outcomes


NASTY_FILES = {
    "utf16": lambda rig: rig.decode().encode("utf-16"),
    "nested": lambda rig: b"[" * 100000 + b"]" * 100000,
    "huge-width": lambda rig: rig.replace(b'"width": 1600,', b'"width": 1000000000000,', 1),
    "string-K": lambda rig: rig.replace(b"1800.0", b'"1800.0"', 1),
    "huge-int": lambda rig: rig.replace(b'"width": 1600,', b'"width": 1' + b"0" * 5000 + b',', 1),
}


@pytest.mark.parametrize("name", sorted(NASTY_FILES))
def test_cli_nasty_rig_is_one_line_exit_2(tmp_path, rig_bytes, name):
    path = tmp_path / "rig.json"
    data = NASTY_FILES[name](rig_bytes)
    assert data != rig_bytes
    path.write_bytes(data)
    proc = subprocess.run(
        [sys.executable, "-m", "lightflow.app.cli", "rig", "check", str(path)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"lightflow: error: {path}: "), proc.stderr


def test_cli_verify_and_replay_nasty_recording(tmp_path, recording_dir):
    root = tmp_path / "rec"
    subprocess.run(["cp", "-r", str(recording_dir), str(root)], check=True)
    doc = json.loads((root / "recording.json").read_text())
    doc["frames"][1]["t"] = doc["frames"][0]["t"]  # timestamps that do not increase
    (root / "recording.json").write_text(json.dumps(doc))
    proc = subprocess.run(
        [sys.executable, "-m", "lightflow.app.cli", "replay", str(root)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        f"lightflow: error: {root}/recording.json: frames[1].t: 0 s does not increase "
        "(frames[0].t = 0 s); check it with `lightflow verify`"
    ]
    (root / "recording.json").write_bytes(b"\xff\xfe{\x00")
    proc = subprocess.run(
        [sys.executable, "-m", "lightflow.app.cli", "replay", str(root)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 2
    assert len(proc.stderr.strip().splitlines()) == 1 and "not UTF-8" in proc.stderr
