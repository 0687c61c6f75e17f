"""RrdFile: the pipe between the Rerun SDK and the .rrd never blocks or fails the SDK."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
from pathlib import Path

from lightflow.app.sinks.rrd_file import CHUNK_BYTES, RrdFile


def write_all(path: str, data: bytes) -> None:
    """Write like the SDK does: open the sink path, write, close."""
    fd = os.open(path, os.O_WRONLY)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view) :]
    finally:
        os.close(fd)


def test_bytes_arrive_in_order(tmp_path):
    path = tmp_path / "a.rrd"
    file = RrdFile(path)
    data = os.urandom(3 * CHUNK_BYTES + 12345)
    write_all(file.sink_path, data)
    file.finish()
    assert file.error is None
    assert path.read_bytes() == data


LIMITED = """
import errno, os, resource, signal, sys
from lightflow.app.sinks.rrd_file import CHUNK_BYTES, RrdFile
sys.path.insert(0, {tests!r})
from test_rrd_file import write_all
# a file size limit fails writes past it with EFBIG (SIGXFSZ ignored), like a full disk
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (100_000, 100_000))
file = RrdFile({path!r})
# far more than the pipe holds: a copy that stopped reading would block this writer
write_all(file.sink_path, bytes(8 * CHUNK_BYTES))
file.finish()
assert isinstance(file.error, OSError) and file.error.errno == errno.EFBIG, file.error
print(file.reason())
"""


def test_failed_write_is_kept_and_the_pipe_still_drains(tmp_path):
    # in a child: the limit holds for every file of the process that sets it
    path = tmp_path / "b.rrd"
    script = LIMITED.format(tests=str(Path(__file__).parent), path=str(path))
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=60)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert done.stdout == "the file size limit was reached\n"
    assert path.stat().st_size <= 100_000


def test_reasons_name_a_full_disk():
    file = RrdFile.__new__(RrdFile)
    file.error = OSError(errno.ENOSPC, "No space left on device")
    assert file.reason() == "the disk is full"
    file.error = OSError(errno.EIO, "Input/output error")
    assert file.reason() == "input/output error"
