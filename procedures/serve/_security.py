"""Who may talk to ``instrument serve``: the address it binds and the token every request carries.

On a loopback address (127.0.0.0/8, ::1) no token is needed, and requests must name a loopback host
(a ``Host`` header of another name is refused, so a web page elsewhere cannot reach the view through
DNS rebinding). Any other address needs ``--allow-remote`` and a token; a request carries it as
``Authorization: Bearer TOKEN``, as the cookie ``instrument_token``, or once as ``?token=TOKEN`` in a
page address (the answer sets the cookie, so a phone's browser needs the link once).
"""

from __future__ import annotations

import ipaddress
import json
import secrets
from collections.abc import Awaitable, Callable, MutableMapping
from http.cookies import SimpleCookie
from typing import Any
from urllib.parse import parse_qsl, urlencode

TOKEN_COOKIE = "instrument_token"
TOKEN_ENV = "INSTRUMENT_SERVE_TOKEN"

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]


def is_loopback(host: str) -> bool:
    """Whether ``host`` (an address or ``localhost``) is a loopback address."""
    if host.strip("[]").lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def new_token() -> str:
    """A random token for ``--allow-remote`` when none is given (printed once at start)."""
    return secrets.token_urlsafe(24)


def _host_name(header: str) -> str:
    if header.startswith("["):
        return header[1:].split("]", 1)[0]
    return header.rsplit(":", 1)[0] if header.count(":") == 1 else header


class AccessGuard:
    """ASGI middleware: the loopback ``Host`` check and the token check (see the module docstring).

    Parameters
    ----------
    app : the wrapped application
    token : required on every request when not None
    loopback_only : refuse ``Host`` headers that do not name a loopback host
    """

    def __init__(self, app: ASGIApp, *, token: str | None, loopback_only: bool) -> None:
        self.app, self.token, self.loopback_only = app, token, loopback_only

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
        if self.loopback_only and not is_loopback(_host_name(headers.get("host", "127.0.0.1"))):
            await _refuse(send, 400, "this view answers loopback host names only (see --allow-remote)")
            return
        if self.token is None:
            await self.app(scope, receive, send)
            return
        query = dict(parse_qsl(scope.get("query_string", b"").decode("latin-1")))
        cookie = SimpleCookie(headers.get("cookie", "")).get(TOKEN_COOKIE)
        given = [headers.get("authorization", "").removeprefix("Bearer ").strip(), cookie.value if cookie else "",
                 query.get("token", "")]
        if not any(g and secrets.compare_digest(g, self.token) for g in given):
            await _refuse(send, 401,
                          "a token is needed: Authorization: Bearer TOKEN, or open a page with ?token=TOKEN")
            return
        if query.get("token") and scope["method"] == "GET" and not scope["path"].startswith("/api/"):
            # A page opened with ?token=: set the cookie and drop the token from the address bar.
            rest = urlencode([(k, v) for k, v in query.items() if k != "token"])
            location = scope["path"] + (f"?{rest}" if rest else "")
            await send({"type": "http.response.start", "status": 303, "headers": [
                (b"location", location.encode("latin-1")),
                (b"set-cookie", f"{TOKEN_COOKIE}={self.token}; HttpOnly; SameSite=Strict; Path=/".encode("latin-1")),
                (b"content-length", b"0")]})
            await send({"type": "http.response.body", "body": b""})
            return
        await self.app(scope, receive, send)


async def _refuse(send: Send, status: int, message: str) -> None:
    body = json.dumps({"error": message}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]})
    await send({"type": "http.response.body", "body": body})
