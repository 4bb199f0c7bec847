"""The service loop's inbox: what the Zenoh handlers and the builder thread hand to the loop
thread, one small request each, answered on the loop."""

from __future__ import annotations

import contextlib
import functools
import logging
import queue
from collections.abc import Callable, Iterable
from concurrent.futures import Future, InvalidStateError
from dataclasses import dataclass
from typing import Any

import zenoh

from inhand_tracker.client import zenoh_encoding
from inhand_tracker.protocol import Error, ErrorCode, encode

from .admission import ServiceError

__all__ = ["Inbox", "Request", "answer", "guarded", "reply"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Request:
    """One thing for the loop to do."""

    name: str
    """What it is, for the log."""
    run: Callable[[Future | None], Any]
    """Does it on the loop thread, given where to answer; returns the answer, or None when there
    is none (yet: an open waiting on a build answers later)."""
    done: Future | None = None
    """Where the asking handler waits for the answer."""


class Inbox:
    """Requests in the order they came, for the one thread that owns the GPU."""

    def __init__(self) -> None:
        self._queue: queue.Queue[Request] = queue.Queue()
        self.in_flight: Future | None = None
        """The answer the loop is working on now."""

    def post(self, name: str, run: Callable[[Future | None], Any], done: Future | None = None) -> None:
        self._queue.put(Request(name, run, done))

    def call(self, name: str, run: Callable[[Future | None], Any], timeout: float = 300.0) -> object:
        """Hand a request to the loop and wait for its answer (opening may build a population)."""
        done: Future = Future()
        self.post(name, run, done)
        return done.result(timeout=timeout)

    def next(self, wait: float) -> Request | None:
        """The next request, waiting up to ``wait`` [s] for one (0: none waited for)."""
        try:
            return self._queue.get(timeout=wait) if wait > 0 else self._queue.get_nowait()
        except queue.Empty:
            return None

    def handle(self, request: Request, refusal: Callable[[ServiceError], Error]) -> None:
        """Run ``request`` and answer it; a refusal answers as ``refusal`` words it, and any other
        failure answers INTERNAL with the reason: the loop never dies of a request."""
        self.in_flight = done = request.done
        try:
            result = request.run(done)
            if result is not None:
                answer(done, result)
        except ServiceError as exc:
            answer(done, refusal(exc))
        except Exception as exc:
            log.exception("request '%s' failed", request.name)
            answer(done, Error(code=ErrorCode.INTERNAL, message=f"{type(exc).__name__}: {exc}"))

    def cancel(self, others: Iterable[Future | None], reason: str) -> None:
        """Answer every request still waiting (queued, in flight, or in ``others``) with ``reason``."""
        pending = [self.in_flight, *others]
        while (request := self.next(0)) is not None:
            pending.append(request.done)
        for done in pending:
            answer(done, Error(code=ErrorCode.INTERNAL, message=reason))


def answer(done: Future | None, value) -> None:
    """Answer a request once: a stopping service may have answered it already."""
    if done is not None:
        with contextlib.suppress(InvalidStateError):
            done.set_result(value)


def reply(query: zenoh.Query, message) -> None:
    """Answer a query with a message, or with an error reply for an :class:`Error`."""
    with query:
        if isinstance(message, Error):
            query.reply_err(encode(message), encoding=zenoh_encoding(Error))
        else:
            query.reply(query.key_expr, encode(message), encoding=zenoh_encoding(type(message)))


def guarded(handler):
    """A Zenoh callback that raises is printed to stderr by Zenoh, past the service's log, and its
    query is left unanswered until the client times out: log it, and answer with the reason."""

    @functools.wraps(handler)
    def run(self, arg) -> None:
        try:
            handler(self, arg)
        except Exception as exc:
            log.exception("%s on %s failed", handler.__name__, getattr(arg, "key_expr", "?"))
            if isinstance(arg, zenoh.Query):
                error = encode(Error(code=ErrorCode.INTERNAL, message=f"{type(exc).__name__}: {exc}"))
                # A query answered before it raised takes no more; `with` finalises it now (the
                # traceback holds it, so the client would wait for its timeout).
                with contextlib.suppress(Exception), arg:
                    arg.reply_err(error, encoding=zenoh_encoding(Error))

    return run
