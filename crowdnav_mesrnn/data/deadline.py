"""An overall deadline for a sequence of URL requests, however slowly a server sends.

A socket time-out bounds one stall: a server that sends one byte just before every time-out keeps a read alive
forever, in the body or already in the status line and headers. :class:`Deadline` bounds the whole: it opens URLs
through an opener whose HTTP(S) connections register their sockets with it, and when the deadline passes a timer
shuts those sockets down, so the read blocked on them returns at once (as an error the caller reports through
:attr:`Deadline.expired`). ``file://`` URLs have no socket; :meth:`Deadline.check` between reads covers them.
"""

from __future__ import annotations

import math
import socket
import threading
import time
import urllib.request
from types import TracebackType
from typing import Any, BinaryIO

#: URL schemes :meth:`Deadline.urlopen` accepts (others are refused: their handlers have no deadline).
SCHEMES: tuple[str, ...] = ("http", "https", "file")


class DeadlineExpired(TimeoutError):
    """The overall deadline passed (raised by :meth:`Deadline.check`)."""


def finite_seconds(name: str, value: object) -> float:
    """``value`` as a float when it is a finite number of seconds > 0; else ``ValueError`` naming ``name``."""
    try:
        seconds = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a finite number of seconds > 0, got {value!r}") from None
    if not (math.isfinite(seconds) and seconds > 0):
        raise ValueError(f"{name} must be a finite number of seconds > 0, got {seconds!r}")
    return seconds


class Deadline:
    """Requests opened through :meth:`urlopen` inside ``with Deadline(seconds):`` end by ``seconds`` from entry.

    Args:
        seconds: the overall budget, finite and > 0 (:func:`finite_seconds`).
    """

    def __init__(self, seconds: float) -> None:
        self.seconds = finite_seconds("deadline", seconds)
        self._end = math.inf
        self._expired = threading.Event()
        self._lock = threading.Lock()
        self._sockets: list[socket.socket] = []
        self._timer: threading.Timer | None = None
        self._opener = urllib.request.build_opener(_WatchedHTTPHandler(self), _WatchedHTTPSHandler(self))

    def __enter__(self) -> Deadline:
        self._end = time.monotonic() + self.seconds
        self._timer = threading.Timer(self.seconds, self._expire)
        self._timer.daemon = True
        self._timer.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._timer is not None:
            self._timer.cancel()
        with self._lock:
            self._sockets.clear()

    @property
    def expired(self) -> bool:
        """True once the deadline has passed."""
        return self._expired.is_set() or time.monotonic() >= self._end

    def remaining(self) -> float:
        """Seconds left (0 when expired)."""
        return max(0.0, self._end - time.monotonic())

    def check(self) -> None:
        """Raise :class:`DeadlineExpired` when the deadline has passed."""
        if self.expired:
            raise DeadlineExpired(f"the deadline of {self.seconds:g} s passed")

    def urlopen(self, url: str, timeout_s: float) -> BinaryIO:
        """Open ``url`` (``http``, ``https`` or ``file``); connecting and every read stall at most ``timeout_s``
        (less when the deadline is nearer), and the whole exchange ends when the deadline does."""
        scheme = url.partition(":")[0].lower()
        if scheme not in SCHEMES:
            raise ValueError(f"{url}: unsupported URL scheme {scheme!r} (use one of {', '.join(SCHEMES)})")
        self.check()
        return self._opener.open(url, timeout=min(timeout_s, max(self.remaining(), 1e-3)))

    def _watch(self, sock: socket.socket | None) -> None:
        if sock is None:
            return
        with self._lock:
            self._sockets.append(sock)
        if self._expired.is_set():  # registered after the timer fired
            _shutdown(sock)

    def _expire(self) -> None:
        self._expired.set()
        with self._lock:
            sockets = list(self._sockets)
        for sock in sockets:
            _shutdown(sock)


def _shutdown(sock: socket.socket) -> None:
    try:
        sock.shutdown(socket.SHUT_RDWR)  # a blocked recv on it returns at once
    except OSError:
        pass  # already closed


def _watched(connection_class: Any, deadline: Deadline) -> Any:
    """``connection_class`` (an ``http.client`` connection) registering its socket with ``deadline`` on connect."""

    class Watched(connection_class):  # type: ignore[misc, valid-type]
        def connect(self) -> None:
            super().connect()
            deadline._watch(self.sock)

    return Watched


class _Watching:
    """Mixed into urllib's HTTP(S) handlers: their connections register their sockets with a :class:`Deadline`."""

    def __init__(self, deadline: Deadline) -> None:
        super().__init__()
        self._deadline = deadline

    def do_open(self, http_class: Any, req: Any, **http_conn_args: Any) -> Any:
        return super().do_open(_watched(http_class, self._deadline), req, **http_conn_args)  # type: ignore[misc]


class _WatchedHTTPHandler(_Watching, urllib.request.HTTPHandler):
    pass


class _WatchedHTTPSHandler(_Watching, urllib.request.HTTPSHandler):
    pass
