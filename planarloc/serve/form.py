"""Reading ``POST /v1/localize`` forms from a Starlette request (FastAPI app and Ray Serve replicas).

The body is read as it arrives and parsed by a streaming multipart parser (python-multipart),
so every limit holds for every transfer encoding — ``Content-Length`` or ``chunked`` — and is
enforced while the bytes come in, never after the fact:

- the whole body: at most ``max_image_bytes + FORM_OVERHEAD_BYTES``; beyond that the upload is
  cut off at once (413), nothing is written to disk;
- each part: the image at most ``max_image_bytes`` (413), a text field at most
  ``MAX_FIELD_BYTES`` (413), at most one part per known field (400);
- time: the body must arrive within ``body_timeout_s`` (408), so a client that trickles its
  body cannot hold anything for longer;
- memory: the bytes held by all uploads in progress share one :class:`UploadBudget` (503 with
  ``Retry-After`` when it is spent), so many concurrent uploads cannot exhaust the server.
"""

from __future__ import annotations

import asyncio

from planarloc.extras import require
from planarloc.serve.requests import FIELDS, LocalizeRequest, MapSet, RequestError, parse_localize_request
from planarloc.serve.settings import DEFAULT_BODY_TIMEOUT_S

#: Room for the multipart envelope and the text fields on top of the image limit.
FORM_OVERHEAD_BYTES = 64 * 1024
#: Largest text field (camera, gravity, ...).
MAX_FIELD_BYTES = 16 * 1024


class UploadBudget:
    """Bytes that all request bodies being read may hold together (one per server or replica).

    Args:
        limit_bytes: the budget; :meth:`take` beyond it raises a 503.
    """

    def __init__(self, limit_bytes: int) -> None:
        self.limit_bytes = int(limit_bytes)
        self.held = 0

    def take(self, n: int) -> None:
        if self.held + n > self.limit_bytes:
            raise RequestError(
                503, f"too many uploads in progress ({self.held} bytes held); retry later", retry_after_s=1
            )
        self.held += n

    def give(self, n: int) -> None:
        self.held -= n


class _Parts:
    """The callbacks of the multipart parser: collects the parts, enforcing the per-part limits."""

    def __init__(self, max_image_bytes: int) -> None:
        self.max_image_bytes = max_image_bytes
        self.fields: dict[str, str] = {}
        self.image: bytes | None = None
        self.filename: str | None = None
        self.ended = False
        self._headers: dict[bytes, bytes] = {}
        self._field = b""
        self._value = b""
        self._name: str | None = None
        self._is_file = False
        self._data: list[bytes] = []
        self._size = 0

    def callbacks(self) -> dict:
        return {
            "on_part_begin": self._part_begin,
            "on_header_field": self._header_field,
            "on_header_value": self._header_value,
            "on_header_end": self._header_end,
            "on_headers_finished": self._headers_finished,
            "on_part_data": self._part_data,
            "on_part_end": self._part_end,
            "on_end": self._end,
        }

    def _part_begin(self) -> None:
        self._headers, self._field, self._value, self._data, self._size = {}, b"", b"", [], 0

    def _header_field(self, data: bytes, start: int, end: int) -> None:
        self._field += data[start:end]

    def _header_value(self, data: bytes, start: int, end: int) -> None:
        self._value += data[start:end]

    def _header_end(self) -> None:
        self._headers[self._field.lower()] = self._value
        self._field, self._value = b"", b""

    def _headers_finished(self) -> None:
        multipart = require("python_multipart.multipart", "serve")
        disposition, options = multipart.parse_options_header(self._headers.get(b"content-disposition", b""))
        if disposition != b"form-data" or b"name" not in options:
            raise RequestError(
                400, "malformed multipart form: a part without 'Content-Disposition: form-data; name=...'"
            )
        name = options[b"name"].decode("utf-8", "replace")
        if name not in FIELDS:
            raise RequestError(400, f"unknown form field {name[:40]!r}; expected {', '.join(FIELDS)}")
        if name in self.fields or (name == "image" and self.image is not None):
            raise RequestError(400, f"{name}: given twice")
        self._is_file = b"filename" in options
        if self._is_file and name != "image":
            raise RequestError(400, f"{name}: unexpected file field (only 'image' is a file)")
        if name == "image" and not self._is_file:
            raise RequestError(400, "image: must be a file field (multipart filename=...), not text")
        self._name = name
        if self._is_file:
            self.filename = options[b"filename"].decode("utf-8", "replace")

    def _part_data(self, data: bytes, start: int, end: int) -> None:
        self._size += end - start
        limit = self.max_image_bytes if self._is_file else MAX_FIELD_BYTES
        if self._size > limit:
            what = "image" if self._is_file else f"{self._name}: text field"
            raise RequestError(413, f"{what} is over the limit of {limit} bytes")
        self._data.append(data[start:end])

    def _part_end(self) -> None:
        raw = b"".join(self._data)
        self._data = []
        if self._is_file:
            self.image = raw
            return
        try:
            self.fields[str(self._name)] = raw.decode("utf-8")
        except UnicodeDecodeError:
            raise RequestError(400, f"{self._name}: not UTF-8 text") from None

    def _end(self) -> None:
        self.ended = True


