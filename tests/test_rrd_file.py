"""RrdFile: the pipe between the Rerun SDK and the .rrd never blocks or fails the SDK."""

from __future__ import annotations

import errno
import os
import resource
import signal

import pytest

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


@pytest.fixture
def size_limit():
    """A file size limit: writes past it fail with EFBIG (SIGXFSZ ignored), like a full disk."""
    old_handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    old_limit = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (100_000, old_limit[1]))
    yield 100_000
    resource.setrlimit(resource.RLIMIT_FSIZE, old_limit)
    signal.signal(signal.SIGXFSZ, old_handler)


def test_failed_write_is_kept_and_the_pipe_still_drains(tmp_path, size_limit):
    file = RrdFile(tmp_path / "b.rrd")
    # far more than the pipe holds: a copy that stopped reading would block this writer
    write_all(file.sink_path, bytes(8 * CHUNK_BYTES))
    file.finish()
    assert isinstance(file.error, OSError) and file.error.errno == errno.EFBIG
    assert file.reason() == "the file size limit was reached"
    assert (tmp_path / "b.rrd").stat().st_size <= size_limit


def test_reasons_name_a_full_disk():
    file = RrdFile.__new__(RrdFile)
    file.error = OSError(errno.ENOSPC, "No space left on device")
    assert file.reason() == "the disk is full"
    file.error = OSError(errno.EIO, "Input/output error")
    assert file.reason() == "input/output error"
