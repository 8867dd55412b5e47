"""Reading ``POST /v1/localize`` forms from a Starlette request (FastAPI app and Ray Serve replicas)."""

from __future__ import annotations

from planarloc.serve.requests import FIELDS, LocalizeRequest, MapSet, RequestError, parse_localize_request

#: Room for the multipart envelope and the text fields on top of the image limit.
FORM_OVERHEAD_BYTES = 64 * 1024
#: Largest text field (camera, gravity, ...).
MAX_FIELD_BYTES = 16 * 1024


async def read_localize_form(request, maps: MapSet, max_image_bytes: int) -> LocalizeRequest:
    """Parse and validate the multipart form of a ``starlette.requests.Request``.

    The body size is checked against ``Content-Length`` before reading; the image part is read
    up to the limit plus one byte (the multipart parser spools large parts to disk, so memory
    stays bounded).

    Raises:
        RequestError: 4xx with a one-line reason.
    """
    ctype = request.headers.get("content-type", "")
    if not ctype.startswith(("multipart/form-data", "application/x-www-form-urlencoded")):
        raise RequestError(415, f"expected a multipart/form-data body, got {ctype[:60]!r}")
    length = request.headers.get("content-length")
    limit = max_image_bytes + FORM_OVERHEAD_BYTES
    if length is not None and length.isdigit() and int(length) > limit:
        raise RequestError(413, f"request body of {length} bytes is over the limit of {limit} bytes")
    try:
        form = await request.form(max_files=1, max_fields=len(FIELDS), max_part_size=MAX_FIELD_BYTES)
    except Exception as exc:  # noqa: BLE001 - the multipart parser's errors are the client's
        raise RequestError(400, f"malformed multipart form: {getattr(exc, 'detail', exc)}") from None
    try:
        fields, image, filename = {}, None, None
        for key, value in form.multi_items():
            if isinstance(value, str):
                fields[key] = value
            elif key == "image":
                image = await value.read(max_image_bytes + 1)
                filename = value.filename
            else:
                raise RequestError(400, f"{key[:40]}: unexpected file field (only 'image' is a file)")
        if "image" in fields:
            raise RequestError(400, "image: must be a file field (multipart filename=...), not text")
        return parse_localize_request(fields, image, filename, maps, max_image_bytes)
    finally:
        await form.close()