def _content_length(request) -> int | None:
    length = request.headers.get("content-length")
    if length is None:
        return None
    if not length.strip().isascii() or not length.strip().isdigit() or len(length.strip()) > 18:
        raise RequestError(400, f"Content-Length: not a byte count ({length[:30]!r})")
    return int(length)


async def read_localize_form(
    request,
    maps: MapSet,
    max_image_bytes: int,
    *,
    body_timeout_s: float = DEFAULT_BODY_TIMEOUT_S,
    budget: UploadBudget | None = None,
) -> LocalizeRequest:
    """Read, parse and validate the multipart form of a ``starlette.requests.Request`` (module docstring).

    Raises:
        RequestError: 4xx with a one-line reason (413 over a limit, 408 too slow, 415 not a
            multipart form), or 503 when the upload budget is spent.
    """
    multipart = require("python_multipart.multipart", "serve")
    disconnect = require("starlette.requests", "serve").ClientDisconnect
    ctype = request.headers.get("content-type", "")
    kind, params = multipart.parse_options_header(ctype)
    if kind == b"application/x-www-form-urlencoded":
        raise RequestError(
            400,
            "image: missing; a urlencoded form cannot carry it: send multipart/form-data with "
            "the file field 'image' (a JPEG or PNG)",
        )
    if kind != b"multipart/form-data":
        raise RequestError(415, f"expected a multipart/form-data body, got {ctype[:60]!r}")
    boundary = params.get(b"boundary")
    if not boundary or len(boundary) > 70:
        raise RequestError(400, "malformed multipart form: the Content-Type has no valid boundary")
    limit = max_image_bytes + FORM_OVERHEAD_BYTES
    length = _content_length(request)
    if length is not None and length > limit:
        raise RequestError(413, f"request body of {length} bytes is over the limit of {limit} bytes")
    parts = _Parts(max_image_bytes)
    parser = multipart.MultipartParser(boundary, parts.callbacks(), max_header_count=4, max_header_size=2048)
    received = 0
    held = 0
    try:
        async with asyncio.timeout(body_timeout_s):
            async for chunk in request.stream():
                if not chunk:
                    continue
                received += len(chunk)
                if received > limit:
                    raise RequestError(
                        413, f"request body is over the limit of {limit} bytes (cut off there)"
                    )
                if budget is not None:
                    budget.take(len(chunk))
                    held += len(chunk)
                try:
                    parser.write(chunk)
                except multipart.MultipartParseError as exc:
                    raise RequestError(400, f"malformed multipart form: {exc}") from None
        parser.finalize()
    except disconnect:
        raise RequestError(
            400, f"the client closed the connection after {received} bytes of the body"
        ) from None
    except TimeoutError:
        raise RequestError(
            408,
            f"the request body did not arrive within {body_timeout_s:g} s "
            f"({received} bytes received); send it faster or smaller",
        ) from None
    finally:
        if budget is not None:
            budget.give(held)
    if not parts.ended:
        raise RequestError(400, "malformed multipart form: the body ends before the closing boundary")
    return parse_localize_request(parts.fields, parts.image, parts.filename, maps, max_image_bytes)
