"""A streamed ``multipart/form-data`` body of known length (frame files are read while sending)."""

import os
import uuid
from typing import Iterator, List, Tuple, Union

_CHUNK = 1 << 20

# A part's payload: bytes held in memory, or the path of a file read while the body is sent.
Payload = Union[bytes, str]


def _quote(value: str) -> str:
    return value.replace("\\", "\\\\").replace('"', "%22").replace("\r", "%0D").replace("\n", "%0A")


class MultipartBody:
    """An iterable ``multipart/form-data`` body with a ``len``, so that ``requests`` sends it with
    a ``Content-Length`` without holding the files in memory."""

    def __init__(self) -> None:
        self.boundary = uuid.uuid4().hex
        self._parts: List[Tuple[bytes, Payload, int]] = []

    @property
    def content_type(self) -> str:
        """The ``Content-Type`` header value, boundary included."""
        return f"multipart/form-data; boundary={self.boundary}"

    def add(self, name: str, payload: Payload, content_type: str, filename: Union[str, None] = None) -> None:
        """Add a part: ``payload`` is bytes or a file path (read when the body is sent)."""
        disposition = f'form-data; name="{_quote(name)}"'
        if filename is not None:
            disposition += f'; filename="{_quote(filename)}"'
        head = (
            f"--{self.boundary}\r\nContent-Disposition: {disposition}\r\nContent-Type: {content_type}\r\n\r\n"
        ).encode("utf-8")
        size = len(payload) if isinstance(payload, bytes) else os.path.getsize(payload)
        self._parts.append((head, payload, size))

    def _tail(self) -> bytes:
        return f"--{self.boundary}--\r\n".encode("ascii")

    def __len__(self) -> int:
        return sum(len(head) + size + 2 for head, _, size in self._parts) + len(self._tail())

    def __iter__(self) -> Iterator[bytes]:
        for head, payload, size in self._parts:
            yield head
            if isinstance(payload, bytes):
                yield payload
            else:
                sent = 0
                with open(payload, "rb") as f:
                    while True:
                        chunk = f.read(_CHUNK)
                        if not chunk:
                            break
                        sent += len(chunk)
                        yield chunk
                if sent != size:
                    raise OSError(f"{payload} changed size while it was uploaded ({size} -> {sent} bytes)")
            yield b"\r\n"
        yield self._tail()
