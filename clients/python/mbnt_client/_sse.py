"""A minimal reader of ``text/event-stream`` (server-sent events)."""

from typing import Iterable, Iterator, List, Optional, Tuple


def _lines(chunks: Iterable[bytes]) -> Iterator[str]:
    pending = b""
    for chunk in chunks:
        pending += chunk
        *lines, pending = pending.split(b"\n")
        for line in lines:
            yield line.rstrip(b"\r").decode("utf-8")
    if pending:
        yield pending.rstrip(b"\r").decode("utf-8")


def events(chunks: Iterable[bytes]) -> Iterator[Tuple[str, str]]:
    """``(event, data)`` of each event in a byte stream; comments (keep-alives) are skipped and an
    event cut off by the end of the stream is dropped, as the SSE standard says."""
    event: Optional[str] = None
    data: List[str] = []
    for line in _lines(chunks):
        if line == "":
            if data:
                yield event or "message", "\n".join(data)
            event, data = None, []
            continue
        if line.startswith(":"):
            continue
        field, _, value = line.partition(":")
        if value.startswith(" "):
            value = value[1:]
        if field == "event":
            event = value
        elif field == "data":
            data.append(value)
