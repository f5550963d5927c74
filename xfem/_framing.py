"""Message framing between a model and its cut worker process (``xfem._background``).

Each message is a pickle (protocol 5) whose arrays of ``_OUT_OF_BAND`` bytes or more travel after it, out of band:
the number of buffers and the lengths (8 bytes each), the pickle, the buffers. The reader reads a whole message
without the GIL (blocking reads), each large buffer into an array of its own aligned to ``_ALIGN`` bytes, so that
unpickling makes views of them instead of copies, and a device copy of a received system can alias them (XLA's CPU
client does so for aligned host arrays).
"""

from __future__ import annotations

import pickle
import struct
from collections.abc import Sequence

import numpy as np

_PROTOCOL = 5
_LENGTH = struct.Struct("<Q")
_OUT_OF_BAND = 4096  # buffers at least this large travel after the pickle (smaller ones: copying them costs less)
_ALIGN = 64  # XLA's CPU client aliases host arrays aligned to this, instead of copying them


def encode(message) -> tuple[bytes, list[memoryview]]:
    """A message's pickle and its out-of-band buffers (views of the message's arrays, not copies)."""
    buffers = []

    def out_of_band(buffer: pickle.PickleBuffer) -> bool:
        raw = buffer.raw()
        if raw.nbytes < _OUT_OF_BAND:
            return True  # in band
        buffers.append(raw)
        return False

    return pickle.dumps(message, protocol=_PROTOCOL, buffer_callback=out_of_band), buffers


def decode(data: bytes, buffers: list[np.ndarray]):
    """``encode`` undone: the message, its large arrays views of ``buffers``."""
    return pickle.loads(data, buffers=buffers)


def write_frame(stream, data: bytes, buffers: Sequence = ()) -> None:
    """One message: the number of buffers, the pickle's and the buffers' lengths, the pickle, the buffers."""
    lengths = [len(data), *(memoryview(b).nbytes for b in buffers)]
    stream.write(struct.pack(f"<{len(lengths) + 1}Q", len(buffers), *lengths))
    stream.write(data)
    for buffer in buffers:
        stream.write(buffer)
    stream.flush()


def read_frame(stream) -> tuple[bytes, list[np.ndarray]]:
    """The next message's pickle and buffers, read whole, each buffer in a byte array of its own aligned to
    ``_ALIGN``; EOFError at the stream's end."""
    head = stream.read(_LENGTH.size)
    if not head:
        raise EOFError("the stream ended")
    count = _LENGTH.unpack(head + _read_exactly(stream, _LENGTH.size - len(head)))[0]
    lengths = struct.unpack(f"<{count + 1}Q", _read_exactly(stream, _LENGTH.size * (count + 1)))
    data = _read_exactly(stream, lengths[0])
    buffers = []
    for size in lengths[1:]:
        block = np.empty(size + _ALIGN, np.uint8)
        start = -block.ctypes.data % _ALIGN
        buffer = block[start : start + size]
        # an ndarray has the buffer protocol (numpy's stubs declare __buffer__ only for Python >= 3.12)
        view, done = memoryview(buffer), 0  # pyright: ignore[reportArgumentType]
        while done < size:
            got = stream.readinto(view[done:])
            if not got:
                raise EOFError("the stream ended within a message")
            done += got
        buffers.append(buffer)
    return data, buffers


def _read_exactly(stream, size: int) -> bytes:
    data = stream.read(size)
    if len(data) < size:
        raise EOFError("the stream ended within a message")
    return data


def portable(error: BaseException) -> BaseException:
    """The error itself if it pickles (ValueError and friends), else a RuntimeError with its text."""
    try:
        pickle.loads(pickle.dumps(error, protocol=_PROTOCOL))
        return error
    except Exception:
        return RuntimeError(f"{type(error).__name__}: {error}")
