"""Sign-in, origin check and TLS for the web app, inside viser's own server.

viser serves its page and its websocket from one ``websockets`` server whose HTTP hook
(``process_request``) it sets itself and offers no way to extend. :func:`install` gives viser's
server module a view of ``websockets`` in which ``serve`` wraps that hook with a :class:`Guard`
and adds the guard's TLS context; nothing else in the process changes, and a server made
without a guard is served exactly as before.

What a guard enforces, for the page, its files and the websocket alike:

* a secret token: ``?token=TOKEN`` once (the answer sets a cookie and sends the browser on to
  the address without the token), then the cookie (HttpOnly, SameSite=Strict, Secure over
  TLS; its value derived from the token, not the token itself); compared in constant time;
  or a password whose salted scrypt hash a password file holds (:class:`PasswordHash`; the
  refusal page asks for it, the cookie follows as with a token);
* wrong tokens or cookies from one address are limited (:data:`MAX_FAILURES` per
  :data:`FAILURE_WINDOW_S`; then 429 until the window passes);
* a websocket upgrade whose ``Origin`` is neither the page's own nor an allowed one is refused,
  with or without the token (another web site open in the same browser cannot drive the app);
* pages are sent with ``frame-ancestors 'none'``, ``no-referrer`` and ``no-store``;
* the token never appears in a log line; the audit log records each refused attempt.
"""

from __future__ import annotations

import hashlib
import hmac
import http
import logging
import os
import secrets
import ssl
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import parse_qsl, urlencode, urlsplit

from registration.io.passwords import PasswordHash

log = logging.getLogger(__name__)

ENV_TOKEN = "ROADMAP3D_TOKEN"
#: Shortest token accepted from the user (characters).
MIN_TOKEN_CHARS = 12
#: Wrong tokens or cookies accepted from one address within FAILURE_WINDOW_S before it is refused.
MAX_FAILURES = 10
FAILURE_WINDOW_S = 60.0

REFUSED_PAGE = (
    "<!doctype html><meta charset=utf-8><title>roadmap3d: sign-in needed</title>"
    "<body style='font-family:sans-serif;background:#1a1b1e;color:#ddd;padding:2em'>"
    "<h2>Sign-in needed</h2><p>Open the address that <code>roadmap3d</code> printed when it started "
    "(it ends in <code>?token=...</code>), or ask whoever started it.</p></body>"
)
PASSWORD_PAGE = (
    "<!doctype html><meta charset=utf-8><title>roadmap3d: sign in</title>"
    "<body style='font-family:sans-serif;background:#1a1b1e;color:#ddd;padding:2em'>"
    "<h2>Sign in to roadmap3d</h2><form method=get action=/><label>Password "
    "<input type=password name=password autofocus autocomplete=current-password style='padding:.4em;width:18em'>"
    "</label> <button type=submit style='padding:.4em 1em'>Sign in</button></form>"
    "<p style='color:#999'>The password was set with <code>roadmap3d password FILE</code> by whoever started the "
    "app.</p></body>"
)


def new_token() -> str:
    """A fresh random token (32 URL-safe characters, 192 bits)."""
    return secrets.token_urlsafe(24)


def check_token(token: str) -> str:
    """A user's token: at least MIN_TOKEN_CHARS printable characters without spaces."""
    if len(token) < MIN_TOKEN_CHARS or not token.isprintable() or any(c.isspace() for c in token):
        raise ValueError(
            f"the token must be at least {MIN_TOKEN_CHARS} printable characters without spaces "
            f"(omit --token and unset {ENV_TOKEN} for a random one)"
        )
    return token


def tls_context(certfile: str | os.PathLike[str], keyfile: str | os.PathLike[str] | None) -> ssl.SSLContext:
    """A server TLS context from a certificate (PEM, with its chain) and its key."""
    for path, what in ((certfile, "--certfile"), (keyfile, "--keyfile")):
        if path is not None and not Path(path).is_file():
            raise ValueError(f"{what} {path}: no such file")
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        context.load_cert_chain(str(certfile), None if keyfile is None else str(keyfile))
    except (ssl.SSLError, OSError) as exc:
        raise ValueError(f"--certfile {certfile} / --keyfile {keyfile}: cannot use them ({exc})") from None
    return context


