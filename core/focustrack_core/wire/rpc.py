"""Request/reply over Zenoh queryables with protobuf messages and Error replies.

A queryable hands each query to `answer` with a function that turns it into a reply
message (or to `serve` with one that replies itself, as often as it needs); a
`RequestError` raised there (for example by `parse_request`) becomes an error reply
(payload an `Error`, encoding ``application/protobuf;focustrack_core.v1.Error``), and
any other exception an INTERNAL error reply, so the service keeps running. A caller
uses `call`, which returns the reply message or raises `RemoteError`.

Within a trace, `call` attaches its client span's context to the query and the queryable
answers in a span of that trace (`focustrack_core.tracing`: `query_span`, `joined`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TypeVar

import zenoh
from google.protobuf.message import DecodeError, Message
from opentelemetry.trace import SpanKind

from focustrack_core import tracing
from focustrack_core.v1 import common_pb2

M = TypeVar("M", bound=Message)

log = logging.getLogger(__name__)

ErrorCode = common_pb2.ErrorCode

#: Codes that say nobody answered (not that a service refused): worth trying again.
UNANSWERED = frozenset({ErrorCode.ERROR_CODE_TIMEOUT, ErrorCode.ERROR_CODE_UNAVAILABLE})

#: Codes worth trying again after a pause: nobody answered, or the service is busy.
RETRYABLE = UNANSWERED | {ErrorCode.ERROR_CODE_BUSY}


def protobuf_encoding(message_type: type[Message]) -> zenoh.Encoding:
    """``application/protobuf;<full message name>``."""
    return zenoh.Encoding.APPLICATION_PROTOBUF.with_schema(message_type.DESCRIPTOR.full_name)


ERROR_ENCODING = protobuf_encoding(common_pb2.Error)


class RemoteError(Exception):
    """An error reply (or no reply at all) to a query; `error` says what went wrong."""

    def __init__(self, error: common_pb2.Error) -> None:
        name = common_pb2.ErrorCode.Name(error.code)
        super().__init__(
            f"{name}: {error.message}" + (f" (field {error.field})" if error.field else "")
        )
        self.error = error


class RequestError(ValueError):
    """A request the service refuses; becomes an error reply with this code and field."""

    def __init__(self, code: common_pb2.ErrorCode, message: str, field: str = "") -> None:
        super().__init__(message)
        self.error = common_pb2.Error(code=code, message=message, field=field)


def parse_request(query: zenoh.Query, message_type: type[M]) -> M:
    """The query's payload as `message_type`; RequestError(MALFORMED_REQUEST) if it is not one."""
    if query.payload is None:
        raise RequestError(
            ErrorCode.ERROR_CODE_MALFORMED_REQUEST,
            f"query has no payload; expected a {message_type.DESCRIPTOR.full_name}",
        )
    try:
        return message_type.FromString(query.payload.to_bytes())
    except DecodeError as error:
        raise RequestError(
            ErrorCode.ERROR_CODE_MALFORMED_REQUEST,
            f"payload is not a {message_type.DESCRIPTOR.full_name}: {error}",
        ) from error


def reply_message(query: zenoh.Query, key_expr: str, message: Message) -> None:
    """Answer `query` on `key_expr` with a protobuf message."""
    query.reply(key_expr, message.SerializeToString(), encoding=protobuf_encoding(type(message)))


def reply_error(query: zenoh.Query, error: common_pb2.Error) -> None:
    """Answer `query` with an error reply."""
    query.reply_err(error.SerializeToString(), encoding=ERROR_ENCODING)


def answer(query: zenoh.Query, key_expr: str, handle: Callable[[zenoh.Query], Message]) -> None:
    """Reply to `query` with `handle(query)`, or with an error reply; always finishes the query."""
    serve(query, key_expr, lambda query: reply_message(query, key_expr, handle(query)))


def declare_answering(
    session: zenoh.Session, key_expr: str, handle: Callable[[zenoh.Query], Message]
) -> zenoh.Queryable[None]:
    """A queryable on `key_expr` whose every query is answered with `handle(query)`
    (`answer`)."""
    return session.declare_queryable(key_expr, lambda query: answer(query, key_expr, handle))


def serve(query: zenoh.Query, key_expr: str, respond: Callable[[zenoh.Query], None]) -> None:
    """Let `respond` reply to `query` (as many replies as it likes); a `RequestError` it
    raises becomes that error reply, any other exception an INTERNAL one. Always
    finishes the query; in the trace the query's attachment names, in a span of its own."""
    attachment = None if query.attachment is None else query.attachment.to_bytes()
    parent = tracing.of_attachment(attachment)
    with query, tracing.joined(f"query {key_expr}", parent, SpanKind.SERVER) as span:
        try:
            respond(query)
        except RequestError as refused:
            log.info("refused query on %s: %s", key_expr, refused)
            tracing.fail(span, str(refused))
            reply_error(query, refused.error)
        except Exception as failure:
            log.exception("query on %s failed", key_expr)
            tracing.fail(span, f"{type(failure).__name__}: {failure}")
            reply_error(
                query,
                common_pb2.Error(
                    code=ErrorCode.ERROR_CODE_INTERNAL,
                    message=f"{type(failure).__name__}: {failure}",
                ),
            )


def error_of(reply_error: zenoh.ReplyError) -> common_pb2.Error:
    """The `Error` of an error reply; Zenoh's own errors become TIMEOUT or UNAVAILABLE.

    Zenoh's own error replies are plain text, not an `Error`: its "Timeout" when
    the queryable did not answer in time, anything else when the query could
    not be routed.
    """
    payload = reply_error.payload.to_bytes()
    if reply_error.encoding == ERROR_ENCODING:
        return common_pb2.Error.FromString(payload)
    text = payload.decode("utf-8", "replace")
    code = ErrorCode.ERROR_CODE_TIMEOUT if text == "Timeout" else ErrorCode.ERROR_CODE_UNAVAILABLE
    return common_pb2.Error(code=code, message=f"zenoh error reply: {text}")


def call(
    session: zenoh.Session,
    key_expr: str,
    request: Message,
    reply_type: type[M],
    timeout_s: float = 10.0,
) -> M:
    """Send `request` to the queryable at `key_expr`; its reply as `reply_type`.

    Raises RemoteError on an error reply, on a timeout and when nobody answers.
    """
    with tracing.query_span(key_expr) as attachment:
        replies = session.get(
            key_expr,
            payload=request.SerializeToString(),
            encoding=protobuf_encoding(type(request)),
            timeout=timeout_s,
            attachment=attachment,
        )
        for reply in replies:
            if reply.ok is not None:
                return reply_type.FromString(reply.ok.payload.to_bytes())
            if reply.err is not None:
                raise RemoteError(error_of(reply.err))
        raise RemoteError(
            common_pb2.Error(
                code=ErrorCode.ERROR_CODE_UNAVAILABLE,
                message=f"no queryable answered on {key_expr}",
            )
        )
