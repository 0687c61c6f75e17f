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

from lightflow.app.errors import ConfigError
from lightflow.app.recording import RECORDING_FORMAT, read_recording
from lightflow.app.rig import load_rig

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