@dataclass
class Guard:
    """What the server asks of every request (see the module's text)."""

    token: str | None
    ssl_context: ssl.SSLContext | None = None
    #: Extra origins (``scheme://host:port``) whose pages may open the websocket.
    allowed_origins: tuple[str, ...] = ()
    #: ``audit(action, client=, result=)`` for sign-ins and refusals.
    audit: Callable[..., Any] | None = None
    #: Sign in by this password (its hash) instead of a token.
    password: PasswordHash | None = None
    _failures: dict[str, deque[float]] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def scheme(self) -> str:
        return "https" if self.ssl_context is not None else "http"

    @property
    def signs_in(self) -> bool:
        return self.token is not None or self.password is not None

    def _secret(self) -> bytes:
        """What the cookie derives from: the token, or the password's hash (never the password)."""
        if self.password is not None:
            return self.password.digest
        assert self.token is not None
        return self.token.encode()

    @property
    def cookie_name(self) -> str:
        """Per secret: two apps on one host (other ports) keep their own cookies."""
        return "roadmap3d_" + hmac.new(self._secret(), b"roadmap3d-cookie-name", hashlib.sha256).hexdigest()[:12]

    def _cookie_value(self) -> str:
        return hmac.new(self._secret(), b"roadmap3d-cookie-v1", hashlib.sha256).hexdigest()

    def _accepts(self, presented: str) -> bool:
        if self.password is not None:
            return self.password.verify(presented)
        assert self.token is not None
        return hmac.compare_digest(presented.encode(), self.token.encode())

    # ----- the checks ------------------------------------------------------------------
    def _limited(self, client: str) -> bool:
        now = time.monotonic()
        with self._lock:
            times = self._failures.get(client)
            while times and now - times[0] > FAILURE_WINDOW_S:
                times.popleft()
            return bool(times) and len(times) >= MAX_FAILURES

    def _failed(self, client: str) -> None:
        with self._lock:
            self._failures.setdefault(client, deque()).append(time.monotonic())

    def _presented(self, request: Any) -> tuple[str | None, str | None]:
        """(token from the query, cookie value) as the request carries them."""
        query = dict(parse_qsl(urlsplit(request.path).query))
        cookie = None
        for header in request.headers.get_all("Cookie"):
            for part in header.split(";"):
                name, _, value = part.strip().partition("=")
                if name == self.cookie_name:
                    cookie = value
        return query.get("password") if self.password is not None else query.get("token"), cookie

    def _origin_ok(self, request: Any) -> bool:
        origin = request.headers.get("Origin")
        if origin is None:
            return True  # not a browser: nothing of a page's to protect; the token still applies
        origin = origin.strip().lower().rstrip("/")
        own = f"{self.scheme}://{str(request.headers.get('Host', '')).strip().lower()}"
        return origin == own or origin in {o.lower().rstrip("/") for o in self.allowed_origins}

    def check(self, connection: Any, request: Any) -> Any:
        """None to let the request through, else the refusal (or the sign-in redirect)."""
        from websockets.datastructures import Headers
        from websockets.http11 import Response

        client = str((connection.remote_address or ("?",))[0])
        upgrade = str(request.headers.get("Upgrade", "")).lower() == "websocket"
        if upgrade and not self._origin_ok(request):
            self._record("websocket-refused", client, "foreign origin")
            return _plain(http.HTTPStatus.FORBIDDEN, "Forbidden: foreign origin")
        if not self.signs_in:
            return None
        if self._limited(client):
            return _plain(http.HTTPStatus.TOO_MANY_REQUESTS, "Too many failed sign-ins; try again in a minute")
        token, cookie = self._presented(request)
        if cookie is not None and hmac.compare_digest(cookie.encode(), self._cookie_value().encode()):
            return None
        if token is not None and self._accepts(token):
            self._record("sign-in", client, "ok")
            if upgrade:
                return None
            # the cookie from now on; the address bar loses the token
            parts = urlsplit(request.path)
            rest = urlencode([(k, v) for k, v in parse_qsl(parts.query) if k not in ("token", "password")])
            secure = "; Secure" if self.ssl_context is not None else ""
            headers = Headers()
            headers["Location"] = (parts.path or "/") + (f"?{rest}" if rest else "")
            cookie = f"{self.cookie_name}={self._cookie_value()}; Path=/; HttpOnly; SameSite=Strict{secure}"
            headers["Set-Cookie"] = cookie
            headers["Cache-Control"] = "no-store"
            headers["Referrer-Policy"] = "no-referrer"
            headers["Content-Length"] = "0"
            return Response(http.HTTPStatus.SEE_OTHER.value, "See Other", headers, b"")
        if token is not None or cookie is not None:
            self._failed(client)
            what = "password" if self.password is not None else "token"
            self._record("sign-in", client, f"refused: wrong {what}" if token is not None else "refused: wrong cookie")
        elif upgrade:
            self._record("websocket-refused", client, "no sign-in")
        status = http.HTTPStatus.UNAUTHORIZED
        page = PASSWORD_PAGE if self.password is not None else REFUSED_PAGE
        return _plain(status, page, html=True) if not upgrade else _plain(status, "Unauthorized")

    def _record(self, action: str, client: str, result: str) -> None:
        log.info("%s from %s: %s", action, client, result)
        if self.audit is not None:
            try:
                self.audit(action, client=client, result=result)
            except Exception:
                log.exception("the audit log failed")

    def url(self, host: str, port: int) -> str:
        """The address to open: ``http(s)://HOST:PORT/`` with ``?token=TOKEN`` when signing in."""
        shown = f"[{host}]" if ":" in host else host
        base = f"{self.scheme}://{shown}:{port}/"
        return base + (f"?token={self.token}" if self.token else "")


def _plain(status: http.HTTPStatus, text: str, *, html: bool = False) -> Any:
    from websockets.datastructures import Headers
    from websockets.http11 import Response

    body = text.encode()
    headers = Headers()
    headers["Content-Type"] = "text/html; charset=utf-8" if html else "text/plain; charset=utf-8"
    headers["Content-Length"] = str(len(body))
    headers["Cache-Control"] = "no-store"
    return Response(status.value, status.phrase, headers, body)


def _harden(response: Any) -> Any:
    """Headers every page and file gets: not framed by other sites, no referrer, not cached."""
    if response is not None:
        response.headers["Content-Security-Policy"] = "frame-ancestors 'none'"
        response.headers["X-Frame-Options"] = "DENY"
        response.headers["Referrer-Policy"] = "no-referrer"
        response.headers["Cache-Control"] = "no-store"
        response.headers["X-Content-Type-Options"] = "nosniff"
    return response


# --------------------------------------------------------------------------------------
# Hooking viser's server
# --------------------------------------------------------------------------------------
_pending: Guard | None = None
_pending_lock = threading.RLock()
_installed = False


class _View:
    """A module seen through: ``overrides`` first, the module's own names otherwise."""

    def __init__(self, module: Any, **overrides: Any) -> None:
        self._module = module
        self._overrides = overrides

    def __getattr__(self, name: str) -> Any:
        if name in self._overrides:
            return self._overrides[name]
        return getattr(self._module, name)


def _serve(handler: Any, host: Any, port: Any, **kwargs: Any) -> Any:
    import websockets.asyncio.server

    guard = _pending
    if guard is not None:
        inner = kwargs.get("process_request")

        def process_request(connection: Any, request: Any) -> Any:
            refused = guard.check(connection, request)
            if refused is not None:
                return refused
            return _harden(inner(connection, request) if inner is not None else None)

        kwargs["process_request"] = process_request
        if guard.ssl_context is not None:
            kwargs["ssl"] = guard.ssl_context
    return websockets.asyncio.server.serve(handler, host, port, **kwargs)


def install() -> None:
    """Let :func:`guarded` servers be made (idempotent)."""
    global _installed
    with _pending_lock:
        if _installed:
            return
        import websockets
        import websockets.asyncio.server
        from viser.infra import _infra

        server_view = _View(websockets.asyncio.server, serve=_serve)
        _infra.websockets = _View(websockets, asyncio=_View(websockets.asyncio, server=server_view))  # type: ignore[attr-defined]
        _installed = True


def guarded(guard: Guard | None, make: Callable[[], Any]) -> Any:
    """``make()`` (which constructs a ``viser.ViserServer``) with its server under ``guard``."""
    global _pending
    install()
    with _pending_lock:
        _pending = guard
        try:
            server = make()
        finally:
            _pending = None
    return server


def client_address(server: Any, client: Any) -> str:
    """The network address of a connected viser client (its ``ClientHandle`` or id); "" if unknown."""
    try:
        client_id = getattr(client, "client_id", client)
        connection = server._websock_server._live_connections[client_id]
        return str(connection.remote_address[0])
    except (AttributeError, KeyError, IndexError, TypeError):
        return ""


def parse_origins(values: Iterable[str]) -> tuple[str, ...]:
    """``--allow-origin`` values: ``scheme://host[:port]`` each."""
    out = []
    for value in values:
        parts = urlsplit(value.strip())
        if parts.scheme not in ("http", "https") or not parts.hostname or parts.path not in ("", "/"):
            raise ValueError(f"--allow-origin {value!r}: must be http(s)://host[:port]")
        out.append(f"{parts.scheme}://{parts.netloc}".lower())
    return tuple(out)
